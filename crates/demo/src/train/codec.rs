//! Stage 1: the latent codec (`AutoencoderKL`) learns to reconstruct world renders.
//!
//! Loss per batch of random crops (mirrored half the time): mean |x̂ − x| + `edge_weight` · mean |∇x̂ − ∇x|
//! (horizontal and vertical pixel differences: keeps stripes, dots and silhouettes crisp, a cheap stand-in
//! for the perceptual loss SD's VAE used) + `kl_weight` · KL(posterior ‖ N(0, I)) per pixel value, with x̂
//! decoded from a posterior *sample* so the decoder tolerates the sampling the editor does.

use candle_core::{DType, Device, Result, Tensor};
use candle_nn::{VarBuilder, VarMap};
use diffusion::vae::{AutoencoderKL, AutoencoderKLConfig};
use rand::Rng;
use rand_distr::StandardNormal;

use super::config::TrainConfig;
use super::data::{random_indices, RenderedSet};

/// A codec being trained.
pub struct CodecTrainer {
    pub varmap: VarMap,
    pub model: AutoencoderKL,
}

/// Loss terms of one batch.
#[derive(Clone, Copy, Debug)]
pub struct CodecLoss {
    pub total: f64,
    pub l1: f64,
}

/// Standard-normal noise of `shape` drawn from `rng` (deterministic for a seeded generator).
pub fn randn<R: Rng>(rng: &mut R, shape: &[usize]) -> Result<Tensor> {
    let n: usize = shape.iter().product();
    let data: Vec<f32> = (0..n).map(|_| rng.sample(StandardNormal)).collect();
    Tensor::from_vec(data, shape, &Device::Cpu)
}

/// The codec's diffusers config (with a placeholder scaling factor until it is measured).
pub fn vae_config(config: &TrainConfig, scaling_factor: f64) -> AutoencoderKLConfig {
    serde_json::from_value(config.vae_config_json(scaling_factor)).expect("generated config parses")
}

/// Mean absolute horizontal and vertical differences between two image batches' gradients.
fn edge_l1(a: &Tensor, b: &Tensor) -> Result<Tensor> {
    let (_, _, h, w) = a.dims4()?;
    let dx = |t: &Tensor| -> Result<Tensor> { t.narrow(3, 1, w - 1)? - t.narrow(3, 0, w - 1)? };
    let dy = |t: &Tensor| -> Result<Tensor> { t.narrow(2, 1, h - 1)? - t.narrow(2, 0, h - 1)? };
    let ex = (dx(a)? - dx(b)?)?.abs()?.mean_all()?;
    let ey = (dy(a)? - dy(b)?)?.abs()?.mean_all()?;
    ex + ey
}

impl CodecTrainer {
    pub fn new(config: &TrainConfig) -> Result<Self> {
        let varmap = VarMap::new();
        let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
        let model = AutoencoderKL::new(&vae_config(config, 1.0), vb)?;
        Ok(Self { varmap, model })
    }

    /// Forward pass and loss of one batch (call `backward` on `.0`).
    pub fn loss<R: Rng>(
        &self,
        config: &TrainConfig,
        data: &RenderedSet,
        rng: &mut R,
    ) -> Result<(Tensor, CodecLoss)> {
        let c = &config.codec;
        let indices = random_indices(data.len(), c.batch, rng);
        let images = data.batch(&indices, c.crop, rng)?;
        let err = |e: diffusion::vae::VaeError| candle_core::Error::Msg(e.to_string());
        let posterior = self.model.encode(&images).map_err(err)?;
        let noise = randn(rng, posterior.mean.dims())?;
        let z = posterior.sample_with_noise(&noise).map_err(err)?;
        let decoded = self.model.decode(&z).map_err(err)?;
        let l1 = (&decoded - &images)?.abs()?.mean_all()?;
        let edges = edge_l1(&decoded, &images)?;
        let values_per_image = images.elem_count() / c.batch;
        let kl = (posterior.kl()?.mean_all()? / values_per_image as f64)?;
        let total = ((&l1 + (edges * c.edge_weight)?)? + (kl * c.kl_weight)?)?;
        let summary = CodecLoss {
            total: total.to_scalar::<f32>()? as f64,
            l1: l1.to_scalar::<f32>()? as f64,
        };
        Ok((total, summary))
    }
}

/// Measures SD's `scaling_factor` for a trained codec: 1 / std of posterior samples over up to `limit`
/// images, so the UNet sees latents of unit variance.
pub fn measure_scaling_factor<R: Rng>(
    model: &AutoencoderKL,
    data: &RenderedSet,
    limit: usize,
    rng: &mut R,
) -> Result<f64> {
    let err = |e: diffusion::vae::VaeError| candle_core::Error::Msg(e.to_string());
    let n = limit.min(data.len());
    let (mut sum, mut sum_sq, mut count) = (0f64, 0f64, 0f64);
    let mut start = 0;
    while start < n {
        let end = (start + 32).min(n);
        let posterior = model.encode(&data.images(start..end)?).map_err(err)?;
        let noise = randn(rng, posterior.mean.dims())?;
        let z = posterior.sample_with_noise(&noise).map_err(err)?;
        let values = z.flatten_all()?.to_dtype(DType::F64)?.to_vec1::<f64>()?;
        sum += values.iter().sum::<f64>();
        sum_sq += values.iter().map(|v| v * v).sum::<f64>();
        count += values.len() as f64;
        start = end;
    }
    let mean = sum / count.max(1.0);
    let std = (sum_sq / count.max(1.0) - mean * mean).max(1e-12).sqrt();
    Ok(1.0 / std)
}

/// Encodes images `0..data.len()` into posterior means and standard deviations (raw latents), in
/// batches; `progress(done)` after each batch.
pub fn encode_all(
    model: &AutoencoderKL,
    data: &RenderedSet,
    progress: &mut dyn FnMut(usize),
) -> Result<(Tensor, Tensor)> {
    let err = |e: diffusion::vae::VaeError| candle_core::Error::Msg(e.to_string());
    let (mut means, mut stds) = (Vec::new(), Vec::new());
    let mut start = 0;
    while start < data.len() {
        let end = (start + 64).min(data.len());
        let posterior = model.encode(&data.images(start..end)?).map_err(err)?;
        means.push(posterior.mean.contiguous()?);
        stds.push(posterior.std.contiguous()?);
        start = end;
        progress(start);
    }
    Ok((Tensor::cat(&means, 0)?, Tensor::cat(&stds, 0)?))
}
