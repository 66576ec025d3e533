//! CLIP directional similarity (InstructPix2Pix / Instruct-NeRF2NeRF): how well the change between a
//! source and an edited view follows the change between the source and the target prompt,
//!
//! `cos(f_img(edited) − f_img(source), f_txt(target) − f_txt(source))`, averaged over views,
//!
//! where `f` are CLIP's projected embeddings, each L2-normalised first (as `ClipSimilarity` of the
//! InstructPix2Pix metrics code, which Instruct-NeRF2NeRF reports with ViT-L/14).
//!
//! # Weights
//! A `transformers` `CLIPModel` folder (`--clip DIR`, e.g. `openai/clip-vit-large-patch14`, or a hub-cache
//! `models--openai--clip-vit-large-patch14` folder): `config.json` with `text_config` / `vision_config`,
//! safetensors weights (`model.safetensors`, sharded or not; PyTorch pickles are refused), the tokenizer
//! (`tokenizer.json` or `vocab.json` + `merges.txt`) and optionally `preprocessor_config.json`.
//! The towers are [`diffusion::clip::ClipTextModel`] and [`diffusion::clip::ClipVisionModel`].
//! Everything runs in f32: ViT-L/14 needs about 1.7 GB.
//!
//! # Image preprocessing
//! As `CLIPImageProcessor` on float images: the shortest side resized to `size.shortest_edge` (antialiased
//! bicubic, the filter of PIL and of torch's `antialias=True`), a centre crop to `crop_size`, then
//! `(x − mean) / std`. (InstructPix2Pix's own script squashes the image to 224² with non-antialiased torch
//! bicubic instead; for the square renders vcedit evaluates the only difference is the filter.)

use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Module, Tensor};
use candle_nn::{linear_no_bias, Linear};
use diffusion::clip::{
    ids_tensor, ClipTextConfig, ClipTextModel, ClipVisionConfig, ClipVisionModel,
};
use diffusion::loader::{find_weight_files, resolve_model_path, var_builder_from_files, LoadError};
use diffusion::tokenizer::{ClipTokenizer, TokenizerError};
use serde::{Deserialize, Serialize};
use serde_json::Value;
use splat::Image;

/// OpenAI CLIP's normalisation constants (`OPENAI_CLIP_MEAN` / `OPENAI_CLIP_STD`).
pub const CLIP_MEAN: [f32; 3] = [0.481_454_66, 0.457_827_5, 0.408_210_73];
pub const CLIP_STD: [f32; 3] = [0.268_629_54, 0.261_302_6, 0.275_777_1];

/// Images per forward pass of the image tower (bounds the activation memory).
const IMAGE_BATCH: usize = 8;

