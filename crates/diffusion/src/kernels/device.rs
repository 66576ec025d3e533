//! The diffusion engine's device seam: where a network runs is decided here and nowhere else.
//!
//! - [`Device`]: the CPU or an opened GPU; the networks' entry points take `&Device`.
//! - [`Storage`]: every op a network needs, declared once; one implementation per backend — candle tensors
//!   on the CPU (`kernels/cpu.rs`: each op is the very candle call or `kernels` function the networks
//!   made before, so CPU results and speed are unchanged) and CubeCL tensors on the GPU
//!   (`kernels/gpu/storage.rs`, one kernel per op, tested against the CPU on lavapipe).
//! - [`DeviceTensor`]: the activation a forward passes from layer to layer, one variant per backend; each of
//!   its ops only dispatches to the variant's [`Storage`].
//!
//! Adding a backend: implement [`Storage`] for its tensor type, add a variant to [`Device`] and
//! [`DeviceTensor`], and one arm to the `dispatch!`/`dispatch2!` macros below. Network code is unchanged.
//!
//! Weights stay CPU candle tensors in the network structs; a backend fetches its device copy when an op
//! uses one (the GPU keeps them in [`GpuDevice::cached`]). One network definition thus runs anywhere.

use candle_core::{Result, Tensor};
use candle_nn::Activation;

use super::gpu::{GpuDevice, GpuTensor};
use gpu::F32Buffer;

/// Where a network runs.
#[derive(Debug, Clone, Default)]
pub enum Device {
    #[default]
    Cpu,
    /// An opened GPU, with its weight cache (shared by clones).
    Gpu(GpuDevice),
}

impl Device {
    /// `t` on this device: uploaded to the GPU, or kept as is on the CPU.
    pub fn tensor(&self, t: &Tensor) -> Result<DeviceTensor> {
        Ok(match self {
            Device::Cpu => DeviceTensor::Cpu(t.clone()),
            Device::Gpu(device) => DeviceTensor::Gpu(GpuTensor::upload(device, t)?),
        })
    }

    /// Whether this is a GPU.
    pub fn is_gpu(&self) -> bool {
        matches!(self, Device::Gpu(_))
    }

    /// The GPU, for callers that manage its memory or weight cache (`None` on the CPU).
    pub fn gpu(&self) -> Option<&GpuDevice> {
        match self {
            Device::Cpu => None,
            Device::Gpu(device) => Some(device),
        }
    }

    /// "CPU" and its products' precision, or the adapter and the weights' precision, for logs and
    /// run.json.
    pub fn describe(&self) -> String {
        match self {
            Device::Cpu => format!("CPU, {}", super::cpu_precision().describe()),
            Device::Gpu(gpu) => {
                format!("{}, {} weights", gpu.context().describe(), gpu.precision())
            }
        }
    }
}

impl From<Option<GpuDevice>> for Device {
    fn from(gpu: Option<GpuDevice>) -> Self {
        gpu.map_or(Device::Cpu, Device::Gpu)
    }
}

/// The activation functions with a kernel of their own (beside candle-nn's [`Activation`]s).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Unary {
    Relu,
    Silu,
    Tanh,
    /// Exact (erf) GELU.
    GeluErf,
    /// tanh-approximated GELU.
    GeluTanh,
    /// `x·σ(1.702·x)` (CLIP ViT-L).
    QuickGelu,
}

/// What a convolution adds to its output besides its bias. A backend may add it in the pass that adds
/// the bias (the GPU does: one pass over the output instead of two).
#[derive(Debug)]
pub enum Addend<'a, T> {
    None,
    /// [batch, out channels, h, w]: a skip connection.
    Residual(&'a T),
    /// [batch, out channels]: one value per image and channel (a ResNet's time embedding).
    PerChannel(&'a T),
}

impl<'a, T> Addend<'a, T> {
    /// The added tensor, if any.
    fn term(self) -> Option<&'a T> {
        match self {
            Addend::None => None,
            Addend::Residual(t) | Addend::PerChannel(t) => Some(t),
        }
    }

    /// The same kind of addend with `u` as its tensor (a backend's own tensor for the dispatched one).
    fn with<U>(self, u: &U) -> Addend<'_, U> {
        match self {
            Addend::None => Addend::None,
            Addend::Residual(_) => Addend::Residual(u),
            Addend::PerChannel(_) => Addend::PerChannel(u),
        }
    }
}

