//! The Stable Diffusion VAE (diffusers `AutoencoderKL`) and a common interface over it and TAESD.
//!
//! Conventions, as in diffusers:
//! - images are NCHW f32 in **[-1, 1]** on both sides (decoded images are not clamped);
//! - "raw" latents are what the autoencoder itself produces/consumes; the UNet works on **scaled** latents
//!   `(z − shift_factor) · scaling_factor` (SD 1.x: `z · 0.18215`). Methods without a suffix take/return raw
//!   latents; the `*_scaled` ones convert.
//! - the posterior is a diagonal Gaussian whose log-variance is clamped to [−30, 20]; sampling takes either an
//!   explicit noise tensor or a caller-owned RNG, so randomness is always under the caller's control.
//!
//! Every op is differentiable when gradients are needed (the kernels switch to their training variants
//! automatically), so a small VAE can be trained with a `VarMap`-backed `VarBuilder`.

use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use rand::Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::Deserialize;

use crate::device;
use crate::kernels::DeviceTensor;
use crate::layers::{
    conv2d, Conv2d, Downsample2D, GroupNorm, ResnetBlock2D, ResnetConfig, SpatialSelfAttention,
    Upsample2D,
};
use crate::taesd::{self, AutoencoderTiny, TaesdError};

pub const CONFIG_FILE: &str = "config.json";
pub const WEIGHTS_FILE: &str = "diffusion_pytorch_model.safetensors";

/// diffusers hard-codes this epsilon for every norm in the VAE's encoder and decoder.
const NORM_EPS: f64 = 1e-6;
/// `DiagonalGaussianDistribution` clamps the log-variance to this range.
const LOGVAR_MIN: f64 = -30.0;
const LOGVAR_MAX: f64 = 20.0;

