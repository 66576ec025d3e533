//! [`DeviceTensor`]: the activation type a network forward passes from layer to layer, on the CPU (a candle
//! tensor: every CPU branch below is the very candle call or `kernels` function the networks made before,
//! so CPU results and speed are unchanged) or on the GPU ([`GpuTensor`], one CubeCL kernel per op).
//!
//! Weights stay CPU candle tensors in the network structs; a GPU op fetches the device copy from the
//! device's weight cache ([`GpuDevice::cached`]). One network definition thus runs on either device.

use candle_core::{Result, Tensor};
use candle_nn::Activation;

use super::gpu::{ops, GpuDevice, GpuTensor};

/// A tensor on the CPU or on the GPU.
#[derive(Debug, Clone)]
pub enum DeviceTensor {
    Cpu(Tensor),
    Gpu(GpuTensor),
}

impl From<Tensor> for DeviceTensor {
    fn from(t: Tensor) -> Self {
        DeviceTensor::Cpu(t)
    }
}

impl DeviceTensor {
    /// `t` on `device`: uploaded to the GPU, or kept as is on the CPU (`None`).
    pub fn on(t: &Tensor, device: Option<&GpuDevice>) -> Result<DeviceTensor> {
        Ok(match device {
            Some(device) => DeviceTensor::Gpu(GpuTensor::upload(device, t)?),
            None => DeviceTensor::Cpu(t.clone()),
        })
    }

    /// The values as a CPU tensor (a read-back from the GPU).
    pub fn to_cpu(&self) -> Result<Tensor> {
        match self {
            DeviceTensor::Cpu(t) => Ok(t.clone()),
            DeviceTensor::Gpu(g) => g.to_cpu(),
        }
    }

    pub fn dims(&self) -> &[usize] {
        match self {
            DeviceTensor::Cpu(t) => t.dims(),
            DeviceTensor::Gpu(g) => g.dims(),
        }
    }

    pub fn dims4(&self) -> Result<(usize, usize, usize, usize)> {
        match self.dims() {
            &[a, b, c, d] => Ok((a, b, c, d)),
            other => candle_core::bail!("expected a 4D tensor, got {other:?}"),
        }
    }

    /// The GPU holding the tensor, if any (where a GPU op fetches its weights).
    pub fn gpu_device(&self) -> Option<&GpuDevice> {
        match self {
            DeviceTensor::Cpu(_) => None,
            DeviceTensor::Gpu(g) => Some(g.device()),
        }
    }

    /// A weight (or any CPU constant) on this tensor's device, in f32.
    fn constant(&self, t: &Tensor) -> Result<GpuTensor> {
        match self {
            DeviceTensor::Gpu(g) => g.device().cached(t),
            DeviceTensor::Cpu(_) => unreachable!("constants are only needed on the GPU"),
        }
    }

    /// The weight of a matrix product on this tensor's device, in the device's precision.
    fn matrix_constant(&self, t: &Tensor) -> Result<GpuTensor> {
        match self {
            DeviceTensor::Gpu(g) => g.device().cached_matrix(t),
            DeviceTensor::Cpu(_) => unreachable!("constants are only needed on the GPU"),
        }
    }

    /// Applies `cpu` or `gpu` by device.
    fn map(
        &self,
        cpu: impl FnOnce(&Tensor) -> Result<Tensor>,
        gpu: impl FnOnce(&GpuTensor) -> Result<GpuTensor>,
    ) -> Result<DeviceTensor> {
        Ok(match self {
            DeviceTensor::Cpu(t) => DeviceTensor::Cpu(cpu(t)?),
            DeviceTensor::Gpu(g) => DeviceTensor::Gpu(gpu(g)?),
        })
    }

    /// Applies `cpu` or `gpu` to two tensors on the same device.
    fn zip(
        &self,
        other: &DeviceTensor,
        cpu: impl FnOnce(&Tensor, &Tensor) -> Result<Tensor>,
        gpu: impl FnOnce(&GpuTensor, &GpuTensor) -> Result<GpuTensor>,
    ) -> Result<DeviceTensor> {
        Ok(match (self, other) {
            (DeviceTensor::Cpu(a), DeviceTensor::Cpu(b)) => DeviceTensor::Cpu(cpu(a, b)?),
            (DeviceTensor::Gpu(a), DeviceTensor::Gpu(b)) => DeviceTensor::Gpu(gpu(a, b)?),
            _ => candle_core::bail!("operands on different devices (CPU and GPU)"),
        })
    }

