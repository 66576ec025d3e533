//! Text-to-image sampling with a loaded model (DDIM with classifier-free guidance), for the demo model's
//! sample grid and for checking what a model learnt.

use candle_core::{Device, Tensor};
use diffusion::clip::ids_tensor;
use diffusion::scheduler::{DdimConfig, DdimScheduler, TimestepSpacing};
use edit::sampler::{tensor_to_images, EditModel};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use splat::Image;

use crate::train::codec::randn;

#[derive(Clone, Debug)]
pub struct SampleSettings {
    pub steps: usize,
    /// Classifier-free guidance scale (1 = conditional prediction only).
    pub guidance: f64,
    /// DDIM's η (0 deterministic, 1 ancestral-like).
    pub eta: f64,
    pub seed: u64,
    /// Output side length in pixels (the model's native size when `None`).
    pub size: Option<usize>,
}

impl Default for SampleSettings {
    fn default() -> Self {
        Self {
            steps: 30,
            guidance: 4.0,
            eta: 0.0,
            seed: 0,
            size: None,
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum SampleError {
    #[error("prompt {prompt:?}: {source}")]
    Prompt {
        prompt: String,
        source: diffusion::tokenizer::TokenizerError,
    },
    #[error(transparent)]
    Scheduler(#[from] diffusion::scheduler::SchedulerError),
    #[error("{0}")]
    Candle(#[from] candle_core::Error),
}

/// The model's native image side: the UNet's `sample_size` times the codec's downscale (128 for the demo).
pub fn native_size(model: &EditModel) -> usize {
    model.unet.config().sample_size.unwrap_or(64) * model.downscale()
}

/// One image per prompt (all in one batch). Each prompt's starting noise depends only on the seed and its
/// position in the list.
pub fn generate(
    model: &EditModel,
    prompts: &[String],
    settings: &SampleSettings,
) -> Result<Vec<Image>, SampleError> {
    let dev = Device::Cpu;
    let size = settings.size.unwrap_or_else(|| native_size(model));
    let f = model.downscale();
    let latent_shape = [1, model.latent_channels(), size / f, size / f];
    let b = prompts.len();

    let tokenizer = &model.tokenizer;
    let mut encodings = Vec::with_capacity(2 * b);
    for _ in 0..b {
        encodings.push(tokenizer.encode(""));
    }
    for p in prompts {
        encodings.push(
            tokenizer
                .encode_strict(p)
                .map_err(|source| SampleError::Prompt {
                    prompt: p.clone(),
                    source,
                })?,
        );
    }
    let context = model.text_encoder.forward(&ids_tensor(&encodings, &dev)?)?;

    let lcm = &model.scheduler_config;
    let mut scheduler = DdimScheduler::new(DdimConfig {
        num_train_timesteps: lcm.num_train_timesteps,
        beta_start: lcm.beta_start,
        beta_end: lcm.beta_end,
        beta_schedule: lcm.beta_schedule,
        trained_betas: lcm.trained_betas.clone(),
        clip_sample: false,
        set_alpha_to_one: false,
        steps_offset: 1,
        prediction_type: lcm.prediction_type,
        timestep_spacing: TimestepSpacing::Leading,
        ..DdimConfig::default()
    })?;
    let timesteps = scheduler.set_timesteps(settings.steps)?.to_vec();

    let noises: Vec<Tensor> = (0..b)
        .map(|k| {
            randn(
                &mut ChaCha8Rng::seed_from_u64(settings.seed.wrapping_add(k as u64)),
                &latent_shape,
            )
        })
        .collect::<Result<_, _>>()?;
    let mut latents = Tensor::cat(&noises, 0)?;
    let mut step_rng = ChaCha8Rng::seed_from_u64(settings.seed ^ 0x5eed);
    for &t in &timesteps {
        let input = Tensor::cat(&[&latents, &latents], 0)?;
        let eps =
            model
                .unet
                .forward(&input, &Tensor::new(t as f32, &dev)?, &context, None, None)?;
        let (uncond, cond) = (eps.narrow(0, 0, b)?, eps.narrow(0, b, b)?);
        let guided = (&uncond + ((cond - &uncond)? * settings.guidance)?)?;
        let noise = if settings.eta > 0.0 {
            let mut shape = latent_shape;
            shape[0] = b;
            Some(randn(&mut step_rng, &shape)?)
        } else {
            None
        };
        latents = scheduler
            .step(&guided, t, &latents, settings.eta, false, noise.as_ref())?
            .prev_sample;
    }
    let decoded = model.decode(&latents)?;
    let images = ((decoded.clamp(-1.0, 1.0)? + 1.0)? * 0.5)?;
    Ok(tensor_to_images(&images)?)
}