impl<T> Clone for Addend<'_, T> {
    fn clone(&self) -> Self {
        *self
    }
}
impl<T> Copy for Addend<'_, T> {}

/// The ops of a network, declared once, implemented once per backend. Shapes are validated by each
/// implementation; operands of the binary ops are on the same device (the dispatch checks that).
pub trait Storage: Sized {
    fn dims(&self) -> &[usize];
    /// The values as a CPU tensor (a read-back from a device).
    fn to_cpu(&self) -> Result<Tensor>;

    /// Same-shape sum.
    fn add(&self, other: &Self) -> Result<Self>;
    fn broadcast_add(&self, other: &Self) -> Result<Self>;
    fn broadcast_mul(&self, other: &Self) -> Result<Self>;
    /// `self + t` with broadcasting, `t` a host tensor used once (masks and other per-call constants; not
    /// cached on a device).
    fn broadcast_add_host(&self, t: &Tensor) -> Result<Self>;
    /// `self · mul + add`.
    fn affine(&self, mul: f64, add: f64) -> Result<Self>;
    fn unary(&self, op: Unary) -> Result<Self>;
    /// A candle-nn activation (the ones diffusers configs name).
    fn activation(&self, act: Activation) -> Result<Self>;

    fn reshape(&self, shape: &[usize]) -> Result<Self>;
    /// Permuted and made contiguous.
    fn permute_contiguous(&self, dims: &[usize]) -> Result<Self>;
    fn narrow(&self, dim: usize, start: usize, len: usize) -> Result<Self>;
    /// `narrow(dim, start, len)`, permuted and made contiguous, in one copy.
    fn narrow_permute(&self, dim: usize, start: usize, len: usize, dims: &[usize]) -> Result<Self>;
    /// The slices of `dim` at `indices`, in that order.
    fn index_select(&self, indices: &[u32], dim: usize) -> Result<Self>;
    /// One zero row at the bottom and one zero column at the right.
    fn pad_bottom_right_with_zeros(&self) -> Result<Self>;
    fn upsample_nearest2d(&self, out_h: usize, out_w: usize) -> Result<Self>;
    fn cat(parts: &[&Self], dim: usize) -> Result<Self>;

    /// [`super::conv2d`] (NCHW, OIHW weights), plus `addend`.
    fn conv2d(
        &self,
        weight: &Tensor,
        bias: Option<&Tensor>,
        stride: usize,
        padding: usize,
        addend: Addend<'_, Self>,
    ) -> Result<Self>;
    /// `x·weightᵀ + bias` (candle-nn `Linear`), plus `residual` (of the output's shape).
    fn linear(&self, layer: &candle_nn::Linear, residual: Option<&Self>) -> Result<Self>;
    /// [`super::group_norm`], SiLU fused when `silu`.
    fn group_norm(
        &self,
        weight: &Tensor,
        bias: &Tensor,
        groups: usize,
        eps: f64,
        silu: bool,
    ) -> Result<Self>;
    /// [`super::layer_norm`] over the last dimension.
    fn layer_norm(&self, weight: &Tensor, bias: &Tensor, eps: f64) -> Result<Self>;
    fn softmax_last_dim(&self) -> Result<Self>;
    /// `super::geglu` (the last dimension split in value and gate halves).
    fn geglu(&self) -> Result<Self>;
    /// `self × otherᵀ` over the last two dimensions.
    fn matmul_t(&self, other: &Self) -> Result<Self>;
    /// Batched matrix product.
    fn matmul(&self, other: &Self) -> Result<Self>;
    /// `softmax(q·kᵀ·scale)·v` (`super::attention`).
    fn attention(q: &Self, k: &Self, v: &Self, scale: f64) -> Result<Self>;