    // ------------------------------------------------------------------------------- elementwise

    /// Same-shape sum (candle `a + b`).
    pub fn add(&self, other: &DeviceTensor) -> Result<DeviceTensor> {
        self.zip(
            other,
            |a, b| a + b,
            |a, b| {
                if a.dims() != b.dims() {
                    candle_core::bail!("add: shapes {:?} and {:?} differ", a.dims(), b.dims());
                }
                ops::add(a, b)
            },
        )
    }

    pub fn broadcast_add(&self, other: &DeviceTensor) -> Result<DeviceTensor> {
        self.zip(other, |a, b| a.broadcast_add(b), ops::add)
    }

    pub fn broadcast_mul(&self, other: &DeviceTensor) -> Result<DeviceTensor> {
        self.zip(other, |a, b| a.broadcast_mul(b), ops::mul)
    }

    /// `self · s` (candle `t * s`).
    pub fn mul_scalar(&self, s: f64) -> Result<DeviceTensor> {
        self.map(|t| t * s, |g| Ok(ops::affine(g, s as f32, 0.0)))
    }

    /// `self / s` (candle `t / s`).
    pub fn div_scalar(&self, s: f64) -> Result<DeviceTensor> {
        self.map(|t| t / s, |g| Ok(ops::affine(g, (1.0 / s) as f32, 0.0)))
    }

    /// `self + s` (candle `t + s`).
    pub fn add_scalar(&self, s: f64) -> Result<DeviceTensor> {
        self.map(|t| t + s, |g| Ok(ops::affine(g, 1.0, s as f32)))
    }

    /// `self − s` (candle `t - s`).
    pub fn sub_scalar(&self, s: f64) -> Result<DeviceTensor> {
        self.map(|t| t - s, |g| Ok(ops::affine(g, 1.0, -s as f32)))
    }

    /// `self · mul + add` (candle `affine`).
    pub fn affine(&self, mul: f64, add: f64) -> Result<DeviceTensor> {
        self.map(
            |t| t.affine(mul, add),
            |g| Ok(ops::affine(g, mul as f32, add as f32)),
        )
    }

    pub fn relu(&self) -> Result<DeviceTensor> {
        self.map(|t| t.relu(), |g| Ok(ops::relu(g)))
    }

    pub fn tanh(&self) -> Result<DeviceTensor> {
        self.map(|t| t.tanh(), |g| Ok(ops::tanh(g)))
    }

    /// Applies `cpu` on the CPU, or the GPU kernel `gpu` (for activations whose CPU form is a composite).
    pub fn unary_op(
        &self,
        cpu: impl FnOnce(&Tensor) -> Result<Tensor>,
        gpu: fn(&GpuTensor) -> GpuTensor,
    ) -> Result<DeviceTensor> {
        self.map(cpu, |g| Ok(gpu(g)))
    }

    /// `self + t` with broadcasting, `t` a CPU tensor that is uploaded for this call (not cached: masks
    /// and other per-call constants).
    pub fn broadcast_add_tensor(&self, t: &Tensor) -> Result<DeviceTensor> {
        self.map(
            |x| x.broadcast_add(t),
            |g| ops::add(g, &GpuTensor::upload(g.device(), t)?),
        )
    }

    /// A candle-nn activation (the ones diffusers configs name).
    pub fn activation(&self, act: Activation) -> Result<DeviceTensor> {
        self.map(
            |t| candle_core::Module::forward(&act, t),
            |g| match act {
                Activation::Relu => Ok(ops::relu(g)),
                Activation::Silu => Ok(ops::silu(g)),
                Activation::Gelu => Ok(ops::gelu(g)),
                Activation::Mish => Ok(ops::mish(g)),
                other => candle_core::bail!("activation {other:?} has no GPU kernel"),
            },
        )
    }

