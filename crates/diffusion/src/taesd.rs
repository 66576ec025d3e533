//! TAESD, the tiny distilled autoencoder (diffusers `AutoencoderTiny`).
//!
//! Conventions (the same as diffusers' `AutoencoderTiny`):
//! - [`AutoencoderTiny::encode`] takes images in **[-1, 1]** (NCHW) and returns latents that are already on the
//!   UNet's scale for SD 1.x (TAESD was distilled against `SD-VAE latents × 0.18215`), so the config's
//!   `scaling_factor` is 1.0.
//! - [`AutoencoderTiny::decode`] returns images in **[-1, 1]**, *not clamped* (diffusers maps the decoder's
//!   native [0, 1] output with `x·2 − 1` and leaves clamping to the image post-processor).
//! - `encode_unit` / `decode_unit` are the native taesd.py conventions: images in [0, 1].
//! - The `*_scaled` variants apply `(z − shift_factor) · scaling_factor` like the diffusers pipelines do, so a
//!   pipeline can treat TAESD and AutoencoderKL alike.
//!
//! Two weight layouts load through [`AutoencoderTiny::load`]:
//! - diffusers: `config.json` (optional; SD 1.x defaults otherwise) + `diffusion_pytorch_model.safetensors`
//!   with keys `encoder.layers.N.*` / `decoder.layers.N.*`;
//! - taesd.py: `taesd_encoder.safetensors` + `taesd_decoder.safetensors`, the `nn.Sequential` index layout. The
//!   decoder's index 0 there is the clamp, so its indices are the diffusers ones plus one. That layout carries no
//!   config; the architecture (stages, blocks per stage, channels, latent channels) is read off the tensor names
//!   and shapes, so taesd.py variants with other widths or latent channels load as well (activation ReLU,
//!   nearest ×2 upsampling, as taesd.py hard-codes).
//!
//! Every op is differentiable (relu, tanh, nearest upsampling, and the shared conv layer, whose kernel has a
//! training variant), so a TAESD can be trained or fine-tuned.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};
use candle_nn::{Activation, VarBuilder};

use crate::device;
use crate::kernels::{Addend, DeviceTensor, Unary};
use crate::layers::Conv2d;
use serde::Deserialize;

/// diffusers' file names for a single-component folder.
pub const DIFFUSERS_CONFIG: &str = "config.json";
pub const DIFFUSERS_WEIGHTS: &str = "diffusion_pytorch_model.safetensors";
/// The half-precision variant diffusers writes with `variant="fp16"`; used when the plain file is absent.
pub const DIFFUSERS_WEIGHTS_FP16: &str = "diffusion_pytorch_model.fp16.safetensors";
/// taesd.py's file names (SD 1.x/2.x TAESD).
pub const ORIGINAL_ENCODER: &str = "taesd_encoder.safetensors";
pub const ORIGINAL_DECODER: &str = "taesd_decoder.safetensors";

#[derive(Debug, thiserror::Error)]
pub enum TaesdError {
    #[error("{dir}: no TAESD weights: {missing}")]
    MissingFiles { dir: PathBuf, missing: String },
    #[error("{path}: {message}")]
    Config { path: PathBuf, message: String },
    #[error("{path}: cannot load TAESD weights: {source}")]
    Weights {
        path: PathBuf,
        source: candle_core::Error,
    },
    #[error("TAESD {what}: expected {expected}, got shape {got:?}")]
    Input {
        what: &'static str,
        expected: String,
        got: Vec<usize>,
    },
    #[error("TAESD forward: {0}")]
    Candle(#[from] candle_core::Error),
}

pub type Result<T> = std::result::Result<T, TaesdError>;

/// Mirrors diffusers' `AutoencoderTiny` `config.json`; every key optional, defaults are SD 1.x TAESD.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(default)]
pub struct TaesdConfig {
    pub in_channels: usize,
    pub out_channels: usize,
    pub encoder_block_out_channels: Vec<usize>,
    pub decoder_block_out_channels: Vec<usize>,
    pub act_fn: String,
    pub upsample_fn: String,
    pub latent_channels: usize,
    pub upsampling_scaling_factor: usize,
    pub num_encoder_blocks: Vec<usize>,
    pub num_decoder_blocks: Vec<usize>,
    /// Only used by [`AutoencoderTiny::latents_to_unit`] (diffusers' `scale_latents`, for 8-bit latent storage).
    pub latent_magnitude: f64,
    pub latent_shift: f64,
    pub scaling_factor: f64,
    /// diffusers writes `null` in some configs; treated as 0.
    pub shift_factor: Option<f64>,
}

impl Default for TaesdConfig {
    fn default() -> Self {
        Self {
            in_channels: 3,
            out_channels: 3,
            encoder_block_out_channels: vec![64; 4],
            decoder_block_out_channels: vec![64; 4],
            act_fn: "relu".into(),
            upsample_fn: "nearest".into(),
            latent_channels: 4,
            upsampling_scaling_factor: 2,
            num_encoder_blocks: vec![1, 3, 3, 3],
            num_decoder_blocks: vec![3, 3, 3, 1],
            latent_magnitude: 3.0,
            latent_shift: 0.5,
            scaling_factor: 1.0,
            shift_factor: None,
        }
    }
}

impl TaesdConfig {
    /// Reads a diffusers `config.json`.
    pub fn from_file(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| TaesdError::Config {
            path: path.to_path_buf(),
            message: e.to_string(),
        })?;
        let cfg: Self = serde_json::from_str(&text).map_err(|e| TaesdError::Config {
            path: path.to_path_buf(),
            message: format!("invalid AutoencoderTiny config: {e}"),
        })?;
        cfg.validate().map_err(|message| TaesdError::Config {
            path: path.to_path_buf(),
            message,
        })?;
        Ok(cfg)
    }

