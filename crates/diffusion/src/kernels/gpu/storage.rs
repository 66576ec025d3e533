//! The GPU bodies of the seam's ops that take more than one call (the others are written in the op
//! lists of `kernels::device`), on the kernels of [`ops`]. Weights are fetched from the device's cache;
//! matrix weights in the device's precision.

use candle_core::{Result, Tensor};
use candle_nn::Activation;

use super::{ops, GpuTensor};
use crate::kernels::op_args::Unary;

impl GpuTensor {
    /// A weight (or any CPU constant) on this tensor's device, in f32.
    pub(crate) fn constant(&self, t: &Tensor) -> Result<GpuTensor> {
        self.device().cached(t)
    }

    /// [`GpuTensor::constant`] of a bias that may be absent.
    pub(crate) fn optional_constant(&self, t: Option<&Tensor>) -> Result<Option<GpuTensor>> {
        t.map(|t| self.constant(t)).transpose()
    }

    /// The weight of a matrix product on this tensor's device, in the device's precision.
    pub(crate) fn matrix_constant(&self, t: &Tensor) -> Result<GpuTensor> {
        self.device().cached_matrix(t)
    }
}

/// `a + b` of equal shapes.
pub(crate) fn same_shape_add(a: &GpuTensor, b: &GpuTensor) -> Result<GpuTensor> {
    if a.dims() != b.dims() {
        candle_core::bail!("add: shapes {:?} and {:?} differ", a.dims(), b.dims());
    }
    ops::add(a, b)
}

/// [`Unary`] `op` of `x`.
pub(crate) fn unary(x: &GpuTensor, op: Unary) -> GpuTensor {
    match op {
        Unary::Relu => ops::relu(x),
        Unary::Silu => ops::silu(x),
        Unary::Tanh => ops::tanh(x),
        Unary::GeluErf => ops::gelu(x),
        Unary::GeluTanh => ops::gelu_tanh(x),
        Unary::QuickGelu => ops::quick_gelu(x),
    }
}

/// The candle-nn activation `act` of `x`, for the ones with a kernel.
pub(crate) fn activation(x: &GpuTensor, act: Activation) -> Result<GpuTensor> {
    match act {
        Activation::Relu => Ok(ops::relu(x)),
        Activation::Silu => Ok(ops::silu(x)),
        Activation::Gelu => Ok(ops::gelu(x)),
        Activation::Mish => Ok(ops::mish(x)),
        other => candle_core::bail!("activation {other:?} has no GPU kernel"),
    }
}
