//! What a demo-model training run builds: the architecture of each component (written out as the
//! diffusers/transformers `config.json` the exported folder carries) and the optimisation settings.

use serde::{Deserialize, Serialize};
use serde_json::{json, Value};

use crate::world::dataset::DatasetConfig;
use crate::world::{GeneratorSettings, PatternKind};

/// The latent codec: a diffusers `AutoencoderKL`, trained on random crops with L1 + edge + KL losses.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CodecConfig {
    /// One `DownEncoderBlock2D`/`UpDecoderBlock2D` per entry; n entries downscale by 2^(n−1).
    pub block_out_channels: Vec<usize>,
    pub layers_per_block: usize,
    pub norm_num_groups: usize,
    pub latent_channels: usize,
    pub steps: u64,
    pub batch: usize,
    /// Square crop side the codec trains on (fully convolutional: it runs on the whole image later).
    pub crop: usize,
    pub lr: f64,
    pub warmup: u64,
    /// Weight of the L1 loss on horizontal/vertical pixel differences (keeps edges and patterns sharp).
    pub edge_weight: f64,
    /// Weight of the posterior's KL divergence (summed over the latent) per image pixel value.
    pub kl_weight: f64,
    pub ema_decay: f64,
}

/// The text encoder: a transformers `CLIPTextModel` (quick-GELU, causal), trained with the UNet.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TextConfig {
    pub hidden_size: usize,
    pub intermediate_size: usize,
    pub layers: usize,
    pub heads: usize,
    /// The padded prompt length (SD's 77; the edit pipeline pads to it).
    pub max_positions: usize,
}

/// The denoiser: a diffusers `UNet2DConditionModel` (ε-prediction).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct UnetConfig {
    pub block_out_channels: Vec<usize>,
    /// Per down block: cross-attention (`CrossAttnDownBlock2D`) or not (`DownBlock2D`); mirrored on the
    /// way up. The mid block always has cross-attention.
    pub cross_attention: Vec<bool>,
    /// Per down block (mirrored on the way up; empty = none): its transformers attend to the text in
    /// both attention layers and never to the image (diffusers' `only_cross_attention`). It puts words
    /// on a fine level without self-attention's cost there (at 32×32 latents a step took 15 s with
    /// self-attention, 2.6 s without; docs/demo-model.md). Only where `cross_attention` is true.
    #[serde(default)]
    pub only_cross_attention: Vec<bool>,
    pub layers_per_block: usize,
    /// Attention heads per transformer (SD 1.x's `attention_head_dim` key, which counts heads).
    pub heads: usize,
    pub norm_num_groups: usize,
    pub steps: u64,
    pub batch: usize,
    pub lr: f64,
    pub warmup: u64,
    /// Fraction of captions replaced by the empty prompt (classifier-free guidance needs both).
    pub caption_dropout: f64,
    /// Min-SNR-γ loss weighting (Hang et al. 2023): weight min(SNR, γ)/SNR per timestep.
    pub min_snr_gamma: f64,
    pub ema_decay: f64,
    /// First and last β of the scaled-linear noise schedule the UNet learns (and the exported scheduler
    /// config carries). SD 1.x's 0.00085 → 0.012 where absent. A latent twice as wide at the same noise
    /// level keeps more of its image (neighbouring latents share it), so a finer codec needs noisier
    /// steps for the same difficulty: 0.00335 → 0.0107 divides SD's signal-to-noise ratio by 4 at every
    /// step to within 10 % (what 32² latents need to match SD's at 16²; Hoogeboom et al. 2023, "simple
    /// diffusion", shift the schedule the same way).
    #[serde(default = "sd_beta_start")]
    pub beta_start: f64,
    #[serde(default = "sd_beta_end")]
    pub beta_end: f64,
}

fn sd_beta_start() -> f64 {
    BETA_START
}

fn sd_beta_end() -> f64 {
    BETA_END
}

/// Everything a run depends on besides its output folder.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrainConfig {
    pub seed: u64,
    pub image_size: u32,
    /// World samples rendered once and reused by both stages.
    pub samples: usize,
    /// Pattern families drawn by the generator (listing one twice doubles its share).
    pub patterns: Vec<PatternKind>,
    pub codec: CodecConfig,
    pub text: TextConfig,
    pub unet: UnetConfig,
    /// Minutes between checkpoints.
    pub checkpoint_minutes: f64,
}

/// The noise schedule of SD 1.x: its step count (every demo model's) and betas (the default of
/// [`UnetConfig::beta_start`] / [`UnetConfig::beta_end`]).
pub const TRAIN_TIMESTEPS: usize = 1000;
pub const BETA_START: f64 = 0.00085;
pub const BETA_END: f64 = 0.012;

