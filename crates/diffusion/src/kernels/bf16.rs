//! bf16 matrix products on the CPU: bf16 operands, f32 accumulation, for the networks' linear layers and
//! convolutions when the CPU has the AVX512-BF16 dot-product instruction (`vdpbf16ps`).
//!
//! - [`CpuPrecision`]: f32 (today's path, unchanged) or bf16 products. The process-wide choice is made
//!   once ([`set_cpu_precision`], the CLI's `--precision`); [`with_cpu_precision`] overrides it on the
//!   calling thread (tests and paired comparisons). bf16 is only ever chosen where the instructions exist
//!   (runtime feature detection); elsewhere every product stays f32.
//! - [`PackedPairs`]: a matrix in the microkernel's layout: bf16 pairs along the summed dimension k
//!   (`vdpbf16ps` multiplies two adjacent k values per f32 lane), in panels of [`MR`] lines (the
//!   broadcast operand) or [`NR`] lines (the vector operand). A model loaded while bf16 is on keeps
//!   only its weights' pairs (`kernels::ProductWeight`); an f32 model run in bf16 (tests, paired checks)
//!   has each weight packed once and cached beside it ([`packed_weight`]); activations are rounded and
//!   packed per call.
//! - [`gemm`]: `C (+)= A·B` over packed operands, tiled for the caches and parallel over output tiles.
//!
//! Only the products' operands are rounded to bf16 (nearest even, as the hardware conversion does). Sums,
//! biases, normalisation statistics, softmax and everything else stay f32, as on the GPU path.
//!
//! AMX-BF16 (tile instructions, Sapphire Rapids and later) would be a second microkernel over the same
//! packed panels, chosen by the same detection; it is not written yet because no machine here has AMX
//! to test it on.

use std::cell::Cell;
use std::collections::HashMap;
use std::sync::atomic::{AtomicU8, Ordering};
use std::sync::{Arc, Mutex};

use candle_core::{Tensor, TensorId};
use rayon::prelude::*;

mod direct;
mod gemm;
pub use direct::{conv as direct_conv, pack_conv_weight, unpack_conv_weight, ConvDims};
pub use gemm::{bf16_products_available, gemm, Output, PackedPairs, MR, NR};

/// How a product's weight is laid out in its bf16 pairs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub(crate) enum WeightLayout {
    /// A linear layer's `[out, in]` in [`NR`] panels (the product's right operand).
    Linear,
    /// A convolution's `[out, in, k, k]` tap-major in [`MR`] panels ([`pack_conv_weight`]), for
    /// [`direct_conv`].
    Conv,
}

impl WeightLayout {
    /// Whether a weight of shape `dims` can be packed in this layout.
    pub(crate) fn fits(self, dims: &[usize]) -> bool {
        match (self, dims) {
            (WeightLayout::Conv, &[_, _, kh, kw]) => kh == kw,
            (WeightLayout::Conv, _) => false,
            (WeightLayout::Linear, _) => dims.len() >= 2,
        }
    }

    /// `values` (f32, row-major `dims`) packed in this layout.
    pub(crate) fn pack(self, values: &[f32], dims: &[usize]) -> candle_core::Result<PackedPairs> {
        match (self, dims) {
            (WeightLayout::Conv, &[c_out, c_in, kh, kw]) if kh == kw => {
                Ok(pack_conv_weight(values, c_out, c_in, kh))
            }
            (WeightLayout::Conv, _) => {
                candle_core::bail!("a convolution weight of shape {dims:?} (square kernels only)")
            }
            (WeightLayout::Linear, _) => {
                let lines = dims.first().copied().unwrap_or(0);
                let k = values.len() / lines.max(1);
                Ok(PackedPairs::pack(values, lines, k, k, 1, NR))
            }
        }
    }

    /// The f32 values (row-major `dims`) of pairs packed by [`Self::pack`]: the bf16 values exactly.
    pub(crate) fn unpack(self, pairs: &PackedPairs, dims: &[usize]) -> Vec<f32> {
        match (self, dims) {
            (WeightLayout::Conv, &[c_out, c_in, k, _]) => unpack_conv_weight(pairs, c_out, c_in, k),
            _ => pairs.unpack(),
        }
    }
}