    // ---------------------------------------------------------------------------- shape and copies

    pub fn reshape(&self, shape: &[usize]) -> Result<DeviceTensor> {
        self.map(|t| t.reshape(shape), |g| g.reshape(shape))
    }

    /// Permuted and made contiguous.
    pub fn permute_contiguous(&self, dims: &[usize]) -> Result<DeviceTensor> {
        self.map(|t| t.permute(dims)?.contiguous(), |g| ops::permute(g, dims))
    }

    /// `narrow(dim, start, len)` (a view on the CPU, a copy on the GPU).
    pub fn narrow(&self, dim: usize, start: usize, len: usize) -> Result<DeviceTensor> {
        self.map(
            |t| t.narrow(dim, start, len),
            |g| ops::narrow(g, dim, start, len),
        )
    }

    /// The slices of `dim` at `indices`, in that order (candle `index_select`).
    pub fn index_select(&self, indices: &[u32], dim: usize) -> Result<DeviceTensor> {
        self.map(
            |t| t.index_select(&Tensor::new(indices, t.device())?, dim),
            |g| ops::index_select(g, indices, dim),
        )
    }

    /// A CPU tensor (a constant, a map from elsewhere) on this tensor's device.
    pub fn same_device(&self, t: &Tensor) -> Result<DeviceTensor> {
        DeviceTensor::on(t, self.gpu_device())
    }

    /// One zero row at the bottom and one zero column at the right (diffusers' `Downsample2D` with
    /// padding 0).
    pub fn pad_bottom_right_with_zeros(&self) -> Result<DeviceTensor> {
        self.map(
            |t| {
                t.pad_with_zeros(candle_core::D::Minus1, 0, 1)?
                    .pad_with_zeros(candle_core::D::Minus2, 0, 1)
            },
            |g| ops::pad_bottom_right(g, 1, 1),
        )
    }

    pub fn upsample_nearest2d(&self, out_h: usize, out_w: usize) -> Result<DeviceTensor> {
        self.map(
            |t| t.upsample_nearest2d(out_h, out_w),
            |g| ops::upsample_nearest2d(g, out_h, out_w),
        )
    }

    pub fn cat(parts: &[&DeviceTensor], dim: usize) -> Result<DeviceTensor> {
        if let Some(cpu) = parts
            .iter()
            .map(|p| match p {
                DeviceTensor::Cpu(t) => Some(t),
                DeviceTensor::Gpu(_) => None,
            })
            .collect::<Option<Vec<&Tensor>>>()
        {
            return Ok(DeviceTensor::Cpu(Tensor::cat(&cpu, dim)?));
        }
        let gpu = parts
            .iter()
            .map(|p| match p {
                DeviceTensor::Gpu(g) => Ok(g),
                DeviceTensor::Cpu(_) => candle_core::bail!("cat: operands on different devices"),
            })
            .collect::<Result<Vec<&GpuTensor>>>()?;
        Ok(DeviceTensor::Gpu(ops::cat(&gpu, dim)?))
    }

    // ------------------------------------------------------------------------ the `kernels` ops

    /// [`super::conv2d`] on either device.
    pub fn conv2d(
        &self,
        weight: &Tensor,
        bias: Option<&Tensor>,
        stride: usize,
        padding: usize,
    ) -> Result<DeviceTensor> {
        self.map(
            |t| super::conv2d(t, weight, bias, stride, padding),
            |g| {
                let bias = bias.map(|b| self.constant(b)).transpose()?;
                ops::conv2d(
                    g,
                    &self.matrix_constant(weight)?,
                    bias.as_ref(),
                    stride,
                    padding,
                )
            },
        )
    }

    /// A linear layer `x·weightᵀ + bias` (candle-nn `Linear`).
    pub fn linear(&self, layer: &candle_nn::Linear) -> Result<DeviceTensor> {
        self.map(
            |t| candle_core::Module::forward(layer, t),
            |g| {
                let bias = layer.bias().map(|b| self.constant(b)).transpose()?;
                ops::linear(g, &self.matrix_constant(layer.weight())?, bias.as_ref())
            },
        )
    }