    /// [`super::vgg::max_pool2x2`] (NCHW, 2×2, stride 2, floor mode).
    fn max_pool2x2(&self) -> Result<Self>;
    /// [`super::vgg::max_pool2x2_backward`]; `self` is the pool's input.
    fn max_pool2x2_backward(&self, grad: &Self) -> Result<Self>;
    /// [`super::vgg::relu_backward`]; `self` is the ReLU's output.
    fn relu_backward(&self, grad: &Self) -> Result<Self>;
    /// [`super::vgg::normalize_channels`].
    fn normalize_channels(&self, eps: f32) -> Result<Self>;
    /// [`super::vgg::lpips_distance`]; `self` holds the features, `lin` the tap's channel weights.
    fn lpips_distance(
        &self,
        target: &Self,
        lin: &Tensor,
        eps: f32,
        with_grad: bool,
    ) -> Result<(Self, Option<Self>)>;
}

/// A tensor on one of the backends.
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

/// `$op` on the backend of `$x` (the one place a unary op meets the variants).
macro_rules! dispatch {
    ($x:expr, $t:ident => $op:expr) => {
        match $x {
            DeviceTensor::Cpu($t) => DeviceTensor::Cpu($op?),
            DeviceTensor::Gpu($t) => DeviceTensor::Gpu($op?),
        }
    };
}

/// `$op` on the common backend of `$a` and `$b`; an error when they differ.
macro_rules! dispatch2 {
    ($a:expr, $b:expr, ($x:ident, $y:ident) => $op:expr) => {
        match ($a, $b) {
            (DeviceTensor::Cpu($x), DeviceTensor::Cpu($y)) => DeviceTensor::Cpu($op?),
            (DeviceTensor::Gpu($x), DeviceTensor::Gpu($y)) => DeviceTensor::Gpu($op?),
            _ => candle_core::bail!("operands on different devices (CPU and GPU)"),
        }
    };
}

/// The operands of `parts` if all are on the backend `$variant`.
macro_rules! all_on {
    ($parts:expr, $variant:path) => {
        $parts
            .iter()
            .map(|p| match p {
                $variant(t) => Some(t),
                _ => None,
            })
            .collect::<Option<Vec<_>>>()
    };
}

impl DeviceTensor {
    /// An f32 tensor of `shape` over values another engine made on `device`'s GPU (the splatting
    /// engine's render); an error on the CPU or when the buffer holds another number of values.
    pub fn from_gpu_buffer(device: &Device, buffer: F32Buffer, shape: Vec<usize>) -> Result<Self> {
        match device {
            Device::Gpu(gpu) => Ok(DeviceTensor::Gpu(GpuTensor::from_buffer(
                gpu, buffer, shape,
            )?)),
            Device::Cpu => candle_core::bail!("a GPU buffer handed to networks on the CPU"),
        }
    }

    /// The values as a buffer another engine on the same GPU can take; an error for a CPU tensor.
    pub fn into_gpu_buffer(self) -> Result<F32Buffer> {
        match self {
            DeviceTensor::Gpu(t) => t.into_buffer(),
            DeviceTensor::Cpu(t) => {
                candle_core::bail!("a CPU tensor {:?} is not a GPU buffer", t.dims())
            }
        }
    }

    /// A host tensor (a constant, a map from elsewhere) on this tensor's device.
    pub fn same_device(&self, t: &Tensor) -> Result<DeviceTensor> {
        match self {
            DeviceTensor::Cpu(_) => Ok(DeviceTensor::Cpu(t.clone())),
            DeviceTensor::Gpu(g) => Ok(DeviceTensor::Gpu(GpuTensor::upload(g.device(), t)?)),
        }
    }

    pub fn to_cpu(&self) -> Result<Tensor> {
        match self {
            DeviceTensor::Cpu(t) => Storage::to_cpu(t),
            DeviceTensor::Gpu(g) => Storage::to_cpu(g),
        }
    }

    pub fn dims(&self) -> &[usize] {
        match self {
            DeviceTensor::Cpu(t) => Storage::dims(t),
            DeviceTensor::Gpu(g) => Storage::dims(g),
        }
    }

    pub fn dims4(&self) -> Result<(usize, usize, usize, usize)> {
        match self.dims() {
            &[a, b, c, d] => Ok((a, b, c, d)),
            other => candle_core::bail!("expected a 4D tensor, got {other:?}"),
        }
    }

    // ------------------------------------------------------------------------------- elementwise