    /// Checks the invariants the architecture relies on; the message names the offending keys.
    pub fn validate(&self) -> std::result::Result<(), String> {
        let pairs = [
            (
                "encoder_block_out_channels",
                &self.encoder_block_out_channels,
                "num_encoder_blocks",
                &self.num_encoder_blocks,
            ),
            (
                "decoder_block_out_channels",
                &self.decoder_block_out_channels,
                "num_decoder_blocks",
                &self.num_decoder_blocks,
            ),
        ];
        for (chan_key, chans, num_key, nums) in pairs {
            if chans.is_empty() || chans.len() != nums.len() {
                return Err(format!(
                    "{chan_key} (len {}) and {num_key} (len {}) must be non-empty and of equal length",
                    chans.len(),
                    nums.len()
                ));
            }
            if chans.contains(&0) {
                return Err(format!("{chan_key} contains 0"));
            }
        }
        if self.in_channels == 0 || self.out_channels == 0 || self.latent_channels == 0 {
            return Err("in_channels, out_channels and latent_channels must be positive".into());
        }
        if self.upsampling_scaling_factor == 0 {
            return Err("upsampling_scaling_factor must be positive".into());
        }
        if self.upsample_fn != "nearest" {
            return Err(format!(
                "upsample_fn {:?} is not supported (only \"nearest\")",
                self.upsample_fn
            ));
        }
        activation(&self.act_fn)?;
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
        // Each encoder stage after the first starts with a stride-2 convolution.
        1 << (self.encoder_block_out_channels.len() - 1)
    }
}

/// diffusers' `get_activation` names.
fn activation(name: &str) -> std::result::Result<Activation, String> {
    match name {
        "relu" => Ok(Activation::Relu),
        "silu" | "swish" => Ok(Activation::Silu),
        // torch.nn.GELU() default is the exact erf form.
        "gelu" => Ok(Activation::Gelu),
        "mish" => Ok(Activation::Mish),
        other => Err(format!(
            "act_fn {other:?} is not supported (relu, silu, swish, gelu, mish)"
        )),
    }
}

fn conv3x3(
    in_c: usize,
    out_c: usize,
    stride: usize,
    bias: bool,
    vb: VarBuilder,
) -> candle_core::Result<Conv2d> {
    Conv2d::load(in_c, out_c, 3, stride, 1, bias, vb)
}

/// `AutoencoderTinyBlock`: three 3×3 convs with the activation between them, identity skip, ReLU fuse.
#[derive(Debug, Clone)]
struct TinyBlock {
    convs: [Conv2d; 3],
    act: Activation,
}

impl TinyBlock {
    fn new(channels: usize, act: Activation, vb: VarBuilder) -> candle_core::Result<Self> {
        // Inside `conv` (an nn.Sequential) the activations sit at indices 1 and 3.
        let vb = vb.pp("conv");
        Ok(Self {
            convs: [
                conv3x3(channels, channels, 1, true, vb.pp("0"))?,
                conv3x3(channels, channels, 1, true, vb.pp("2"))?,
                conv3x3(channels, channels, 1, true, vb.pp("4"))?,
            ],
            act,
        })
    }

    fn forward(&self, x: &DeviceTensor) -> candle_core::Result<DeviceTensor> {
        // A ReLU (TAESD's usual activation, and always the fuse after the skip) goes into the
        // convolution's store.
        let conv_act = |conv: &Conv2d, x: &DeviceTensor| match self.act {
            Activation::Relu => conv.forward_device_add_act(x, Addend::None, Unary::Relu),
            act => conv.forward_device(x)?.activation(act),
        };
        let h = conv_act(&self.convs[0], x)?;
        let h = conv_act(&self.convs[1], &h)?;
        self.convs[2].forward_device_add_act(&h, Addend::Residual(x), Unary::Relu)
    }
}

#[derive(Debug, Clone)]
enum Layer {
    Conv(Conv2d),
    Block(TinyBlock),
    Act(Activation),
    Upsample(usize),
}

impl Layer {
    fn forward(&self, x: &DeviceTensor) -> candle_core::Result<DeviceTensor> {
        match self {
            Layer::Conv(c) => c.forward_device(x),
            Layer::Block(b) => b.forward(x),
            Layer::Act(a) => x.activation(*a),
            Layer::Upsample(f) => {
                let (_, _, h, w) = x.dims4()?;
                x.upsample_nearest2d(h * f, w * f)
            }
        }
    }
}

fn run(layers: &[Layer], x: DeviceTensor) -> candle_core::Result<DeviceTensor> {
    layers.iter().try_fold(x, |x, layer| layer.forward(&x))
}

/// diffusers' `EncoderTiny` (without its [-1, 1] → [0, 1] input mapping, which lives in [`AutoencoderTiny`]).
#[derive(Debug, Clone)]
pub struct TinyEncoder {
    layers: Vec<Layer>,
    in_channels: usize,
}

