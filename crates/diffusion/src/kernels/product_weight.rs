//! The weights of the networks' matrix products (linear layers, convolutions) as the layers keep them.
//!
//! A [`ProductWeight`] is an f32 tensor, or — for a model loaded while the CPU's products run in bf16
//! ([`super::bf16`]) — only its packed bf16 pairs: the f32 values are dropped once packed, so the
//! weights are stored once (SD 1.5's UNet: 1.7 GB instead of 3.4 GB f32 plus 1.7 GB packed). Biases and
//! the normalisations' weights stay f32 tensors in their layers.
//!
//! A packed weight still serves an f32 product (f32 products asked for on this thread, training, a GPU
//! upload): its f32 values are then unpacked once (the bf16 values exactly) and kept beside it.

use std::sync::{Arc, OnceLock};

use candle_core::{DType, Module, Result, Tensor};

use super::bf16::{self, PackedPairs, WeightLayout};

/// A matrix product's weight: f32, or packed bf16 pairs only (see the module).
#[derive(Debug, Clone)]
pub struct ProductWeight(Repr);

#[derive(Debug, Clone)]
enum Repr {
    F32(Tensor),
    Packed(Arc<PackedWeight>),
}

/// A weight kept only as bf16 pairs.
#[derive(Debug)]
struct PackedWeight {
    packed: Arc<PackedPairs>,
    layout: WeightLayout,
    dims: Vec<usize>,
    /// The f32 values of the pairs, made on the first f32 product that needs them.
    unpacked: OnceLock<Tensor>,
}

impl ProductWeight {
    /// A linear layer's weight `[out, in]` (the product's right operand).
    pub fn linear(weight: Tensor) -> Result<Self> {
        Self::new(weight, WeightLayout::Linear)
    }

    /// A convolution's weight `[out, in, k, k]` (the product's left operand, tap-major).
    pub fn conv(weight: Tensor) -> Result<Self> {
        Self::new(weight, WeightLayout::Conv)
    }

    /// Packs `weight` in `layout` and drops its f32 values when the CPU's products run in bf16 now and
    /// the weight is a plain f32 CPU tensor (not a variable being trained) of the layout's shape; else
    /// keeps it.
    fn new(weight: Tensor, layout: WeightLayout) -> Result<Self> {
        let packable = bf16::bf16_active()
            && weight.dtype() == DType::F32
            && weight.device().is_cpu()
            && !weight.track_op()
            && layout.fits(weight.dims());
        if !packable {
            return Ok(Self(Repr::F32(weight)));
        }
        let values = weight.flatten_all()?.to_vec1::<f32>()?;
        Ok(Self(Repr::Packed(Arc::new(PackedWeight {
            packed: Arc::new(layout.pack(&values, weight.dims())?),
            layout,
            dims: weight.dims().to_vec(),
            unpacked: OnceLock::new(),
        }))))
    }

    /// The weight's shape.
    pub fn dims(&self) -> &[usize] {
        match &self.0 {
            Repr::F32(t) => t.dims(),
            Repr::Packed(p) => &p.dims,
        }
    }

    /// Whether only the bf16 pairs are kept (no f32 values made yet).
    pub fn is_packed_only(&self) -> bool {
        matches!(&self.0, Repr::Packed(p) if p.unpacked.get().is_none())
    }

    /// The f32 tensor: the weight itself, or a packed weight's values unpacked once and kept (the same
    /// tensor, same id, on every call: device caches key on it).
    pub fn tensor(&self) -> Result<Tensor> {
        match &self.0 {
            Repr::F32(t) => Ok(t.clone()),
            Repr::Packed(p) => {
                if let Some(t) = p.unpacked.get() {
                    return Ok(t.clone());
                }
                let t = Tensor::from_vec(
                    p.layout.unpack(&p.packed, &p.dims),
                    p.dims.as_slice(),
                    &candle_core::Device::Cpu,
                )?;
                Ok(p.unpacked.get_or_init(|| t).clone())
            }
        }
    }

    /// The f32 tensor when the weight is one (not packed).
    pub fn as_f32(&self) -> Option<&Tensor> {
        match &self.0 {
            Repr::F32(t) => Some(t),
            Repr::Packed(_) => None,
        }
    }

    /// The weight as bf16 pairs in `layout` when this thread's products run in bf16 now: the kept
    /// pairs, or an f32 weight packed once (and cached beside it, [`bf16::packed_weight`]). `None` for
    /// f32 products or a weight that cannot be packed (a variable, another dtype or shape).
    pub(crate) fn packed(&self, layout: WeightLayout) -> Result<Option<Arc<PackedPairs>>> {
        if !bf16::bf16_active() {
            return Ok(None);
        }
        match &self.0 {
            Repr::Packed(p) if p.layout == layout => Ok(Some(p.packed.clone())),
            Repr::Packed(p) => {
                candle_core::bail!("a weight packed as {:?} used as {layout:?}", p.layout)
            }
            Repr::F32(t) => {
                if t.dtype() != DType::F32
                    || !t.device().is_cpu()
                    || t.track_op()
                    || !t.is_contiguous()
                    || !layout.fits(t.dims())
                {
                    return Ok(None);
                }
                bf16::packed_weight(t, layout).map(Some)
            }
        }
    }

