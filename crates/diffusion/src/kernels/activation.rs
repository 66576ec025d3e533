//! Inference kernels for the GELU-like activations of the transformer MLPs (CLIP's `quick_gelu`, exact
//! GELU): one vectorised pass over the input. candle's composite (`x · sigmoid(1.702·x)`) makes three
//! passes, each allocating its output, with a scalar `expf` per element; in CLIP's MLP ([tokens, 3072])
//! that cost as much as a third of the encoder's products.
//!
//! Only while the CPU's products run in bf16 ([`super::bf16`]): the f32 path stays candle's composite
//! bit for bit (libm's `expf`), as the f32 fixtures and the demo's f32 `edited.ply` were made with it,
//! and the kernels' approximate `exp` (within 1e-7) is far inside bf16's rounding.

use candle_core::{CpuStorage, CustomOp1, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

use super::approx;
use super::bf16;
use super::op_args::Unary;
use super::{cpu_f32, f32_slice, needs_grad};

/// `op` of `x` in one pass, for inference with bf16 products on f32 CPU tensors and an activation with
/// a kernel here; `None` otherwise (the caller runs candle's ops, which have backward passes).
pub(super) fn fused(x: &Tensor, op: Unary) -> Result<Option<Tensor>> {
    if !bf16::bf16_active() {
        return Ok(None);
    }
    single_pass(x, op)
}

/// [`fused`] whatever the precision.
fn single_pass(x: &Tensor, op: Unary) -> Result<Option<Tensor>> {
    if !matches!(op, Unary::QuickGelu | Unary::GeluErf) || needs_grad(&[x]) || !cpu_f32(&[x]) {
        return Ok(None);
    }
    x.contiguous()?.apply_op1_no_bwd(&Activation(op)).map(Some)
}

#[inline(always)]
fn quick_gelu_kernel(out: &mut [f32], x: &[f32]) {
    for (o, &x) in out.iter_mut().zip(x) {
        *o = x * approx::sigmoid(1.702 * x);
    }
}

#[inline(always)]
fn gelu_erf_kernel(out: &mut [f32], x: &[f32]) {
    for (o, &x) in out.iter_mut().zip(x) {
        *o = x * approx::normal_cdf(x);
    }
}

simd_dispatch!(
    /// `x·σ(1.702·x)` of a slice.
    fn quick_gelu(out: &mut [f32], x: &[f32]) => quick_gelu_kernel
);

simd_dispatch!(
    /// `x·Φ(x)` of a slice.
    fn gelu_erf(out: &mut [f32], x: &[f32]) => gelu_erf_kernel
);

/// Elements one parallel task maps.
const TASK_ELEMENTS: usize = 16 * 1024;

struct Activation(Unary);

impl CustomOp1 for Activation {
    fn name(&self) -> &'static str {
        "fused-activation"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> Result<(CpuStorage, Shape)> {
        let x = f32_slice(storage, layout, self.name())?;
        let kernel = match self.0 {
            Unary::QuickGelu => quick_gelu,
            Unary::GeluErf => gelu_erf,
            other => candle_core::bail!("{}: no kernel for {other:?}", self.name()),
        };
        let mut out = vec![0f32; x.len()];
        out.par_chunks_mut(TASK_ELEMENTS)
            .zip(x.par_chunks(TASK_ELEMENTS))
            .for_each(|(out, x)| kernel(out, x));
        Ok((CpuStorage::F32(out), layout.shape().clone()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    /// The fused pass is candle's composite to float rounding, over the range where the activations bend
    /// and far into both tails.
    #[test]
    fn fused_activations_match_candles_composites() {
        let x = Tensor::randn(0f32, 4.0, (3, 7, 1031), &Device::Cpu).unwrap();
        let quick = single_pass(&x, Unary::QuickGelu)
            .unwrap()
            .expect("a kernel");
        let want = (&x * candle_nn::ops::sigmoid(&(&x * 1.702).unwrap()).unwrap()).unwrap();
        assert!(testkit::diff::tensor_max_abs_diff(&quick, &want) < 2e-6);
        let gelu = single_pass(&x, Unary::GeluErf).unwrap().expect("a kernel");
        assert!(testkit::diff::tensor_max_abs_diff(&gelu, &x.gelu_erf().unwrap()) < 2e-6);
        assert!(
            single_pass(&x, Unary::Relu).unwrap().is_none(),
            "no kernel: candle's op"
        );
        // f32 products keep candle's composite.
        assert!(fused(&x, Unary::QuickGelu).unwrap().is_none());
    }
}