impl TinyEncoder {
    /// `vb` points at the sequential container (`encoder.layers` in diffusers, the file root in taesd.py; the
    /// encoder indices are the same in both).
    pub fn new(cfg: &TaesdConfig, vb: VarBuilder) -> candle_core::Result<Self> {
        let act = activation(&cfg.act_fn).map_err(candle_core::Error::msg)?;
        let chans = &cfg.encoder_block_out_channels;
        let mut layers = Vec::new();
        for (stage, (&ch, &blocks)) in chans.iter().zip(&cfg.num_encoder_blocks).enumerate() {
            let idx = layers.len().to_string();
            layers.push(Layer::Conv(if stage == 0 {
                conv3x3(cfg.in_channels, ch, 1, true, vb.pp(idx))?
            } else {
                // Downsampling conv. diffusers uses `ch` as its input width too (it assumes equal widths);
                // the previous stage's width is the same whenever diffusers itself can run the model.
                conv3x3(chans[stage - 1], ch, 2, false, vb.pp(idx))?
            }));
            for _ in 0..blocks {
                let idx = layers.len().to_string();
                layers.push(Layer::Block(TinyBlock::new(ch, act, vb.pp(idx))?));
            }
        }
        let idx = layers.len().to_string();
        let last = *chans.last().expect("validated non-empty");
        layers.push(Layer::Conv(conv3x3(
            last,
            cfg.latent_channels,
            1,
            true,
            vb.pp(idx),
        )?));
        Ok(Self {
            layers,
            in_channels: cfg.in_channels,
        })
    }

    /// Image in [0, 1] → latents.
    pub fn forward(&self, image_unit: &Tensor) -> Result<Tensor> {
        Ok(self.forward_device(&image_unit.clone().into())?.to_cpu()?)
    }

    /// [`Self::forward`] on the input's device.
    pub fn forward_device(&self, image_unit: &DeviceTensor) -> Result<DeviceTensor> {
        check_nchw(image_unit.dims(), self.in_channels, "encoder input")?;
        Ok(run(&self.layers, image_unit.clone())?)
    }
}

/// diffusers' `DecoderTiny`: tanh soft-clamp `tanh(z/3)·3`, then the layers; output in [0, 1] (native taesd).
#[derive(Debug, Clone)]
pub struct TinyDecoder {
    layers: Vec<Layer>,
    latent_channels: usize,
}

impl TinyDecoder {
    /// `vb` points at the sequential container; `index_offset` is 0 for diffusers (`decoder.layers`) and 1 for
    /// taesd.py, whose `nn.Sequential` starts with the parameter-free clamp at index 0.
    pub fn new(
        cfg: &TaesdConfig,
        vb: VarBuilder,
        index_offset: usize,
    ) -> candle_core::Result<Self> {
        let act = activation(&cfg.act_fn).map_err(candle_core::Error::msg)?;
        let chans = &cfg.decoder_block_out_channels;
        let key = |layers: &Vec<Layer>| (layers.len() + index_offset).to_string();
        let mut layers = Vec::new();
        layers.push(Layer::Conv(conv3x3(
            cfg.latent_channels,
            chans[0],
            1,
            true,
            vb.pp(key(&layers)),
        )?));
        layers.push(Layer::Act(act));
        let stages = chans.len();
        for (stage, (&ch, &blocks)) in chans.iter().zip(&cfg.num_decoder_blocks).enumerate() {
            for _ in 0..blocks {
                let idx = key(&layers);
                layers.push(Layer::Block(TinyBlock::new(ch, act, vb.pp(idx))?));
            }
            let is_final = stage + 1 == stages;
            if !is_final {
                layers.push(Layer::Upsample(cfg.upsampling_scaling_factor));
            }
            // Non-final convs lead into the next stage; diffusers sizes them `ch -> ch` (equal widths assumed),
            // which is the same thing whenever diffusers can run the model.
            let out = if is_final {
                cfg.out_channels
            } else {
                chans[stage + 1]
            };
            let idx = key(&layers);
            layers.push(Layer::Conv(conv3x3(ch, out, 1, is_final, vb.pp(idx))?));
        }
        Ok(Self {
            layers,
            latent_channels: cfg.latent_channels,
        })
    }

    /// Latents → image in [0, 1] (not clamped).
    pub fn forward(&self, latents: &Tensor) -> Result<Tensor> {
        Ok(self.forward_device(&latents.clone().into())?.to_cpu()?)
    }

    /// [`Self::forward`] on the input's device.
    pub fn forward_device(&self, latents: &DeviceTensor) -> Result<DeviceTensor> {
        check_nchw(latents.dims(), self.latent_channels, "decoder input")?;
        let clamped = latents.div_scalar(3.0)?.tanh()?.mul_scalar(3.0)?;
        Ok(run(&self.layers, clamped)?)
    }
}

fn check_nchw(dims: &[usize], channels: usize, what: &'static str) -> Result<()> {
    if dims.len() != 4 || dims[1] != channels || dims[2] == 0 || dims[3] == 0 || dims[0] == 0 {
        return Err(TaesdError::Input {
            what,
            expected: format!("NCHW with C = {channels}"),
            got: dims.to_vec(),
        });
    }
    Ok(())
}

