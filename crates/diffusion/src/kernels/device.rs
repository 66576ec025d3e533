//! The diffusion engine's device seam: where a network runs is decided here and nowhere else.
//!
//! - [`Device`]: the CPU or an opened GPU; the networks' entry points take `&Device`.
//! - [`Storage`]: every op a network needs, declared once in one list ([`seam_ops!`]) with its one-line
//!   body per backend — candle tensors on the CPU (each op the very candle call or `kernels` function
//!   the networks made before, so CPU results and speed are unchanged; longer bodies in
//!   `kernels/cpu.rs`) and CubeCL tensors on the GPU (one kernel per op in [`ops`], tested against
//!   the CPU on lavapipe; longer bodies in `kernels/gpu/storage.rs`). A feature's own ops extend it
//!   beside their CPU bodies (LPIPS's VGG ops: `kernels::vgg::VggStorage`).
//! - [`DeviceTensor`]: the activation a forward passes from layer to layer, one variant per backend; each
//!   op of the lists gets its method, which dispatches to the variant's backend.
//!
//! Adding an op: one line in a list (its signature and the body on each backend), its CPU body where it
//! is more than a candle call, its GPU kernel and launcher in the family's file of `kernels/gpu/`
//! (tested there against the CPU). docs/layout.md walks through an example.
//!
//! Adding a backend: one more `impl` in [`seam_ops!`], a variant of [`Device`] and [`DeviceTensor`], and
//! one arm of the `dispatch!`/`dispatch2!` macros below. Network code is unchanged.
//!
//! Weights stay on the host in the network structs (products' weights as [`ProductWeight`]s: f32
//! tensors, or bf16 pairs only for a model loaded for bf16 products on the CPU); a backend fetches its
//! device copy when an op uses one (the GPU keeps them in [`GpuDevice::cached`]). One network
//! definition thus runs anywhere.

use candle_core::{Module, Result, Tensor, D};
use candle_nn::Activation;

use super::cpu as on_cpu;
use super::gpu::storage as on_gpu;
use super::gpu::{ops, GpuDevice, GpuTensor};
use gpu::{F32Buffer, F32Values};

pub use super::op_args::{Addend, Unary};
use super::{Linear, ProductWeight};

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

