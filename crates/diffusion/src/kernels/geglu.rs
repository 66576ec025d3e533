//! diffusers' GEGLU: `hidden · gelu(gate)` with the exact (erf) GELU, for x = [..., hidden | gate].

use candle_core::{CpuStorage, CustomOp1, CustomOp2, Layout, Result, Shape, Tensor, D};
use rayon::prelude::*;

use super::approx;
use super::{cpu_f32, f32_slice, f32_slices, needs_grad, rows_per_task};

/// `hidden · gelu_erf(gate)` where `x` = [..., 2·inner] holds `[hidden | gate]`.
pub fn geglu(x: &Tensor) -> Result<Tensor> {
    let width = x.dim(D::Minus1)?;
    if width == 0 || width % 2 != 0 {
        candle_core::bail!("geglu: last dimension {width} is not a positive even number");
    }
    match (needs_grad(&[x]), cpu_f32(&[x])) {
        (false, true) => x.contiguous()?.apply_op1_no_bwd(&Geglu),
        (true, true) => x.contiguous()?.apply_op1(Geglu),
        _ => {
            let inner = width / 2;
            let hidden = x.narrow(D::Minus1, 0, inner)?;
            let gate = x.narrow(D::Minus1, inner, inner)?;
            hidden * gate.gelu_erf()?
        }
    }
}

#[inline(always)]
fn geglu_kernel(out: &mut [f32], hidden: &[f32], gate: &[f32]) {
    for ((o, &h), &g) in out.iter_mut().zip(hidden).zip(gate) {
        *o = h * g * approx::normal_cdf(g);
    }
}

simd_dispatch!(
    /// One row `[hidden | gate]` → `hidden · gelu(gate)`.
    fn geglu_row(out: &mut [f32], hidden: &[f32], gate: &[f32]) => geglu_kernel
);

/// GEGLU of contiguous f32 rows; the backward pass is [`GegluBackward`].
struct Geglu;

impl CustomOp1 for Geglu {
    fn name(&self) -> &'static str {
        "geglu"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> Result<(CpuStorage, Shape)> {
        let x = f32_slice(storage, layout, self.name())?;
        let mut dims = layout.shape().dims().to_vec();
        let width = dims.last().copied().unwrap_or(0);
        let inner = width / 2;
        if inner == 0 {
            candle_core::bail!("geglu: last dimension {width} is too small");
        }
        *dims.last_mut().expect("rank ≥ 1") = inner;
        let mut out = vec![0f32; x.len() / 2];
        let rows = rows_per_task(inner);
        out.par_chunks_mut(inner * rows)
            .zip(x.par_chunks(width * rows))
            .for_each(|(out, x)| {
                for (o, row) in out.chunks_mut(inner).zip(x.chunks(width)) {
                    let (hidden, gate) = row.split_at(inner);
                    geglu_row(o, hidden, gate);
                }
            });
        Ok((CpuStorage::F32(out), Shape::from(dims)))
    }

    fn bwd(&self, arg: &Tensor, _res: &Tensor, grad: &Tensor) -> Result<Option<Tensor>> {
        let dx = arg
            .contiguous()?
            .apply_op2_no_bwd(&grad.contiguous()?, &GegluBackward)?;
        Ok(Some(dx))
    }
}

/// d(hidden) = g · gelu(gate), d(gate) = g · hidden · gelu'(gate), from (x, output gradient g).
struct GegluBackward;

impl CustomOp2 for GegluBackward {
    fn name(&self) -> &'static str {
        "geglu-backward"
    }

    fn cpu_fwd(
        &self,
        xs: &CpuStorage,
        xl: &Layout,
        gs: &CpuStorage,
        gl: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let [x, g] = f32_slices([(xs, xl), (gs, gl)], self.name())?;
        let width = xl.shape().dims().last().copied().unwrap_or(0);
        let inner = width / 2;
        if inner == 0 || g.len() * 2 != x.len() {
            candle_core::bail!("{}: gradient does not fit {:?}", self.name(), xl.shape());
        }
        let mut dx = vec![0f32; x.len()];
        let rows = rows_per_task(inner);
        dx.par_chunks_mut(width * rows)
            .zip(x.par_chunks(width * rows))
            .zip(g.par_chunks(inner * rows))
            .for_each(|((dx, x), g)| {
                for ((d, row), g) in dx
                    .chunks_mut(width)
                    .zip(x.chunks(width))
                    .zip(g.chunks(inner))
                {
                    let (hidden, gate) = row.split_at(inner);
                    let (dh, dg) = d.split_at_mut(inner);
                    for k in 0..inner {
                        let (h, z) = (hidden[k], gate[k]);
                        let cdf = approx::normal_cdf(z);
                        dh[k] = g[k] * z * cdf;
                        dg[k] = g[k] * h * (cdf + z * approx::normal_pdf(z));
                    }
                }
            });
        Ok((CpuStorage::F32(dx), xl.shape().clone()))
    }
}

#[cfg(test)]
mod tests {
    use super::super::test_support::{check_gradients, max_diff, var};
    use super::*;
    use candle_core::{DType, Device};

    fn composite(x: &Tensor) -> Tensor {
        let inner = x.dim(D::Minus1).unwrap() / 2;
        let h = x.narrow(D::Minus1, 0, inner).unwrap();
        let g = x.narrow(D::Minus1, inner, inner).unwrap();
        (h * g.gelu_erf().unwrap()).unwrap()
    }

    #[test]
    fn matches_candle_with_gradients() {
        for shape in [vec![2, 5, 16], vec![3, 2], vec![70, 6]] {
            let vars = [var(&shape, 0.0, 2.0)];
            check_gradients(
                &vars,
                |t| geglu(&t[0]).unwrap(),
                |t| composite(&t[0]),
                &format!("geglu {shape:?}"),
            );
        }
        assert!(geglu(&Tensor::zeros((2, 3), DType::F32, &Device::Cpu).unwrap()).is_err());
    }

    #[test]
    fn inference_matches_exact_gelu() {
        let x = Tensor::randn(0f32, 3.0, (2, 5, 24), &Device::Cpu).unwrap();
        assert!(max_diff(&geglu(&x).unwrap(), &composite(&x)) < 1e-5);
    }

    /// Inference and training run the same forward kernel, so a model computes the same values whether or
    /// not it is being trained.
    #[test]
    fn inference_and_training_forward_are_identical() {
        let x = var(&[3, 7, 40], 0.0, 3.0);
        let training = geglu(x.as_tensor()).unwrap();
        let inference = geglu(&x.as_tensor().detach()).unwrap();
        assert_eq!(max_diff(&training, &inference), 0.0);
    }
}