    /// Same-shape sum (candle `a + b`).
    pub fn add(&self, other: &DeviceTensor) -> Result<DeviceTensor> {
        Ok(dispatch2!(self, other, (a, b) => Storage::add(a, b)))
    }

    pub fn broadcast_add(&self, other: &DeviceTensor) -> Result<DeviceTensor> {
        Ok(dispatch2!(self, other, (a, b) => Storage::broadcast_add(a, b)))
    }

    pub fn broadcast_mul(&self, other: &DeviceTensor) -> Result<DeviceTensor> {
        Ok(dispatch2!(self, other, (a, b) => Storage::broadcast_mul(a, b)))
    }

    /// `self + t` with broadcasting, `t` a CPU tensor used for this call only (not cached: masks and other
    /// per-call constants).
    pub fn broadcast_add_tensor(&self, t: &Tensor) -> Result<DeviceTensor> {
        Ok(dispatch!(self, x => Storage::broadcast_add_host(x, t)))
    }

    /// `self · mul + add` (candle `affine`; candle's scalar `*`, `/`, `+`, `-` are this affine too).
    pub fn affine(&self, mul: f64, add: f64) -> Result<DeviceTensor> {
        Ok(dispatch!(self, x => Storage::affine(x, mul, add)))
    }

    /// `self · s` (candle `t * s`).
    pub fn mul_scalar(&self, s: f64) -> Result<DeviceTensor> {
        self.affine(s, 0.0)
    }

    /// `self / s` (candle `t / s`).
    pub fn div_scalar(&self, s: f64) -> Result<DeviceTensor> {
        self.affine(1.0 / s, 0.0)
    }

    /// `self + s` (candle `t + s`).
    pub fn add_scalar(&self, s: f64) -> Result<DeviceTensor> {
        self.affine(1.0, s)
    }

    /// `self − s` (candle `t - s`).
    pub fn sub_scalar(&self, s: f64) -> Result<DeviceTensor> {
        self.affine(1.0, -s)
    }

    pub fn unary(&self, op: Unary) -> Result<DeviceTensor> {
        Ok(dispatch!(self, x => Storage::unary(x, op)))
    }

    pub fn relu(&self) -> Result<DeviceTensor> {
        self.unary(Unary::Relu)
    }

    pub fn tanh(&self) -> Result<DeviceTensor> {
        self.unary(Unary::Tanh)
    }

    /// A candle-nn activation (the ones diffusers configs name).
    pub fn activation(&self, act: Activation) -> Result<DeviceTensor> {
        Ok(dispatch!(self, x => Storage::activation(x, act)))
    }

    // ---------------------------------------------------------------------------- shape and copies

    pub fn reshape(&self, shape: &[usize]) -> Result<DeviceTensor> {
        Ok(dispatch!(self, x => Storage::reshape(x, shape)))
    }

    /// Permuted and made contiguous.
    pub fn permute_contiguous(&self, dims: &[usize]) -> Result<DeviceTensor> {
        Ok(dispatch!(self, x => Storage::permute_contiguous(x, dims)))
    }

    /// `narrow(dim, start, len)` (a view on the CPU, a copy on the GPU).
    pub fn narrow(&self, dim: usize, start: usize, len: usize) -> Result<DeviceTensor> {
        Ok(dispatch!(self, x => Storage::narrow(x, dim, start, len)))
    }

    /// `narrow(dim, start, len)` permuted by `dims` and made contiguous, in one copy (a part of a fused
    /// projection taken out head-major).
    pub fn narrow_permute(
        &self,
        dim: usize,
        start: usize,
        len: usize,
        dims: &[usize],
    ) -> Result<DeviceTensor> {
        Ok(dispatch!(self, x => Storage::narrow_permute(x, dim, start, len, dims)))
    }

    /// The slices of `dim` at `indices`, in that order (candle `index_select`).
    pub fn index_select(&self, indices: &[u32], dim: usize) -> Result<DeviceTensor> {
        Ok(dispatch!(self, x => Storage::index_select(x, indices, dim)))
    }

    /// One zero row at the bottom and one zero column at the right (diffusers' `Downsample2D` with
    /// padding 0).
    pub fn pad_bottom_right_with_zeros(&self) -> Result<DeviceTensor> {
        Ok(dispatch!(self, x => Storage::pad_bottom_right_with_zeros(x)))
    }

