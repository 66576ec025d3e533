//! CLIP vision transformer (`transformers.CLIPVisionModel`), for the CLIP directional similarity metric.
//!
//! Patch embedding (a stride-`patch` convolution without bias, computed here as one matrix product over the
//! flattened patches), a learnt class token prepended, learnt position embeddings, `pre_layrnorm`,
//! pre-LayerNorm transformer blocks without a mask, and `post_layernorm` of the class token: the pooled
//! output that `CLIPModel.visual_projection` maps into the joint space.
//!
//! Weights use transformers' key names under `vision_model.`.

use candle_core::Tensor;
use candle_nn::VarBuilder;
use serde::Deserialize;

use super::encoder::{ClipActivation, EncoderLayer, EncoderLayerConfig};
use crate::layers::LayerNorm;

fn d_hidden() -> usize {
    768
}
fn d_intermediate() -> usize {
    3072
}
fn d_layers() -> usize {
    12
}
fn d_heads() -> usize {
    12
}
fn d_channels() -> usize {
    3
}
fn d_image_size() -> usize {
    224
}
fn d_patch() -> usize {
    32
}
fn d_act() -> ClipActivation {
    ClipActivation::QuickGelu
}
fn d_eps() -> f64 {
    1e-5
}

/// `vision_config` of a CLIP `config.json` (defaults are transformers' `CLIPVisionConfig` defaults).
#[derive(Debug, Clone, Deserialize)]
pub struct ClipVisionConfig {
    #[serde(default = "d_hidden")]
    pub hidden_size: usize,
    #[serde(default = "d_intermediate")]
    pub intermediate_size: usize,
    #[serde(default = "d_layers")]
    pub num_hidden_layers: usize,
    #[serde(default = "d_heads")]
    pub num_attention_heads: usize,
    #[serde(default = "d_channels")]
    pub num_channels: usize,
    #[serde(default = "d_image_size")]
    pub image_size: usize,
    #[serde(default = "d_patch")]
    pub patch_size: usize,
    #[serde(default = "d_act")]
    pub hidden_act: ClipActivation,
    #[serde(default = "d_eps")]
    pub layer_norm_eps: f64,
}

impl ClipVisionConfig {
    /// A description of the first inconsistency, if any.
    pub fn problem(&self) -> Option<String> {
        if self.num_attention_heads == 0
            || !self.hidden_size.is_multiple_of(self.num_attention_heads)
        {
            return Some(format!(
                "vision hidden_size {} is not divisible by num_attention_heads {}",
                self.hidden_size, self.num_attention_heads
            ));
        }
        if self.patch_size == 0 || !self.image_size.is_multiple_of(self.patch_size) {
            return Some(format!(
                "vision image_size {} is not a multiple of patch_size {}",
                self.image_size, self.patch_size
            ));
        }
        if self.num_channels != 3 {
            return Some(format!(
                "vision num_channels {} (only RGB models are supported)",
                self.num_channels
            ));
        }
        None
    }

    /// Patches per side.
    pub fn grid(&self) -> usize {
        self.image_size / self.patch_size
    }

    fn encoder_layer(&self) -> EncoderLayerConfig {
        EncoderLayerConfig {
            hidden_size: self.hidden_size,
            intermediate_size: self.intermediate_size,
            num_attention_heads: self.num_attention_heads,
            layer_norm_eps: self.layer_norm_eps,
            hidden_act: self.hidden_act,
        }
    }
}

/// The CLIP image tower up to the pooled (post-LayerNorm class token) output.
#[derive(Debug, Clone)]
pub struct ClipVisionModel {
    /// Patch convolution kernel as a [D, 3·p·p] matrix (input order channel, row, column).
    patch_weight: Tensor,
    class_embedding: Tensor,
    position_embedding: Tensor,
    pre_layrnorm: LayerNorm,
    layers: Vec<EncoderLayer>,
    post_layernorm: LayerNorm,
    config: ClipVisionConfig,
}

impl ClipVisionModel {
    /// Builds the model from a `VarBuilder` positioned at `vision_model`.
    pub fn new(vb: VarBuilder, config: ClipVisionConfig) -> candle_core::Result<Self> {
        if let Some(p) = config.problem() {
            candle_core::bail!("{p}");
        }
        let c = &config;
        let d = c.hidden_size;
        let p = c.patch_size;
        let emb = vb.pp("embeddings");
        let patch_weight = emb
            .pp("patch_embedding")
            .get((d, c.num_channels, p, p), "weight")?
            .reshape((d, c.num_channels * p * p))?;
        let class_embedding = emb.get(d, "class_embedding")?;
        let positions = c.grid() * c.grid() + 1;
        let position_embedding = emb.pp("position_embedding").get((positions, d), "weight")?;
        let eps = c.layer_norm_eps;
        let pre_layrnorm = LayerNorm::load(d, eps, vb.pp("pre_layrnorm"))?;
        let layers = (0..c.num_hidden_layers)
            .map(|i| EncoderLayer::load(vb.pp("encoder").pp("layers").pp(i), &c.encoder_layer()))
            .collect::<candle_core::Result<Vec<_>>>()?;
        let post_layernorm = LayerNorm::load(d, eps, vb.pp("post_layernorm"))?;
        Ok(Self {
            patch_weight,
            class_embedding,
            position_embedding,
            pre_layrnorm,
            layers,
            post_layernorm,
            config,
        })
    }