    /// Bytes the weight holds on the host (its f32 values, or its pairs plus any unpacked copy).
    pub fn host_bytes(&self) -> usize {
        match &self.0 {
            Repr::F32(t) => t.elem_count() * t.dtype().size_in_bytes(),
            Repr::Packed(p) => {
                p.packed.bytes() + p.unpacked.get().map_or(0, |t| t.elem_count() * 4)
            }
        }
    }
}

impl From<Tensor> for ProductWeight {
    /// An f32 weight as it is (never packed: a caller that wants bf16 storage uses
    /// [`ProductWeight::linear`] or [`ProductWeight::conv`]).
    fn from(weight: Tensor) -> Self {
        Self(Repr::F32(weight))
    }
}

/// A linear layer `x·weightᵀ + bias` (PyTorch's `nn.Linear`), its weight a [`ProductWeight`].
#[derive(Debug, Clone)]
pub struct Linear {
    weight: ProductWeight,
    bias: Option<Tensor>,
}

impl Linear {
    /// `weight` [out, in] (packed when the CPU's products run in bf16 now), `bias` [out].
    pub fn new(weight: Tensor, bias: Option<Tensor>) -> Result<Self> {
        Ok(Self {
            weight: ProductWeight::linear(weight)?,
            bias,
        })
    }

    pub fn weight(&self) -> &ProductWeight {
        &self.weight
    }

    pub fn bias(&self) -> Option<&Tensor> {
        self.bias.as_ref()
    }
}

impl Module for Linear {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        super::cpu::linear(x, self, None)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::{with_cpu_precision, CpuPrecision};

    /// Loaded under bf16 products, a layer keeps only the pairs (half the f32 bytes), computes what the
    /// f32-kept layer computes with bf16 products, and unpacks its f32 values only for an f32 product.
    #[test]
    fn a_layer_loaded_for_bf16_keeps_only_its_pairs() {
        let dev = candle_core::Device::Cpu;
        let w = Tensor::randn(0f32, 0.2, (64, 96), &dev).unwrap();
        let b = Tensor::randn(0f32, 1.0, 64, &dev).unwrap();
        let x = Tensor::randn(0f32, 1.0, (3, 5, 96), &dev).unwrap();
        let kept = Linear::new(w.clone(), Some(b.clone())).unwrap();
        assert!(kept.weight().as_f32().is_some(), "f32 products keep f32");
        let Ok(packed) = with_cpu_precision(CpuPrecision::Bf16, || {
            Linear::new(w.clone(), Some(b.clone())).unwrap()
        }) else {
            eprintln!("skipped: no AVX512-BF16 on this CPU");
            return;
        };
        assert!(packed.weight().is_packed_only());
        assert!(
            packed.weight().host_bytes() <= 64 * 96 * 2 + 64 * 2,
            "pairs only"
        );
        assert_eq!(packed.weight().dims(), &[64, 96]);
        let bf16_of = |layer: &Linear| {
            with_cpu_precision(CpuPrecision::Bf16, || layer.forward(&x).unwrap()).unwrap()
        };
        let (a, b16) = (bf16_of(&kept), bf16_of(&packed));
        assert_eq!(testkit::diff::tensor_max_abs_diff(&a, &b16), 0.0);
        assert!(
            packed.weight().is_packed_only(),
            "a bf16 product unpacks nothing"
        );
        // An f32 product over the pairs: f32 values made once, the same tensor afterwards.
        let f32_out = packed.forward(&x).unwrap();
        assert!(!packed.weight().is_packed_only());
        let first = packed.weight().tensor().unwrap();
        assert_eq!(first.id(), packed.weight().tensor().unwrap().id());
        let want = kept.forward(&x).unwrap();
        let rel = testkit::diff::tensor_relative_l2(&f32_out, &want);
        assert!(rel > 0.0 && rel < 5e-3, "relative L2 {rel}");
    }

    /// Variables (weights being trained) are never packed: an optimiser changes them in place.
    #[test]
    fn variables_stay_f32() {
        let var = candle_core::Var::randn(0f32, 1.0, (8, 8), &candle_core::Device::Cpu).unwrap();
        let Ok(w) = with_cpu_precision(CpuPrecision::Bf16, || {
            ProductWeight::linear(var.as_tensor().clone()).unwrap()
        }) else {
            return;
        };
        assert!(w.as_f32().is_some());
    }
}