    pub fn upsample_nearest2d(&self, out_h: usize, out_w: usize) -> Result<DeviceTensor> {
        Ok(dispatch!(self, x => Storage::upsample_nearest2d(x, out_h, out_w)))
    }

    pub fn cat(parts: &[&DeviceTensor], dim: usize) -> Result<DeviceTensor> {
        if let Some(cpu) = all_on!(parts, DeviceTensor::Cpu) {
            return Ok(DeviceTensor::Cpu(Storage::cat(&cpu, dim)?));
        }
        if let Some(gpu) = all_on!(parts, DeviceTensor::Gpu) {
            return Ok(DeviceTensor::Gpu(Storage::cat(&gpu, dim)?));
        }
        candle_core::bail!("cat: operands on different devices")
    }

    // ------------------------------------------------------------------------ the `kernels` ops

    /// [`super::conv2d`] on the tensor's device.
    pub fn conv2d(
        &self,
        weight: &Tensor,
        bias: Option<&Tensor>,
        stride: usize,
        padding: usize,
    ) -> Result<DeviceTensor> {
        self.conv2d_add(weight, bias, stride, padding, Addend::None)
    }

    /// [`Self::conv2d`] plus `addend` (on the same device).
    pub fn conv2d_add(
        &self,
        weight: &Tensor,
        bias: Option<&Tensor>,
        stride: usize,
        padding: usize,
        addend: Addend<'_, DeviceTensor>,
    ) -> Result<DeviceTensor> {
        let Some(term) = addend.term() else {
            return Ok(
                dispatch!(self, x => Storage::conv2d(x, weight, bias, stride, padding, Addend::None)),
            );
        };
        Ok(dispatch2!(self, term, (x, t) =>
            Storage::conv2d(x, weight, bias, stride, padding, addend.with(t))))
    }

    /// A linear layer `x·weightᵀ + bias` (candle-nn `Linear`).
    pub fn linear(&self, layer: &candle_nn::Linear) -> Result<DeviceTensor> {
        Ok(dispatch!(self, x => Storage::linear(x, layer, None)))
    }

    /// [`Self::linear`] plus `residual` (of the output's shape, on the same device): a skip connection
    /// added in the bias's pass.
    pub fn linear_add(
        &self,
        layer: &candle_nn::Linear,
        residual: &DeviceTensor,
    ) -> Result<DeviceTensor> {
        Ok(dispatch2!(self, residual, (x, r) => Storage::linear(x, layer, Some(r))))
    }

    /// [`super::group_norm`] on the tensor's device.
    pub fn group_norm(
        &self,
        weight: &Tensor,
        bias: &Tensor,
        groups: usize,
        eps: f64,
        silu: bool,
    ) -> Result<DeviceTensor> {
        Ok(dispatch!(self, x => Storage::group_norm(x, weight, bias, groups, eps, silu)))
    }

    /// [`super::layer_norm`] on the tensor's device.
    pub fn layer_norm(&self, weight: &Tensor, bias: &Tensor, eps: f64) -> Result<DeviceTensor> {
        Ok(dispatch!(self, x => Storage::layer_norm(x, weight, bias, eps)))
    }

    /// [`super::softmax_last_dim`] on the tensor's device.
    pub fn softmax_last_dim(&self) -> Result<DeviceTensor> {
        Ok(dispatch!(self, x => Storage::softmax_last_dim(x)))
    }

    /// `super::geglu` on the tensor's device.
    pub fn geglu(&self) -> Result<DeviceTensor> {
        Ok(dispatch!(self, x => Storage::geglu(x)))
    }

    /// `self × otherᵀ` over the last two dimensions (candle `a.matmul(&b.t()?)`).
    pub fn matmul_t(&self, other: &DeviceTensor) -> Result<DeviceTensor> {
        Ok(dispatch2!(self, other, (a, b) => Storage::matmul_t(a, b)))
    }

    /// Batched matrix product (candle `matmul`).
    pub fn matmul(&self, other: &DeviceTensor) -> Result<DeviceTensor> {
        Ok(dispatch2!(self, other, (a, b) => Storage::matmul(a, b)))
    }

