//! The GPU backend of the device seam: [`Storage`] on [`GpuTensor`]s, one CubeCL kernel (in [`ops`]) per
//! op. Weights are fetched from the device's cache; matrix weights in the device's precision.

use candle_core::{Result, Tensor};
use candle_nn::Activation;

use super::{ops, GpuTensor};
use crate::kernels::device::{Addend, Storage, Unary};

impl GpuTensor {
    /// A weight (or any CPU constant) on this tensor's device, in f32.
    fn constant(&self, t: &Tensor) -> Result<GpuTensor> {
        self.device().cached(t)
    }

    /// The weight of a matrix product on this tensor's device, in the device's precision.
    fn matrix_constant(&self, t: &Tensor) -> Result<GpuTensor> {
        self.device().cached_matrix(t)
    }
}

impl Storage for GpuTensor {
    fn dims(&self) -> &[usize] {
        GpuTensor::dims(self)
    }

    fn to_cpu(&self) -> Result<Tensor> {
        GpuTensor::to_cpu(self)
    }

    fn add(&self, other: &Self) -> Result<Self> {
        if self.dims() != other.dims() {
            candle_core::bail!(
                "add: shapes {:?} and {:?} differ",
                self.dims(),
                other.dims()
            );
        }
        ops::add(self, other)
    }

    fn broadcast_add(&self, other: &Self) -> Result<Self> {
        ops::add(self, other)
    }

    fn broadcast_mul(&self, other: &Self) -> Result<Self> {
        ops::mul(self, other)
    }

    fn broadcast_add_host(&self, t: &Tensor) -> Result<Self> {
        ops::add(self, &GpuTensor::upload(self.device(), t)?)
    }

    fn affine(&self, mul: f64, add: f64) -> Result<Self> {
        Ok(ops::affine(self, mul as f32, add as f32))
    }

    fn unary(&self, op: Unary) -> Result<Self> {
        Ok(match op {
            Unary::Relu => ops::relu(self),
            Unary::Silu => ops::silu(self),
            Unary::Tanh => ops::tanh(self),
            Unary::GeluErf => ops::gelu(self),
            Unary::GeluTanh => ops::gelu_tanh(self),
            Unary::QuickGelu => ops::quick_gelu(self),
        })
    }

    fn activation(&self, act: Activation) -> Result<Self> {
        match act {
            Activation::Relu => Ok(ops::relu(self)),
            Activation::Silu => Ok(ops::silu(self)),
            Activation::Gelu => Ok(ops::gelu(self)),
            Activation::Mish => Ok(ops::mish(self)),
            other => candle_core::bail!("activation {other:?} has no GPU kernel"),
        }
    }

    fn reshape(&self, shape: &[usize]) -> Result<Self> {
        GpuTensor::reshape(self, shape)
    }

    fn permute_contiguous(&self, dims: &[usize]) -> Result<Self> {
        ops::permute(self, dims)
    }

    fn narrow(&self, dim: usize, start: usize, len: usize) -> Result<Self> {
        ops::narrow(self, dim, start, len)
    }

    fn narrow_permute(&self, dim: usize, start: usize, len: usize, dims: &[usize]) -> Result<Self> {
        ops::narrow_permute(self, dim, start, len, dims)
    }

    fn index_select(&self, indices: &[u32], dim: usize) -> Result<Self> {
        ops::index_select(self, indices, dim)
    }

    fn pad_bottom_right_with_zeros(&self) -> Result<Self> {
        ops::pad_bottom_right(self, 1, 1)
    }

    fn upsample_nearest2d(&self, out_h: usize, out_w: usize) -> Result<Self> {
        ops::upsample_nearest2d(self, out_h, out_w)
    }

    fn cat(parts: &[&Self], dim: usize) -> Result<Self> {
        ops::cat(parts, dim)
    }

    fn conv2d(
        &self,
        weight: &Tensor,
        bias: Option<&Tensor>,
        stride: usize,
        padding: usize,
        addend: Addend<'_, Self>,
    ) -> Result<Self> {
        let bias = bias.map(|b| self.constant(b)).transpose()?;
        ops::conv2d(
            self,
            &self.matrix_constant(weight)?,
            bias.as_ref(),
            stride,
            padding,
            addend,
        )
    }

    fn linear(&self, layer: &candle_nn::Linear, residual: Option<&Self>) -> Result<Self> {
        let bias = layer.bias().map(|b| self.constant(b)).transpose()?;
        ops::linear(
            self,
            &self.matrix_constant(layer.weight())?,
            bias.as_ref(),
            residual,
        )
    }

    fn group_norm(
        &self,
        weight: &Tensor,
        bias: &Tensor,
        groups: usize,
        eps: f64,
        silu: bool,
    ) -> Result<Self> {
        ops::group_norm(
            self,
            &self.constant(weight)?,
            &self.constant(bias)?,
            groups,
            eps,
            silu,
        )
    }

    fn layer_norm(&self, weight: &Tensor, bias: &Tensor, eps: f64) -> Result<Self> {
        ops::layer_norm(self, &self.constant(weight)?, &self.constant(bias)?, eps)
    }

    fn softmax_last_dim(&self) -> Result<Self> {
        ops::softmax_last_dim(self)
    }

    fn geglu(&self) -> Result<Self> {
        ops::geglu(self)
    }

    fn matmul_t(&self, other: &Self) -> Result<Self> {
        ops::matmul_scaled(self, other, true, 1.0)
    }

    fn matmul(&self, other: &Self) -> Result<Self> {
        ops::matmul(self, other)
    }

    fn attention(q: &Self, k: &Self, v: &Self, scale: f64) -> Result<Self> {
        ops::attention(q, k, v, scale)
    }

    fn max_pool2x2(&self) -> Result<Self> {
        ops::max_pool2x2(self)
    }

    fn max_pool2x2_backward(&self, grad: &Self) -> Result<Self> {
        ops::max_pool2x2_backward(self, grad)
    }

    fn relu_backward(&self, grad: &Self) -> Result<Self> {
        ops::relu_backward(self, grad)
    }

    fn normalize_channels(&self, eps: f32) -> Result<Self> {
        ops::normalize_channels(self, eps)
    }

    fn lpips_distance(
        &self,
        target: &Self,
        lin: &Tensor,
        eps: f32,
        with_grad: bool,
    ) -> Result<(Self, Option<Self>)> {
        ops::lpips_distance(self, target, &self.constant(lin)?, eps, with_grad)
    }
}