/// Declares ops of the seam once: a trait with one method per op, its implementation for each backend
/// (the CPU's [`Tensor`], the GPU's [`GpuTensor`]) from the op's one-line body per backend, and the
/// [`DeviceTensor`] method that dispatches to them. Used here for the core [`Storage`] and beside a
/// feature's own ops for its extension trait (`kernels::vgg::VggStorage`).
///
/// Each op reads `KIND fn NAME(PARAMETERS) [-> RETURN] => cpu EXPRESSION, gpu EXPRESSION;`, the
/// expressions the op's body on each backend (`self` the backend's tensor). KIND is one of
/// - `unary`: `self` is the only device tensor; returns `Result<Self>`; the forward runs the op on
///   `self`'s backend;
/// - `binary`: the parameter after `self` is a second device tensor (`other: &Self`); the forward fails
///   when the two are on different devices;
/// - `special`: any signature, RETURN written out; its [`DeviceTensor`] method is written by hand.
///
/// A new backend is one more `impl` in this macro (and a variant of [`Device`], [`DeviceTensor`] and the
/// `dispatch!` macros); the lists of ops are unchanged.
macro_rules! seam_ops {
    (
        $(#[$trait_meta:meta])*
        $vis:vis trait $Trait:ident $(: $Super:ident)? {
            $(
                $(#[$meta:meta])*
                $kind:ident fn $name:ident $params:tt $(-> $ret:ty)?
                    => cpu $cpu:expr, gpu $gpu:expr;
            )*
        }
    ) => {
        $(#[$trait_meta])*
        $vis trait $Trait: Sized $(+ $Super)? {
            $($crate::kernels::device::seam_op!(
                @decl $kind, $(#[$meta])* $name $params $(-> $ret)?
            );)*
        }

        impl $Trait for candle_core::Tensor {
            $($crate::kernels::device::seam_op!(@body $kind, $name $params $(-> $ret)?, $cpu);)*
        }

        impl $Trait for $crate::kernels::gpu::GpuTensor {
            $($crate::kernels::device::seam_op!(@body $kind, $name $params $(-> $ret)?, $gpu);)*
        }

        impl $crate::kernels::device::DeviceTensor {
            $($crate::kernels::device::seam_op!(
                @forward $Trait, $kind, $(#[$meta])* $name $params
            );)*
        }
    };
}
pub(crate) use seam_ops;

/// One op of [`seam_ops!`]: its trait method (`@decl`), a backend's body (`@body`), its
/// [`DeviceTensor`] forward (`@forward`).
macro_rules! seam_op {
    (@decl special, $(#[$meta:meta])* $name:ident $params:tt -> $ret:ty) => {
        $(#[$meta])*
        fn $name $params -> $ret;
    };
    (@decl $kind:ident, $(#[$meta:meta])* $name:ident $params:tt) => {
        $(#[$meta])*
        fn $name $params -> candle_core::Result<Self>;
    };
    (@body special, $name:ident $params:tt -> $ret:ty, $body:expr) => {
        fn $name $params -> $ret {
            $body
        }
    };
    (@body $kind:ident, $name:ident $params:tt, $body:expr) => {
        fn $name $params -> candle_core::Result<Self> {
            $body
        }
    };
    (@forward $Trait:ident, unary, $(#[$meta:meta])* $name:ident
        (&$s:ident $(, $a:ident: $t:ty)* $(,)?)) => {
        $(#[$meta])*
        pub fn $name(
            &self
            $(, $a: $t)*
        ) -> candle_core::Result<$crate::kernels::device::DeviceTensor> {
            Ok($crate::kernels::device::dispatch!(self, x => $Trait::$name(x $(, $a)*)))
        }
    };
    (@forward $Trait:ident, binary, $(#[$meta:meta])* $name:ident
        (&$s:ident, $other:ident: &Self $(, $a:ident: $t:ty)* $(,)?)) => {
        $(#[$meta])*
        pub fn $name(
            &self,
            $other: &$crate::kernels::device::DeviceTensor
            $(, $a: $t)*
        ) -> candle_core::Result<$crate::kernels::device::DeviceTensor> {
            Ok($crate::kernels::device::dispatch2!(
                self, $other, (x, y) => $Trait::$name(x, y $(, $a)*)
            ))
        }
    };
    (@forward $Trait:ident, special, $($signature:tt)*) => {};
}
pub(crate) use seam_op;

seam_ops! {
    /// The ops of a network, each declared once, here, with its body on each backend: on the CPU the
    /// candle call or `kernels` function the networks made before the seam existed (so CPU results and
    /// speed are those of plain candle code), on the GPU its CubeCL op ([`ops`], tested against
    /// the CPU on lavapipe). Shapes are validated by each backend; operands of the binary ops are on
    /// the same device (the dispatch checks that).
    pub trait Storage {
        special fn dims(&self) -> &[usize] => cpu Tensor::dims(self), gpu GpuTensor::dims(self);
        /// The values as a CPU tensor (a read-back from a device).
        special fn to_cpu(&self) -> Result<Tensor>
            => cpu Ok(self.clone()), gpu GpuTensor::to_cpu(self);

        // ------------------------------------------------------------------------------ elementwise
        /// Same-shape sum (candle `a + b`).
        binary fn add(&self, other: &Self)
            => cpu self + other, gpu on_gpu::same_shape_add(self, other);
        binary fn broadcast_add(&self, other: &Self)
            => cpu Tensor::broadcast_add(self, other), gpu ops::add(self, other);
        binary fn broadcast_mul(&self, other: &Self)
            => cpu Tensor::broadcast_mul(self, other), gpu ops::mul(self, other);
        /// `self + t` with broadcasting, `t` a CPU tensor used for this call only (not cached on a
        /// device: masks and other per-call constants).
        unary fn broadcast_add_tensor(&self, t: &Tensor)
            => cpu Tensor::broadcast_add(self, t),
               gpu ops::add(self, &GpuTensor::upload(self.device(), t)?);
        /// `self · mul + add` (candle `affine`; candle's scalar `*`, `/`, `+`, `-` are this affine too).
        unary fn affine(&self, mul: f64, add: f64)
            => cpu Tensor::affine(self, mul, add),
               gpu Ok(ops::affine(self, mul as f32, add as f32));
        /// The values clamped to `[min, max]` (candle `clamp`).
        unary fn clamp(&self, min: f32, max: f32)
            => cpu Tensor::clamp(self, min, max), gpu Ok(ops::clamp(self, min, max));
        /// One of the activations with a kernel of their own.
        unary fn unary(&self, op: Unary)
            => cpu on_cpu::unary(self, op), gpu Ok(on_gpu::unary(self, op));
        /// A candle-nn activation (the ones diffusers configs name).
        unary fn activation(&self, act: Activation)
            => cpu act.forward(self), gpu on_gpu::activation(self, act);

        // ------------------------------------------------------------------------ shape and copies
        unary fn reshape(&self, shape: &[usize])
            => cpu Tensor::reshape(self, shape), gpu GpuTensor::reshape(self, shape);
        /// Permuted and made contiguous.
        unary fn permute_contiguous(&self, dims: &[usize])
            => cpu self.permute(dims)?.contiguous(), gpu ops::permute(self, dims);
        /// `narrow(dim, start, len)` (a view on the CPU, a copy on the GPU).
        unary fn narrow(&self, dim: usize, start: usize, len: usize)
            => cpu Tensor::narrow(self, dim, start, len), gpu ops::narrow(self, dim, start, len);
        /// `narrow(dim, start, len)` permuted by `dims` and made contiguous, in one copy (a part of a
        /// fused projection taken out head-major).
        unary fn narrow_permute(&self, dim: usize, start: usize, len: usize, dims: &[usize])
            => cpu Tensor::narrow(self, dim, start, len)?.permute(dims)?.contiguous(),
               gpu ops::narrow_permute(self, dim, start, len, dims);
        /// The slices of `dim` at `indices`, in that order (candle `index_select`).
        unary fn index_select(&self, indices: &[u32], dim: usize)
            => cpu Tensor::index_select(self, &Tensor::new(indices, self.device())?, dim),
               gpu ops::index_select(self, indices, dim);
        /// One zero row at the bottom and one zero column at the right (diffusers' `Downsample2D`
        /// with padding 0).
        unary fn pad_bottom_right_with_zeros(&self)
            => cpu self.pad_with_zeros(D::Minus1, 0, 1)?.pad_with_zeros(D::Minus2, 0, 1),
               gpu ops::pad_bottom_right(self, 1, 1);
        unary fn upsample_nearest2d(&self, out_h: usize, out_w: usize)
            => cpu Tensor::upsample_nearest2d(self, out_h, out_w),
               gpu ops::upsample_nearest2d(self, out_h, out_w);
        special fn cat(parts: &[&Self], dim: usize) -> Result<Self>
            => cpu Tensor::cat(parts, dim), gpu ops::cat(parts, dim);

        // ---------------------------------------------------------------------- the `kernels` ops
        /// [`super::conv2d`] (NCHW, OIHW weights), plus `addend`, then `act` if any
        /// ([`super::conv2d_add_act`]: under the CPU's bf16 products a ReLU is applied as the sums are
        /// stored).
        special fn conv2d(
            &self,
            weight: &ProductWeight,
            bias: Option<&Tensor>,
            stride: usize,
            padding: usize,
            addend: Addend<'_, Self>,
            act: Option<Unary>,
        ) -> Result<Self>
            => cpu super::conv2d_add_act(self, weight, bias, stride, padding, addend, act),
               gpu ops::conv2d(
                   self,
                   &self.matrix_constant(&weight.tensor()?)?,
                   self.optional_constant(bias)?.as_ref(),
                   stride,
                   padding,
                   addend,
               )
               .map(|y| match act {
                   Some(act) => on_gpu::unary(&y, act),
                   None => y,
               });
        /// `x·weightᵀ + bias` ([`Linear`]), plus `residual` (of the output's shape).
        special fn linear(&self, layer: &Linear, residual: Option<&Self>) -> Result<Self>
            => cpu on_cpu::linear(self, layer, residual),
               gpu ops::linear(
                   self,
                   &self.matrix_constant(&layer.weight().tensor()?)?,
                   self.optional_constant(layer.bias())?.as_ref(),
                   residual,
               );
        /// [`super::group_norm`], SiLU fused when `silu`.
        unary fn group_norm(
            &self,
            weight: &Tensor,
            bias: &Tensor,
            groups: usize,
            eps: f64,
            silu: bool,
        ) => cpu super::group_norm(self, weight, bias, groups, eps, silu),
             gpu ops::group_norm(
                 self,
                 &self.constant(weight)?,
                 &self.constant(bias)?,
                 groups,
                 eps,
                 silu,
             );
        /// [`super::layer_norm`] over the last dimension.
        unary fn layer_norm(&self, weight: &Tensor, bias: &Tensor, eps: f64)
            => cpu super::layer_norm(self, weight, bias, eps),
               gpu ops::layer_norm(self, &self.constant(weight)?, &self.constant(bias)?, eps);
        /// [`super::softmax_last_dim`].
        unary fn softmax_last_dim(&self)
            => cpu super::softmax_last_dim(self), gpu ops::softmax_last_dim(self);
        /// `super::geglu` (the last dimension split in value and gate halves).
        unary fn geglu(&self) => cpu super::geglu(self), gpu ops::geglu(self);
        /// `self × otherᵀ` over the last two dimensions (candle `a.matmul(&b.t()?)`).
        binary fn matmul_t(&self, other: &Self)
            => cpu self.matmul(&other.t()?), gpu ops::matmul_scaled(self, other, true, 1.0);
        /// Batched matrix product (candle `matmul`).
        binary fn matmul(&self, other: &Self)
            => cpu Tensor::matmul(self, other), gpu ops::matmul(self, other);
        /// `softmax(q·kᵀ·scale)·v` (`super::attention`; on the GPU, [`ops::attention`]'s path).
        special fn attention(q: &Self, k: &Self, v: &Self, scale: f64) -> Result<Self>
            => cpu super::attention(q, k, v, scale), gpu ops::attention(q, k, v, scale);
    }
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
            $crate::kernels::device::DeviceTensor::Cpu($t) => {
                $crate::kernels::device::DeviceTensor::Cpu($op?)
            }
            $crate::kernels::device::DeviceTensor::Gpu($t) => {
                $crate::kernels::device::DeviceTensor::Gpu($op?)
            }
        }
    };
}
pub(crate) use dispatch;

/// `$op` on the common backend of `$a` and `$b`; an error when they differ.
macro_rules! dispatch2 {
    ($a:expr, $b:expr, ($x:ident, $y:ident) => $op:expr) => {
        match ($a, $b) {
            (
                $crate::kernels::device::DeviceTensor::Cpu($x),
                $crate::kernels::device::DeviceTensor::Cpu($y),
            ) => $crate::kernels::device::DeviceTensor::Cpu($op?),
            (
                $crate::kernels::device::DeviceTensor::Gpu($x),
                $crate::kernels::device::DeviceTensor::Gpu($y),
            ) => $crate::kernels::device::DeviceTensor::Gpu($op?),
            _ => candle_core::bail!("operands on different devices (CPU and GPU)"),
        }
    };
}
pub(crate) use dispatch2;

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

    /// The values in f32 where they are, for another engine: a GPU tensor's buffer as it is (no copy),
    /// a CPU tensor's values on the host.
    pub fn into_f32_values(self) -> Result<F32Values> {
        match self {
            DeviceTensor::Gpu(t) => Ok(F32Values::Device(t.into_buffer()?)),
            DeviceTensor::Cpu(t) => Ok(F32Values::Host(
                t.to_dtype(candle_core::DType::F32)?
                    .flatten_all()?
                    .to_vec1()?,
            )),
        }
    }

    /// An f32 tensor of `shape` on `device` over values another engine handed back: a device buffer
    /// taken as it is (on the GPU; an error on the CPU), host values wrapped or uploaded.
    pub fn from_f32_values(device: &Device, values: F32Values, shape: Vec<usize>) -> Result<Self> {
        match values {
            F32Values::Device(buffer) => Self::from_gpu_buffer(device, buffer, shape),
            F32Values::Host(values) => {
                device.tensor(&Tensor::from_vec(values, shape, &candle_core::Device::Cpu)?)
            }
        }
    }

    /// The tensor in f32 (CPU tensors of other dtypes converted; GPU activations are f32 already, a
    /// packed f16 weight is an error).
    pub fn to_f32(&self) -> Result<DeviceTensor> {
        match self {
            DeviceTensor::Cpu(t) => Ok(DeviceTensor::Cpu(t.to_dtype(candle_core::DType::F32)?)),
            DeviceTensor::Gpu(t) if t.is_f16() => {
                candle_core::bail!("a packed f16 GPU tensor {:?} is not f32", t.dims())
            }
            DeviceTensor::Gpu(_) => Ok(self.clone()),
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

    pub fn relu(&self) -> Result<DeviceTensor> {
        self.unary(Unary::Relu)
    }

    pub fn tanh(&self) -> Result<DeviceTensor> {
        self.unary(Unary::Tanh)
    }

    // ---------------------------------------------------------------------------- shape and copies

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

    /// [`super::conv2d`] on the tensor's device (a plain tensor converts with `.into()`).
    pub fn conv2d(
        &self,
        weight: &ProductWeight,
        bias: Option<&Tensor>,
        stride: usize,
        padding: usize,
    ) -> Result<DeviceTensor> {
        self.conv2d_add(weight, bias, stride, padding, Addend::None)
    }

    /// [`Self::conv2d`] plus `addend` (on the same device).
    pub fn conv2d_add(
        &self,
        weight: &ProductWeight,
        bias: Option<&Tensor>,
        stride: usize,
        padding: usize,
        addend: Addend<'_, DeviceTensor>,
    ) -> Result<DeviceTensor> {
        self.conv2d_with(weight, (bias, stride, padding), addend, None)
    }

    /// [`Self::conv2d_add`] followed by `act` (on the CPU under bf16 products a ReLU costs no pass of
    /// its own).
    pub fn conv2d_add_act(
        &self,
        weight: &ProductWeight,
        bias: Option<&Tensor>,
        stride: usize,
        padding: usize,
        addend: Addend<'_, DeviceTensor>,
        act: Unary,
    ) -> Result<DeviceTensor> {
        self.conv2d_with(weight, (bias, stride, padding), addend, Some(act))
    }

    fn conv2d_with(
        &self,
        weight: &ProductWeight,
        (bias, stride, padding): (Option<&Tensor>, usize, usize),
        addend: Addend<'_, DeviceTensor>,
        act: Option<Unary>,
    ) -> Result<DeviceTensor> {
        let Some(term) = addend.term() else {
            return Ok(dispatch!(self, x =>
                Storage::conv2d(x, weight, bias, stride, padding, Addend::None, act)));
        };
        Ok(dispatch2!(self, term, (x, t) =>
            Storage::conv2d(x, weight, bias, stride, padding, addend.with(t), act)))
    }

    /// A linear layer `x·weightᵀ + bias`.
    pub fn linear(&self, layer: &Linear) -> Result<DeviceTensor> {
        Ok(dispatch!(self, x => Storage::linear(x, layer, None)))
    }

    /// [`Self::linear`] plus `residual` (of the output's shape, on the same device): a skip connection
    /// added in the bias's pass.
    pub fn linear_add(&self, layer: &Linear, residual: &DeviceTensor) -> Result<DeviceTensor> {
        Ok(dispatch2!(self, residual, (x, r) => Storage::linear(x, layer, Some(r))))
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
            .conv2d(&w.clone().into(), None, 1, 1)
            .unwrap()
            .to_cpu()
            .unwrap();
        let want = super::super::conv2d(&x, &w.into(), None, 1, 1).unwrap();
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