    /// `super::attention` on the operands' device (on the GPU, `ops::attention`'s path).
    pub fn attention(
        q: &DeviceTensor,
        k: &DeviceTensor,
        v: &DeviceTensor,
        scale: f64,
    ) -> Result<DeviceTensor> {
        Ok(match (q, k, v) {
            (DeviceTensor::Cpu(q), DeviceTensor::Cpu(k), DeviceTensor::Cpu(v)) => {
                DeviceTensor::Cpu(Storage::attention(q, k, v, scale)?)
            }
            (DeviceTensor::Gpu(q), DeviceTensor::Gpu(k), DeviceTensor::Gpu(v)) => {
                DeviceTensor::Gpu(Storage::attention(q, k, v, scale)?)
            }
            _ => candle_core::bail!("attention: operands on different devices"),
        })
    }

    // --------------------------------------------------------------- VGG feature-loss ops (LPIPS)

    /// 2×2 max-pool, stride 2, floor mode ([`super::vgg::max_pool2x2`]).
    pub fn max_pool2x2(&self) -> Result<DeviceTensor> {
        Ok(dispatch!(self, x => Storage::max_pool2x2(x)))
    }

    /// The input gradient of [`DeviceTensor::max_pool2x2`]; `self` is the pool's input.
    pub fn max_pool2x2_backward(&self, grad: &DeviceTensor) -> Result<DeviceTensor> {
        Ok(dispatch2!(self, grad, (x, g) => Storage::max_pool2x2_backward(x, g)))
    }

    /// A ReLU's input gradient; `self` is the ReLU's output.
    pub fn relu_backward(&self, grad: &DeviceTensor) -> Result<DeviceTensor> {
        Ok(dispatch2!(self, grad, (out, g) => Storage::relu_backward(out, g)))
    }

    /// `f / (‖f‖ + eps)` over the channels of each pixel ([`super::vgg::normalize_channels`]).
    pub fn normalize_channels(&self, eps: f32) -> Result<DeviceTensor> {
        Ok(dispatch!(self, x => Storage::normalize_channels(x, eps)))
    }

    /// The LPIPS distance of one tap per pixel, [N, 1, H, W], and with `with_grad` the gradient of its
    /// spatial mean with respect to `self` ([`super::vgg::lpips_distance`]).
    pub fn lpips_distance(
        &self,
        target: &DeviceTensor,
        lin: &Tensor,
        eps: f32,
        with_grad: bool,
    ) -> Result<(DeviceTensor, Option<DeviceTensor>)> {
        Ok(match (self, target) {
            (DeviceTensor::Cpu(f), DeviceTensor::Cpu(t)) => {
                let (map, grad) = Storage::lpips_distance(f, t, lin, eps, with_grad)?;
                (DeviceTensor::Cpu(map), grad.map(DeviceTensor::Cpu))
            }
            (DeviceTensor::Gpu(f), DeviceTensor::Gpu(t)) => {
                let (map, grad) = Storage::lpips_distance(f, t, lin, eps, with_grad)?;
                (DeviceTensor::Gpu(map), grad.map(DeviceTensor::Gpu))
            }
            _ => candle_core::bail!("lpips_distance: operands on different devices"),
        })
    }
}

#[cfg(test)]
mod tests {
    use candle_core::Tensor;

    use super::super::gpu::testing::device_or_skip;
    use super::*;

    #[test]
    fn cpu_branch_is_the_candle_call() {
        let x = Tensor::randn(0f32, 1.0, (2, 3, 4, 5), &candle_core::Device::Cpu).unwrap();
        let w = Tensor::randn(0f32, 1.0, (6, 3, 3, 3), &candle_core::Device::Cpu).unwrap();
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
        let w = Tensor::randn(0f32, 1.0, (4, 4), &candle_core::Device::Cpu).unwrap();
        let a = dev.cached(&w).unwrap();
        let b = dev.cached(&w).unwrap();
        assert!(a.same_buffer(&b));
        let x = Device::Gpu(dev.clone()).tensor(&w).unwrap();
        let err = x
            .add(&DeviceTensor::Cpu(w.clone()))
            .unwrap_err()
            .to_string();
        assert!(err.contains("different devices"), "{err}");
    }
}
