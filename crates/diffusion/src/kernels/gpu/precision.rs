//! The storage precision of the GPU's weight matrices, and the packing of f16 weights into u32 words.
//!
//! f16 weights are stored two per u32 (the lower half first) rather than as a native f16 buffer: WGSL's
//! `f16` needs the optional `shader-f16` feature, which Mesa lavapipe and several other adapters lack,
//! while bit operations on u32 work on every adapter. The kernels unpack each half to f32 and do all
//! arithmetic (and accumulation) in f32; only the weights' memory and bandwidth halve.

use std::fmt;
use std::str::FromStr;

/// How the GPU stores the weights of its matrix products (linear and convolution weights). Activations,
/// biases and normalisation parameters are always f32, and so is every sum.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum Precision {
    /// f32 weights: the CPU's numbers up to summation order (relative error ~1e-6).
    F32,
    /// f16 weights (rounded to nearest), f32 arithmetic: half the weight memory, relative error ~1e-3.
    #[default]
    F16,
}

/// A precision name other than `f32` or `f16`.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown precision '{0}' (expected f32 or f16)")]
pub struct UnknownPrecision(pub String);

impl FromStr for Precision {
    type Err = UnknownPrecision;

    fn from_str(s: &str) -> Result<Self, UnknownPrecision> {
        match s.trim().to_ascii_lowercase().as_str() {
            "f32" | "fp32" => Ok(Precision::F32),
            "f16" | "fp16" => Ok(Precision::F16),
            _ => Err(UnknownPrecision(s.to_string())),
        }
    }
}

impl fmt::Display for Precision {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Precision::F32 => "f32",
            Precision::F16 => "f16",
        })
    }
}

impl Precision {
    /// Bytes one weight element takes on the device.
    pub fn weight_bytes_per_element(self) -> usize {
        match self {
            Precision::F32 => 4,
            Precision::F16 => 2,
        }
    }
}

/// `values` rounded to f16 (nearest even) and packed two per word, element `2i` in the low 16 bits of
/// word `i`; an odd count leaves the last word's high half zero.
pub(crate) fn pack_f16(values: &[f32]) -> Vec<u32> {
    values
        .chunks(2)
        .map(|pair| {
            let half = |v: f32| u32::from(half::f16::from_f32(v).to_bits());
            half(pair[0]) | pair.get(1).map_or(0, |&v| half(v) << 16)
        })
        .collect()
}

/// The inverse of [`pack_f16`] for the first `len` elements.
pub(crate) fn unpack_f16(words: &[u32], len: usize) -> Vec<f32> {
    (0..len)
        .map(|i| {
            let bits = (words[i / 2] >> (16 * (i % 2))) & 0xFFFF;
            half::f16::from_bits(bits as u16).to_f32()
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_and_prints_both_names() {
        for p in [Precision::F32, Precision::F16] {
            assert_eq!(p.to_string().parse::<Precision>(), Ok(p));
        }
        assert_eq!(" FP16 ".parse::<Precision>(), Ok(Precision::F16));
        let err = "bf16".parse::<Precision>().unwrap_err().to_string();
        assert_eq!(err, "unknown precision 'bf16' (expected f32 or f16)");
    }

    #[test]
    fn packing_round_trips_through_f16() {
        // Normals, a subnormal, zeros of both signs, the largest f16 and an odd count.
        let values = [1.0f32, -2.5, 3.0e-6, 0.0, -0.0, 65504.0, 0.1];
        let words = pack_f16(&values);
        assert_eq!(words.len(), 4);
        assert_eq!(words[3] >> 16, 0, "the unused half is zero");
        let back = unpack_f16(&words, values.len());
        for (v, b) in values.iter().zip(&back) {
            let want = half::f16::from_f32(*v).to_f32();
            assert_eq!(b.to_bits(), want.to_bits(), "{v}");
        }
    }
}
