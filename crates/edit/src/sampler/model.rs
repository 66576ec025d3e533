//! The diffusion model an edit runs on: tokenizer, text encoder, UNet, latent codec and noise schedule,
//! loaded from a user-given folder (diffusers layout or a hub-cache snapshot), optionally with TAESD as codec;
//! and the codecs' image convention (RGB images ↔ `[B, 3, H, W]` tensors).

use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};
use diffusion::clip::ClipTextModel;
use diffusion::loader::{Component, ModelDir};
use diffusion::scheduler::{LcmConfig, LcmScheduler, LcmVariant};
use diffusion::tokenizer::ClipTokenizer;
use diffusion::unet::{AttentionHook, UNet2DConditionModel};
use diffusion::vae::Autoencoder;
use splat::Image;

use super::noise::NoiseSource;
use crate::compute::Compute;

#[derive(Debug, thiserror::Error)]
pub enum ModelError {
    #[error(transparent)]
    Load(#[from] diffusion::loader::LoadError),
    #[error(transparent)]
    Tokenizer(#[from] diffusion::tokenizer::TokenizerError),
    #[error(transparent)]
    TextEncoder(#[from] diffusion::clip::ClipError),
    #[error("{}: {source}", .path.display())]
    Unet {
        path: PathBuf,
        source: diffusion::unet::UNetError,
    },
    #[error("{}: {source}", .path.display())]
    Codec {
        path: PathBuf,
        source: diffusion::vae::VaeError,
    },
    #[error("{0}")]
    Candle(#[from] candle_core::Error),
}

/// A loaded latent diffusion model.
pub struct EditModel {
    pub root: PathBuf,
    pub tokenizer: ClipTokenizer,
    pub text_encoder: ClipTextModel,
    pub unet: UNet2DConditionModel,
    pub codec: Autoencoder,
    /// Whether the codec is the pipeline's own VAE (false when TAESD replaced it).
    pub codec_is_vae: bool,
    /// The beta schedule (read from the scheduler config whatever its class; LCM selects the timesteps).
    pub scheduler_config: LcmConfig,
    /// Parameters of the UNet, text encoder and codec (held in f32).
    pub parameters: u64,
    /// Where the networks (and the run's renders and fits) run: the CPU unless [`Self::on`] says else.
    pub compute: Compute,
}

impl EditModel {
    /// Loads every component of `path`. With `taesd`, that folder's TAESD replaces the VAE (and the pipeline's
    /// `vae/` folder is not needed).
    pub fn load(path: &Path, taesd: Option<&Path>) -> Result<Self, ModelError> {
        let components: &[Component] = if taesd.is_some() {
            &[
                Component::Unet,
                Component::TextEncoder,
                Component::Tokenizer,
                Component::Scheduler,
            ]
        } else {
            &Component::ALL
        };
        let dir = ModelDir::open_components(path, components)?;
        let device = Device::Cpu;
        let text_encoder = ClipTextModel::load(&dir, DType::F32, &device)?;
        let tokenizer = ClipTokenizer::from_dir(dir.component_dir(Component::Tokenizer))?
            .with_max_length(text_encoder.max_positions());
        let unet_dir = dir.component_dir(Component::Unet);
        let weights = dir.weight_files(Component::Unet)?;
        let unet =
            UNet2DConditionModel::from_files(&dir.config_path(Component::Unet), &weights.files)
                .map_err(|source| ModelError::Unet {
                    path: unet_dir,
                    source,
                })?;
        let codec_dir = taesd
            .map(Path::to_path_buf)
            .unwrap_or_else(|| dir.component_dir(Component::Vae));
        let codec = Autoencoder::load(&codec_dir).map_err(|source| ModelError::Codec {
            path: codec_dir.clone(),
            source,
        })?;
        let scheduler_config: LcmConfig = dir.read_config(Component::Scheduler)?;
        // The schedule is built per edit; an impossible one (betas outside [0, 1)) is refused here, naming
        // its file, rather than sampling black images.
        LcmScheduler::new(scheduler_config.clone(), LcmVariant::default()).map_err(|e| {
            diffusion::loader::LoadError::BadFile {
                path: dir.config_path(Component::Scheduler),
                message: e.to_string(),
            }
        })?;
        let mut parameters = 0u64;
        for component in [Component::Unet, Component::TextEncoder, Component::Vae] {
            if component == Component::Vae && taesd.is_some() {
                continue;
            }
            for f in dir.weight_files(component)?.files {
                for t in diffusion::loader::read_safetensors_header(&f)? {
                    parameters += t.num_elements() as u64;
                }
            }
        }
        Ok(Self {
            root: dir.root().to_path_buf(),
            tokenizer,
            text_encoder,
            unet,
            codec,
            codec_is_vae: taesd.is_none(),
            scheduler_config,
            parameters,
            compute: Compute::cpu(),
        })
    }

    /// The model with its networks (and the run's splatting) on `compute`'s device.
    pub fn on(mut self, compute: Compute) -> Self {
        self.compute = compute;
        self
    }

    /// Text embeddings (`last_hidden_state`, f32) of token ids [B, S].
    pub fn encode_text(&self, ids: &Tensor) -> candle_core::Result<Tensor> {
        self.text_encoder
            .forward_skip_on(ids, 0, self.compute.networks())?
            .to_dtype(DType::F32)
    }

    /// The UNet's prediction for `sample` (see [`UNet2DConditionModel::forward`]) on the model's device.
    pub fn predict(
        &self,
        sample: &Tensor,
        timesteps: &Tensor,
        context: &Tensor,
        hook: Option<&mut (dyn AttentionHook + '_)>,
    ) -> candle_core::Result<Tensor> {
        self.unet.forward_on(
            sample,
            timesteps,
            context,
            None,
            hook,
            self.compute.networks(),
        )
    }

    /// A UNet pass run only for what `hook` observes: it may end early (see
    /// [`diffusion::unet::AttentionHook::finished`]); its prediction, if it got that far, is dropped.
    pub fn observe(
        &self,
        sample: &Tensor,
        timesteps: &Tensor,
        context: &Tensor,
        hook: &mut (dyn AttentionHook + '_),
    ) -> candle_core::Result<()> {
        self.unet
            .forward_observed(
                sample,
                timesteps,
                context,
                None,
                hook,
                self.compute.networks(),
            )
            .map(|_| ())
    }

    /// Latent channels of the UNet input (4 for SD; 8-channel InstructPix2Pix UNets take image latents too).
    pub fn latent_channels(&self) -> usize {
        self.codec.latent_channels()
    }

    /// Pixels per latent pixel.
    pub fn downscale(&self) -> usize {
        self.codec.spatial_factor()
    }

    /// Encodes images `[B, 3, H, W]` in [-1, 1] to UNet latents. The KL autoencoder samples its posterior
    /// (as the reference does) with noise from `noise`; TAESD is deterministic and draws nothing.
    pub fn encode(
        &self,
        image: &Tensor,
        noise: &mut dyn NoiseSource,
    ) -> candle_core::Result<Tensor> {
        let err = |e: diffusion::vae::VaeError| candle_core::Error::Msg(e.to_string());
        let device = self.compute.networks();
        match &self.codec {
            Autoencoder::Kl(vae) => {
                let (b, _, h, w) = image.dims4()?;
                let f = self.downscale();
                let n = noise.sample(&[b, vae.config().latent_channels, h / f, w / f])?;
                self.codec
                    .encode_scaled_on(image, Some(&n), device)
                    .map_err(err)
            }
            Autoencoder::Tiny(_) => self
                .codec
                .encode_scaled_on(image, None, device)
                .map_err(err),
        }
    }

    /// Encodes images (each `[1, 3, H, W]` in [-1, 1]) `batch` at a time, one latent per image. The noise
    /// is drawn in image order, so the result is the one-at-a-time result (up to the arithmetic of a
    /// larger batch).
    pub fn encode_each(
        &self,
        images: &[Tensor],
        batch: usize,
        noise: &mut dyn NoiseSource,
    ) -> candle_core::Result<Vec<Tensor>> {
        let (h, w) = images
            .first()
            .map_or((0, 0), |t| (t.dims()[t.rank() - 2], t.dims()[t.rank() - 1]));
        let batch = self.codec_batch(batch, h, w);
        let mut out = Vec::with_capacity(images.len());
        for chunk in images.chunks(batch) {
            let latents = match chunk {
                [one] => self.encode(one, noise)?,
                _ => self.encode(&Tensor::cat(chunk, 0)?, noise)?,
            };
            for v in 0..chunk.len() {
                out.push(latents.narrow(0, v, 1)?);
            }
        }
        Ok(out)
    }

    /// Decodes latents (each `[1, C, h, w]`) to RGB images, `batch` at a time (see [`Self::decode_images`]).
    pub fn decode_each(
        &self,
        latents: &[&Tensor],
        batch: usize,
    ) -> candle_core::Result<Vec<Image>> {
        let f = self.downscale();
        let (h, w) = latents.first().map_or((0, 0), |t| {
            (t.dims()[t.rank() - 2] * f, t.dims()[t.rank() - 1] * f)
        });
        let batch = self.codec_batch(batch, h, w);
        let mut out = Vec::with_capacity(latents.len());
        for chunk in latents.chunks(batch) {
            match chunk {
                [one] => out.extend(self.decode_images(one)?),
                _ => out.extend(self.decode_images(&Tensor::cat(chunk, 0)?)?),
            }
        }
        Ok(out)
    }

    /// Images of `h × w` pixels the codec takes per call, at most `batch`: on a GPU as many as keep its
    /// largest activation within the device's largest buffer.
    fn codec_batch(&self, batch: usize, h: usize, w: usize) -> usize {
        let batch = batch.max(1);
        let Some(limits) = self.compute.gpu_limits() else {
            return batch;
        };
        let per_image = self.codec.largest_activation_bytes(h, w).max(1) as u64;
        let limit = limits.max_buffer_bytes;
        batch.min((limit / per_image).max(1) as usize)
    }

    /// Decodes UNet latents to images in [-1, 1] (unclamped). A non-finite value is an error: it comes
    /// from damaged weights (or a broken schedule) and would otherwise be saved as black pixels.
    pub fn decode(&self, latents: &Tensor) -> candle_core::Result<Tensor> {
        let images = self
            .codec
            .decode_scaled_on(latents, self.compute.networks())
            .map_err(|e| candle_core::Error::Msg(e.to_string()))?;
        let finite = images
            .flatten_all()?
            .to_dtype(DType::F32)?
            .to_vec1::<f32>()?
            .iter()
            .all(|v| v.is_finite());
        if !finite {
            candle_core::bail!(
                "{}: the decoded images hold NaN or infinite values; the weights may be damaged \
                 (`vcedit model check` on this folder looks at every value)",
                self.root.display()
            );
        }
        Ok(images)
    }

    /// Decodes UNet latents to images `[B, 3, H, W]` in [0, 1], clamped: the range images are shown, saved
    /// and fitted in.
    pub fn decode_unit(&self, latents: &Tensor) -> candle_core::Result<Tensor> {
        self.decode(latents)?.affine(0.5, 0.5)?.clamp(0f32, 1f32)
    }

    /// [`Self::decode_unit`] as RGB images.
    pub fn decode_images(&self, latents: &Tensor) -> candle_core::Result<Vec<Image>> {
        tensor_to_images(&self.decode_unit(latents)?)
    }
}

/// An RGB image as a `[1, 3, H, W]` tensor in [-1, 1] (the codecs' input range).
pub fn image_to_tensor(img: &Image) -> candle_core::Result<Tensor> {
    assert_eq!(img.channels, 3, "image_to_tensor needs RGB");
    let (w, h) = (img.width as usize, img.height as usize);
    let hwc = Tensor::from_vec(img.data.clone(), (h, w, 3), &Device::Cpu)?;
    hwc.permute((2, 0, 1))?
        .unsqueeze(0)?
        .affine(2.0, -1.0)?
        .contiguous()
}

/// Images `[B, 3, H, W]` in [0, 1] as RGB images.
pub fn tensor_to_images(t: &Tensor) -> candle_core::Result<Vec<Image>> {
    let (b, c, h, w) = t.dims4()?;
    let hwc = t
        .to_dtype(DType::F32)?
        .permute((0, 2, 3, 1))?
        .contiguous()?;
    (0..b)
        .map(|i| {
            Ok(Image::from_data(
                w as u32,
                h as u32,
                c as u32,
                hwc.get(i)?.flatten_all()?.to_vec1()?,
            ))
        })
        .collect()
}