/// Which files a TAESD folder holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TaesdLayout {
    /// `config.json` + `diffusion_pytorch_model.safetensors` with `encoder.layers.N` / `decoder.layers.N` keys.
    Diffusers,
    /// `taesd_encoder.safetensors` + `taesd_decoder.safetensors` with `nn.Sequential` index keys.
    Original,
}

/// diffusers' `AutoencoderTiny`.
#[derive(Debug, Clone)]
pub struct AutoencoderTiny {
    pub encoder: TinyEncoder,
    pub decoder: TinyDecoder,
    config: TaesdConfig,
    layout: TaesdLayout,
}

impl AutoencoderTiny {
    /// Builds from a diffusers-named `VarBuilder` (`encoder.layers.*`, `decoder.layers.*`); use this with a
    /// `VarMap` to train.
    pub fn new(cfg: &TaesdConfig, vb: VarBuilder) -> candle_core::Result<Self> {
        cfg.validate().map_err(candle_core::Error::msg)?;
        Ok(Self {
            encoder: TinyEncoder::new(cfg, vb.pp("encoder").pp("layers"))?,
            decoder: TinyDecoder::new(cfg, vb.pp("decoder").pp("layers"), 0)?,
            config: cfg.clone(),
            layout: TaesdLayout::Diffusers,
        })
    }

    /// Loads a folder in either layout (see the module docs), computing in f32 on the CPU whatever the stored
    /// dtype (f32/f16/bf16).
    pub fn load(dir: &Path) -> Result<Self> {
        match detect_layout(dir)? {
            TaesdLayout::Diffusers => Self::load_diffusers(dir),
            TaesdLayout::Original => {
                Self::load_original(&dir.join(ORIGINAL_ENCODER), &dir.join(ORIGINAL_DECODER))
            }
        }
    }

    fn load_diffusers(dir: &Path) -> Result<Self> {
        let config_path = dir.join(DIFFUSERS_CONFIG);
        let cfg = if config_path.is_file() {
            TaesdConfig::from_file(&config_path)?
        } else {
            TaesdConfig::default()
        };
        let weights = diffusers_weights(dir).ok_or_else(|| TaesdError::MissingFiles {
            dir: dir.to_path_buf(),
            missing: format!("missing {DIFFUSERS_WEIGHTS}"),
        })?;
        let vb = mmap_var_builder(&weights)?;
        Self::new(&cfg, vb).map_err(|source| TaesdError::Weights {
            path: weights,
            source,
        })
    }

    /// Loads taesd.py weight files (any names), reading the architecture off the tensor names and shapes.
    pub fn load_original(encoder_path: &Path, decoder_path: &Path) -> Result<Self> {
        let enc_arch = inspect_sequential(encoder_path)?;
        let dec_arch = inspect_sequential(decoder_path)?;
        let cfg = original_config(encoder_path, &enc_arch, decoder_path, &dec_arch)?;
        let encoder =
            TinyEncoder::new(&cfg, mmap_var_builder(encoder_path)?).map_err(|source| {
                TaesdError::Weights {
                    path: encoder_path.to_path_buf(),
                    source,
                }
            })?;
        let decoder =
            TinyDecoder::new(&cfg, mmap_var_builder(decoder_path)?, 1).map_err(|source| {
                TaesdError::Weights {
                    path: decoder_path.to_path_buf(),
                    source,
                }
            })?;
        Ok(Self {
            encoder,
            decoder,
            config: cfg,
            layout: TaesdLayout::Original,
        })
    }

    pub fn config(&self) -> &TaesdConfig {
        &self.config
    }

    /// The layout the weights were loaded from.
    pub fn layout(&self) -> TaesdLayout {
        self.layout
    }

    /// Image in [-1, 1] → latents (diffusers `AutoencoderTiny.encode(x).latents`).
    pub fn encode(&self, image: &Tensor) -> Result<Tensor> {
        self.encode_on(image, &device::Device::Cpu)
    }

    /// Image in [0, 1] → latents (taesd.py convention).
    pub fn encode_unit(&self, image_unit: &Tensor) -> Result<Tensor> {
        self.encoder.forward(image_unit)
    }

    /// Latents → image in [-1, 1], unclamped (diffusers `AutoencoderTiny.decode(z).sample`).
    pub fn decode(&self, latents: &Tensor) -> Result<Tensor> {
        self.decode_on(latents, &device::Device::Cpu)
    }

    /// Latents → image in [0, 1], unclamped (taesd.py convention).
    pub fn decode_unit(&self, latents: &Tensor) -> Result<Tensor> {
        self.decoder.forward(latents)
    }

    /// [`Self::encode`] on `device`; the result is read back.
    pub fn encode_on(&self, image: &Tensor, device: &device::Device) -> Result<Tensor> {
        let image = device.tensor(image)?;
        Ok(self.encode_device(&image)?.to_cpu()?)
    }

    /// [`Self::decode`] on `device`; the result is read back.
    pub fn decode_on(&self, latents: &Tensor, device: &device::Device) -> Result<Tensor> {
        let latents = device.tensor(latents)?;
        Ok(self.decode_device(&latents)?.to_cpu()?)
    }

    /// [`Self::encode`] on the image's device; the latents stay there.
    pub fn encode_device(&self, image: &DeviceTensor) -> Result<DeviceTensor> {
        let unit = image.add_scalar(1.0)?.div_scalar(2.0)?;
        self.encoder.forward_device(&unit)
    }

