//! Stage 2: the text encoder and the UNet learn, jointly, to predict the noise added to scaled latents.
//!
//! Per batch: random samples; latents drawn from each sample's codec posterior (mean + std·n) times the
//! scaling factor; captions replaced by the empty prompt with probability `caption_dropout` (for
//! classifier-free guidance); timesteps stratified over [0, 1000) (one per equal-width bin, so every batch
//! covers the whole schedule); loss = mean over the batch of min(SNR, γ)/SNR · |ε̂ − ε|².

use candle_core::{DType, Device, Result, Tensor};
use candle_nn::{VarBuilder, VarMap};
use diffusion::clip::{ClipTextConfig, ClipTextModel};
use diffusion::scheduler::{BetaParams, BetaSchedule, NoiseSchedule};
use diffusion::unet::{UNet2DConditionModel, UNetConfig};
use rand::Rng;

use super::codec::randn;
use super::config::{TrainConfig, UnetConfig, TRAIN_TIMESTEPS};
use super::data::random_indices;

/// The encoded training set: posterior statistics of every sample and its caption's token ids.
pub struct LatentSet {
    /// Raw (unscaled) posterior means [N, C, h, w].
    pub mean: Tensor,
    /// Posterior standard deviations [N, C, h, w].
    pub std: Tensor,
    /// Token ids [N, max_positions] (u32).
    pub ids: Tensor,
    /// Ids of the empty prompt `[max_positions]` (u32).
    pub empty_ids: Tensor,
    pub scaling_factor: f64,
}

impl LatentSet {
    pub fn len(&self) -> usize {
        self.ids.dim(0).unwrap_or(0)
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// The training noise schedule: SD 1.x's shape with the run's betas.
pub fn noise_schedule(unet: &UnetConfig) -> NoiseSchedule {
    NoiseSchedule::new(&BetaParams {
        num_train_timesteps: TRAIN_TIMESTEPS,
        beta_start: unet.beta_start,
        beta_end: unet.beta_end,
        beta_schedule: BetaSchedule::ScaledLinear,
        trained_betas: None,
        rescale_betas_zero_snr: false,
        set_alpha_to_one: false,
    })
    .expect("betas checked by TrainConfig::validate")
}

/// The text encoder and UNet being trained, in one `VarMap` (prefixes `text_encoder.` and `unet.`).
pub struct DenoiserTrainer {
    pub varmap: VarMap,
    pub text_encoder: ClipTextModel,
    pub unet: UNet2DConditionModel,
    schedule: NoiseSchedule,
}

/// Loss of one batch.
#[derive(Clone, Copy, Debug)]
pub struct DenoiserLoss {
    /// The weighted loss that is optimised.
    pub total: f64,
    /// Unweighted mean squared error of the noise prediction.
    pub mse: f64,
}

impl DenoiserTrainer {
    pub fn new(config: &TrainConfig, vocab_size: usize) -> Result<Self> {
        let varmap = VarMap::new();
        let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
        let text_config: ClipTextConfig =
            serde_json::from_value(config.text_config_json(vocab_size))
                .expect("generated config parses");
        let text_encoder = ClipTextModel::new(vb.pp("text_encoder"), text_config)
            .map_err(|e| candle_core::Error::Msg(e.to_string()))?;
        let unet_config = UNetConfig::from_json(&config.unet_config_json().to_string())
            .map_err(|e| candle_core::Error::Msg(e.to_string()))?;
        let unet = UNet2DConditionModel::load(&unet_config, vb.pp("unet"))
            .map_err(|e| candle_core::Error::Msg(e.to_string()))?;
        Ok(Self {
            varmap,
            text_encoder,
            unet,
            schedule: noise_schedule(&config.unet),
        })
    }

    /// Forward pass and loss of one batch (call `backward` on `.0`).
    pub fn loss<R: Rng>(
        &self,
        config: &TrainConfig,
        data: &LatentSet,
        rng: &mut R,
    ) -> Result<(Tensor, DenoiserLoss)> {
        let u = &config.unet;
        let b = u.batch;
        let dev = Device::Cpu;
        let indices = random_indices(data.len(), b, rng);
        let index = Tensor::new(indices.iter().map(|&i| i as u32).collect::<Vec<_>>(), &dev)?;
        let mean = data.mean.index_select(&index, 0)?;
        let std = data.std.index_select(&index, 0)?;
        let posterior_noise = randn(rng, mean.dims())?;
        let latents = ((mean + (std * posterior_noise)?)? * data.scaling_factor)?;

        let ids: Vec<Tensor> = indices
            .iter()
            .map(|&i| {
                if rng.gen_bool(u.caption_dropout) {
                    Ok(data.empty_ids.clone())
                } else {
                    data.ids.get(i)
                }
            })
            .collect::<Result<_>>()?;
        let ids = Tensor::stack(&ids, 0)?;

        // Stratified timesteps: sample k falls in the k-th of b equal bins.
        let steps = TRAIN_TIMESTEPS as f64;
        let timesteps: Vec<usize> = (0..b)
            .map(|k| {
                (((k as f64 + rng.gen::<f64>()) / b as f64 * steps) as usize)
                    .min(TRAIN_TIMESTEPS - 1)
            })
            .collect();
        let alphas: Vec<f64> = timesteps
            .iter()
            .map(|&t| self.schedule.alphas_cumprod[t])
            .collect();
        let column = |f: &dyn Fn(f64) -> f64| -> Result<Tensor> {
            Tensor::from_vec(
                alphas.iter().map(|&a| f(a) as f32).collect::<Vec<_>>(),
                (b, 1, 1, 1),
                &dev,
            )
        };
        let noise = randn(rng, latents.dims())?;
        let noisy = (latents.broadcast_mul(&column(&|a| a.sqrt())?)?
            + noise.broadcast_mul(&column(&|a| (1.0 - a).sqrt())?)?)?;
        let weights: Vec<f32> = alphas
            .iter()
            .map(|&a| {
                let snr = a / (1.0 - a);
                (snr.min(u.min_snr_gamma) / snr) as f32
            })
            .collect();
        let weights = Tensor::from_vec(weights, b, &dev)?;
        let t = Tensor::from_vec(
            timesteps.iter().map(|&t| t as f32).collect::<Vec<_>>(),
            b,
            &dev,
        )?;

        let context = self.text_encoder.forward(&ids)?;
        let predicted = self.unet.forward(&noisy, &t, &context, None, None)?;
        let per_sample = (predicted - noise)?.sqr()?.flatten_from(1)?.mean(1)?;
        let total = (&per_sample * &weights)?.mean_all()?;
        let summary = DenoiserLoss {
            total: total.to_scalar::<f32>()? as f64,
            mse: per_sample.mean_all()?.to_scalar::<f32>()? as f64,
        };
        Ok((total, summary))
    }
}
