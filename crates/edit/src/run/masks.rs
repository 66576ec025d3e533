//! Which Gaussians an edit may change (local editing).
//!
//! A mask is one boolean per Gaussian. It comes from a 3D box, from per-view mask images lifted onto the
//! Gaussians, or from the source prompt's attention to a word, lifted the same way; a Gaussian is editable
//! when its lifted value exceeds the threshold (0.5 by default, GaussianEditor's `mask_thres`).

use std::path::Path;

use candle_core::{DType, Device, Tensor};
use diffusion::device::DeviceTensor;
use diffusion::unet::{AttentionHook, AttnCall, AttnKind};
use gpu::GpuError;
use splat::render::{render, ExtraChannels, RenderSettings};
use splat::{Camera, GaussianScene, Image};

use crate::compute::Compute;
use crate::present::viz::resize_map;
use crate::sampler::{image_to_tensor, EditModel, NoiseSource};

#[derive(Debug, thiserror::Error)]
pub enum MaskError {
    #[error("{0}")]
    Invalid(String),
    #[error("{}: no mask image for camera {camera} (expected {camera}.png)", .dir.display())]
    MissingImage {
        dir: std::path::PathBuf,
        camera: String,
    },
    #[error(transparent)]
    Image(#[from] splat::image::ImageError),
    #[error("{0}")]
    Candle(#[from] candle_core::Error),
    #[error(transparent)]
    Gpu(#[from] GpuError),
}

/// An axis-aligned box `[min, max]`.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct Box3 {
    pub min: [f32; 3],
    pub max: [f32; 3],
}

impl std::str::FromStr for Box3 {
    type Err = String;
    /// "xmin,ymin,zmin,xmax,ymax,zmax"
    fn from_str(s: &str) -> Result<Self, String> {
        let v: Vec<f32> = s
            .split(',')
            .map(|x| {
                x.trim()
                    .parse::<f32>()
                    .map_err(|_| format!("'{x}' is not a number"))
            })
            .collect::<Result<_, _>>()?;
        if v.len() != 6 || v.iter().any(|x| !x.is_finite()) {
            return Err(format!(
                "expected 6 finite numbers xmin,ymin,zmin,xmax,ymax,zmax, got '{s}'"
            ));
        }
        let b = Box3 {
            min: [v[0], v[1], v[2]],
            max: [v[3], v[4], v[5]],
        };
        if (0..3).any(|a| b.min[a] > b.max[a]) {
            return Err(format!("box minimum exceeds maximum in '{s}'"));
        }
        Ok(b)
    }
}

/// Gaussians whose centres lie inside the box.
pub fn mask_from_box(scene: &GaussianScene, b: &Box3) -> Vec<bool> {
    scene
        .means
        .chunks_exact(3)
        .map(|p| (0..3).all(|a| p[a] >= b.min[a] && p[a] <= b.max[a]))
        .collect()
}

/// Lifted per-Gaussian values above `threshold`.
pub fn threshold(values: &[f32], threshold: f32) -> Vec<bool> {
    values.iter().map(|&v| v > threshold).collect()
}

/// Lifts single-channel per-view maps (each H*W for its camera) onto the Gaussians.
pub fn lift_maps(
    compute: &Compute,
    scene: &GaussianScene,
    cameras: &[Camera],
    maps: &[Vec<f32>],
) -> Result<Vec<f32>, GpuError> {
    let mut acc = compute.splat().lifter(scene, 1);
    for (cam, m) in cameras.iter().zip(maps) {
        acc.add_view(cam, m)?;
    }
    Ok(acc.finish()?.values)
}

/// Per-view mask images from a folder: `<camera name>.png` (or .jpg), white = editable, resized to the camera.
pub fn load_mask_images(dir: &Path, cameras: &[Camera]) -> Result<Vec<Vec<f32>>, MaskError> {
    let mut out = Vec::with_capacity(cameras.len());
    for cam in cameras {
        let stem = Path::new(&cam.name)
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default();
        let path = ["png", "jpg", "jpeg"]
            .iter()
            .map(|e| dir.join(format!("{stem}.{e}")))
            .find(|p| p.is_file());
        let Some(path) = path else {
            return Err(MaskError::MissingImage {
                dir: dir.to_path_buf(),
                camera: stem,
            });
        };
        let img = Image::load(&path)?;
        let img = img
            .center_crop_to_aspect(cam.width, cam.height)
            .resize(cam.width, cam.height);
        let c = img.channels as usize;
        // Luminance of RGB (alpha ignored), so both grey and colour masks work.
        out.push(
            img.data
                .chunks_exact(c)
                .map(|p| (p[0] + p[1] + p[2]) / 3.0)
                .collect(),
        );
    }
    Ok(out)
}

/// The editable mask rendered from a camera (1 where editable Gaussians cover the pixel).
pub fn render_mask(scene: &GaussianScene, mask: &[bool], camera: &Camera) -> Vec<f32> {
    let values: Vec<f32> = mask.iter().map(|&m| if m { 1.0 } else { 0.0 }).collect();
    let out = render(
        scene,
        camera,
        &RenderSettings::default(),
        Some(ExtraChannels {
            values: &values,
            channels: 1,
        }),
    );
    out.into_frame().extra
}

/// Records the conditional cross-attention maps of the layers of one spatial size.
struct WordAttention {
    size: (usize, usize),
    sum: Option<Tensor>,
    layers: usize,
}

impl AttentionHook for WordAttention {
    fn wants_probs(&self, call: &AttnCall) -> bool {
        call.kind == AttnKind::CrossAttn && (call.height, call.width) == self.size
    }

    fn probs(&mut self, call: &AttnCall, probs: DeviceTensor) -> candle_core::Result<DeviceTensor> {
        if self.wants_probs(call) && !call.layer.starts_with("mid") {
            // [batch, heads, N, tokens] → mean over batch and heads: [N, tokens]. The maps are small (the
            // blend resolution), so they are read back whole.
            let m = probs.to_cpu()?.to_dtype(DType::F32)?.mean(0)?.mean(0)?;
            self.sum = Some(match self.sum.take() {
                Some(s) => s.add(&m)?,
                None => m,
            });
            self.layers += 1;
        }
        Ok(probs)
    }
}

/// Per-view attention maps of `word` (its tokens in `prompt`) at the working resolution, each normalised to
/// [0, 1] by its maximum: the source image is encoded, noised to timestep `t`, and one UNet pass with the
/// prompt records the cross-attention of the blend-resolution layers (averaged over layers and heads, max
/// over the word's tokens). Returns the maps (H*W per view).
pub fn word_attention_maps(
    model: &EditModel,
    images: &[Image],
    prompt: &str,
    word: &str,
    t: usize,
    blend_size: (usize, usize),
    noise: &mut dyn NoiseSource,
) -> Result<Vec<Vec<f32>>, MaskError> {
    let tok = &model.tokenizer;
    let prompt_ids = tok.encode_unpadded(prompt);
    let word_ids = tok.tokenize(word);
    if word_ids.is_empty() {
        return Err(MaskError::Invalid("--mask-word is empty".into()));
    }
    // Positions of the word's tokens inside the prompt (first occurrence of the whole sequence).
    let pos = prompt_ids
        .windows(word_ids.len())
        .position(|w| w == word_ids.as_slice())
        .ok_or_else(|| {
            MaskError::Invalid(format!(
                "mask word '{word}' does not occur in the prompt '{prompt}'"
            ))
        })?;
    let positions: Vec<u32> = (pos..pos + word_ids.len()).map(|p| p as u32).collect();
    let enc = tok
        .encode_strict(prompt)
        .map_err(|e| MaskError::Invalid(e.to_string()))?;
    let ids = diffusion::clip::ids_tensor(&[enc], &Device::Cpu)?;
    let context = model.encode_text(&ids)?;
    let sched = diffusion::scheduler::LcmScheduler::new(
        model.scheduler_config.clone(),
        diffusion::scheduler::LcmVariant::Diffusers022,
    )
    .map_err(|e| MaskError::Invalid(e.to_string()))?;
    let alpha = sched
        .alpha_cumprod(t)
        .map_err(|e| MaskError::Invalid(e.to_string()))?;
    let mut maps = Vec::with_capacity(images.len());
    for img in images {
        let x0 = model.encode(&image_to_tensor(img)?, noise)?;
        let n = noise.sample(x0.dims())?;
        let zt = x0
            .affine(alpha.sqrt(), 0.0)?
            .add(&n.affine((1.0 - alpha).sqrt(), 0.0)?)?;
        let mut rec = WordAttention {
            size: blend_size,
            sum: None,
            layers: 0,
        };
        let ts = Tensor::new(&[t as f32], &Device::Cpu)?;
        model.predict(&zt, &ts, &context, Some(&mut rec))?;
        let sum = rec.sum.ok_or_else(|| {
            MaskError::Invalid("the UNet has no cross-attention at the blend resolution".into())
        })?;
        let sel = sum
            .index_select(&Tensor::new(positions.as_slice(), &Device::Cpu)?, 1)?
            .max(1)?;
        let m = sel.reshape(blend_size)?;
        let up = resize_map(&m, img.height as usize, img.width as usize)?;
        let max = up.iter().copied().fold(0.0f32, f32::max);
        maps.push(
            up.into_iter()
                .map(|v| if max > 0.0 { v / max } else { 0.0 })
                .collect(),
        );
    }
    Ok(maps)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn box_parsing_and_selection() {
        let b: Box3 = "-1,-1,-1,1,1,1".parse().unwrap();
        assert!("1,2,3".parse::<Box3>().is_err());
        assert!("1,0,0,0,1,1".parse::<Box3>().is_err());
        assert!("a,0,0,1,1,1".parse::<Box3>().is_err());
        let scene = GaussianScene {
            sh_degree: 0,
            means: vec![0.0, 0.0, 0.0, 2.0, 0.0, 0.0],
            log_scales: vec![0.0; 6],
            quats: vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0],
            opacity_logits: vec![0.0; 2],
            sh: vec![0.0; 6],
        };
        assert_eq!(mask_from_box(&scene, &b), vec![true, false]);
        assert_eq!(threshold(&[0.2, 0.7], 0.5), vec![false, true]);
    }
}