#[derive(Debug, thiserror::Error)]
pub enum ClipScoreError {
    #[error(transparent)]
    Load(#[from] LoadError),
    #[error(transparent)]
    Tokenizer(#[from] TokenizerError),
    #[error("{}: {msg}", .path.display())]
    Config { path: PathBuf, msg: String },
    #[error("CLIP weights in {}: {source}", .dir.display())]
    Weights {
        dir: PathBuf,
        #[source]
        source: candle_core::Error,
    },
    #[error("CLIP: {0}")]
    Input(String),
    #[error("CLIP: {0}")]
    Candle(#[from] candle_core::Error),
}

/// How images are brought to the image tower's input.
#[derive(Debug, Clone, PartialEq)]
pub struct ClipPreprocess {
    pub resize: ResizeRule,
    /// Centre crop (height, width); `None` = no crop.
    pub crop: Option<(usize, usize)>,
    pub mean: [f32; 3],
    pub std: [f32; 3],
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ResizeRule {
    /// Shortest side to this length, aspect kept (longer side truncated like transformers).
    ShortestEdge(usize),
    /// Exactly (height, width).
    Exact(usize, usize),
}

impl ClipPreprocess {
    /// transformers' defaults for a model whose image tower takes `size`².
    pub fn for_size(size: usize) -> Self {
        Self {
            resize: ResizeRule::ShortestEdge(size),
            crop: Some((size, size)),
            mean: CLIP_MEAN,
            std: CLIP_STD,
        }
    }

    /// Reads `preprocessor_config.json` (old integer or current dict forms of `size` / `crop_size`);
    /// missing keys keep the defaults for `size`.
    pub fn from_json(value: &Value, size: usize) -> Result<Self, String> {
        let mut p = Self::for_size(size);
        let as_usize = |v: &Value| v.as_u64().map(|n| n as usize);
        if value.get("do_resize") != Some(&Value::Bool(false)) {
            match value.get("size") {
                None | Some(Value::Null) => {}
                Some(v) => {
                    p.resize = if let Some(n) = as_usize(v) {
                        ResizeRule::ShortestEdge(n)
                    } else if let Some(n) = v.get("shortest_edge").and_then(as_usize) {
                        ResizeRule::ShortestEdge(n)
                    } else if let (Some(h), Some(w)) = (
                        v.get("height").and_then(as_usize),
                        v.get("width").and_then(as_usize),
                    ) {
                        ResizeRule::Exact(h, w)
                    } else {
                        return Err(format!("unsupported \"size\": {v}"));
                    };
                }
            }
        }
        if value.get("do_center_crop") == Some(&Value::Bool(false)) {
            p.crop = None;
        } else {
            match value.get("crop_size") {
                None | Some(Value::Null) => {}
                Some(v) => {
                    p.crop = Some(if let Some(n) = as_usize(v) {
                        (n, n)
                    } else if let (Some(h), Some(w)) = (
                        v.get("height").and_then(as_usize),
                        v.get("width").and_then(as_usize),
                    ) {
                        (h, w)
                    } else {
                        return Err(format!("unsupported \"crop_size\": {v}"));
                    });
                }
            }
        }
        for (key, dst) in [("image_mean", &mut p.mean), ("image_std", &mut p.std)] {
            if let Some(v) = value.get(key) {
                let vals: Vec<f32> = v
                    .as_array()
                    .map(|a| {
                        a.iter()
                            .filter_map(|x| x.as_f64())
                            .map(|x| x as f32)
                            .collect()
                    })
                    .unwrap_or_default();
                if vals.len() != 3 {
                    return Err(format!("\"{key}\" must be three numbers, got {v}"));
                }
                dst.copy_from_slice(&vals);
            }
        }
        if p.std
            .iter()
            .any(|s| s.abs().partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater))
        {
            return Err("\"image_std\" has a zero".into());
        }
        match p.resize {
            ResizeRule::ShortestEdge(0) | ResizeRule::Exact(0, _) | ResizeRule::Exact(_, 0) => {
                return Err("resize size 0".into())
            }
            _ => {}
        }
        if matches!(p.crop, Some((0, _)) | Some((_, 0))) {
            return Err("crop size 0".into());
        }
        Ok(p)
    }

    /// Output (height, width).
    pub fn output_size(&self, height: usize, width: usize) -> (usize, usize) {
        self.crop
            .unwrap_or_else(|| self.resized_size(height, width))
    }

    fn resized_size(&self, height: usize, width: usize) -> (usize, usize) {
        match self.resize {
            ResizeRule::Exact(h, w) => (h, w),
            ResizeRule::ShortestEdge(s) => {
                if height <= width {
                    (s, (s as f64 * width as f64 / height as f64) as usize)
                } else {
                    ((s as f64 * height as f64 / width as f64) as usize, s)
                }
            }
        }
    }

    /// The normalised CHW pixel values of an RGB or RGBA image (alpha ignored; composite first if needed).
    pub fn apply(&self, image: &Image) -> Result<Vec<f32>, ClipScoreError> {
        let (h, w) = (image.height as usize, image.width as usize);
        let c = image.channels as usize;
        if c < 3 || h == 0 || w == 0 {
            return Err(ClipScoreError::Input(format!(
                "image of {w}x{h}x{c} is not an RGB image"
            )));
        }
        let rgb: Vec<f32> = if c == 3 {
            image.data.clone()
        } else {
            image
                .data
                .chunks_exact(c)
                .flat_map(|p| [p[0], p[1], p[2]])
                .collect()
        };
        let (rh, rw) = self.resized_size(h, w);
        let resized = if (rh, rw) == (h, w) {
            rgb
        } else {
            resize_bicubic_aa(&rgb, h, w, rh, rw, 3)
        };
        let (oh, ow) = self.output_size(h, w);
        // transformers pads with zeros when the crop is larger than the image, centred (left/top floor).
        let offset = |have: usize, want: usize| -> i64 {
            if have >= want {
                ((have - want) / 2) as i64
            } else {
                -(((want - have) / 2) as i64)
            }
        };
        let (top, left) = (offset(rh, oh), offset(rw, ow));
        let mut out = vec![0.0f32; 3 * oh * ow];
        for ch in 0..3 {
            for y in 0..oh {
                let sy = y as i64 + top;
                for x in 0..ow {
                    let sx = x as i64 + left;
                    let v = if sy >= 0 && sx >= 0 && (sy as usize) < rh && (sx as usize) < rw {
                        resized[(sy as usize * rw + sx as usize) * 3 + ch]
                    } else {
                        0.0
                    };
                    out[(ch * oh + y) * ow + x] = (v - self.mean[ch]) / self.std[ch];
                }
            }
        }
        Ok(out)
    }
}

/// Keys's cubic with a = −0.5 (PIL's bicubic, and torch's antialiased bicubic).
fn cubic(x: f64) -> f64 {
    const A: f64 = -0.5;
    let x = x.abs();
    if x < 1.0 {
        ((A + 2.0) * x - (A + 3.0)) * x * x + 1.0
    } else if x < 2.0 {
        (((x - 5.0) * x + 8.0) * x - 4.0) * A
    } else {
        0.0
    }
}

/// Per-output-pixel (first input index, normalised weights) of a 1-D antialiased resampling: the filter
/// is stretched by the downscale factor so every input pixel contributes (PIL's `precompute_coeffs`).
fn resample_taps(input: usize, output: usize) -> Vec<(usize, Vec<f64>)> {
    let scale = input as f64 / output as f64;
    let stretch = scale.max(1.0);
    let support = 2.0 * stretch;
    (0..output)
        .map(|i| {
            let center = scale * (i as f64 + 0.5);
            let lo = ((center - support + 0.5).trunc() as i64).max(0) as usize;
            let hi = ((center + support + 0.5).trunc() as i64).clamp(0, input as i64) as usize;
            let mut weights: Vec<f64> = (lo..hi.max(lo))
                .map(|j| cubic((j as f64 - center + 0.5) / stretch))
                .collect();
            let total: f64 = weights.iter().sum();
            if total != 0.0 {
                weights.iter_mut().for_each(|w| *w /= total);
            }
            (lo, weights)
        })
        .collect()
}

/// Antialiased bicubic resampling of a row-major, channel-interleaved image (torch
/// `interpolate(mode="bicubic", antialias=True, align_corners=False)`, PIL `BICUBIC`); not clamped.
pub fn resize_bicubic_aa(
    src: &[f32],
    h: usize,
    w: usize,
    out_h: usize,
    out_w: usize,
    channels: usize,
) -> Vec<f32> {
    let xs = resample_taps(w, out_w);
    let ys = resample_taps(h, out_h);
    // Horizontal pass into [h, out_w], then vertical.
    let mut mid = vec![0.0f64; h * out_w * channels];
    for y in 0..h {
        for (ox, (x0, wts)) in xs.iter().enumerate() {
            for c in 0..channels {
                let mut acc = 0.0;
                for (k, wt) in wts.iter().enumerate() {
                    acc += wt * src[(y * w + x0 + k) * channels + c] as f64;
                }
                mid[(y * out_w + ox) * channels + c] = acc;
            }
        }
    }
    let mut out = vec![0.0f32; out_h * out_w * channels];
    for (oy, (y0, wts)) in ys.iter().enumerate() {
        for ox in 0..out_w {
            for c in 0..channels {
                let mut acc = 0.0;
                for (k, wt) in wts.iter().enumerate() {
                    acc += wt * mid[((y0 + k) * out_w + ox) * channels + c];
                }
                out[(oy * out_w + ox) * channels + c] = acc as f32;
            }
        }
    }
    out
}

/// Result of [`ClipModel::directional_similarity`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ClipDirectionalReport {
    /// Mean over views of the directional similarity (higher = the edit follows the text change).
    pub directional: f64,
    /// Per view, in input order.
    pub per_view: Vec<f64>,
    /// Mean cos(f_img(source), f_img(edited)): how much of the image is kept.
    pub image_similarity: f64,
    /// Mean cos(f_img(edited), f_txt(target)).
    pub target_text_similarity: f64,
    pub source_prompt: String,
    pub target_prompt: String,
    /// The CLIP folder used.
    pub model: PathBuf,
}

/// A CLIP model with both towers, their projections, the tokenizer and the image preprocessing.
pub struct ClipModel {
    text: ClipTextModel,
    text_projection: Linear,
    vision: ClipVisionModel,
    visual_projection: Linear,
    tokenizer: ClipTokenizer,
    preprocess: ClipPreprocess,
    dir: PathBuf,
}

/// transformers' `CLIPTextConfig` defaults, for keys a config may omit.
fn text_defaults() -> Value {
    serde_json::json!({
        "vocab_size": 49408, "hidden_size": 512, "intermediate_size": 2048,
        "num_hidden_layers": 12, "num_attention_heads": 8, "max_position_embeddings": 77,
        "hidden_act": "quick_gelu", "layer_norm_eps": 1e-5, "eos_token_id": 49407
    })
}

/// `base` overlaid with `section` and then `section_dict` of `config` (older configs repeat the complete
/// sub-config as `*_config_dict`, which transformers gives precedence).
fn merged_section(config: &Value, section: &str, base: Value) -> Value {
    let mut out = match base {
        Value::Object(m) => m,
        _ => serde_json::Map::new(),
    };
    for key in [section.to_string(), format!("{section}_dict")] {
        if let Some(Value::Object(m)) = config.get(&key) {
            for (k, v) in m {
                if !v.is_null() {
                    out.insert(k.clone(), v.clone());
                }
            }
        }
    }
    // `eos_token_id` may be a list; transformers' text model compares against a single id.
    if let Some(Value::Array(a)) = out.get("eos_token_id") {
        match a.first().cloned() {
            Some(first) => out.insert("eos_token_id".into(), first),
            None => out.remove("eos_token_id"),
        };
    }
    Value::Object(out)
}

impl ClipModel {
    /// Loads a `CLIPModel` folder (see the module docs).
    pub fn load(dir: &Path) -> Result<Self, ClipScoreError> {
        let dir = resolve_model_path(dir)?;
        let config_path = dir.join("config.json");
        let config: Value = diffusion::loader::read_json(&config_path)?;
        let cfg_err = |msg: String| ClipScoreError::Config {
            path: config_path.clone(),
            msg,
        };
        if config.get("text_config").is_none() || config.get("vision_config").is_none() {
            return Err(cfg_err(
                "not a CLIPModel config (needs text_config and vision_config)".into(),
            ));
        }
        let text_config: ClipTextConfig =
            serde_json::from_value(merged_section(&config, "text_config", text_defaults()))
                .map_err(|e| cfg_err(format!("text_config: {e}")))?;
        let vision_config: ClipVisionConfig = serde_json::from_value(merged_section(
            &config,
            "vision_config",
            Value::Object(Default::default()),
        ))
        .map_err(|e| cfg_err(format!("vision_config: {e}")))?;
        if let Some(p) = vision_config.problem() {
            return Err(cfg_err(p));
        }
        let projection_dim = config
            .get("projection_dim")
            .and_then(Value::as_u64)
            .unwrap_or(512) as usize;

        let pre_path = dir.join("preprocessor_config.json");
        let preprocess = if pre_path.is_file() {
            let v: Value = diffusion::loader::read_json(&pre_path)?;
            ClipPreprocess::from_json(&v, vision_config.image_size).map_err(|msg| {
                ClipScoreError::Config {
                    path: pre_path.clone(),
                    msg,
                }
            })?
        } else {
            ClipPreprocess::for_size(vision_config.image_size)
        };
        if preprocess.output_size(1, 1) != (vision_config.image_size, vision_config.image_size)
            && preprocess.crop.is_some()
        {
            return Err(ClipScoreError::Config {
                path: pre_path,
                msg: format!(
                    "crop size {:?} differs from the image tower's {}",
                    preprocess.crop, vision_config.image_size
                ),
            });
        }

        let tokenizer =
            ClipTokenizer::from_dir(&dir)?.with_max_length(text_config.max_position_embeddings);

        let files = find_weight_files(&dir)?;
        let device = Device::Cpu;
        let vb = var_builder_from_files(&files.files, DType::F32, &device)?;
        let weights = |source: candle_core::Error| ClipScoreError::Weights {
            dir: dir.clone(),
            source,
        };
        let text_hidden = text_config.hidden_size;
        let vision_hidden = vision_config.hidden_size;
        let text = ClipTextModel::new(vb.clone(), text_config).map_err(|e| match e {
            diffusion::clip::ClipError::Candle(source) => weights(source),
            other => ClipScoreError::Config {
                path: config_path.clone(),
                msg: other.to_string(),
            },
        })?;
        let vision = ClipVisionModel::new(vb.pp("vision_model"), vision_config).map_err(weights)?;
        let text_projection = linear_no_bias(text_hidden, projection_dim, vb.pp("text_projection"))
            .map_err(weights)?;
        let visual_projection =
            linear_no_bias(vision_hidden, projection_dim, vb.pp("visual_projection"))
                .map_err(weights)?;
        Ok(Self {
            text,
            text_projection,
            vision,
            visual_projection,
            tokenizer,
            preprocess,
            dir,
        })
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }

    pub fn preprocess(&self) -> &ClipPreprocess {
        &self.preprocess
    }

    pub fn tokenizer(&self) -> &ClipTokenizer {
        &self.tokenizer
    }

    /// Projected text embeddings (not normalised), one per prompt. Long prompts are truncated as CLIP does.
    pub fn text_features(&self, prompts: &[&str]) -> Result<Vec<Vec<f32>>, ClipScoreError> {
        if prompts.is_empty() {
            return Ok(Vec::new());
        }
        let encodings: Vec<_> = prompts.iter().map(|p| self.tokenizer.encode(p)).collect();
        let ids = ids_tensor(&encodings, self.text.device())?;
        let hidden = self.text.forward(&ids)?;
        let pooled = self.text.pooled_output(&hidden, &ids)?;
        Ok(self.text_projection.forward(&pooled)?.to_vec2()?)
    }

    /// Projected image embeddings (not normalised) of images with values in [0, 1].
    pub fn image_features(&self, images: &[&Image]) -> Result<Vec<Vec<f32>>, ClipScoreError> {
        let mut out = Vec::with_capacity(images.len());
        for chunk in images.chunks(IMAGE_BATCH) {
            let mut pixels = Vec::new();
            for img in chunk {
                pixels.extend(self.preprocess.apply(img)?);
            }
            let (h, w) = self.preprocess.output_size(1, 1);
            let t = Tensor::from_vec(pixels, (chunk.len(), 3, h, w), &Device::Cpu)?;
            out.extend(self.image_features_from_pixels(&t)?);
        }
        Ok(out)
    }

    /// Projected image embeddings of already preprocessed `pixel_values` [B, 3, S, S].
    pub fn image_features_from_pixels(
        &self,
        pixel_values: &Tensor,
    ) -> Result<Vec<Vec<f32>>, ClipScoreError> {
        let pooled = self.vision.forward(pixel_values)?;
        Ok(self.visual_projection.forward(&pooled)?.to_vec2()?)
    }

    /// The directional similarity of `edited[k]` vs `sources[k]` for the prompt change (see module docs).
    pub fn directional_similarity(
        &self,
        sources: &[&Image],
        edited: &[&Image],
        source_prompt: &str,
        target_prompt: &str,
    ) -> Result<ClipDirectionalReport, ClipScoreError> {
        if sources.len() != edited.len() || sources.is_empty() {
            return Err(ClipScoreError::Input(format!(
                "directional similarity needs as many source as edited images (and at least one): {} vs {}",
                sources.len(),
                edited.len()
            )));
        }
        let text = self.text_features(&[source_prompt, target_prompt])?;
        let src = self.image_features(sources)?;
        let edt = self.image_features(edited)?;
        let (ts, tt) = (normalized(&text[0]), normalized(&text[1]));
        let text_dir: Vec<f64> = tt.iter().zip(&ts).map(|(a, b)| a - b).collect();
        let mut per_view = Vec::with_capacity(src.len());
        let (mut image_sim, mut target_sim) = (0.0, 0.0);
        for (s, e) in src.iter().zip(&edt) {
            let (s, e) = (normalized(s), normalized(e));
            let img_dir: Vec<f64> = e.iter().zip(&s).map(|(a, b)| a - b).collect();
            per_view.push(cosine(&img_dir, &text_dir));
            image_sim += cosine(&s, &e);
            target_sim += cosine(&e, &tt);
        }
        let n = per_view.len() as f64;
        Ok(ClipDirectionalReport {
            directional: per_view.iter().sum::<f64>() / n,
            per_view,
            image_similarity: image_sim / n,
            target_text_similarity: target_sim / n,
            source_prompt: source_prompt.to_string(),
            target_prompt: target_prompt.to_string(),
            model: self.dir.clone(),
        })
    }
}

fn normalized(v: &[f32]) -> Vec<f64> {
    let n = v.iter().map(|&x| (x as f64).powi(2)).sum::<f64>().sqrt();
    let n = if n > 0.0 { n } else { 1.0 };
    v.iter().map(|&x| x as f64 / n).collect()
}

/// Cosine similarity with torch's per-norm clamp at 1e-8.
pub fn cosine(a: &[f64], b: &[f64]) -> f64 {
    let dot: f64 = a.iter().zip(b).map(|(x, y)| x * y).sum();
    let na = a.iter().map(|x| x * x).sum::<f64>().sqrt().max(1e-8);
    let nb = b.iter().map(|x| x * x).sum::<f64>().sqrt().max(1e-8);
    dot / (na * nb)
}

/// Whether `dir` looks like a CLIP folder (for early, friendly CLI errors).
pub fn looks_like_clip_dir(dir: &Path) -> bool {
    resolve_model_path(dir)
        .map(|d| d.join("config.json").is_file())
        .unwrap_or(false)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn resize_keeps_constants_and_is_identity_at_same_size() {
        let src = vec![0.25f32; 7 * 5 * 3];
        for (oh, ow) in [(3, 2), (14, 10), (4, 9)] {
            let r = resize_bicubic_aa(&src, 7, 5, oh, ow, 3);
            assert!(r.iter().all(|v| (v - 0.25).abs() < 1e-6));
        }
        let ramp: Vec<f32> = (0..20).map(|i| i as f32).collect();
        assert_eq!(resize_bicubic_aa(&ramp, 4, 5, 4, 5, 1), ramp);
    }

    #[test]
    fn downscale_by_two_averages_neighbourhoods() {
        // A 2-periodic stripe pattern must come out as its mean when halved (the antialiasing at work).
        let src: Vec<f32> = (0..16 * 16).map(|i| ((i % 16) % 2) as f32).collect();
        let r = resize_bicubic_aa(&src, 16, 16, 8, 8, 1);
        // Interior pixels: the stretched filter is symmetric about the pair, so exactly 0.5.
        for y in 2..6 {
            for x in 2..6 {
                assert!((r[y * 8 + x] - 0.5).abs() < 1e-6, "{}", r[y * 8 + x]);
            }
        }
    }

    #[test]
    fn preprocess_config_forms() {
        let old: Value = serde_json::json!({"size": 224, "crop_size": 224});
        let p = ClipPreprocess::from_json(&old, 224).unwrap();
        assert_eq!(p.resize, ResizeRule::ShortestEdge(224));
        assert_eq!(p.crop, Some((224, 224)));
        let new: Value = serde_json::json!({"size": {"height": 30, "width": 20},
            "do_center_crop": false, "image_mean": [0.5, 0.5, 0.5], "image_std": [0.5, 0.5, 0.5]});
        let p = ClipPreprocess::from_json(&new, 224).unwrap();
        assert_eq!(p.resize, ResizeRule::Exact(30, 20));
        assert_eq!(p.crop, None);
        assert_eq!(p.mean, [0.5; 3]);
        assert!(
            ClipPreprocess::from_json(&serde_json::json!({"image_std": [1, 0, 1]}), 8).is_err()
        );
        assert!(ClipPreprocess::from_json(&serde_json::json!({"size": "big"}), 8).is_err());
    }

    #[test]
    fn shortest_edge_sizes_truncate_like_transformers() {
        let p = ClipPreprocess::for_size(224);
        assert_eq!(p.resized_size(480, 640), (224, 298));
        assert_eq!(p.resized_size(641, 480), (299, 224));
    }

    #[test]
    fn merged_section_prefers_dict_and_unpacks_lists() {
        let cfg = serde_json::json!({"text_config": {"hidden_size": 8, "eos_token_id": [5, 6]},
                                     "text_config_dict": {"hidden_size": 16}});
        let m = merged_section(&cfg, "text_config", text_defaults());
        assert_eq!(m["hidden_size"], 16);
        assert_eq!(m["eos_token_id"], 5);
        assert_eq!(m["vocab_size"], 49408);
    }
}
