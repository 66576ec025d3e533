//! The numeric ops of the diffusion stack, one public function per op:
//! [`attention`], [`conv2d`], [`geglu`], [`group_norm`], [`layer_norm`], [`softmax_last_dim`].
//!
//! Network code (layers, UNet, VAE, CLIP) calls only these functions; each picks its implementation per call:
//! - **inference** (no operand tracks gradients), f32 on the CPU: fused kernels that avoid intermediate
//!   tensors (group norm + SiLU in one pass, attention without the full score matrix, im2col + GEMM conv);
//! - **training** (an operand is a `Var` or was computed from one), f32 on the CPU: the same forward
//!   kernels registered with an analytic backward pass. candle differentiates composite ops, but on the CPU
//!   they are slow for the shapes of a small UNet or VAE (every broadcast costs a strided reduction in the
//!   backward pass, its conv2d backward is a naive transposed convolution): a 3M-parameter UNet training step
//!   took ~40× longer than PyTorch's before these kernels;
//! - anything else (other dtypes or devices): composite candle ops, differentiable.
//!
//! Inference and training share their forward kernels, so a model computes the same values whether or
//! not it is being trained.
//!
//! The device seam ([`device`]): networks pass a [`DeviceTensor`] from layer to layer; on the CPU each of its ops is the
//! very function above (or candle call), on the GPU the CubeCL twin in [`gpu::ops`] (tested against the
//! CPU function on lavapipe). One network definition thus runs on either device.

use candle_core::{CpuStorage, Layout, Result, Tensor};

/// Runs `$kernel($args)` compiled for AVX-512 or AVX2+FMA when the CPU has them (the kernels are
/// `#[inline(always)]` loops, so each instantiation is vectorised for its instruction set).
macro_rules! simd_dispatch {
    ($(#[$meta:meta])* $vis:vis fn $name:ident($($arg:ident: $ty:ty),*) => $kernel:ident) => {
        $(#[$meta])*
        $vis fn $name($($arg: $ty),*) {
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx512f")]
                unsafe fn avx512($($arg: $ty),*) {
                    $kernel($($arg),*)
                }
                #[target_feature(enable = "avx2,fma")]
                unsafe fn avx2($($arg: $ty),*) {
                    $kernel($($arg),*)
                }
                if std::is_x86_feature_detected!("avx512f") {
                    // SAFETY: the CPU supports the enabled features (checked just above).
                    return unsafe { avx512($($arg),*) };
                }
                if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
                    // SAFETY: as above.
                    return unsafe { avx2($($arg),*) };
                }
            }
            $kernel($($arg),*)
        }
    };
}

mod activation;
mod approx;
mod attention;
pub mod bf16;
mod conv;
mod cpu;
pub(crate) mod device;
mod geglu;
pub mod gpu;
mod norm;
mod op_args;
mod product_weight;
mod softmax;
mod vgg;

pub use attention::attention;
pub use bf16::{
    bf16_products_available, cpu_precision, set_cpu_precision, with_cpu_precision, Bf16Unavailable,
    CpuPrecision, CpuPrecisionError,
};
pub use conv::{conv2d, conv2d_add_act};
pub use device::{Addend, Device, DeviceTensor, Storage, Unary};
pub use geglu::geglu;
pub use norm::{group_norm, layer_norm};
pub use product_weight::{Linear, ProductWeight};
pub use softmax::softmax_last_dim;

/// True when the computation must stay differentiable: any of the given tensors is a variable or was
/// computed from one.
fn needs_grad(tensors: &[&Tensor]) -> bool {
    tensors.iter().any(|t| t.track_op())
}

/// Whether the CPU kernels apply: every operand is f32 on the CPU.
fn cpu_f32(tensors: &[&Tensor]) -> bool {
    tensors
        .iter()
        .all(|t| t.dtype() == candle_core::DType::F32 && t.device().is_cpu())
}

/// The contiguous f32 data of a CPU operand; `op` names the kernel in errors.
fn f32_slice<'a>(storage: &'a CpuStorage, layout: &Layout, op: &str) -> Result<&'a [f32]> {
    let CpuStorage::F32(data) = storage else {
        candle_core::bail!("{op}: expects f32 tensors");
    };
    match layout.contiguous_offsets() {
        Some((start, end)) => Ok(&data[start..end]),
        None => candle_core::bail!("{op}: expects contiguous tensors"),
    }
}

/// [`f32_slice`] of each operand.
fn f32_slices<'a, const N: usize>(
    operands: [(&'a CpuStorage, &Layout); N],
    op: &str,
) -> Result<[&'a [f32]; N]> {
    let mut slices = [&[][..]; N];
    for (slice, (storage, layout)) in slices.iter_mut().zip(operands) {
        *slice = f32_slice(storage, layout, op)?;
    }
    Ok(slices)
}

/// The gradients a three-operand op (x, weight, bias) returns from its backward pass.
type Grads3 = (Option<Tensor>, Option<Tensor>, Option<Tensor>);

/// Splits the output of a backward kernel, all gradients packed in one flat tensor [dx, dweight, dbias].
fn split_grads(packed: &Tensor, x: &Tensor, weight: &Tensor, bias: &Tensor) -> Result<Grads3> {
    let mut offset = 0;
    let mut part = |t: &Tensor| -> Result<Option<Tensor>> {
        let n = t.elem_count();
        let part = packed.narrow(0, offset, n)?.reshape(t.dims())?;
        offset += n;
        Ok(Some(part))
    };
    Ok((part(x)?, part(weight)?, part(bias)?))
}

/// Rows of `row_len` elements one rayon task handles in the row-wise kernels: enough that a task does
/// ~8K elements of work (training rows are short), at least one.
fn rows_per_task(row_len: usize) -> usize {
    (8192 / row_len.max(1)).max(1)
}

#[cfg(test)]
pub(crate) mod test_support {
    use candle_core::{Device, Tensor, Var};

    pub use testkit::diff::{tensor_max_abs as max_abs, tensor_max_abs_diff as max_diff};

    pub fn var(shape: &[usize], mean: f32, std: f32) -> Var {
        Var::randn(mean, std, shape, &Device::Cpu).unwrap()
    }

    /// Runs `fused` and `reference` on the same variables with the same random output weighting and
    /// checks values and every gradient agree (relative to the gradient's magnitude).
    pub fn check_gradients(
        vars: &[Var],
        fused: impl Fn(&[Tensor]) -> Tensor,
        reference: impl Fn(&[Tensor]) -> Tensor,
        what: &str,
    ) {
        let ts: Vec<Tensor> = vars.iter().map(|v| v.as_tensor().clone()).collect();
        let (a, b) = (fused(&ts), reference(&ts));
        assert_eq!(a.dims(), b.dims(), "{what}: shapes");
        let scale = max_abs(&b).max(1.0);
        assert!(
            max_diff(&a, &b) < 1e-4 * scale,
            "{what}: values differ by {}",
            max_diff(&a, &b)
        );
        let weighting = Tensor::randn(0f32, 1.0, a.dims(), &Device::Cpu).unwrap();
        let ga = (&a * &weighting)
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        let gb = (&b * &weighting)
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        for (k, v) in vars.iter().enumerate() {
            let (x, y) = (
                ga.get(v.as_tensor()).unwrap(),
                gb.get(v.as_tensor()).unwrap(),
            );
            let tol = 2e-4 * max_abs(y).max(1e-2);
            let d = max_diff(x, y);
            assert!(
                d < tol,
                "{what}: gradient {k} differs by {d} (scale {})",
                max_abs(y)
            );
        }
    }
}