impl TrainConfig {
    /// The committed demo model (see the module docs of [`crate::train`] for the reasoning).
    pub fn demo() -> Self {
        Self {
            seed: 0,
            image_size: 128,
            samples: 24_000,
            patterns: vec![
                PatternKind::Solid,
                PatternKind::Solid,
                PatternKind::Stripes,
                PatternKind::Checker,
                PatternKind::Dots,
                PatternKind::Gradient,
            ],
            codec: CodecConfig {
                block_out_channels: vec![16, 32, 64],
                layers_per_block: 1,
                norm_num_groups: 8,
                latent_channels: 4,
                steps: 2000,
                batch: 16,
                crop: 64,
                lr: 1e-3,
                warmup: 100,
                edge_weight: 0.5,
                kl_weight: 1e-6,
                ema_decay: 0.999,
            },
            text: TextConfig {
                hidden_size: 64,
                intermediate_size: 256,
                layers: 2,
                heads: 4,
                max_positions: 77,
            },
            unet: UnetConfig {
                block_out_channels: vec![16, 32, 64, 128],
                cross_attention: vec![false, true, true, false],
                only_cross_attention: Vec::new(),
                layers_per_block: 1,
                heads: 4,
                norm_num_groups: 8,
                steps: 4000,
                batch: 32,
                lr: 5e-4,
                warmup: 200,
                caption_dropout: 0.1,
                min_snr_gamma: 5.0,
                ema_decay: 0.999,
                // SD's schedule shifted for 32² latents (see `UnetConfig::beta_start`): with SD's
                // own the words bound weakly (docs/demo-model.md, "The fully trained candidate").
                beta_start: 0.00335,
                beta_end: 0.0107,
            },
            checkpoint_minutes: 5.0,
        }
    }

    /// A minute-scale configuration for tests: 32×32 images, tiny networks, a few steps.
    pub fn tiny() -> Self {
        let mut c = Self::demo();
        c.image_size = 32;
        c.samples = 48;
        c.codec = CodecConfig {
            block_out_channels: vec![8, 8, 8, 8],
            norm_num_groups: 4,
            steps: 30,
            batch: 4,
            crop: 32,
            lr: 2e-3,
            warmup: 5,
            ..c.codec
        };
        c.text = TextConfig {
            hidden_size: 16,
            intermediate_size: 32,
            layers: 1,
            heads: 2,
            max_positions: 77,
        };
        c.unet = UnetConfig {
            block_out_channels: vec![16, 16],
            cross_attention: vec![true, true],
            heads: 2,
            norm_num_groups: 8,
            steps: 30,
            batch: 8,
            lr: 2e-3,
            warmup: 5,
            // 4² latents: SD's schedule, not the preset's shift for 32².
            beta_start: BETA_START,
            beta_end: BETA_END,
            ..c.unet
        };
        c.checkpoint_minutes = 60.0;
        c
    }

    /// The world's dataset settings for this run.
    pub fn dataset(&self) -> DatasetConfig {
        DatasetConfig {
            width: self.image_size,
            height: self.image_size,
            generator: GeneratorSettings {
                patterns: self.patterns.clone(),
                ..Default::default()
            },
            ..Default::default()
        }
    }

    /// Latent side length.
    pub fn latent_size(&self) -> usize {
        self.image_size as usize >> (self.codec.block_out_channels.len() - 1)
    }

    /// Whether a run with `other` can continue this one's checkpoints (only step counts and the
    /// checkpoint interval may differ).
    pub fn compatible_with(&self, other: &TrainConfig) -> bool {
        let strip = |c: &TrainConfig| {
            let mut c = c.clone();
            c.codec.steps = 0;
            c.unet.steps = 0;
            c.checkpoint_minutes = 0.0;
            c
        };
        strip(self) == strip(other)
    }