/// How the CPU computes the networks' matrix products.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum CpuPrecision {
    /// f32 operands and sums (the reference path).
    F32,
    /// bf16 operands, f32 sums (AVX512-BF16): about twice the f32 throughput, relative error ~4e-3 per
    /// product.
    Bf16,
}

impl CpuPrecision {
    /// The CPU's precision for a `--precision` value: none means bf16 where the CPU has the instructions
    /// ([`bf16_products_available`]), else f32; `bf16` is an error where the CPU lacks them; `f32`, or
    /// `f16` (the GPU's half precision, which the CPU does not have), is f32.
    ///
    /// bf16 became the default after the demo's shape scores and `--compare` table came out the same
    /// within their seed-to-seed noise in both precisions (docs/performance.md).
    pub fn from_request(requested: Option<&str>) -> Result<Self, CpuPrecisionError> {
        let requested = requested.map(|s| s.trim().to_ascii_lowercase());
        match requested.as_deref() {
            None if bf16_products_available() => Ok(CpuPrecision::Bf16),
            None | Some("f16" | "fp16") => Ok(CpuPrecision::F32),
            Some("f32" | "fp32") => Ok(CpuPrecision::F32),
            Some("bf16") if bf16_products_available() => Ok(CpuPrecision::Bf16),
            Some("bf16") => Err(CpuPrecisionError::Unavailable(Bf16Unavailable)),
            Some(other) => Err(CpuPrecisionError::Unknown(other.to_string())),
        }
    }

    /// The name used by `--precision` and in logs.
    pub fn name(self) -> &'static str {
        match self {
            CpuPrecision::F32 => "f32",
            CpuPrecision::Bf16 => "bf16",
        }
    }

    /// What the CPU's products run on, for the run log: "bf16 products (AVX512-BF16)" or "f32 products".
    pub fn describe(self) -> &'static str {
        match self {
            CpuPrecision::F32 => "f32 products",
            CpuPrecision::Bf16 => "bf16 products (AVX512-BF16)",
        }
    }
}