#[derive(Debug, thiserror::Error)]
pub enum VaeError {
    #[error("{dir}: not a VAE folder: {missing}")]
    MissingFiles { dir: PathBuf, missing: String },
    #[error("{path}: {message}")]
    Config { path: PathBuf, message: String },
    #[error("{path}: cannot load VAE weights: {source}")]
    Weights {
        path: PathBuf,
        source: candle_core::Error,
    },
    #[error("VAE {what}: expected {expected}, got shape {got:?}")]
    Input {
        what: &'static str,
        expected: String,
        got: Vec<usize>,
    },
    #[error(transparent)]
    Taesd(#[from] TaesdError),
    #[error("VAE forward: {0}")]
    Candle(#[from] candle_core::Error),
}

pub type Result<T> = std::result::Result<T, VaeError>;

/// Mirrors diffusers' `AutoencoderKL` `config.json`; keys absent from the file take diffusers' defaults.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(default)]
pub struct AutoencoderKLConfig {
    pub in_channels: usize,
    pub out_channels: usize,
    pub down_block_types: Vec<String>,
    pub up_block_types: Vec<String>,
    pub block_out_channels: Vec<usize>,
    pub layers_per_block: usize,
    pub act_fn: String,
    pub latent_channels: usize,
    pub norm_num_groups: usize,
    pub scaling_factor: f64,
    /// `null` or absent in SD 1.x configs (treated as 0); set by SD3/Flux-style VAEs.
    pub shift_factor: Option<f64>,
    /// Per-channel latent statistics some pipelines use; diffusers' `AutoencoderKL` itself ignores them.
    pub latents_mean: Option<Vec<f64>>,
    pub latents_std: Option<Vec<f64>>,
    pub force_upcast: bool,
    pub use_quant_conv: bool,
    pub use_post_quant_conv: bool,
    pub mid_block_add_attention: bool,
}

impl Default for AutoencoderKLConfig {
    fn default() -> Self {
        Self {
            in_channels: 3,
            out_channels: 3,
            down_block_types: vec!["DownEncoderBlock2D".into()],
            up_block_types: vec!["UpDecoderBlock2D".into()],
            block_out_channels: vec![64],
            layers_per_block: 1,
            act_fn: "silu".into(),
            latent_channels: 4,
            norm_num_groups: 32,
            scaling_factor: 0.18215,
            shift_factor: None,
            latents_mean: None,
            latents_std: None,
            force_upcast: true,
            use_quant_conv: true,
            use_post_quant_conv: true,
            mid_block_add_attention: true,
        }
    }
}

impl AutoencoderKLConfig {
    /// The SD 1.x VAE (`runwayml/stable-diffusion-v1-5/vae/config.json`).
    pub fn sd15() -> Self {
        Self {
            down_block_types: vec!["DownEncoderBlock2D".into(); 4],
            up_block_types: vec!["UpDecoderBlock2D".into(); 4],
            block_out_channels: vec![128, 256, 512, 512],
            layers_per_block: 2,
            ..Self::default()
        }
    }

    pub fn from_file(path: &Path) -> Result<Self> {
        let bad = |message: String| VaeError::Config {
            path: path.to_path_buf(),
            message,
        };
        let text = std::fs::read_to_string(path).map_err(|e| bad(e.to_string()))?;
        let cfg: Self = serde_json::from_str(&text)
            .map_err(|e| bad(format!("invalid AutoencoderKL config: {e}")))?;
        cfg.validate().map_err(bad)?;
        Ok(cfg)
    }

    /// Checks what the architecture relies on; the message names the offending keys.
    pub fn validate(&self) -> std::result::Result<(), String> {
        let n = self.block_out_channels.len();
        if n == 0 || self.block_out_channels.contains(&0) {
            return Err("block_out_channels must be non-empty and positive".into());
        }
        if self.down_block_types.len() != n || self.up_block_types.len() != n {
            return Err(format!(
                "down_block_types ({}) and up_block_types ({}) must have one entry per block_out_channels ({n})",
                self.down_block_types.len(),
                self.up_block_types.len()
            ));
        }
        if let Some(t) = self
            .down_block_types
            .iter()
            .find(|t| *t != "DownEncoderBlock2D")
        {
            return Err(format!(
                "down block type {t:?} is not supported (DownEncoderBlock2D)"
            ));
        }
        if let Some(t) = self
            .up_block_types
            .iter()
            .find(|t| *t != "UpDecoderBlock2D")
        {
            return Err(format!(
                "up block type {t:?} is not supported (UpDecoderBlock2D)"
            ));
        }
        // The shared ResNet blocks apply SiLU; diffusers' VAE configs all use it.
        if self.act_fn != "silu" && self.act_fn != "swish" {
            return Err(format!("act_fn {:?} is not supported (silu)", self.act_fn));
        }
        let g = self.norm_num_groups;
        if g == 0 {
            return Err("norm_num_groups 0 must be at least 1".into());
        }
        if self.block_out_channels.iter().any(|c| c % g != 0) {
            return Err(format!(
                "norm_num_groups {g} must divide every block_out_channels entry {:?}",
                self.block_out_channels
            ));
        }
        if self.in_channels == 0 || self.out_channels == 0 || self.latent_channels == 0 {
            return Err("in_channels, out_channels and latent_channels must be positive".into());
        }
        if !(self.scaling_factor.is_finite() && self.scaling_factor != 0.0) {
            return Err(format!(
                "scaling_factor {} must be finite and non-zero",
                self.scaling_factor
            ));
        }
        Ok(())
    }

    /// Image pixels per latent pixel along each axis.
    pub fn spatial_factor(&self) -> usize {
        1 << (self.block_out_channels.len() - 1)
    }

    fn resnet(&self, in_channels: usize, out_channels: usize) -> ResnetConfig {
        ResnetConfig::new(
            in_channels,
            out_channels,
            None,
            self.norm_num_groups,
            NORM_EPS,
        )
    }
}

/// A block's `count` resnets (weights under `vb_block`'s `resnets.{j}`): the first from `in_ch` to
/// `out_ch` channels, the others `out_ch` to `out_ch`.
fn resnet_stack(
    cfg: &AutoencoderKLConfig,
    count: usize,
    in_ch: usize,
    out_ch: usize,
    vb_block: &VarBuilder,
) -> candle_core::Result<Vec<ResnetBlock2D>> {
    (0..count)
        .map(|j| {
            let cin = if j == 0 { in_ch } else { out_ch };
            ResnetBlock2D::load(
                &cfg.resnet(cin, out_ch),
                vb_block.pp(format!("resnets.{j}")),
            )
        })
        .collect()
}

/// `UNetMidBlock2D` without time embedding: resnet, single-head self-attention (optional), resnet.
#[derive(Debug, Clone)]
struct MidBlock {
    resnet_in: ResnetBlock2D,
    attention: Option<SpatialSelfAttention>,
    resnet_out: ResnetBlock2D,
}

impl MidBlock {
    fn new(
        cfg: &AutoencoderKLConfig,
        channels: usize,
        vb: VarBuilder,
    ) -> candle_core::Result<Self> {
        let resnet = cfg.resnet(channels, channels);
        let attention = if cfg.mid_block_add_attention {
            // attention_head_dim = channels: one head over all channels.
            Some(SpatialSelfAttention::load(
                channels,
                channels,
                cfg.norm_num_groups,
                NORM_EPS,
                vb.pp("attentions.0"),
            )?)
        } else {
            None
        };
        Ok(Self {
            resnet_in: ResnetBlock2D::load(&resnet, vb.pp("resnets.0"))?,
            attention,
            resnet_out: ResnetBlock2D::load(&resnet, vb.pp("resnets.1"))?,
        })
    }

    fn forward(&self, x: &DeviceTensor) -> candle_core::Result<DeviceTensor> {
        let mut h = self.resnet_in.forward_device(x, None)?;
        if let Some(attention) = &self.attention {
            h = attention.forward_device(&h)?;
        }
        self.resnet_out.forward_device(&h, None)
    }
}

/// `DownEncoderBlock2D`: resnets, then (except in the last block) a stride-2 conv with the asymmetric
/// (0, 1, 0, 1) zero padding diffusers uses for `padding=0`.
#[derive(Debug, Clone)]
struct DownBlock {
    resnets: Vec<ResnetBlock2D>,
    downsample: Option<Downsample2D>,
}

/// `UpDecoderBlock2D`: `layers_per_block + 1` resnets, then (except in the last block) nearest ×2 + conv.
#[derive(Debug, Clone)]
struct UpBlock {
    resnets: Vec<ResnetBlock2D>,
    upsample: Option<Upsample2D>,
}

/// diffusers' VAE `Encoder`: image → `2·latent_channels` moments (before `quant_conv`).
#[derive(Debug, Clone)]
pub struct VaeEncoder {
    conv_in: Conv2d,
    down_blocks: Vec<DownBlock>,
    mid_block: MidBlock,
    conv_norm_out: GroupNorm,
    conv_out: Conv2d,
}

impl VaeEncoder {
    pub fn new(cfg: &AutoencoderKLConfig, vb: VarBuilder) -> candle_core::Result<Self> {
        let chans = &cfg.block_out_channels;
        let conv_in = conv2d(cfg.in_channels, chans[0], 3, 1, 1, vb.pp("conv_in"))?;
        let mut down_blocks = Vec::with_capacity(chans.len());
        let mut in_ch = chans[0];
        for (i, &out_ch) in chans.iter().enumerate() {
            let vb_block = vb.pp(format!("down_blocks.{i}"));
            let resnets = resnet_stack(cfg, cfg.layers_per_block, in_ch, out_ch, &vb_block)?;
            let downsample = if i + 1 < chans.len() {
                Some(Downsample2D::load(
                    out_ch,
                    out_ch,
                    0,
                    vb_block.pp("downsamplers.0"),
                )?)
            } else {
                None
            };
            down_blocks.push(DownBlock {
                resnets,
                downsample,
            });
            in_ch = out_ch;
        }
        let last = *chans.last().expect("validated non-empty");
        Ok(Self {
            conv_in,
            down_blocks,
            mid_block: MidBlock::new(cfg, last, vb.pp("mid_block"))?,
            conv_norm_out: GroupNorm::load(
                cfg.norm_num_groups,
                last,
                NORM_EPS,
                vb.pp("conv_norm_out"),
            )?,
            conv_out: conv2d(last, 2 * cfg.latent_channels, 3, 1, 1, vb.pp("conv_out"))?,
        })
    }

    pub fn forward(&self, image: &Tensor) -> candle_core::Result<Tensor> {
        self.forward_device(&image.clone().into())?.to_cpu()
    }

    /// [`Self::forward`] on the image's device.
    pub fn forward_device(&self, image: &DeviceTensor) -> candle_core::Result<DeviceTensor> {
        let mut h = self.conv_in.forward_device(image)?;
        for block in &self.down_blocks {
            for resnet in &block.resnets {
                h = resnet.forward_device(&h, None)?;
            }
            if let Some(down) = &block.downsample {
                h = down.forward_device(&h)?;
            }
        }
        let h = self.mid_block.forward(&h)?;
        // conv_act is always SiLU in diffusers' Encoder.
        let h = self.conv_norm_out.forward_device(&h, true)?;
        self.conv_out.forward_device(&h)
    }
}

/// diffusers' VAE `Decoder`: latents (after `post_quant_conv`) → image in [-1, 1].
#[derive(Debug, Clone)]
pub struct VaeDecoder {
    conv_in: Conv2d,
    mid_block: MidBlock,
    up_blocks: Vec<UpBlock>,
    conv_norm_out: GroupNorm,
    conv_out: Conv2d,
}

impl VaeDecoder {
    pub fn new(cfg: &AutoencoderKLConfig, vb: VarBuilder) -> candle_core::Result<Self> {
        let reversed: Vec<usize> = cfg.block_out_channels.iter().rev().copied().collect();
        let top = reversed[0];
        let conv_in = conv2d(cfg.latent_channels, top, 3, 1, 1, vb.pp("conv_in"))?;
        let mid_block = MidBlock::new(cfg, top, vb.pp("mid_block"))?;
        let mut up_blocks = Vec::with_capacity(reversed.len());
        let mut in_ch = top;
        for (i, &out_ch) in reversed.iter().enumerate() {
            let vb_block = vb.pp(format!("up_blocks.{i}"));
            let resnets = resnet_stack(cfg, cfg.layers_per_block + 1, in_ch, out_ch, &vb_block)?;
            let upsample = if i + 1 < reversed.len() {
                Some(Upsample2D::load(
                    out_ch,
                    out_ch,
                    vb_block.pp("upsamplers.0"),
                )?)
            } else {
                None
            };
            up_blocks.push(UpBlock { resnets, upsample });
            in_ch = out_ch;
        }
        let bottom = cfg.block_out_channels[0];
        Ok(Self {
            conv_in,
            mid_block,
            up_blocks,
            conv_norm_out: GroupNorm::load(
                cfg.norm_num_groups,
                bottom,
                NORM_EPS,
                vb.pp("conv_norm_out"),
            )?,
            conv_out: conv2d(bottom, cfg.out_channels, 3, 1, 1, vb.pp("conv_out"))?,
        })
    }

    pub fn forward(&self, latents: &Tensor) -> candle_core::Result<Tensor> {
        self.forward_device(&latents.clone().into())?.to_cpu()
    }

    /// [`Self::forward`] on the latents' device.
    pub fn forward_device(&self, latents: &DeviceTensor) -> candle_core::Result<DeviceTensor> {
        let h = self.conv_in.forward_device(latents)?;
        let mut h = self.mid_block.forward(&h)?;
        for block in &self.up_blocks {
            for resnet in &block.resnets {
                h = resnet.forward_device(&h, None)?;
            }
            if let Some(up) = &block.upsample {
                h = up.forward_device(&h, None)?;
            }
        }
        let h = self.conv_norm_out.forward_device(&h, true)?;
        self.conv_out.forward_device(&h)
    }
}

/// The encoder's posterior `N(mean, exp(logvar))` per latent element (diffusers
/// `DiagonalGaussianDistribution`, non-deterministic mode).
#[derive(Debug, Clone)]
pub struct DiagonalGaussian {
    pub mean: Tensor,
    /// Clamped to [−30, 20].
    pub logvar: Tensor,
    pub std: Tensor,
}

impl DiagonalGaussian {
    /// Splits `moments` [B, 2C, H, W] into mean and log-variance along channels.
    pub fn from_moments(moments: &Tensor) -> candle_core::Result<Self> {
        let c = moments.dim(1)?;
        if c % 2 != 0 {
            candle_core::bail!("posterior moments need an even channel count, got {c}");
        }
        let mean = moments.narrow(1, 0, c / 2)?;
        let logvar = moments
            .narrow(1, c / 2, c / 2)?
            .clamp(LOGVAR_MIN, LOGVAR_MAX)?;
        let std = (&logvar * 0.5)?.exp()?;
        Ok(Self { mean, logvar, std })
    }

    /// The mode (= mean), what editing pipelines use for deterministic latents.
    pub fn mode(&self) -> &Tensor {
        &self.mean
    }

    /// `mean + std · noise` with caller-provided standard-normal `noise` shaped like the mean.
    pub fn sample_with_noise(&self, noise: &Tensor) -> Result<Tensor> {
        if noise.dims() != self.mean.dims() {
            return Err(VaeError::Input {
                what: "posterior noise",
                expected: format!("shape {:?}", self.mean.dims()),
                got: noise.dims().to_vec(),
            });
        }
        let noise = noise.to_dtype(self.mean.dtype())?;
        Ok((&self.mean + (&self.std * noise)?)?)
    }

    /// Draws the standard-normal noise from `rng` (row-major over [B, C, H, W]) and samples.
    pub fn sample<R: Rng + ?Sized>(&self, rng: &mut R) -> Result<Tensor> {
        let values: Vec<f32> = (0..self.mean.elem_count())
            .map(|_| StandardNormal.sample(rng))
            .collect();
        let noise = Tensor::from_vec(values, self.mean.shape(), self.mean.device())?;
        self.sample_with_noise(&noise)
    }

    /// KL divergence to N(0, I) per batch element (summed over C, H, W), as diffusers' `kl()`.
    pub fn kl(&self) -> candle_core::Result<Tensor> {
        let var = self.logvar.exp()?;
        let terms = ((self.mean.sqr()? + var)? - 1.0)?.sub(&self.logvar)?;
        terms.flatten_from(1)?.sum(1)? * 0.5
    }
}

/// diffusers' `AutoencoderKL`.
#[derive(Debug, Clone)]
pub struct AutoencoderKL {
    pub encoder: VaeEncoder,
    pub decoder: VaeDecoder,
    quant_conv: Option<Conv2d>,
    post_quant_conv: Option<Conv2d>,
    config: AutoencoderKLConfig,
}

impl AutoencoderKL {
    /// Builds from a `VarBuilder` with diffusers' key names (a loaded checkpoint, or a `VarMap` to train).
    pub fn new(cfg: &AutoencoderKLConfig, vb: VarBuilder) -> candle_core::Result<Self> {
        cfg.validate().map_err(candle_core::Error::msg)?;
        let l = cfg.latent_channels;
        let quant_conv = if cfg.use_quant_conv {
            Some(conv2d(2 * l, 2 * l, 1, 1, 0, vb.pp("quant_conv"))?)
        } else {
            None
        };
        let post_quant_conv = if cfg.use_post_quant_conv {
            Some(conv2d(l, l, 1, 1, 0, vb.pp("post_quant_conv"))?)
        } else {
            None
        };
        Ok(Self {
            encoder: VaeEncoder::new(cfg, vb.pp("encoder"))?,
            decoder: VaeDecoder::new(cfg, vb.pp("decoder"))?,
            quant_conv,
            post_quant_conv,
            config: cfg.clone(),
        })
    }

    /// Loads a diffusers `vae/` folder (`config.json` + `diffusion_pytorch_model.safetensors` or its `.fp16`
    /// variant; weights in f32/f16/bf16, computed in f32 on the CPU).
    pub fn load(dir: &Path) -> Result<Self> {
        let config_path = dir.join(CONFIG_FILE);
        let weights = taesd::diffusers_weights(dir);
        let mut missing = Vec::new();
        if !config_path.is_file() {
            missing.push(CONFIG_FILE);
        }
        if weights.is_none() {
            missing.push("diffusion_pytorch_model.safetensors (or its .fp16 variant)");
        }
        let Some(weights) = weights.filter(|_| missing.is_empty()) else {
            return Err(VaeError::MissingFiles {
                dir: dir.to_path_buf(),
                missing: format!("missing {}", missing.join(", ")),
            });
        };
        let cfg = AutoencoderKLConfig::from_file(&config_path)?;
        let weights_err = |source| VaeError::Weights {
            path: weights.clone(),
            source,
        };
        let vb = crate::weights::mmap_var_builder(&[&weights], DType::F32, &Device::Cpu)
            .map_err(weights_err)?;
        Self::new(&cfg, vb).map_err(weights_err)
    }

    pub fn config(&self) -> &AutoencoderKLConfig {
        &self.config
    }

    /// Image in [-1, 1] → posterior over raw latents.
    pub fn encode(&self, image: &Tensor) -> Result<DiagonalGaussian> {
        self.encode_on(image, &device::Device::Cpu)
    }

    /// [`Self::encode`] with the network on `device`; the moments are
    /// read back for the posterior.
    pub fn encode_on(&self, image: &Tensor, device: &device::Device) -> Result<DiagonalGaussian> {
        check_nchw(image.dims(), self.config.in_channels, "image")?;
        let h = self.encoder.forward_device(&device.tensor(image)?)?;
        let moments = match &self.quant_conv {
            Some(conv) => conv.forward_device(&h)?,
            None => h,
        };
        Ok(DiagonalGaussian::from_moments(&moments.to_cpu()?)?)
    }

    /// Image in [-1, 1] → posterior mean (raw latents).
    pub fn encode_mean(&self, image: &Tensor) -> Result<Tensor> {
        Ok(self.encode(image)?.mean)
    }

    /// Image in [-1, 1] → posterior mean as UNet latents (`(mean − shift) · scaling_factor`).
    pub fn encode_mean_scaled(&self, image: &Tensor) -> Result<Tensor> {
        let mean = self.encode_mean(image)?;
        Ok(self.scale(&mean)?)
    }

    /// Image in [-1, 1] → posterior sample `mean + std · noise` (raw latents), `noise` standard normal.
    pub fn encode_sample(&self, image: &Tensor, noise: &Tensor) -> Result<Tensor> {
        self.encode(image)?.sample_with_noise(noise)
    }

    /// [`Self::encode_sample`] as UNet latents.
    pub fn encode_sample_scaled(&self, image: &Tensor, noise: &Tensor) -> Result<Tensor> {
        let z = self.encode_sample(image, noise)?;
        Ok(self.scale(&z)?)
    }

    /// Image in [-1, 1] → posterior sample with noise drawn from `rng` (raw latents).
    pub fn encode_sample_rng<R: Rng + ?Sized>(
        &self,
        image: &Tensor,
        rng: &mut R,
    ) -> Result<Tensor> {
        self.encode(image)?.sample(rng)
    }

    /// Raw latents → image in [-1, 1] (unclamped).
    pub fn decode(&self, latents: &Tensor) -> Result<Tensor> {
        self.decode_on(latents, &device::Device::Cpu)
    }

    /// [`Self::decode`] on `device`; the image is read back.
    pub fn decode_on(&self, latents: &Tensor, device: &device::Device) -> Result<Tensor> {
        Ok(self.decode_device(&device.tensor(latents)?)?.to_cpu()?)
    }

    /// [`Self::decode`] on the latents' device; the image stays there.
    pub fn decode_device(&self, latents: &DeviceTensor) -> Result<DeviceTensor> {
        check_nchw(latents.dims(), self.config.latent_channels, "latents")?;
        let z = match &self.post_quant_conv {
            Some(conv) => conv.forward_device(latents)?,
            None => latents.clone(),
        };
        Ok(self.decoder.forward_device(&z)?)
    }

    /// UNet latents → image in [-1, 1]: `decode(latents / scaling_factor + shift)`.
    pub fn decode_scaled(&self, latents: &Tensor) -> Result<Tensor> {
        self.decode_scaled_on(latents, &device::Device::Cpu)
    }

    /// [`Self::decode_scaled`] on `device`.
    pub fn decode_scaled_on(&self, latents: &Tensor, device: &device::Device) -> Result<Tensor> {
        let z = taesd::unscale_latents(latents, self.config.scaling_factor, self.shift())?;
        self.decode_on(&z, device)
    }

    /// Raw → UNet latents.
    pub fn scale(&self, raw: &Tensor) -> candle_core::Result<Tensor> {
        taesd::scale_latents(raw, self.config.scaling_factor, self.shift())
    }

    fn shift(&self) -> f64 {
        self.config.shift_factor.unwrap_or(0.0)
    }
}

fn check_nchw(dims: &[usize], channels: usize, what: &'static str) -> Result<()> {
    if dims.len() != 4 || dims[1] != channels || dims.contains(&0) {
        return Err(VaeError::Input {
            what,
            expected: format!("NCHW with C = {channels}"),
            got: dims.to_vec(),
        });
    }
    Ok(())
}

/// Either autoencoder, behind the interface an editing pipeline needs (UNet-scale latents, [-1, 1] images).
#[derive(Debug, Clone)]
pub enum Autoencoder {
    Kl(Box<AutoencoderKL>),
    Tiny(Box<AutoencoderTiny>),
}

impl Autoencoder {
    /// Loads a VAE folder: TAESD in either layout (`config.json` with `_class_name: AutoencoderTiny`, or the
    /// taesd.py files), otherwise an `AutoencoderKL`.
    pub fn load(dir: &Path) -> Result<Self> {
        let config_path = dir.join(CONFIG_FILE);
        let is_tiny = if config_path.is_file() {
            #[derive(Deserialize)]
            struct ClassName {
                #[serde(rename = "_class_name")]
                class_name: Option<String>,
            }
            let text = std::fs::read_to_string(&config_path).map_err(|e| VaeError::Config {
                path: config_path.clone(),
                message: e.to_string(),
            })?;
            let probe: ClassName = serde_json::from_str(&text).map_err(|e| VaeError::Config {
                path: config_path.clone(),
                message: format!("invalid JSON: {e}"),
            })?;
            probe.class_name.as_deref() == Some("AutoencoderTiny")
        } else {
            // No config: only TAESD (either layout) can do without one.
            true
        };
        if is_tiny {
            Ok(Self::Tiny(Box::new(AutoencoderTiny::load(dir)?)))
        } else {
            Ok(Self::Kl(Box::new(AutoencoderKL::load(dir)?)))
        }
    }

    /// Image in [-1, 1] → UNet latents (posterior mean for the KL autoencoder).
    pub fn encode_scaled(&self, image: &Tensor) -> Result<Tensor> {
        self.encode_scaled_on(image, None, &device::Device::Cpu)
    }

    /// Image in [-1, 1] → UNet latents with the network on `device`: the
    /// KL autoencoder's posterior sample `mean + std · noise` when `noise` is given, else its mean; TAESD is
    /// deterministic and ignores `noise`.
    pub fn encode_scaled_on(
        &self,
        image: &Tensor,
        noise: Option<&Tensor>,
        device: &device::Device,
    ) -> Result<Tensor> {
        match self {
            Self::Kl(vae) => {
                let posterior = vae.encode_on(image, device)?;
                let z = match noise {
                    Some(noise) => posterior.sample_with_noise(noise)?,
                    None => posterior.mean,
                };
                Ok(vae.scale(&z)?)
            }
            Self::Tiny(tiny) => Ok(tiny.encode_scaled_on(image, device)?),
        }
    }

    /// UNet latents → image in [-1, 1] (unclamped).
    pub fn decode_scaled(&self, latents: &Tensor) -> Result<Tensor> {
        self.decode_scaled_on(latents, &device::Device::Cpu)
    }

    /// [`Self::decode_scaled`] with the network on `device`.
    pub fn decode_scaled_on(&self, latents: &Tensor, device: &device::Device) -> Result<Tensor> {
        match self {
            Self::Kl(vae) => vae.decode_scaled_on(latents, device),
            Self::Tiny(tiny) => Ok(tiny.decode_scaled_on(latents, device)?),
        }
    }

    /// Bytes (f32) of the largest activation one `height × width` image makes in the encoder or decoder:
    /// at each level the wider of its own and the next level's channels (the decoder upsamples before it
    /// narrows) at that level's resolution. A batch's largest buffer is this times the batch; callers keep
    /// it under the device's largest buffer (convolutions block their own im2col buffers).
    pub fn largest_activation_bytes(&self, height: usize, width: usize) -> usize {
        let levels: Vec<usize> = match self {
            Self::Kl(vae) => {
                let ch = &vae.config().block_out_channels;
                (0..ch.len())
                    .map(|j| ch[j].max(ch[(j + 1).min(ch.len() - 1)]))
                    .collect()
            }
            // TAESD runs at full resolution with its widest block (conservative).
            Self::Tiny(tiny) => {
                let c = tiny.config();
                let widest = c
                    .encoder_block_out_channels
                    .iter()
                    .chain(&c.decoder_block_out_channels)
                    .copied()
                    .max()
                    .unwrap_or(64);
                vec![widest]
            }
        };
        levels
            .iter()
            .enumerate()
            .map(|(j, &c)| c * (height >> j).max(1) * (width >> j).max(1) * 4)
            .max()
            .unwrap_or(0)
    }

    pub fn latent_channels(&self) -> usize {
        match self {
            Self::Kl(vae) => vae.config().latent_channels,
            Self::Tiny(tiny) => tiny.config().latent_channels,
        }
    }

    /// Image pixels per latent pixel along each axis.
    pub fn spatial_factor(&self) -> usize {
        match self {
            Self::Kl(vae) => vae.config().spatial_factor(),
            Self::Tiny(tiny) => tiny.config().spatial_factor(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    fn small_config() -> AutoencoderKLConfig {
        AutoencoderKLConfig {
            down_block_types: vec!["DownEncoderBlock2D".into(); 2],
            up_block_types: vec!["UpDecoderBlock2D".into(); 2],
            block_out_channels: vec![4, 8],
            norm_num_groups: 2,
            latent_channels: 2,
            ..AutoencoderKLConfig::default()
        }
    }

    #[test]
    fn the_largest_activation_is_the_decoders_full_resolution_upsample() {
        let vae = AutoencoderKL::new(&small_config(), VarBuilder::zeros(DType::F32, &Device::Cpu))
            .unwrap();
        // Channels [4, 8]: the decoder upsamples 8 channels to full resolution before narrowing to 4.
        let bytes = Autoencoder::Kl(Box::new(vae)).largest_activation_bytes(64, 32);
        assert_eq!(bytes, 8 * 64 * 32 * 4);
    }

    #[test]
    fn config_defaults_mirror_diffusers_and_validation_names_keys() {
        let cfg: AutoencoderKLConfig = serde_json::from_str("{}").unwrap();
        assert_eq!(cfg, AutoencoderKLConfig::default());
        assert_eq!(AutoencoderKLConfig::sd15().spatial_factor(), 8);
        assert!(AutoencoderKLConfig::sd15().validate().is_ok());
        let cfg = AutoencoderKLConfig {
            norm_num_groups: 3,
            ..small_config()
        };
        assert!(cfg.validate().unwrap_err().contains("norm_num_groups"));
        let cfg = AutoencoderKLConfig {
            up_block_types: vec!["AttnUpDecoderBlock2D".into(); 2],
            ..small_config()
        };
        assert!(cfg.validate().unwrap_err().contains("AttnUpDecoderBlock2D"));
    }

    #[test]
    fn posterior_clamps_logvar_and_samples_reproducibly() {
        let dev = Device::Cpu;
        // Channels 0..2 are the mean, 2..4 the log-variance (one value beyond each clamp bound).
        let moments = Tensor::new(&[[[[0.5f32]], [[-1.0]], [[40.0]], [[-50.0]]]], &dev).unwrap();
        let post = DiagonalGaussian::from_moments(&moments).unwrap();
        let logvar: Vec<f32> = post.logvar.flatten_all().unwrap().to_vec1().unwrap();
        assert_eq!(logvar, vec![20.0, -30.0]);
        let std: Vec<f32> = post.std.flatten_all().unwrap().to_vec1().unwrap();
        assert!((std[0] - 10f32.exp()).abs() / 10f32.exp() < 1e-6);

        let noise = Tensor::new(&[[[[1.0f32]], [[2.0]]]], &dev).unwrap();
        let s: Vec<f32> = post
            .sample_with_noise(&noise)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        assert!((s[0] - (0.5 + 10f32.exp())).abs() < 1e-2);
        assert!((s[1] - (-1.0 + 2.0 * (-15f32).exp())).abs() < 1e-6);

        let a = post
            .sample(&mut rand_chacha::ChaCha8Rng::seed_from_u64(7))
            .unwrap();
        let b = post
            .sample(&mut rand_chacha::ChaCha8Rng::seed_from_u64(7))
            .unwrap();
        let c = post
            .sample(&mut rand_chacha::ChaCha8Rng::seed_from_u64(8))
            .unwrap();
        let v = |t: &Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        assert_eq!(v(&a), v(&b));
        assert_ne!(v(&a), v(&c));

        let wrong = Tensor::zeros((1, 3, 1, 1), DType::F32, &dev).unwrap();
        assert!(matches!(
            post.sample_with_noise(&wrong),
            Err(VaeError::Input { .. })
        ));
    }

    #[test]
    fn kl_matches_the_closed_form() {
        let dev = Device::Cpu;
        let moments = Tensor::new(&[[[[0.3f32, -0.2]], [[0.5, -0.4]]]], &dev).unwrap();
        let post = DiagonalGaussian::from_moments(&moments).unwrap();
        let expected: f32 = [(0.3f32, 0.5f32), (-0.2, -0.4)]
            .iter()
            .map(|&(m, lv)| 0.5 * (m * m + lv.exp() - 1.0 - lv))
            .sum();
        let kl = post.kl().unwrap().to_vec1::<f32>().unwrap();
        assert!((kl[0] - expected).abs() < 1e-6, "{kl:?} vs {expected}");
    }

    #[test]
    fn missing_files_are_listed_together() {
        let dir = tempfile::tempdir().unwrap();
        let err = AutoencoderKL::load(dir.path()).unwrap_err().to_string();
        assert!(
            err.contains(CONFIG_FILE) && err.contains(WEIGHTS_FILE),
            "{err}"
        );
        std::fs::write(dir.path().join(CONFIG_FILE), "{}").unwrap();
        let err = AutoencoderKL::load(dir.path()).unwrap_err().to_string();
        assert!(
            err.contains(WEIGHTS_FILE) && !err.contains(CONFIG_FILE),
            "{err}"
        );
        std::fs::write(dir.path().join(WEIGHTS_FILE), b"junk").unwrap();
        assert!(matches!(
            AutoencoderKL::load(dir.path()),
            Err(VaeError::Weights { .. })
        ));
        std::fs::write(dir.path().join(CONFIG_FILE), "{\"block_out_channels\": 5}").unwrap();
        assert!(matches!(
            AutoencoderKL::load(dir.path()),
            Err(VaeError::Config { .. })
        ));
    }

    /// Training a VAE needs gradients through encode → sample → decode for every parameter, and the
    /// composite (training) path must compute the same values as the fused inference path.
    #[test]
    fn vae_is_differentiable_and_both_paths_agree() {
        let dev = Device::Cpu;
        let cfg = small_config();
        let varmap = candle_nn::VarMap::new();
        let vae =
            AutoencoderKL::new(&cfg, VarBuilder::from_varmap(&varmap, DType::F32, &dev)).unwrap();
        let image = Tensor::rand(-1f32, 1.0, (2, 3, 8, 8), &dev).unwrap();
        let noise = Tensor::randn(0f32, 1.0, (2, 2, 4, 4), &dev).unwrap();
        let post = vae.encode(&image).unwrap();
        let z = post.sample_with_noise(&noise).unwrap();
        let recon = vae.decode(&z).unwrap();
        let loss = ((recon.clone() - &image)
            .unwrap()
            .sqr()
            .unwrap()
            .mean_all()
            .unwrap()
            + (post.kl().unwrap().mean_all().unwrap() * 1e-3).unwrap())
        .unwrap();
        let grads = loss.backward().unwrap();
        for (name, var) in varmap.data().lock().unwrap().iter() {
            let g = grads
                .get(var)
                .unwrap_or_else(|| panic!("no gradient for {name}"));
            let norm = g
                .sqr()
                .unwrap()
                .sum_all()
                .unwrap()
                .to_scalar::<f32>()
                .unwrap();
            assert!(norm.is_finite(), "{name}");
        }

        // Same weights as plain tensors (no Var): the fused kernels run; values must agree.
        let frozen: std::collections::HashMap<String, Tensor> = varmap
            .data()
            .lock()
            .unwrap()
            .iter()
            .map(|(k, v)| (k.clone(), v.as_tensor().detach()))
            .collect();
        let fast =
            AutoencoderKL::new(&cfg, VarBuilder::from_tensors(frozen, DType::F32, &dev)).unwrap();
        let fast_recon = fast
            .decode(&fast.encode_sample(&image, &noise).unwrap())
            .unwrap();
        assert!(crate::kernels::test_support::max_diff(&fast_recon, &recon) < 1e-4);
    }

    #[test]
    fn wrong_shapes_are_errors() {
        let dev = Device::Cpu;
        let varmap = candle_nn::VarMap::new();
        let vae = AutoencoderKL::new(
            &small_config(),
            VarBuilder::from_varmap(&varmap, DType::F32, &dev),
        )
        .unwrap();
        let img = Tensor::zeros((1, 4, 8, 8), DType::F32, &dev).unwrap();
        assert!(matches!(vae.encode_mean(&img), Err(VaeError::Input { .. })));
        let z = Tensor::zeros((1, 4, 2), DType::F32, &dev).unwrap();
        assert!(matches!(vae.decode(&z), Err(VaeError::Input { .. })));
    }
}