    /// Checks the numbers fit together; the message names the offending setting.
    pub fn validate(&self) -> Result<(), String> {
        let n = self.codec.block_out_channels.len();
        if n < 2 || !(self.image_size as usize).is_multiple_of(1 << (n - 1)) {
            return Err(format!(
                "image size {} is not divisible by the codec's downscale {}",
                self.image_size,
                1usize << n.saturating_sub(1)
            ));
        }
        if self.codec.crop == 0
            || self.codec.crop > self.image_size as usize
            || !self.codec.crop.is_multiple_of(1 << (n - 1))
        {
            return Err(format!(
                "codec crop {} must divide into latents and fit the image",
                self.codec.crop
            ));
        }
        let u = &self.unet;
        if u.cross_attention.len() != u.block_out_channels.len()
            || !u.cross_attention.contains(&true)
        {
            return Err(
                "unet.cross_attention needs one entry per block and at least one true".into(),
            );
        }
        let only = &u.only_cross_attention;
        if !(only.is_empty() || only.len() == u.cross_attention.len())
            || only.iter().zip(&u.cross_attention).any(|(&o, &c)| o && !c)
        {
            return Err(
                "unet.only_cross_attention needs one entry per block (or none), true only \
                 where unet.cross_attention is"
                    .into(),
            );
        }
        if !self
            .latent_size()
            .is_multiple_of(1 << (u.block_out_channels.len() - 1))
        {
            return Err(format!(
                "latent size {} is not divisible by the UNet's downscale",
                self.latent_size()
            ));
        }
        if !self.text.hidden_size.is_multiple_of(self.text.heads) {
            return Err("text hidden size must be divisible by its heads".into());
        }
        if self.samples == 0 || self.codec.batch == 0 || u.batch == 0 {
            return Err("samples and batch sizes must be positive".into());
        }
        if !(0.0..1.0).contains(&u.caption_dropout) {
            return Err("caption dropout must be in [0, 1)".into());
        }
        if !(u.beta_start > 0.0 && u.beta_start < u.beta_end && u.beta_end < 1.0) {
            return Err(format!(
                "unet.beta_start {} and unet.beta_end {} must satisfy 0 < start < end < 1",
                u.beta_start, u.beta_end
            ));
        }
        Ok(())
    }

    /// `vae/config.json`.
    pub fn vae_config_json(&self, scaling_factor: f64) -> Value {
        let c = &self.codec;
        let n = c.block_out_channels.len();
        json!({
            "_class_name": "AutoencoderKL",
            "_diffusers_version": "0.42.1",
            "act_fn": "silu",
            "block_out_channels": c.block_out_channels,
            "down_block_types": vec!["DownEncoderBlock2D"; n],
            "up_block_types": vec!["UpDecoderBlock2D"; n],
            "force_upcast": false,
            "in_channels": 3,
            "out_channels": 3,
            "latent_channels": c.latent_channels,
            "latents_mean": null,
            "latents_std": null,
            "layers_per_block": c.layers_per_block,
            "mid_block_add_attention": true,
            "norm_num_groups": c.norm_num_groups,
            "sample_size": self.image_size,
            "scaling_factor": scaling_factor,
            "shift_factor": null,
            "use_quant_conv": true,
            "use_post_quant_conv": true,
        })
    }

    /// `unet/config.json`.
    pub fn unet_config_json(&self) -> Value {
        let u = &self.unet;
        let down: Vec<&str> = u
            .cross_attention
            .iter()
            .map(|&x| {
                if x {
                    "CrossAttnDownBlock2D"
                } else {
                    "DownBlock2D"
                }
            })
            .collect();
        let up: Vec<&str> = u
            .cross_attention
            .iter()
            .rev()
            .map(|&x| if x { "CrossAttnUpBlock2D" } else { "UpBlock2D" })
            .collect();
        // diffusers' key takes one flag for all blocks or one per down block.
        let only_cross_attention = if u.only_cross_attention.contains(&true) {
            json!(u.only_cross_attention)
        } else {
            json!(false)
        };
        json!({
            "_class_name": "UNet2DConditionModel",
            "_diffusers_version": "0.42.1",
            "act_fn": "silu",
            "attention_head_dim": u.heads,
            "block_out_channels": u.block_out_channels,
            "center_input_sample": false,
            "cross_attention_dim": self.text.hidden_size,
            "down_block_types": down,
            "downsample_padding": 1,
            "dual_cross_attention": false,
            "flip_sin_to_cos": true,
            "freq_shift": 0,
            "in_channels": self.codec.latent_channels,
            "layers_per_block": u.layers_per_block,
            "mid_block_scale_factor": 1,
            "mid_block_type": "UNetMidBlock2DCrossAttn",
            "norm_eps": 1e-5,
            "norm_num_groups": u.norm_num_groups,
            "num_attention_heads": null,
            "only_cross_attention": only_cross_attention,
            "out_channels": self.codec.latent_channels,
            "sample_size": self.latent_size(),
            "time_cond_proj_dim": null,
            "transformer_layers_per_block": 1,
            "up_block_types": up,
            "upcast_attention": false,
            "use_linear_projection": false,
        })
    }