impl std::fmt::Display for CpuPrecision {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// bf16 products were asked for on a CPU without the instructions.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("bf16 precision needs a CPU with AVX512-BF16 (this one has none); use --precision f32")]
pub struct Bf16Unavailable;

/// A `--precision` the CPU cannot run.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CpuPrecisionError {
    #[error(transparent)]
    Unavailable(#[from] Bf16Unavailable),
    #[error("unknown precision '{0}' (expected bf16, f32 or f16)")]
    Unknown(String),
}

const F32_CODE: u8 = 0;
const BF16_CODE: u8 = 1;

/// The process-wide choice (f32 until a program asks for more: the command line's default is bf16 where
/// the CPU has it, a library's f32).
static PROCESS_PRECISION: AtomicU8 = AtomicU8::new(F32_CODE);

thread_local! {
    /// [`with_cpu_precision`]'s override on this thread.
    static THREAD_PRECISION: Cell<Option<CpuPrecision>> = const { Cell::new(None) };
}

/// Sets how every later CPU product of this process is computed; bf16 needs the instructions.
pub fn set_cpu_precision(precision: CpuPrecision) -> Result<(), Bf16Unavailable> {
    if precision == CpuPrecision::Bf16 && !bf16_products_available() {
        return Err(Bf16Unavailable);
    }
    let code = match precision {
        CpuPrecision::F32 => F32_CODE,
        CpuPrecision::Bf16 => BF16_CODE,
    };
    PROCESS_PRECISION.store(code, Ordering::Relaxed);
    Ok(())
}

/// The precision CPU products use now (this thread's override, else the process's choice).
pub fn cpu_precision() -> CpuPrecision {
    THREAD_PRECISION.with(Cell::get).unwrap_or_else(|| {
        if PROCESS_PRECISION.load(Ordering::Relaxed) == BF16_CODE {
            CpuPrecision::Bf16
        } else {
            CpuPrecision::F32
        }
    })
}

/// Runs `f` with the products of this thread in `precision` (networks decide per product on the calling
/// thread, so a whole forward pass follows it). bf16 needs the instructions.
pub fn with_cpu_precision<R>(
    precision: CpuPrecision,
    f: impl FnOnce() -> R,
) -> Result<R, Bf16Unavailable> {
    if precision == CpuPrecision::Bf16 && !bf16_products_available() {
        return Err(Bf16Unavailable);
    }
    struct Restore(Option<CpuPrecision>);
    impl Drop for Restore {
        fn drop(&mut self) {
            THREAD_PRECISION.with(|p| p.set(self.0));
        }
    }
    let _restore = Restore(THREAD_PRECISION.with(|p| p.replace(Some(precision))));
    Ok(f())
}

/// True when products on this thread run in bf16 now.
pub(crate) fn bf16_active() -> bool {
    cpu_precision() == CpuPrecision::Bf16
}

/// `x·weightᵀ + bias (+ residual)` as a bf16 product, for x [.., in], weight [out, in], bias [out] and
/// residual of the output's shape; `None` when the products are f32 now or an operand does not suit (not
/// f32 on the CPU, tracking gradients, a weight that cannot be packed), so the caller runs its f32 path.
pub(crate) fn linear(
    x: &Tensor,
    weight: &super::ProductWeight,
    bias: Option<&Tensor>,
    residual: Option<&Tensor>,
) -> candle_core::Result<Option<Tensor>> {
    let mut operands = vec![x];
    operands.extend(bias);
    operands.extend(residual);
    if !bf16_active()
        || !super::cpu_f32(&operands)
        || super::needs_grad(&operands)
        || weight.dims().len() != 2
        || x.rank() < 2
    {
        return Ok(None);
    }
    let Some(w) = weight.packed(WeightLayout::Linear)? else {
        return Ok(None);
    };
    let (out_dim, in_dim) = (weight.dims()[0], weight.dims()[1]);
    if x.dim(candle_core::D::Minus1)? != in_dim {
        candle_core::bail!(
            "linear: input {:?} does not fit weight {:?}",
            x.dims(),
            weight.dims()
        );
    }
    let rows = x.elem_count() / in_dim.max(1);
    let mut shape = x.dims().to_vec();
    *shape.last_mut().expect("rank ≥ 2") = out_dim;
    let mut out = match residual {
        Some(r) => {
            if r.dims() != shape.as_slice() {
                candle_core::bail!("linear: residual {:?} for output {shape:?}", r.dims());
            }
            r.flatten_all()?.to_vec1::<f32>()?
        }
        None => vec![0f32; rows * out_dim],
    };
    if let Some(b) = bias {
        let b = b.to_vec1::<f32>()?;
        if b.len() != out_dim {
            candle_core::bail!("linear: bias of {} for {out_dim} outputs", b.len());
        }
        out.par_chunks_mut(out_dim)
            .for_each(|row| row.iter_mut().zip(&b).for_each(|(o, b)| *o += b));
    }
    let xs = x.flatten_all()?.to_vec1::<f32>()?;
    let a = PackedPairs::pack(&xs, rows, in_dim, in_dim, 1, MR);
    gemm(
        &a,
        &w,
        Output {
            data: &mut out,
            rows,
            cols: out_dim,
            row_stride: out_dim,
        },
        bias.is_some() || residual.is_some(),
    );
    Ok(Some(Tensor::from_vec(out, shape, x.device())?))
}

/// A weight matrix packed once, kept beside its source tensor so the tensor's id stays unique.
struct CachedWeight {
    _source: Tensor,
    packed: Arc<PackedPairs>,
}

/// Packed weights by tensor id and layout.
static WEIGHTS: Mutex<Option<HashMap<(TensorId, WeightLayout), CachedWeight>>> = Mutex::new(None);

/// The weight `weight` (f32, contiguous) packed in `layout`, packed on first use and kept for the process
/// (or until [`clear_weight_cache`]). Only immutable tensors may come here: a `Var`'s values change
/// under the same id (callers skip tensors that track gradients).
pub(crate) fn packed_weight(
    weight: &Tensor,
    layout: WeightLayout,
) -> candle_core::Result<Arc<PackedPairs>> {
    let key = (weight.id(), layout);
    if let Some(hit) = WEIGHTS
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .get_or_insert_with(HashMap::new)
        .get(&key)
    {
        return Ok(hit.packed.clone());
    }
    let values = weight.flatten_all()?.to_vec1::<f32>()?;
    let packed = Arc::new(layout.pack(&values, weight.dims())?);
    WEIGHTS
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .get_or_insert_with(HashMap::new)
        .insert(
            key,
            CachedWeight {
                _source: weight.clone(),
                packed: packed.clone(),
            },
        );
    Ok(packed)
}

/// Drops every packed weight (after a model is dropped, to free their memory).
pub fn clear_weight_cache() {
    if let Some(map) = WEIGHTS.lock().unwrap_or_else(|e| e.into_inner()).as_mut() {
        map.clear();
    }
}

/// Bytes the packed-weight cache holds.
pub fn weight_cache_bytes() -> usize {
    WEIGHTS
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .as_ref()
        .map_or(0, |m| m.values().map(|w| w.packed.bytes()).sum())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The bf16 linear layer against candle's f32 one with bias and residual: within bf16's rounding
    /// (relative L2 ≤ 5e-3, above 1e-6 so bf16 ran); in f32 it declines (the caller's path runs).
    #[test]
    fn linear_is_within_bf16_rounding_of_f32() {
        let dev = candle_core::Device::Cpu;
        let x = Tensor::randn(0f32, 1.0, (2, 45, 70), &dev).unwrap();
        let w = Tensor::randn(0f32, 0.2, (33, 70), &dev).unwrap();
        let b = Tensor::randn(0f32, 1.0, 33, &dev).unwrap();
        let r = Tensor::randn(0f32, 1.0, (2, 45, 33), &dev).unwrap();
        let w = super::super::ProductWeight::from(w);
        assert!(linear(&x, &w, Some(&b), None).unwrap().is_none());
        let want = x
            .broadcast_matmul(&w.tensor().unwrap().t().unwrap())
            .unwrap()
            .broadcast_add(&b)
            .unwrap();
        for (residual, want) in [(None, want.clone()), (Some(&r), (&want + &r).unwrap())] {
            let Ok(got) = with_cpu_precision(CpuPrecision::Bf16, || {
                linear(&x, &w, Some(&b), residual).unwrap().unwrap()
            }) else {
                eprintln!("skipped: no AVX512-BF16 on this CPU");
                return;
            };
            let rel = testkit::diff::tensor_relative_l2(&got, &want);
            assert!(rel <= 5e-3 && rel > 1e-6, "relative L2 {rel}");
        }
    }

    /// No `--precision` means bf16 where the instructions exist and f32 elsewhere; f32 and f16 mean f32;
    /// bf16 without the instructions is refused.
    #[test]
    fn the_default_is_bf16_only_where_the_cpu_has_it() {
        let available = bf16_products_available();
        let default = if available {
            CpuPrecision::Bf16
        } else {
            CpuPrecision::F32
        };
        assert_eq!(CpuPrecision::from_request(None), Ok(default));
        for f32_name in ["f32", "FP32", "f16"] {
            assert_eq!(
                CpuPrecision::from_request(Some(f32_name)),
                Ok(CpuPrecision::F32)
            );
        }
        let bf16 = CpuPrecision::from_request(Some("bf16"));
        if available {
            assert_eq!(bf16, Ok(CpuPrecision::Bf16));
        } else {
            assert_eq!(bf16, Err(CpuPrecisionError::Unavailable(Bf16Unavailable)));
        }
        assert!(CpuPrecision::from_request(Some("int8")).is_err());
    }

    #[test]
    fn thread_override_is_scoped() {
        assert_eq!(cpu_precision(), CpuPrecision::F32);
        if bf16_products_available() {
            let inner = with_cpu_precision(CpuPrecision::Bf16, cpu_precision).unwrap();
            assert_eq!(inner, CpuPrecision::Bf16);
        } else {
            assert_eq!(
                with_cpu_precision(CpuPrecision::Bf16, || ()),
                Err(Bf16Unavailable)
            );
        }
        assert_eq!(cpu_precision(), CpuPrecision::F32);
    }
}
