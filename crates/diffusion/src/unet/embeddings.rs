//! Timestep embeddings: diffusers' `get_timestep_embedding` and `TimestepEmbedding`.

use candle_core::{Module, Result, Tensor};
use candle_nn::VarBuilder;

use crate::layers::{linear, Linear};

/// Sinusoidal embedding of `timesteps` ([batch], any float dtype) with `dim` channels, as diffusers'
/// `get_timestep_embedding(t, dim, flip_sin_to_cos, downscale_freq_shift, scale=1, max_period=10000)`.
///
/// Computed in f32 with the same operation order as PyTorch so large timesteps (arguments near 1000 rad)
/// round the same way.
pub fn timestep_embedding(
    timesteps: &Tensor,
    dim: usize,
    flip_sin_to_cos: bool,
    freq_shift: f64,
) -> Result<Tensor> {
    let ts = timesteps
        .to_dtype(candle_core::DType::F32)?
        .to_vec1::<f32>()?;
    let half = dim / 2;
    let log_max = -(10000f64.ln()) as f32;
    let denom = (half as f64 - freq_shift) as f32;
    let freqs: Vec<f32> = (0..half)
        .map(|i| ((log_max * i as f32) / denom).exp())
        .collect();
    let mut data = Vec::with_capacity(ts.len() * dim);
    for &t in &ts {
        let args = freqs.iter().map(|&f| t * f);
        let (sin, cos): (Vec<f32>, Vec<f32>) = args.map(|a| (a.sin(), a.cos())).unzip();
        if flip_sin_to_cos {
            data.extend_from_slice(&cos);
            data.extend_from_slice(&sin);
        } else {
            data.extend_from_slice(&sin);
            data.extend_from_slice(&cos);
        }
        // Odd widths get a zero column at the end, as in diffusers.
        if dim % 2 == 1 {
            data.push(0.0);
        }
    }
    Tensor::from_vec(data, (ts.len(), dim), timesteps.device())
}

/// diffusers `TimestepEmbedding`: `linear_1` → SiLU → `linear_2`, with the LCM condition
/// (`cond_proj`, no bias) added to the input when the config has `time_cond_proj_dim`.
#[derive(Debug, Clone)]
pub struct TimestepEmbedding {
    linear_1: Linear,
    linear_2: Linear,
    cond_proj: Option<Linear>,
}

impl TimestepEmbedding {
    pub fn load(
        in_dim: usize,
        embed_dim: usize,
        cond_dim: Option<usize>,
        vb: VarBuilder,
    ) -> Result<Self> {
        Ok(Self {
            linear_1: linear(in_dim, embed_dim, true, vb.pp("linear_1"))?,
            linear_2: linear(embed_dim, embed_dim, true, vb.pp("linear_2"))?,
            cond_proj: match cond_dim {
                Some(c) => Some(linear(c, in_dim, false, vb.pp("cond_proj"))?),
                None => None,
            },
        })
    }

    /// Whether the model expects a `timestep_cond` (LCM w-embedding).
    pub fn has_condition(&self) -> bool {
        self.cond_proj.is_some()
    }

    pub fn forward(&self, sample: &Tensor, condition: Option<&Tensor>) -> Result<Tensor> {
        let sample = match (&self.cond_proj, condition) {
            (Some(proj), Some(c)) => (sample + proj.forward(c)?)?,
            _ => sample.clone(),
        };
        self.linear_2
            .forward(&self.linear_1.forward(&sample)?.silu()?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    #[test]
    fn embedding_matches_closed_form() {
        let t = Tensor::new(&[0f32, 10.0, 999.0], &Device::Cpu).unwrap();
        let e = timestep_embedding(&t, 8, true, 0.0)
            .unwrap()
            .to_vec2::<f32>()
            .unwrap();
        // t = 0: cos part ones, sin part zeros (flipped: cos first).
        assert_eq!(&e[0][..4], &[1.0; 4]);
        assert_eq!(&e[0][4..], &[0.0; 4]);
        // frequency i = 10000^(-i/4); check one entry by the formula in f64.
        let f = 10000f64.powf(-1.0 / 4.0);
        assert!((e[1][1] as f64 - (10.0 * f).cos()).abs() < 1e-5);
        assert!((e[1][5] as f64 - (10.0 * f).sin()).abs() < 1e-5);
        let unflipped = timestep_embedding(&t, 9, false, 1.0)
            .unwrap()
            .to_vec2::<f32>()
            .unwrap();
        assert_eq!(unflipped[2].len(), 9);
        assert_eq!(unflipped[2][8], 0.0);
        let f = 10000f64.powf(-2.0 / 3.0);
        assert!((unflipped[2][2] as f64 - (999.0 * f).sin()).abs() < 1e-3);
    }
}