    /// `text_encoder/config.json` for a vocabulary of `vocab_size` tokens whose last two are the start
    /// and end tokens.
    pub fn text_config_json(&self, vocab_size: usize) -> Value {
        let t = &self.text;
        json!({
            "architectures": ["CLIPTextModel"],
            "model_type": "clip_text_model",
            "attention_dropout": 0.0,
            "bos_token_id": vocab_size - 2,
            "eos_token_id": vocab_size - 1,
            "pad_token_id": vocab_size - 1,
            "hidden_act": "quick_gelu",
            "hidden_size": t.hidden_size,
            "initializer_factor": 1.0,
            "initializer_range": 0.02,
            "intermediate_size": t.intermediate_size,
            "layer_norm_eps": 1e-5,
            "max_position_embeddings": t.max_positions,
            "num_attention_heads": t.heads,
            "num_hidden_layers": t.layers,
            "projection_dim": t.hidden_size,
            "torch_dtype": "float32",
            "vocab_size": vocab_size,
        })
    }

    /// `scheduler/scheduler_config.json`: an `LCMScheduler` over the scaled-linear schedule the UNet
    /// learned, so the editor's LCM step selection (15 of 50 "original" steps) applies; DDIM reads the
    /// same betas.
    pub fn scheduler_config_json(&self) -> Value {
        json!({
            "_class_name": "LCMScheduler",
            "_diffusers_version": "0.42.1",
            "beta_end": self.unet.beta_end,
            "beta_schedule": "scaled_linear",
            "beta_start": self.unet.beta_start,
            "clip_sample": false,
            "clip_sample_range": 1.0,
            "dynamic_thresholding_ratio": 0.995,
            "num_train_timesteps": TRAIN_TIMESTEPS,
            "original_inference_steps": 50,
            "prediction_type": "epsilon",
            "rescale_betas_zero_snr": false,
            "sample_max_value": 1.0,
            "set_alpha_to_one": true,
            "steps_offset": 1,
            "thresholding": false,
            "timestep_scaling": 10.0,
            "timestep_spacing": "leading",
            "trained_betas": null,
        })
    }