    pub fn config(&self) -> &ClipVisionConfig {
        &self.config
    }

    /// Pooled output [B, D] for `pixel_values` [B, 3, S, S] (S = `image_size`, already normalised).
    pub fn forward(&self, pixel_values: &Tensor) -> candle_core::Result<Tensor> {
        let c = &self.config;
        let (b, ch, h, w) = pixel_values.dims4()?;
        if ch != c.num_channels || h != c.image_size || w != c.image_size {
            candle_core::bail!(
                "CLIP vision input is {ch}x{h}x{w}, the model takes {}x{}x{}",
                c.num_channels,
                c.image_size,
                c.image_size
            );
        }
        let (g, p, d) = (c.grid(), c.patch_size, c.hidden_size);
        // [B, C, gy, p, gx, p] -> [B, gy, gx, C, p, p]: each patch flattened in the kernel's order.
        let patches = pixel_values
            .reshape((b, ch, g, p, g, p))?
            .permute((0, 2, 4, 1, 3, 5))?
            .contiguous()?
            .reshape((b * g * g, ch * p * p))?;
        let tokens = patches
            .matmul(&self.patch_weight.t()?)?
            .reshape((b, g * g, d))?;
        let class = self
            .class_embedding
            .reshape((1, 1, d))?
            .broadcast_as((b, 1, d))?;
        let mut x = Tensor::cat(&[&class, &tokens], 1)?.broadcast_add(&self.position_embedding)?;
        x = self.pre_layrnorm.forward(&x)?;
        for layer in &self.layers {
            x = layer.forward(&x, None)?;
        }
        let cls = x.narrow(1, 0, 1)?.squeeze(1)?;
        self.post_layernorm.forward(&cls)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Device};

    fn random_model() -> (ClipVisionModel, candle_nn::VarMap) {
        let cfg: ClipVisionConfig = serde_json::from_str(
            r#"{"hidden_size": 8, "intermediate_size": 12, "num_hidden_layers": 1,
                "num_attention_heads": 2, "image_size": 8, "patch_size": 4}"#,
        )
        .unwrap();
        let vm = candle_nn::VarMap::new();
        let vb = VarBuilder::from_varmap(&vm, DType::F32, &Device::Cpu);
        (ClipVisionModel::new(vb, cfg).unwrap(), vm)
    }

    #[test]
    fn patch_embedding_equals_strided_convolution() {
        let (m, _vm) = random_model();
        let x = Tensor::randn(0f32, 1.0, (2, 3, 8, 8), &Device::Cpu).unwrap();
        let kernel = m.patch_weight.reshape((8, 3, 4, 4)).unwrap();
        let conv = x
            .conv2d(&kernel, 0, 4, 1, 1)
            .unwrap()
            .flatten_from(2)
            .unwrap()
            .transpose(1, 2)
            .unwrap();
        let (b, ch, g, p) = (2, 3, 2, 4);
        let mine = x
            .reshape((b, ch, g, p, g, p))
            .unwrap()
            .permute((0, 2, 4, 1, 3, 5))
            .unwrap()
            .contiguous()
            .unwrap()
            .reshape((b * g * g, ch * p * p))
            .unwrap()
            .matmul(&m.patch_weight.t().unwrap())
            .unwrap()
            .reshape((b, g * g, 8))
            .unwrap();
        let diff = testkit::diff::tensor_max_abs_diff(&conv, &mine);
        assert!(diff < 1e-5, "{diff}");
    }

    #[test]
    fn wrong_input_size_is_an_error() {
        let (m, _vm) = random_model();
        let x = Tensor::zeros((1, 3, 9, 9), DType::F32, &Device::Cpu).unwrap();
        assert!(m.forward(&x).is_err());
        let ok = Tensor::zeros((1, 3, 8, 8), DType::F32, &Device::Cpu).unwrap();
        assert_eq!(m.forward(&ok).unwrap().dims(), &[1, 8]);
    }

    #[test]
    fn config_problems_are_reported() {
        let bad: ClipVisionConfig =
            serde_json::from_str(r#"{"image_size": 30, "patch_size": 8}"#).unwrap();
        assert!(bad.problem().unwrap().contains("patch_size"));
        let bad: ClipVisionConfig =
            serde_json::from_str(r#"{"hidden_size": 10, "num_attention_heads": 3}"#).unwrap();
        assert!(bad.problem().unwrap().contains("divisible"));
    }
}
