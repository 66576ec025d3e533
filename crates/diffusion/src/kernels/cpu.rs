//! The CPU bodies of the seam's ops that take more than one call (the others are written in the op
//! lists of `kernels::device`): each is the very candle code or `kernels` function the networks ran
//! before the seam existed, so CPU results and speed are those of plain candle code.

use candle_core::{Module, Result, Tensor};

use super::op_args::Unary;

/// [`Unary`] `op` of `x`: one fused pass for inference with bf16 products where [`super::activation`]
/// has a kernel.
pub(super) fn unary(x: &Tensor, op: Unary) -> Result<Tensor> {
    if let Some(out) = super::activation::fused(x, op)? {
        return Ok(out);
    }
    match op {
        Unary::Relu => x.relu(),
        Unary::Silu => x.silu(),
        Unary::Tanh => x.tanh(),
        Unary::GeluErf => x.gelu_erf(),
        Unary::GeluTanh => x.gelu(),
        Unary::QuickGelu => x * candle_nn::ops::sigmoid(&(x * 1.702)?)?,
    }
}

/// The linear `layer` of `x` plus `residual`: bf16 products where they are on, else candle-nn's (over
/// the f32 weight, unpacked once where only bf16 pairs were kept).
pub(super) fn linear(
    x: &Tensor,
    layer: &super::Linear,
    residual: Option<&Tensor>,
) -> Result<Tensor> {
    if let Some(out) = super::bf16::linear(x, layer.weight(), layer.bias(), residual)? {
        return Ok(out);
    }
    let out = candle_nn::Linear::new(layer.weight().tensor()?, layer.bias().cloned()).forward(x)?;
    match residual {
        Some(r) => out + r,
        None => Ok(out),
    }
}
