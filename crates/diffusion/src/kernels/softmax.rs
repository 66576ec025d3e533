//! Softmax over the last dimension: one row kernel, used inside the fused attention and, with its
//! backward pass, when training.

use candle_core::{CpuStorage, CustomOp1, CustomOp2, Layout, Result, Shape, Tensor, D};
use rayon::prelude::*;

use super::approx::{self, LANES};
use super::{cpu_f32, f32_slice, f32_slices, needs_grad, rows_per_task};

/// Softmax over the last dimension of `x`.
///
/// Inference outside the fused attention (attention maps an `AttentionHook` reads, the CLIP towers) runs
/// candle's fused CPU kernel, which computes `exp` exactly: these feed InfEdit's conformance fixtures,
/// whose 1e-4 tolerance float noise alone fills to 60–80%, so their values are kept bit for bit.
pub fn softmax_last_dim(x: &Tensor) -> Result<Tensor> {
    let training = needs_grad(&[x]);
    if training && cpu_f32(&[x]) {
        x.contiguous()?.apply_op1(Softmax)
    } else if training || !x.device().is_cpu() {
        candle_nn::ops::softmax(x, D::Minus1)
    } else {
        candle_nn::ops::softmax_last_dim(x)
    }
}

#[inline(always)]
fn softmax_row(row: &mut [f32]) {
    let max = approx::max_lanes(row);
    // The exponentials are written in place and summed in the same pass.
    let mut sums = [0f32; LANES];
    let mut chunks = row.chunks_exact_mut(LANES);
    for c in &mut chunks {
        for (s, x) in sums.iter_mut().zip(c.iter_mut()) {
            *x = approx::exp(*x - max);
            *s += *x;
        }
    }
    let mut sum: f32 = 0.0;
    for x in chunks.into_remainder() {
        *x = approx::exp(*x - max);
        sum += *x;
    }
    sum += sums.iter().sum::<f32>();
    let inv = 1.0 / sum;
    for x in row.iter_mut() {
        *x *= inv;
    }
}

simd_dispatch!(
    /// Numerically stable softmax of one row, in place, vectorised for the CPU it runs on.
    pub(super) fn softmax_in_place(row: &mut [f32]) => softmax_row
);

/// Softmax of contiguous f32 rows; the backward pass is [`SoftmaxBackward`].
struct Softmax;

impl CustomOp1 for Softmax {
    fn name(&self) -> &'static str {
        "softmax-last-dim"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> Result<(CpuStorage, Shape)> {
        let x = f32_slice(storage, layout, self.name())?;
        let dim = layout.shape().dims().last().copied().unwrap_or(0);
        let mut out = x.to_vec();
        if dim > 0 {
            out.par_chunks_mut(dim * rows_per_task(dim))
                .for_each(|rows| rows.chunks_exact_mut(dim).for_each(softmax_in_place));
        }
        Ok((CpuStorage::F32(out), layout.shape().clone()))
    }

    fn bwd(&self, _arg: &Tensor, res: &Tensor, grad: &Tensor) -> Result<Option<Tensor>> {
        let dx = res
            .contiguous()?
            .apply_op2_no_bwd(&grad.contiguous()?, &SoftmaxBackward)?;
        Ok(Some(dx))
    }
}

/// dx = y ⊙ (g − Σ g·y) per row, from (softmax output y, output gradient g).
struct SoftmaxBackward;

impl CustomOp2 for SoftmaxBackward {
    fn name(&self) -> &'static str {
        "softmax-last-dim-backward"
    }

    fn cpu_fwd(
        &self,
        ys: &CpuStorage,
        yl: &Layout,
        gs: &CpuStorage,
        gl: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let [y, g] = f32_slices([(ys, yl), (gs, gl)], self.name())?;
        let dim = yl.shape().dims().last().copied().unwrap_or(0);
        if g.len() != y.len() {
            candle_core::bail!("{}: gradient does not fit {:?}", self.name(), yl.shape());
        }
        let mut dx = vec![0f32; y.len()];
        if dim > 0 {
            let chunk = dim * rows_per_task(dim);
            dx.par_chunks_mut(chunk)
                .zip(y.par_chunks(chunk))
                .zip(g.par_chunks(chunk))
                .for_each(|((dx, y), g)| {
                    for ((dx, y), g) in dx.chunks_mut(dim).zip(y.chunks(dim)).zip(g.chunks(dim)) {
                        let dot = approx::dot_lanes(y, g);
                        for ((d, &y), &g) in dx.iter_mut().zip(y).zip(g) {
                            *d = y * (g - dot);
                        }
                    }
                });
        }
        Ok((CpuStorage::F32(dx), yl.shape().clone()))
    }
}

#[cfg(test)]
mod tests {
    use super::super::test_support::{check_gradients, max_diff, var};
    use super::*;

    #[test]
    fn matches_candle_with_gradients() {
        for shape in [vec![2, 3, 7, 77], vec![200, 9], vec![4, 1]] {
            let vars = [var(&shape, 0.0, 3.0)];
            check_gradients(
                &vars,
                |t| softmax_last_dim(&t[0]).unwrap(),
                |t| candle_nn::ops::softmax(&t[0], D::Minus1).unwrap(),
                &format!("softmax {shape:?}"),
            );
        }
    }

    #[test]
    fn row_kernel_matches_candle_and_masks_to_zero() {
        let x = Tensor::randn(0f32, 4.0, (3, 5, 300), &candle_core::Device::Cpu).unwrap();
        let want = candle_nn::ops::softmax_last_dim(&x).unwrap();
        let training = softmax_last_dim(&candle_core::Var::from_tensor(&x).unwrap()).unwrap();
        assert!(max_diff(&training, &want) < 1e-6);
        let mut row = [0f32, f32::NEG_INFINITY, 1.0];
        softmax_in_place(&mut row);
        assert!(row[1] < 1e-37 && (row[0] + row[2] - 1.0).abs() < 1e-6);
    }

    #[test]
    fn non_contiguous_inputs_and_gradients_work() {
        // A transposed input and a transposed (non-contiguous) upstream gradient.
        let x = var(&[2, 5, 4, 3], 0.0, 1.0);
        let xt = x.as_tensor().transpose(2, 3).unwrap();
        let y = softmax_last_dim(&xt).unwrap().transpose(1, 2).unwrap();
        let grads = y.sqr().unwrap().sum_all().unwrap().backward().unwrap();
        let want = candle_nn::ops::softmax(&xt, D::Minus1)
            .unwrap()
            .transpose(1, 2)
            .unwrap();
        let gw = want.sqr().unwrap().sum_all().unwrap().backward().unwrap();
        let d = max_diff(
            grads.get(x.as_tensor()).unwrap(),
            gw.get(x.as_tensor()).unwrap(),
        );
        assert!(d < 1e-5, "{d}");
    }
}