    /// [`Self::decode`] on the latents' device; the image stays there.
    pub fn decode_device(&self, latents: &DeviceTensor) -> Result<DeviceTensor> {
        let unit = self.decoder.forward_device(latents)?;
        Ok(unit.mul_scalar(2.0)?.sub_scalar(1.0)?)
    }

    /// Image in [-1, 1] → UNet-scale latents: `(encode(x) − shift_factor) · scaling_factor` (identity for SD TAESD).
    pub fn encode_scaled(&self, image: &Tensor) -> Result<Tensor> {
        self.encode_scaled_on(image, &device::Device::Cpu)
    }

    /// [`Self::encode_scaled`] on `device`.
    pub fn encode_scaled_on(&self, image: &Tensor, device: &device::Device) -> Result<Tensor> {
        let z = self.encode_on(image, device)?;
        Ok(scale_latents(&z, self.config.scaling_factor, self.shift())?)
    }

    /// UNet-scale latents → image in [-1, 1]: `decode(z / scaling_factor + shift_factor)`.
    pub fn decode_scaled(&self, latents: &Tensor) -> Result<Tensor> {
        self.decode_scaled_on(latents, &device::Device::Cpu)
    }

    /// [`Self::decode_scaled`] on `device`.
    pub fn decode_scaled_on(&self, latents: &Tensor, device: &device::Device) -> Result<Tensor> {
        let z = unscale_latents(latents, self.config.scaling_factor, self.shift())?;
        self.decode_on(&z, device)
    }

    /// diffusers' `scale_latents`: raw latents → [0, 1] via `z / (2·magnitude) + shift`, clamped.
    pub fn latents_to_unit(&self, latents: &Tensor) -> Result<Tensor> {
        let m = 2.0 * self.config.latent_magnitude;
        Ok(((latents / m)? + self.config.latent_shift)?.clamp(0f32, 1f32)?)
    }

    /// diffusers' `unscale_latents`: [0, 1] → raw latents.
    pub fn latents_from_unit(&self, unit: &Tensor) -> Result<Tensor> {
        let m = 2.0 * self.config.latent_magnitude;
        Ok(((unit - self.config.latent_shift)? * m)?)
    }

    fn shift(&self) -> f64 {
        self.config.shift_factor.unwrap_or(0.0)
    }
}

/// `(z − shift) · scale`, skipping the no-op arithmetic for scale 1 / shift 0.
pub(crate) fn scale_latents(z: &Tensor, scale: f64, shift: f64) -> candle_core::Result<Tensor> {
    let z = if shift != 0.0 {
        (z - shift)?
    } else {
        z.clone()
    };
    if scale != 1.0 {
        z * scale
    } else {
        Ok(z)
    }
}

/// `z / scale + shift`.
pub(crate) fn unscale_latents(z: &Tensor, scale: f64, shift: f64) -> candle_core::Result<Tensor> {
    let z = if scale != 1.0 {
        (z / scale)?
    } else {
        z.clone()
    };
    if shift != 0.0 {
        z + shift
    } else {
        Ok(z)
    }
}

/// The diffusers weight file in `dir`: the plain one, else its fp16 variant.
pub(crate) fn diffusers_weights(dir: &Path) -> Option<PathBuf> {
    [DIFFUSERS_WEIGHTS, DIFFUSERS_WEIGHTS_FP16]
        .iter()
        .map(|name| dir.join(name))
        .find(|p| p.is_file())
}

/// Finds which layout `dir` holds; the error names every file that was looked for.
pub fn detect_layout(dir: &Path) -> Result<TaesdLayout> {
    if diffusers_weights(dir).is_some() {
        return Ok(TaesdLayout::Diffusers);
    }
    let enc = dir.join(ORIGINAL_ENCODER).is_file();
    let dec = dir.join(ORIGINAL_DECODER).is_file();
    let missing = match (enc, dec) {
        (true, true) => return Ok(TaesdLayout::Original),
        (true, false) => format!("{ORIGINAL_DECODER} is missing (found {ORIGINAL_ENCODER})"),
        (false, true) => format!("{ORIGINAL_ENCODER} is missing (found {ORIGINAL_DECODER})"),
        (false, false) if !dir.is_dir() => "not a directory".to_string(),
        (false, false) => format!(
            "expected {DIFFUSERS_WEIGHTS} (+ optional {DIFFUSERS_CONFIG}) or {ORIGINAL_ENCODER} + {ORIGINAL_DECODER}"
        ),
    };
    Err(TaesdError::MissingFiles {
        dir: dir.to_path_buf(),
        missing,
    })
}

fn mmap_var_builder(path: &Path) -> Result<VarBuilder<'static>> {
    crate::weights::mmap_var_builder(&[path], DType::F32, &Device::Cpu).map_err(|source| {
        TaesdError::Weights {
            path: path.to_path_buf(),
            source,
        }
    })
}

/// One top-level entry of a taesd.py `nn.Sequential`, as seen in the weight file.
#[derive(Debug, Clone, PartialEq)]
enum Entry {
    /// A plain conv: `N.weight` (+ `N.bias`).
    Conv {
        in_c: usize,
        out_c: usize,
        bias: bool,
    },
    /// A `Block`: `N.conv.{0,2,4}.*`.
    Block { in_c: usize, out_c: usize },
}

