//! CLIP text encoder (`transformers.CLIPTextModel`): token + position embeddings, pre-LayerNorm
//! transformer blocks with a causal mask, final LayerNorm. Output `last_hidden_state` [B, S, D] is the
//! UNet's cross-attention context.
//!
//! Weights use transformers' key names, with or without the `text_model.` prefix (transformers 4 saved
//! it, transformers 5 does not).

use candle_core::{DType, Device, Module, Tensor};
use candle_nn::{embedding, Embedding, VarBuilder};
use serde::Deserialize;

use super::encoder::{ClipActivation, EncoderLayer, EncoderLayerConfig};
use crate::device;
use crate::layers::LayerNorm;
use crate::loader::{Component, LoadError, ModelDir};
use crate::tokenizer::{ClipTokenizer, Encoding};

/// Errors from building or running the text encoder.
#[derive(Debug, thiserror::Error)]
pub enum ClipError {
    #[error(transparent)]
    Load(#[from] LoadError),
    #[error("text encoder weights in {path}: {source}")]
    Weights {
        path: String,
        #[source]
        source: candle_core::Error,
    },
    #[error("text encoder config: {0}")]
    Config(String),
    #[error(transparent)]
    Candle(#[from] candle_core::Error),
}

fn d_max_pos() -> usize {
    77
}
fn d_act() -> ClipActivation {
    ClipActivation::QuickGelu
}
fn d_eps() -> f64 {
    1e-5
}
fn d_eos() -> u32 {
    2
}

/// `text_encoder/config.json` (the keys the model needs; others are ignored).
#[derive(Debug, Clone, Deserialize)]
pub struct ClipTextConfig {
    pub vocab_size: usize,
    pub hidden_size: usize,
    pub intermediate_size: usize,
    pub num_hidden_layers: usize,
    pub num_attention_heads: usize,
    #[serde(default = "d_max_pos")]
    pub max_position_embeddings: usize,
    #[serde(default = "d_act")]
    pub hidden_act: ClipActivation,
    #[serde(default = "d_eps")]
    pub layer_norm_eps: f64,
    #[serde(default = "d_eos")]
    pub eos_token_id: u32,
    #[serde(default)]
    pub projection_dim: Option<usize>,
}

impl ClipTextConfig {
    fn validate(&self) -> Result<(), ClipError> {
        if self.num_attention_heads == 0
            || !self.hidden_size.is_multiple_of(self.num_attention_heads)
        {
            return Err(ClipError::Config(format!(
                "hidden_size {} is not divisible by num_attention_heads {}",
                self.hidden_size, self.num_attention_heads
            )));
        }
        if self.max_position_embeddings < 2 || self.vocab_size == 0 {
            return Err(ClipError::Config(format!(
                "max_position_embeddings {} / vocab_size {} too small",
                self.max_position_embeddings, self.vocab_size
            )));
        }
        Ok(())
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

/// The CLIP text transformer.
#[derive(Debug, Clone)]
pub struct ClipTextModel {
    token_embedding: Embedding,
    position_embedding: Tensor,
    layers: Vec<EncoderLayer>,
    final_layer_norm: LayerNorm,
    config: ClipTextConfig,
}

impl ClipTextModel {
    /// Builds the model from a `VarBuilder` rooted at the weight file (prefix detected automatically).
    pub fn new(vb: VarBuilder, config: ClipTextConfig) -> Result<Self, ClipError> {
        config.validate()?;
        let vb = if vb.contains_tensor("text_model.embeddings.token_embedding.weight") {
            vb.pp("text_model")
        } else {
            vb
        };
        let c = &config;
        let emb = vb.pp("embeddings");
        let token_embedding = embedding(c.vocab_size, c.hidden_size, emb.pp("token_embedding"))?;
        let position_embedding = emb.pp("position_embedding").get_with_hints(
            (c.max_position_embeddings, c.hidden_size),
            "weight",
            // transformers' initialisation; only used when training from scratch.
            candle_nn::Init::Randn {
                mean: 0.0,
                stdev: 0.02,
            },
        )?;
        let layers = (0..c.num_hidden_layers)
            .map(|i| EncoderLayer::load(vb.pp("encoder").pp("layers").pp(i), &c.encoder_layer()))
            .collect::<candle_core::Result<Vec<_>>>()?;
        let final_layer_norm =
            LayerNorm::load(c.hidden_size, c.layer_norm_eps, vb.pp("final_layer_norm"))?;
        Ok(ClipTextModel {
            token_embedding,
            position_embedding,
            layers,
            final_layer_norm,
            config,
        })
    }

    /// Loads `text_encoder/` of a model folder in `dtype` (weights converted on load).
    pub fn load(model: &ModelDir, dtype: DType, device: &Device) -> Result<Self, ClipError> {
        let config: ClipTextConfig = model.read_config(Component::TextEncoder)?;
        let vb = model.var_builder(Component::TextEncoder, dtype, device)?;
        Self::new(vb, config).map_err(|e| match e {
            ClipError::Candle(source) => ClipError::Weights {
                path: model
                    .component_dir(Component::TextEncoder)
                    .display()
                    .to_string(),
                source,
            },
            other => other,
        })
    }

    pub fn config(&self) -> &ClipTextConfig {
        &self.config
    }

    /// Number of positions, i.e. the padded prompt length (77 for SD).
    pub fn max_positions(&self) -> usize {
        self.config.max_position_embeddings
    }

    pub fn dtype(&self) -> DType {
        self.position_embedding.dtype()
    }

    pub fn device(&self) -> &Device {
        self.position_embedding.device()
    }

    /// The input embedding of each id (token-embedding lookup, no position): [B, S, D]. This is
    /// `text_encoder.get_input_embeddings()(ids)`.
    pub fn token_embeddings(&self, input_ids: &Tensor) -> candle_core::Result<Tensor> {
        self.token_embedding.forward(input_ids)
    }

    /// `last_hidden_state` for ids [B, S] (u32), S ≤ max positions: [B, S, D].
    pub fn forward(&self, input_ids: &Tensor) -> candle_core::Result<Tensor> {
        self.forward_skip(input_ids, 0)
    }

    /// Like [`Self::forward`] but stops `clip_skip` layers early (then applies the final LayerNorm), as
    /// diffusers' `clip_skip` does.
    pub fn forward_skip(
        &self,
        input_ids: &Tensor,
        clip_skip: usize,
    ) -> candle_core::Result<Tensor> {
        self.forward_skip_on(input_ids, clip_skip, &device::Device::Cpu)
    }

    /// [`Self::forward_skip`] with the encoder layers on `device`: the
    /// embedding lookup runs on the CPU, the hidden states are read back at the end.
    pub fn forward_skip_on(
        &self,
        input_ids: &Tensor,
        clip_skip: usize,
        device: &device::Device,
    ) -> candle_core::Result<Tensor> {
        let (_, s) = input_ids.dims2()?;
        if s > self.config.max_position_embeddings {
            candle_core::bail!(
                "sequence length {s} exceeds the text encoder's {} positions",
                self.config.max_position_embeddings
            );
        }
        let positions = self.position_embedding.narrow(0, 0, s)?;
        let x = self
            .token_embedding
            .forward(input_ids)?
            .broadcast_add(&positions)?;
        let mask = causal_mask(s, x.dtype(), x.device())?;
        let mut x = device.tensor(&x)?;
        let used = self.layers.len().saturating_sub(clip_skip);
        for layer in &self.layers[..used] {
            x = layer.forward_device(&x, Some(&mask))?;
        }
        self.final_layer_norm.forward_device(&x)?.to_cpu()
    }

    /// The pooled output: the final hidden state at each sequence's first end token (transformers' rule;
    /// configs with the legacy `eos_token_id` 2 use the position of the largest id instead).
    pub fn pooled_output(
        &self,
        last_hidden_state: &Tensor,
        input_ids: &Tensor,
    ) -> candle_core::Result<Tensor> {
        let ids = input_ids.to_dtype(DType::U32)?.to_vec2::<u32>()?;
        let rows = ids
            .iter()
            .enumerate()
            .map(|(b, row)| {
                let pos = if self.config.eos_token_id == 2 {
                    row.iter()
                        .enumerate()
                        .max_by_key(|(i, &v)| (v, std::cmp::Reverse(*i)))
                        .map_or(0, |(i, _)| i)
                } else {
                    row.iter()
                        .position(|&v| v == self.config.eos_token_id)
                        .unwrap_or(0)
                };
                last_hidden_state.get(b)?.get(pos)
            })
            .collect::<candle_core::Result<Vec<_>>>()?;
        Tensor::stack(&rows, 0)
    }

    /// Tokenises and encodes prompts in one batch: the context [B, S, D] and each prompt's encoding
    /// (which tells about truncation).
    pub fn encode_prompts(
        &self,
        tokenizer: &ClipTokenizer,
        prompts: &[&str],
    ) -> candle_core::Result<(Tensor, Vec<Encoding>)> {
        let encodings: Vec<Encoding> = prompts.iter().map(|p| tokenizer.encode(p)).collect();
        let ids = ids_tensor(&encodings, self.device())?;
        Ok((self.forward(&ids)?, encodings))
    }
}

/// Stacks encodings' ids into a [B, S] u32 tensor.
pub fn ids_tensor(encodings: &[Encoding], device: &Device) -> candle_core::Result<Tensor> {
    let len = encodings.first().map_or(0, |e| e.ids.len());
    if encodings.iter().any(|e| e.ids.len() != len) {
        candle_core::bail!("encodings of different lengths cannot form one batch");
    }
    let flat: Vec<u32> = encodings
        .iter()
        .flat_map(|e| e.ids.iter().copied())
        .collect();
    Tensor::from_vec(flat, (encodings.len(), len), device)
}

/// Additive causal mask [S, S]: 0 on and below the diagonal, −∞ above.
fn causal_mask(s: usize, dtype: DType, device: &Device) -> candle_core::Result<Tensor> {
    let data: Vec<f32> = (0..s)
        .flat_map(|i| (0..s).map(move |j| if j > i { f32::NEG_INFINITY } else { 0.0 }))
        .collect();
    Tensor::from_vec(data, (s, s), device)?.to_dtype(dtype)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A random tiny model and the variables it was built from.
    fn random_model_and_vars(act: ClipActivation) -> (ClipTextModel, candle_nn::VarMap) {
        let cfg = ClipTextConfig {
            vocab_size: 10,
            hidden_size: 8,
            intermediate_size: 16,
            num_hidden_layers: 2,
            num_attention_heads: 2,
            max_position_embeddings: 6,
            hidden_act: act,
            layer_norm_eps: 1e-5,
            eos_token_id: 9,
            projection_dim: None,
        };
        let vm = candle_nn::VarMap::new();
        let vb = VarBuilder::from_varmap(&vm, DType::F32, &Device::Cpu);
        (ClipTextModel::new(vb, cfg).unwrap(), vm)
    }

    fn random_model(act: ClipActivation) -> ClipTextModel {
        random_model_and_vars(act).0
    }

    #[test]
    fn causal_mask_hides_later_positions() {
        // Changing a later token must not change earlier hidden states.
        let m = random_model(ClipActivation::QuickGelu);
        let a = Tensor::new(&[[8u32, 1, 2, 3, 9, 9]], &Device::Cpu).unwrap();
        let b = Tensor::new(&[[8u32, 1, 2, 5, 9, 9]], &Device::Cpu).unwrap();
        let ha = m.forward(&a).unwrap();
        let hb = m.forward(&b).unwrap();
        let early = testkit::diff::tensor_max_abs_diff(
            &ha.narrow(1, 0, 3).unwrap(),
            &hb.narrow(1, 0, 3).unwrap(),
        );
        assert_eq!(early, 0.0);
        let late = testkit::diff::tensor_max_abs_diff(
            &ha.narrow(1, 3, 1).unwrap(),
            &hb.narrow(1, 3, 1).unwrap(),
        );
        assert!(late > 0.0);
    }

    #[test]
    fn pooled_output_takes_first_end_token() {
        let m = random_model(ClipActivation::Gelu);
        let ids = Tensor::new(&[[8u32, 1, 9, 9, 9, 9]], &Device::Cpu).unwrap();
        let h = m.forward(&ids).unwrap();
        let pooled = m.pooled_output(&h, &ids).unwrap();
        let expected = h.get(0).unwrap().get(2).unwrap();
        let diff = testkit::diff::tensor_max_abs_diff(&pooled.get(0).unwrap(), &expected);
        assert_eq!(diff, 0.0);
    }

    #[test]
    fn every_parameter_gets_a_gradient() {
        let dev = Device::Cpu;
        let (m, vm) = random_model_and_vars(ClipActivation::QuickGelu);
        let ids = Tensor::new(&[[8u32, 1, 2, 3, 9, 9], [8, 4, 9, 9, 9, 9]], &dev).unwrap();
        let out = m.forward(&ids).unwrap();
        let weighting = Tensor::randn(0f32, 1.0, out.dims(), &dev).unwrap();
        let grads = (out * weighting)
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        for (name, var) in vm.data().lock().unwrap().iter() {
            let g = grads.get(var.as_tensor());
            let norm = g.map_or(0.0, |g| {
                g.abs()
                    .unwrap()
                    .sum_all()
                    .unwrap()
                    .to_scalar::<f32>()
                    .unwrap()
            });
            // Token 0 and later positions may legitimately be unused; everything else must learn.
            assert!(norm > 0.0 && norm.is_finite(), "{name}: gradient {norm}");
        }
    }

    #[test]
    fn too_long_input_is_an_error() {
        let m = random_model(ClipActivation::QuickGelu);
        let ids = Tensor::zeros((1, 7), DType::U32, &Device::Cpu).unwrap();
        assert!(m.forward(&ids).is_err());
    }
}