    /// [`super::group_norm`] on either device.
    pub fn group_norm(
        &self,
        weight: &Tensor,
        bias: &Tensor,
        groups: usize,
        eps: f64,
        silu: bool,
    ) -> Result<DeviceTensor> {
        self.map(
            |t| super::group_norm(t, weight, bias, groups, eps, silu),
            |g| {
                ops::group_norm(
                    g,
                    &self.constant(weight)?,
                    &self.constant(bias)?,
                    groups,
                    eps,
                    silu,
                )
            },
        )
    }

    /// [`super::layer_norm`] on either device.
    pub fn layer_norm(&self, weight: &Tensor, bias: &Tensor, eps: f64) -> Result<DeviceTensor> {
        self.map(
            |t| super::layer_norm(t, weight, bias, eps),
            |g| ops::layer_norm(g, &self.constant(weight)?, &self.constant(bias)?, eps),
        )
    }

    /// [`super::softmax_last_dim`] on either device.
    pub fn softmax_last_dim(&self) -> Result<DeviceTensor> {
        self.map(super::softmax_last_dim, ops::softmax_last_dim)
    }

    /// [`super::geglu`] on either device.
    pub fn geglu(&self) -> Result<DeviceTensor> {
        self.map(super::geglu, ops::geglu)
    }

    /// `self × otherᵀ` over the last two dimensions (candle `a.matmul(&b.t()?)`).
    pub fn matmul_t(&self, other: &DeviceTensor) -> Result<DeviceTensor> {
        self.zip(
            other,
            |a, b| a.matmul(&b.t()?),
            |a, b| ops::matmul_scaled(a, b, true, 1.0),
        )
    }

    /// Batched matrix product (candle `matmul`).
    pub fn matmul(&self, other: &DeviceTensor) -> Result<DeviceTensor> {
        self.zip(other, |a, b| a.matmul(b), ops::matmul)
    }

    /// [`super::attention`] on either device (flash-style on the GPU: no probability matrix).
    pub fn attention(
        q: &DeviceTensor,
        k: &DeviceTensor,
        v: &DeviceTensor,
        scale: f64,
    ) -> Result<DeviceTensor> {
        match (q, k, v) {
            (DeviceTensor::Cpu(q), DeviceTensor::Cpu(k), DeviceTensor::Cpu(v)) => {
                Ok(DeviceTensor::Cpu(super::attention(q, k, v, scale)?))
            }
            (DeviceTensor::Gpu(q), DeviceTensor::Gpu(k), DeviceTensor::Gpu(v)) => {
                Ok(DeviceTensor::Gpu(ops::attention(q, k, v, scale)?))
            }
            _ => candle_core::bail!("attention: operands on different devices"),
        }
    }
}

#[cfg(test)]
mod tests {
    use candle_core::{Device, Tensor};

    use super::super::gpu::testing::device_or_skip;
    use super::*;

    #[test]
    fn cpu_branch_is_the_candle_call() {
        let x = Tensor::randn(0f32, 1.0, (2, 3, 4, 5), &Device::Cpu).unwrap();
        let w = Tensor::randn(0f32, 1.0, (6, 3, 3, 3), &Device::Cpu).unwrap();
        let got = DeviceTensor::Cpu(x.clone())
            .conv2d(&w, None, 1, 1)
            .unwrap()
            .to_cpu()
            .unwrap();
        let want = super::super::conv2d(&x, &w, None, 1, 1).unwrap();
        assert_eq!(
            got.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
            want.flatten_all().unwrap().to_vec1::<f32>().unwrap()
        );
    }

    #[test]
    fn weights_are_uploaded_once_and_mixed_devices_are_an_error() {
        let Some(dev) = device_or_skip() else {
            return;
        };
        let w = Tensor::randn(0f32, 1.0, (4, 4), &Device::Cpu).unwrap();
        let a = dev.cached(&w).unwrap();
        let b = dev.cached(&w).unwrap();
        assert!(a.same_buffer(&b));
        let x = DeviceTensor::on(&w, Some(&dev)).unwrap();
        let err = x
            .add(&DeviceTensor::Cpu(w.clone()))
            .unwrap_err()
            .to_string();
        assert!(err.contains("different devices"), "{err}");
    }
}