/// Reads the tensor names/shapes of a taesd.py file into index → entry (parameter-free indices are absent).
fn inspect_sequential(path: &Path) -> Result<BTreeMap<usize, Entry>> {
    let bad = |message: String| TaesdError::Config {
        path: path.to_path_buf(),
        message,
    };
    let shapes: BTreeMap<String, Vec<usize>> = crate::weights::read_safetensors_header(path)
        .map_err(|e| bad(crate::loader::short_reason(&e)))?
        .into_iter()
        .map(|info| (info.name, info.shape))
        .collect();
    let mut entries = BTreeMap::new();
    for (name, shape) in &shapes {
        let (index, rest) = name
            .split_once('.')
            .and_then(|(i, rest)| Some((i.parse::<usize>().ok()?, rest)))
            .ok_or_else(|| {
                bad(format!(
                    "tensor {name:?} is not in the taesd.py index layout"
                ))
            })?;
        let entry = match rest {
            "weight" => {
                if shape.len() != 4 {
                    return Err(bad(format!(
                        "{name} has shape {shape:?}, expected a conv kernel"
                    )));
                }
                Entry::Conv {
                    in_c: shape[1],
                    out_c: shape[0],
                    bias: shapes.contains_key(&format!("{index}.bias")),
                }
            }
            "conv.0.weight" => {
                if shape.len() != 4 {
                    return Err(bad(format!(
                        "{name} has shape {shape:?}, expected a conv kernel"
                    )));
                }
                Entry::Block {
                    in_c: shape[1],
                    out_c: shape[0],
                }
            }
            _ => continue,
        };
        entries.insert(index, entry);
    }
    if entries.is_empty() {
        return Err(bad(
            "no taesd.py layer weights (keys like `0.weight`) found".into(),
        ));
    }
    Ok(entries)
}