    /// `model_index.json`.
    pub fn model_index_json() -> Value {
        json!({
            "_class_name": "StableDiffusionPipeline",
            "_diffusers_version": "0.42.1",
            "feature_extractor": [null, null],
            "image_encoder": [null, null],
            "requires_safety_checker": false,
            "safety_checker": [null, null],
            "scheduler": ["diffusers", "LCMScheduler"],
            "text_encoder": ["transformers", "CLIPTextModel"],
            "tokenizer": ["transformers", "CLIPTokenizer"],
            "unet": ["diffusers", "UNet2DConditionModel"],
            "vae": ["diffusers", "AutoencoderKL"],
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use diffusion::clip::ClipTextConfig;
    use diffusion::unet::UNetConfig;
    use diffusion::vae::AutoencoderKLConfig;

    #[test]
    fn the_scaling_factor_reads_back_bit_exactly() {
        // `--init` takes the codec's scaling factor from its config.json; serde_json's default float
        // parser is one ulp off on values like this one (seen in CI), hence `float_roundtrip`.
        let scaling = 0.477_375_679_563_579_07;
        let text = TrainConfig::tiny().vae_config_json(scaling).to_string();
        let json: serde_json::Value = serde_json::from_str(&text).unwrap();
        assert_eq!(json["scaling_factor"].as_f64(), Some(scaling));
    }

    #[test]
    fn configs_validate_and_parse_with_the_model_code() {
        for c in [TrainConfig::demo(), TrainConfig::tiny()] {
            c.validate().unwrap();
            let unet = UNetConfig::from_json(&c.unet_config_json().to_string()).unwrap();
            let resolved = unet.resolve().unwrap();
            assert_eq!(resolved.heads[0], c.unet.heads);
            let vae: AutoencoderKLConfig = serde_json::from_value(c.vae_config_json(0.5)).unwrap();
            vae.validate().unwrap();
            assert_eq!(
                vae.spatial_factor() * c.latent_size(),
                c.image_size as usize
            );
            let text: ClipTextConfig = serde_json::from_value(c.text_config_json(600)).unwrap();
            assert_eq!((text.eos_token_id, text.max_position_embeddings), (599, 77));
        }
        let demo = TrainConfig::demo();
        assert_eq!(demo.latent_size(), 32);
        // Cross-attention at two resolutions (16×16 and 8×8): the editor's blend and CCM need maps.
        assert!(demo.unet.cross_attention.iter().filter(|&&x| x).count() >= 2);
    }

    #[test]
    fn compatibility_ignores_only_step_counts() {
        let a = TrainConfig::demo();
        let mut b = a.clone();
        b.unet.steps += 1000;
        b.codec.steps += 5;
        assert!(a.compatible_with(&b));
        b.unet.lr *= 2.0;
        assert!(!a.compatible_with(&b));
    }

    #[test]
    fn invalid_settings_are_named() {
        let mut c = TrainConfig::demo();
        c.image_size = 102;
        assert!(c.validate().unwrap_err().contains("image size"));
        let mut c = TrainConfig::demo();
        c.unet.cross_attention = vec![false, false, false];
        assert!(c.validate().unwrap_err().contains("cross_attention"));
        let mut c = TrainConfig::demo();
        c.unet.beta_end = c.unet.beta_start;
        assert!(c.validate().unwrap_err().contains("beta_end"));
        // only_cross_attention: one entry per block, and only on blocks that have attention.
        let mut c = TrainConfig::demo();
        c.unet.only_cross_attention = vec![true, false];
        assert!(c.validate().unwrap_err().contains("only_cross_attention"));
        c.unet.only_cross_attention = vec![true, false, false, false];
        assert!(c.validate().unwrap_err().contains("only_cross_attention"));
    }

    #[test]
    fn only_cross_attention_reaches_the_model_config() {
        let mut c = TrainConfig::demo();
        assert_eq!(c.unet_config_json()["only_cross_attention"], json!(false));
        c.unet.cross_attention = vec![true, true, true, false];
        c.unet.only_cross_attention = vec![true, false, false, false];
        c.validate().unwrap();
        let resolved = UNetConfig::from_json(&c.unet_config_json().to_string())
            .unwrap()
            .resolve()
            .unwrap();
        assert_eq!(resolved.only_cross_attention, [true, false, false, false]);
        // A config written before the field existed reads as none.
        let mut old = serde_json::to_value(TrainConfig::demo()).unwrap();
        old["unet"]
            .as_object_mut()
            .unwrap()
            .remove("only_cross_attention");
        let old: TrainConfig = serde_json::from_value(old).unwrap();
        assert_eq!(old, TrainConfig::demo());
    }

    #[test]
    fn the_exported_scheduler_runs_the_schedule_the_unet_learned() {
        use diffusion::scheduler::{LcmConfig, LcmScheduler, LcmVariant};
        let c = TrainConfig::demo();
        assert_eq!((c.unet.beta_start, c.unet.beta_end), (0.00335, 0.0107));
        let lcm: LcmConfig = serde_json::from_value(c.scheduler_config_json()).unwrap();
        let exported = LcmScheduler::new(lcm, LcmVariant::default()).unwrap();
        let trained = super::super::denoiser::noise_schedule(&c.unet);
        let mut sd = c.unet.clone();
        (sd.beta_start, sd.beta_end) = (BETA_START, BETA_END);
        let sd = super::super::denoiser::noise_schedule(&sd);
        for t in [0, 250, 999] {
            let (e, l) = (
                exported.noise_schedule().alpha_cumprod(t).unwrap(),
                trained.alpha_cumprod(t).unwrap(),
            );
            assert_eq!(e, l, "t {t}");
            // Not SD's: the shifted schedule is noisier at every step.
            assert!(l < sd.alpha_cumprod(t).unwrap(), "t {t}");
        }
    }

    #[test]
    fn the_committed_training_configs_parse_and_fit() {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tools/demo-model");
        let mut seen = 0;
        for entry in std::fs::read_dir(&dir).unwrap() {
            let path = entry.unwrap().path();
            if path.extension().is_some_and(|e| e == "json") {
                let text = std::fs::read_to_string(&path).unwrap();
                let config: TrainConfig = serde_json::from_str(&text)
                    .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
                config
                    .validate()
                    .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
                seen += 1;
            }
        }
        assert!(seen >= 2, "configs in {}", dir.display());
    }

    #[test]
    fn configs_written_before_the_schedule_was_configurable_mean_sds() {
        let mut json = serde_json::to_value(TrainConfig::demo()).unwrap();
        let unet = json["unet"].as_object_mut().unwrap();
        unet.remove("beta_start");
        unet.remove("beta_end");
        let parsed: TrainConfig = serde_json::from_value(json).unwrap();
        let mut expected = TrainConfig::demo();
        (expected.unet.beta_start, expected.unet.beta_end) = (BETA_START, BETA_END);
        assert_eq!(parsed, expected);
        assert_eq!(
            (parsed.unet.beta_start, parsed.unet.beta_end),
            (0.00085, 0.012)
        );
    }
}
