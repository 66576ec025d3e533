//! The CPU backend of the device seam: [`Storage`] on candle tensors. Each op is the very candle call or
//! `kernels` function the networks made before the seam existed, so CPU results and speed are those of
//! plain candle code.

use candle_core::{Module, Result, Tensor, D};
use candle_nn::Activation;

use super::device::{Addend, Storage, Unary};

impl Storage for Tensor {
    fn dims(&self) -> &[usize] {
        Tensor::dims(self)
    }

    fn to_cpu(&self) -> Result<Tensor> {
        Ok(self.clone())
    }

    fn add(&self, other: &Self) -> Result<Self> {
        self + other
    }

    fn broadcast_add(&self, other: &Self) -> Result<Self> {
        Tensor::broadcast_add(self, other)
    }

    fn broadcast_mul(&self, other: &Self) -> Result<Self> {
        Tensor::broadcast_mul(self, other)
    }

    fn broadcast_add_host(&self, t: &Tensor) -> Result<Self> {
        Tensor::broadcast_add(self, t)
    }

    fn affine(&self, mul: f64, add: f64) -> Result<Self> {
        Tensor::affine(self, mul, add)
    }

    fn unary(&self, op: Unary) -> Result<Self> {
        match op {
            Unary::Relu => self.relu(),
            Unary::Silu => self.silu(),
            Unary::Tanh => self.tanh(),
            Unary::GeluErf => self.gelu_erf(),
            Unary::GeluTanh => self.gelu(),
            Unary::QuickGelu => self * candle_nn::ops::sigmoid(&(self * 1.702)?)?,
        }
    }

    fn activation(&self, act: Activation) -> Result<Self> {
        act.forward(self)
    }

    fn reshape(&self, shape: &[usize]) -> Result<Self> {
        Tensor::reshape(self, shape)
    }

    fn permute_contiguous(&self, dims: &[usize]) -> Result<Self> {
        self.permute(dims)?.contiguous()
    }

    fn narrow(&self, dim: usize, start: usize, len: usize) -> Result<Self> {
        Tensor::narrow(self, dim, start, len)
    }

    fn narrow_permute(&self, dim: usize, start: usize, len: usize, dims: &[usize]) -> Result<Self> {
        Tensor::narrow(self, dim, start, len)?
            .permute(dims)?
            .contiguous()
    }

    fn index_select(&self, indices: &[u32], dim: usize) -> Result<Self> {
        Tensor::index_select(self, &Tensor::new(indices, self.device())?, dim)
    }

    fn pad_bottom_right_with_zeros(&self) -> Result<Self> {
        self.pad_with_zeros(D::Minus1, 0, 1)?
            .pad_with_zeros(D::Minus2, 0, 1)
    }

    fn upsample_nearest2d(&self, out_h: usize, out_w: usize) -> Result<Self> {
        Tensor::upsample_nearest2d(self, out_h, out_w)
    }

    fn cat(parts: &[&Self], dim: usize) -> Result<Self> {
        Tensor::cat(parts, dim)
    }

    fn conv2d(
        &self,
        weight: &Tensor,
        bias: Option<&Tensor>,
        stride: usize,
        padding: usize,
        addend: Addend<'_, Self>,
    ) -> Result<Self> {
        let out = super::conv2d(self, weight, bias, stride, padding)?;
        match addend {
            Addend::None => Ok(out),
            Addend::Residual(r) => out + r,
            Addend::PerChannel(t) => {
                let (n, c, _, _) = out.dims4()?;
                out.broadcast_add(&t.reshape((n, c, 1, 1))?)
            }
        }
    }

    fn linear(&self, layer: &candle_nn::Linear, residual: Option<&Self>) -> Result<Self> {
        if let Some(out) = super::bf16::linear(self, layer.weight(), layer.bias(), residual)? {
            return Ok(out);
        }
        let out = layer.forward(self)?;
        match residual {
            Some(r) => out + r,
            None => Ok(out),
        }
    }

    fn group_norm(
        &self,
        weight: &Tensor,
        bias: &Tensor,
        groups: usize,
        eps: f64,
        silu: bool,
    ) -> Result<Self> {
        super::group_norm(self, weight, bias, groups, eps, silu)
    }

    fn layer_norm(&self, weight: &Tensor, bias: &Tensor, eps: f64) -> Result<Self> {
        super::layer_norm(self, weight, bias, eps)
    }

    fn softmax_last_dim(&self) -> Result<Self> {
        super::softmax_last_dim(self)
    }

    fn geglu(&self) -> Result<Self> {
        super::geglu(self)
    }

    fn matmul_t(&self, other: &Self) -> Result<Self> {
        self.matmul(&other.t()?)
    }

    fn matmul(&self, other: &Self) -> Result<Self> {
        Tensor::matmul(self, other)
    }

    fn attention(q: &Self, k: &Self, v: &Self, scale: f64) -> Result<Self> {
        super::attention(q, k, v, scale)
    }

    fn max_pool2x2(&self) -> Result<Self> {
        super::vgg::max_pool2x2(self)
    }

    fn max_pool2x2_backward(&self, grad: &Self) -> Result<Self> {
        super::vgg::max_pool2x2_backward(self, grad)
    }

    fn relu_backward(&self, grad: &Self) -> Result<Self> {
        super::vgg::relu_backward(self, grad)
    }

    fn normalize_channels(&self, eps: f32) -> Result<Self> {
        super::vgg::normalize_channels(self, eps)
    }

    fn lpips_distance(
        &self,
        target: &Self,
        lin: &Tensor,
        eps: f32,
        with_grad: bool,
    ) -> Result<(Self, Option<Self>)> {
        super::vgg::lpips_distance(self, target, lin, eps, with_grad)
    }
}