/// Builds the config a pair of taesd.py files implies: encoder `conv, block*, (stride conv, block*)*, conv`;
/// decoder `[clamp], conv, [relu], (block*, [upsample], conv)*, block*, conv` (bracketed entries hold no
/// weights).
fn original_config(
    enc_path: &Path,
    enc: &BTreeMap<usize, Entry>,
    dec_path: &Path,
    dec: &BTreeMap<usize, Entry>,
) -> Result<TaesdConfig> {
    let bad = |path: &Path, message: String| TaesdError::Config {
        path: path.to_path_buf(),
        message: format!("unexpected taesd.py layer structure: {message}"),
    };
    let block = |entry: Option<&Entry>| match entry {
        Some(Entry::Block { in_c, out_c }) if in_c == out_c => Some(*out_c),
        _ => None,
    };

    // Encoder: indices are contiguous from 0.
    let last = *enc.keys().next_back().expect("non-empty");
    if enc.len() != last + 1 {
        return Err(bad(enc_path, "encoder indices are not contiguous".into()));
    }
    let (in_channels, first_ch) = match enc.get(&0) {
        Some(Entry::Conv {
            in_c,
            out_c,
            bias: true,
        }) => (*in_c, *out_c),
        other => {
            return Err(bad(
                enc_path,
                format!("index 0 should be the input conv, found {other:?}"),
            ))
        }
    };
    let latent_channels = match enc.get(&last) {
        Some(Entry::Conv {
            out_c, bias: true, ..
        }) if last > 0 => *out_c,
        other => {
            return Err(bad(
                enc_path,
                format!("index {last} should be the output conv, found {other:?}"),
            ))
        }
    };
    let mut enc_chans = vec![first_ch];
    let mut enc_blocks = vec![0];
    for i in 1..last {
        match &enc[&i] {
            Entry::Block { .. } => {
                block(enc.get(&i))
                    .filter(|c| c == enc_chans.last().expect("non-empty"))
                    .ok_or_else(|| bad(enc_path, format!("block {i} has mismatched widths")))?;
                *enc_blocks.last_mut().expect("non-empty") += 1;
            }
            Entry::Conv {
                in_c,
                out_c,
                bias: false,
            } if in_c == enc_chans.last().expect("non-empty") => {
                enc_chans.push(*out_c);
                enc_blocks.push(0);
            }
            other => return Err(bad(enc_path, format!("index {i}: unexpected {other:?}"))),
        }
    }

    // Decoder: 0 = clamp, 1 = conv, 2 = ReLU, then stages; an upsample is a missing index before a bias-free conv.
    let (dec_latent, dec_first) = match dec.get(&1) {
        Some(Entry::Conv {
            in_c,
            out_c,
            bias: true,
        }) => (*in_c, *out_c),
        other => {
            return Err(bad(
                dec_path,
                format!("index 1 should be the input conv, found {other:?}"),
            ))
        }
    };
    if dec.contains_key(&0) || dec.contains_key(&2) {
        return Err(bad(
            dec_path,
            "indices 0 and 2 should be the parameter-free clamp and ReLU".into(),
        ));
    }
    let dec_last = *dec.keys().next_back().expect("non-empty");
    let mut dec_chans = vec![dec_first];
    let mut dec_blocks = vec![0];
    let mut out_channels = None;
    let mut i = 3;
    while i <= dec_last {
        let current = *dec_chans.last().expect("non-empty");
        match dec.get(&i) {
            Some(Entry::Block { .. }) => {
                block(dec.get(&i))
                    .filter(|&c| c == current)
                    .ok_or_else(|| bad(dec_path, format!("block {i} has mismatched widths")))?;
                *dec_blocks.last_mut().expect("non-empty") += 1;
                i += 1;
            }
            // Upsample (no weights) followed by the stage's bias-free conv.
            None => match dec.get(&(i + 1)) {
                Some(Entry::Conv {
                    in_c,
                    out_c,
                    bias: false,
                }) if *in_c == current => {
                    dec_chans.push(*out_c);
                    dec_blocks.push(0);
                    i += 2;
                }
                other => {
                    return Err(bad(
                        dec_path,
                        format!(
                            "index {}: expected a conv after an upsample, found {other:?}",
                            i + 1
                        ),
                    ))
                }
            },
            Some(Entry::Conv {
                in_c,
                out_c,
                bias: true,
            }) if i == dec_last && *in_c == current => {
                out_channels = Some(*out_c);
                i += 1;
            }
            other => return Err(bad(dec_path, format!("index {i}: unexpected {other:?}"))),
        }
    }
    let out_channels =
        out_channels.ok_or_else(|| bad(dec_path, "no output conv with bias at the end".into()))?;
    if dec_latent != latent_channels {
        return Err(bad(
            dec_path,
            format!(
                "decoder takes {dec_latent} latent channels, encoder produces {latent_channels}"
            ),
        ));
    }
    let cfg = TaesdConfig {
        in_channels,
        out_channels,
        encoder_block_out_channels: enc_chans,
        decoder_block_out_channels: dec_chans,
        latent_channels,
        num_encoder_blocks: enc_blocks,
        num_decoder_blocks: dec_blocks,
        ..TaesdConfig::default()
    };
    cfg.validate().map_err(|m| bad(enc_path, m))?;
    Ok(cfg)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashMap;

    #[test]
    fn config_defaults_are_sd_taesd() {
        let cfg: TaesdConfig = serde_json::from_str("{}").unwrap();
        assert_eq!(cfg, TaesdConfig::default());
        assert_eq!(cfg.spatial_factor(), 8);
        assert!(cfg.validate().is_ok());
    }

    #[test]
    fn config_rejects_inconsistent_lengths_and_unknown_activation() {
        let cfg = TaesdConfig {
            num_encoder_blocks: vec![1, 3],
            ..TaesdConfig::default()
        };
        assert!(cfg.validate().unwrap_err().contains("num_encoder_blocks"));
        let cfg = TaesdConfig {
            act_fn: "tanhshrink".into(),
            ..TaesdConfig::default()
        };
        assert!(cfg.validate().unwrap_err().contains("tanhshrink"));
    }

    #[test]
    fn missing_files_are_one_clear_error() {
        let dir = tempfile::tempdir().unwrap();
        let err = AutoencoderTiny::load(dir.path()).unwrap_err().to_string();
        assert!(
            err.contains(ORIGINAL_ENCODER) && err.contains(DIFFUSERS_WEIGHTS),
            "{err}"
        );
        std::fs::write(dir.path().join(ORIGINAL_ENCODER), b"").unwrap();
        let err = AutoencoderTiny::load(dir.path()).unwrap_err().to_string();
        assert!(
            err.contains(&format!("{ORIGINAL_DECODER} is missing")),
            "{err}"
        );
    }

    #[test]
    fn garbage_weights_are_an_error_not_a_panic() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join(ORIGINAL_ENCODER), b"not safetensors").unwrap();
        std::fs::write(
            dir.path().join(ORIGINAL_DECODER),
            b"\x08\0\0\0\0\0\0\0{}      ",
        )
        .unwrap();
        assert!(AutoencoderTiny::load(dir.path()).is_err());
        std::fs::write(dir.path().join(DIFFUSERS_WEIGHTS), b"zz").unwrap();
        assert!(matches!(
            AutoencoderTiny::load(dir.path()),
            Err(TaesdError::Weights { .. })
        ));
    }

    /// A random model in diffusers names, re-saved under taesd.py names, must infer the same architecture and
    /// compute the same thing.
    #[test]
    fn original_layout_round_trip_infers_the_architecture() {
        let cfg = TaesdConfig {
            encoder_block_out_channels: vec![4, 4, 4],
            decoder_block_out_channels: vec![5, 5, 5],
            num_encoder_blocks: vec![1, 2, 0],
            num_decoder_blocks: vec![2, 0, 1],
            latent_channels: 3,
            ..TaesdConfig::default()
        };
        let varmap = candle_nn::VarMap::new();
        let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
        let model = AutoencoderTiny::new(&cfg, vb).unwrap();

        let mut enc = HashMap::new();
        let mut dec = HashMap::new();
        for (name, var) in varmap.data().lock().unwrap().iter() {
            let t = var.as_tensor().clone();
            if let Some(rest) = name.strip_prefix("encoder.layers.") {
                enc.insert(rest.to_string(), t);
            } else if let Some(rest) = name.strip_prefix("decoder.layers.") {
                let (idx, tail) = rest.split_once('.').unwrap();
                let idx: usize = idx.parse().unwrap();
                dec.insert(format!("{}.{tail}", idx + 1), t);
            } else {
                panic!("unexpected parameter {name}");
            }
        }
        let dir = tempfile::tempdir().unwrap();
        candle_core::safetensors::save(&enc, dir.path().join(ORIGINAL_ENCODER)).unwrap();
        candle_core::safetensors::save(&dec, dir.path().join(ORIGINAL_DECODER)).unwrap();
        let loaded = AutoencoderTiny::load(dir.path()).unwrap();
        assert_eq!(loaded.layout(), TaesdLayout::Original);
        assert_eq!(loaded.config(), &cfg);

        let image = Tensor::randn(0f32, 0.5, (2, 3, 12, 12), &Device::Cpu).unwrap();
        let a = model.encode(&image).unwrap();
        let b = loaded.encode(&image).unwrap();
        assert_eq!(a.dims(), &[2, 3, 3, 3]);
        // The VarMap model runs candle's differentiable conv, the loaded one the fast inference conv: same
        // values up to f32 summation order, relative to the output's size (random decoders reach ~40, where
        // 1e-5 absolute is below that noise; CI once saw it).
        let assert_close = |x: &Tensor, y: &Tensor, what: &str| {
            let max = |t: Tensor| {
                t.abs()
                    .unwrap()
                    .max_all()
                    .unwrap()
                    .to_scalar::<f32>()
                    .unwrap()
            };
            let scale = max(x.clone()).max(1.0);
            let diff = max((x - y).unwrap());
            assert!(
                diff <= 1e-5 * scale,
                "{what} differs by {diff} (output scale {scale})"
            );
        };
        assert_close(&a, &b, "encode");
        let x = model.decode(&b).unwrap();
        let y = loaded.decode(&b).unwrap();
        assert_eq!(x.dims(), &[2, 3, 12, 12]);
        assert_close(&x, &y, "decode");
    }

    #[test]
    fn wrong_input_channels_are_reported() {
        let varmap = candle_nn::VarMap::new();
        let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
        let cfg = TaesdConfig {
            encoder_block_out_channels: vec![2, 2],
            decoder_block_out_channels: vec![2, 2],
            num_encoder_blocks: vec![1, 1],
            num_decoder_blocks: vec![1, 1],
            ..TaesdConfig::default()
        };
        let model = AutoencoderTiny::new(&cfg, vb).unwrap();
        let bad = Tensor::zeros((1, 4, 8, 8), DType::F32, &Device::Cpu).unwrap();
        assert!(matches!(model.encode(&bad), Err(TaesdError::Input { .. })));
        let bad = Tensor::zeros((1, 3, 8, 8), DType::F32, &Device::Cpu).unwrap();
        assert!(matches!(model.decode(&bad), Err(TaesdError::Input { .. })));
    }

    /// Training needs gradients through encode and decode: every parameter gets one, and one of them
    /// agrees with a finite difference.
    #[test]
    fn encode_decode_is_differentiable() {
        let cfg = TaesdConfig {
            encoder_block_out_channels: vec![3, 3],
            decoder_block_out_channels: vec![3, 3],
            num_encoder_blocks: vec![1, 1],
            num_decoder_blocks: vec![1, 1],
            ..TaesdConfig::default()
        };
        let dev = Device::Cpu;
        let varmap = candle_nn::VarMap::new();
        // f64 so the finite difference can use a step small enough not to cross ReLU kinks.
        let model =
            AutoencoderTiny::new(&cfg, VarBuilder::from_varmap(&varmap, DType::F64, &dev)).unwrap();
        let image = Tensor::rand(-1f64, 1.0, (1, 3, 8, 8), &dev).unwrap();
        let loss = |m: &AutoencoderTiny| {
            let out = m.decode(&m.encode(&image).unwrap()).unwrap();
            (out - &image).unwrap().sqr().unwrap().mean_all().unwrap()
        };
        let grads = loss(&model).backward().unwrap();
        let vars = varmap.all_vars();
        assert!(!vars.is_empty());
        for var in &vars {
            assert!(
                grads.get(var).is_some(),
                "no gradient for a parameter of shape {:?}",
                var.dims()
            );
        }
        let data = varmap.data().lock().unwrap();
        let var = data["encoder.layers.0.bias"].clone();
        drop(data);
        let analytic = grads.get(&var).unwrap().to_vec1::<f64>().unwrap()[0];
        let base = var.as_tensor().to_vec1::<f64>().unwrap();
        let eps = 1e-6;
        let eval_at = |delta: f64| {
            let mut v = base.clone();
            v[0] += delta;
            var.set(&Tensor::new(v.as_slice(), &dev).unwrap()).unwrap();
            loss(&model).to_scalar::<f64>().unwrap()
        };
        let numeric = (eval_at(eps) - eval_at(-eps)) / (2.0 * eps);
        assert!(
            (numeric - analytic).abs() <= 1e-4 * analytic.abs().max(1e-3),
            "numeric {numeric}, analytic {analytic}"
        );
    }

    #[test]
    fn scaled_variants_apply_scale_and_shift() {
        let z = Tensor::new(&[1.0f32, -2.0], &Device::Cpu).unwrap();
        let s = scale_latents(&z, 0.5, 1.0).unwrap();
        assert_eq!(s.to_vec1::<f32>().unwrap(), vec![0.0, -1.5]);
        let back = unscale_latents(&s, 0.5, 1.0).unwrap();
        assert_eq!(back.to_vec1::<f32>().unwrap(), vec![1.0, -2.0]);
    }
}
