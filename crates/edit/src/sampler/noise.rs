//! Where the sampler's random numbers come from.
//!
//! Every random draw of an edit goes through a [`NoiseSource`], in a fixed order (posterior sample of the
//! source image when the codec samples, the initial latents, then one tensor per step). A seeded source makes
//! runs reproducible; a recorded source replays noise saved by the Python reference so both sides see the
//! same numbers.

use std::path::Path;

use candle_core::{Device, Tensor};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

/// A stream of standard-normal tensors.
pub trait NoiseSource {
    /// The next tensor of the given shape (f32, CPU).
    fn sample(&mut self, shape: &[usize]) -> candle_core::Result<Tensor>;
}

/// Standard-normal noise from a seeded ChaCha8 generator: the same seed gives the same stream on every
/// machine (no platform-dependent RNG underneath).
pub struct SeededNoise {
    rng: ChaCha8Rng,
}

impl SeededNoise {
    pub fn new(seed: u64) -> Self {
        Self {
            rng: ChaCha8Rng::seed_from_u64(seed),
        }
    }

    /// Draws `n` standard-normal values.
    pub fn values(&mut self, n: usize) -> Vec<f32> {
        (0..n)
            .map(|_| StandardNormal.sample(&mut self.rng))
            .collect()
    }
}

impl NoiseSource for SeededNoise {
    fn sample(&mut self, shape: &[usize]) -> candle_core::Result<Tensor> {
        let n = shape.iter().product();
        Tensor::from_vec(self.values(n), shape, &Device::Cpu)
    }
}

/// Replays tensors in order (e.g. `noise_0`, `noise_1`, ... from a safetensors file written by the reference).
pub struct RecordedNoise {
    tensors: std::collections::VecDeque<Tensor>,
}

impl RecordedNoise {
    pub fn new(tensors: Vec<Tensor>) -> Self {
        Self {
            tensors: tensors.into(),
        }
    }

    /// Loads `prefix0`, `prefix1`, ... from a safetensors file, in index order.
    pub fn from_safetensors(path: &Path, prefix: &str) -> candle_core::Result<Self> {
        let all = candle_core::safetensors::load(path, &Device::Cpu)?;
        let mut list = Vec::new();
        while let Some(t) = all.get(&format!("{prefix}{}", list.len())) {
            list.push(t.to_dtype(candle_core::DType::F32)?);
        }
        Ok(Self::new(list))
    }

    pub fn remaining(&self) -> usize {
        self.tensors.len()
    }
}

impl NoiseSource for RecordedNoise {
    fn sample(&mut self, shape: &[usize]) -> candle_core::Result<Tensor> {
        let t = self
            .tensors
            .pop_front()
            .ok_or_else(|| candle_core::Error::Msg("recorded noise exhausted".into()))?;
        if t.dims() != shape {
            candle_core::bail!(
                "recorded noise has shape {:?}, the sampler asked for {shape:?}",
                t.dims()
            );
        }
        Ok(t)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn seeded_noise_is_deterministic_and_standard() {
        let a = SeededNoise::new(7).values(20000);
        let b = SeededNoise::new(7).values(20000);
        assert_eq!(a, b);
        let mean = a.iter().sum::<f32>() / a.len() as f32;
        let var = a.iter().map(|x| (x - mean) * (x - mean)).sum::<f32>() / a.len() as f32;
        assert!(mean.abs() < 0.03, "{mean}");
        assert!((var - 1.0).abs() < 0.05, "{var}");
        assert_ne!(SeededNoise::new(8).values(4), a[..4].to_vec());
    }

    #[test]
    fn recorded_noise_checks_shapes_and_runs_out() {
        let t = Tensor::zeros((1, 2), candle_core::DType::F32, &Device::Cpu).unwrap();
        let mut r = RecordedNoise::new(vec![t.clone(), t]);
        assert!(r.sample(&[1, 2]).is_ok());
        assert!(r.sample(&[2, 1]).is_err());
        assert!(r.sample(&[1, 2]).is_err());
    }
}
