//! diffusers `UNet2DConditionModel` for SD 1.x topologies (including LCM's time condition and
//! InstructPix2Pix's 8 input channels), with an [`AttentionHook`] on every attention call.
//!
//! Weights load unchanged by diffusers key names; every architecture number comes from `unet/config.json`.

mod attention;
mod blocks;
mod config;
mod cost;
mod embeddings;
mod memory;
mod transformer;

use std::path::{Path, PathBuf};

use candle_core::{DType, Tensor};
use candle_nn::VarBuilder;

pub use attention::{edit_maps, AttentionHook, AttnCall, AttnKind, MapEdit, Qkv};
use blocks::{BlockAttention, DownBlock, MidBlock, ResnetShared, UpBlock};
use config::ResolvedBlocks;
pub use config::{BlockKind, PerBlock, UNetConfig};
use embeddings::{timestep_embedding, TimestepEmbedding};
pub use memory::ActivationEstimate;

use crate::device;
use crate::layers::{conv2d, Conv2d, GroupNorm, TimeEmbeddingNorm};

/// Errors from building a UNet.
#[derive(Debug, thiserror::Error)]
pub enum UNetError {
    #[error("{path}: cannot read UNet config: {source}")]
    ReadConfig {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}: invalid UNet config: {source}")]
    ParseConfig {
        path: PathBuf,
        source: serde_json::Error,
    },
    #[error("unsupported UNet config: {}", .0.join("; "))]
    Unsupported(Vec<String>),
    #[error("UNet weights: {0}")]
    Weights(#[from] candle_core::Error),
}

/// The denoising UNet. See [`UNet2DConditionModel::forward`].
#[derive(Debug, Clone)]
pub struct UNet2DConditionModel {
    config: UNetConfig,
    conv_in: Conv2d,
    time_embedding: TimestepEmbedding,
    down_blocks: Vec<DownBlock>,
    mid_block: MidBlock,
    up_blocks: Vec<UpBlock>,
    conv_norm_out: GroupNorm,
    conv_out: Conv2d,
}

impl UNet2DConditionModel {
    /// Builds the model from its config and a `VarBuilder` rooted at the UNet's weights (keys such as
    /// `conv_in.weight`, `down_blocks.0.attentions.0...`).
    pub fn load(config: &UNetConfig, vb: VarBuilder) -> Result<Self, UNetError> {
        let r = config.resolve().map_err(UNetError::Unsupported)?;
        Ok(Self::build(config, &r, vb)?)
    }

    /// Reads `config.json` and memory-maps the safetensors weight files (any float dtype; computed in f32).
    pub fn from_files(config_path: &Path, weights: &[PathBuf]) -> Result<Self, UNetError> {
        let text =
            std::fs::read_to_string(config_path).map_err(|source| UNetError::ReadConfig {
                path: config_path.to_path_buf(),
                source,
            })?;
        let config = UNetConfig::from_json(&text).map_err(|source| UNetError::ParseConfig {
            path: config_path.to_path_buf(),
            source,
        })?;
        let vb = crate::weights::mmap_var_builder(weights, DType::F32, &candle_core::Device::Cpu)?;
        Self::load(&config, vb)
    }

    fn build(cfg: &UNetConfig, r: &ResolvedBlocks, vb: VarBuilder) -> candle_core::Result<Self> {
        let ch = &cfg.block_out_channels;
        let n = ch.len();
        let shared = ResnetShared {
            temb_channels: r.time_embed_dim,
            groups: r.groups,
            eps: cfg.norm_eps,
            time_embedding_norm: if r.scale_shift {
                TimeEmbeddingNorm::ScaleShift
            } else {
                TimeEmbeddingNorm::Default
            },
        };
        let attention = |i: usize, kind: BlockKind| -> Option<BlockAttention> {
            (kind == BlockKind::CrossAttn).then_some(BlockAttention {
                heads: r.heads[i],
                transformer_layers: r.transformer_layers[i],
                context_dim: r.cross_attention_dim[i],
                linear_projection: cfg.use_linear_projection,
                only_cross_attention: r.only_cross_attention[i],
            })
        };
        let conv_in = conv2d(
            cfg.in_channels,
            ch[0],
            cfg.conv_in_kernel,
            1,
            cfg.conv_in_kernel / 2,
            vb.pp("conv_in"),
        )?;
        let time_embedding = TimestepEmbedding::load(
            ch[0],
            r.time_embed_dim,
            cfg.time_cond_proj_dim,
            vb.pp("time_embedding"),
        )?;

        let mut down_blocks = Vec::with_capacity(n);
        let mut prev = ch[0];
        for (i, &out) in ch.iter().enumerate() {
            let is_final = i + 1 == n;
            down_blocks.push(DownBlock::load(
                prev,
                out,
                r.layers[i],
                &shared,
                cfg.resnet_out_scale_factor,
                attention(i, r.down[i]),
                (!is_final).then_some(cfg.downsample_padding),
                vb.pp(format!("down_blocks.{i}")),
            )?);
            prev = out;
        }

        let mid_attention = BlockAttention {
            heads: r.heads[n - 1],
            transformer_layers: r.transformer_layers[n - 1],
            context_dim: r.cross_attention_dim[n - 1],
            linear_projection: cfg.use_linear_projection,
            only_cross_attention: false,
        };
        let mid_block = MidBlock::load(
            ch[n - 1],
            &shared,
            cfg.mid_block_scale_factor,
            mid_attention,
            vb.pp("mid_block"),
        )?;

        let mut up_blocks = Vec::with_capacity(n);
        let mut prev_out = ch[n - 1];
        for i in 0..n {
            let block = n - 1 - i; // the down block this up block mirrors
            let out = ch[block];
            let input = ch[block.saturating_sub(1)];
            let layers = r.layers[block] + 1;
            let skips: Vec<usize> = (0..layers)
                .map(|j| if j + 1 == layers { input } else { out })
                .collect();
            up_blocks.push(UpBlock::load(
                prev_out,
                out,
                &skips,
                &shared,
                cfg.resnet_out_scale_factor,
                attention(block, r.up[i]),
                i + 1 != n,
                vb.pp(format!("up_blocks.{i}")),
            )?);
            prev_out = out;
        }

        Ok(Self {
            config: cfg.clone(),
            conv_in,
            time_embedding,
            down_blocks,
            mid_block,
            up_blocks,
            conv_norm_out: GroupNorm::load(r.groups, ch[0], cfg.norm_eps, vb.pp("conv_norm_out"))?,
            conv_out: conv2d(
                ch[0],
                cfg.out_channels,
                cfg.conv_out_kernel,
                1,
                cfg.conv_out_kernel / 2,
                vb.pp("conv_out"),
            )?,
        })
    }

    pub fn config(&self) -> &UNetConfig {
        &self.config
    }

    /// Whether the model has LCM's `cond_proj`, i.e. accepts a `timestep_cond` (guidance-scale embedding of
    /// width `time_cond_proj_dim`). Passing none is allowed, as in diffusers (InfEdit does so).
    pub fn expects_timestep_cond(&self) -> bool {
        self.time_embedding.has_condition()
    }

    /// Predicts the noise (or whatever the checkpoint was trained on) for `sample` [batch, in_channels, h, w].
    ///
    /// - `timesteps`: a scalar, `[1]` or `[batch]` (one timestep per sample), any float or integer dtype;
    /// - `encoder_hidden_states`: [batch, tokens, cross_attention_dim];
    /// - `timestep_cond`: [batch, time_cond_proj_dim] for LCM checkpoints, or `None` (then `cond_proj` is
    ///   skipped, as diffusers does; ignored for models without `cond_proj`);
    /// - `hook`: sees every attention call (see [`AttentionHook`]); `None` runs the plain fast path.
    ///
    /// Differentiable when the input or the weights are `Var`s (composite ops are then used throughout).
    pub fn forward(
        &self,
        sample: &Tensor,
        timesteps: &Tensor,
        encoder_hidden_states: &Tensor,
        timestep_cond: Option<&Tensor>,
        hook: Option<&mut (dyn AttentionHook + '_)>,
    ) -> candle_core::Result<Tensor> {
        self.forward_on(
            sample,
            timesteps,
            encoder_hidden_states,
            timestep_cond,
            hook,
            &device::Device::Cpu,
        )
    }

    /// [`Self::forward`] with the network on `device`: the timestep
    /// embedding is computed on the CPU, the blocks run on the device, the prediction is read back.
    pub fn forward_on(
        &self,
        sample: &Tensor,
        timesteps: &Tensor,
        encoder_hidden_states: &Tensor,
        timestep_cond: Option<&Tensor>,
        hook: Option<&mut (dyn AttentionHook + '_)>,
        device: &device::Device,
    ) -> candle_core::Result<Tensor> {
        let out = self.run(
            sample,
            timesteps,
            encoder_hidden_states,
            timestep_cond,
            hook,
            device,
            false,
        )?;
        Ok(out.expect("a pass that may not stop runs to its end"))
    }

    /// [`Self::forward_on`] for a pass whose hook only observes: it ends after the first block at whose end
    /// the hook says it has seen all it needs ([`AttentionHook::finished`]), and then returns `None`
    /// instead of a prediction.
    pub fn forward_observed(
        &self,
        sample: &Tensor,
        timesteps: &Tensor,
        encoder_hidden_states: &Tensor,
        timestep_cond: Option<&Tensor>,
        hook: &mut (dyn AttentionHook + '_),
        device: &device::Device,
    ) -> candle_core::Result<Option<Tensor>> {
        self.run(
            sample,
            timesteps,
            encoder_hidden_states,
            timestep_cond,
            Some(hook),
            device,
            true,
        )
    }

    #[allow(clippy::too_many_arguments)]
    fn run(
        &self,
        sample: &Tensor,
        timesteps: &Tensor,
        encoder_hidden_states: &Tensor,
        timestep_cond: Option<&Tensor>,
        mut hook: Option<&mut (dyn AttentionHook + '_)>,
        device: &device::Device,
        may_stop: bool,
    ) -> candle_core::Result<Option<Tensor>> {
        let finished = |hook: &Option<&mut (dyn AttentionHook + '_)>| {
            may_stop && hook.as_ref().is_some_and(|h| h.finished())
        };
        let (batch, _, _, _) = sample.dims4()?;
        let timesteps = match timesteps.dims() {
            [] => timesteps.reshape(1)?.repeat(batch)?,
            [1] if batch != 1 => timesteps.repeat(batch)?,
            _ => timesteps.clone(),
        };
        if timesteps.dims() != [batch] {
            candle_core::bail!(
                "unet: {} timesteps for a batch of {batch}",
                timesteps.elem_count()
            );
        }
        // Without `timestep_cond` an LCM checkpoint runs without its guidance embedding, as diffusers does
        // when none is passed; InfEdit relies on this (it does classifier-free guidance explicitly).
        let ch0 = self.config.block_out_channels[0];
        let t_emb = timestep_embedding(
            &timesteps,
            ch0,
            self.config.flip_sin_to_cos,
            self.config.freq_shift,
        )?
        .to_device(sample.device())?
        .to_dtype(sample.dtype())?;
        let emb = self.time_embedding.forward(&t_emb, timestep_cond)?;

        let sample = if self.config.center_input_sample {
            sample.affine(2.0, -1.0)?
        } else {
            sample.clone()
        };
        let sample = device.tensor(&sample)?;
        let emb = device.tensor(&emb)?;
        let encoder_hidden_states = &device.tensor(encoder_hidden_states)?;
        let mut h = self.conv_in.forward_device(&sample)?;
        let mut skips = vec![h.clone()];
        for block in &self.down_blocks {
            let (out, produced) =
                block.forward(&h, &emb, encoder_hidden_states, hook.as_deref_mut())?;
            h = out;
            skips.extend(produced);
            if finished(&hook) {
                return Ok(None);
            }
        }
        h = self
            .mid_block
            .forward(&h, &emb, encoder_hidden_states, hook.as_deref_mut())?;
        for block in &self.up_blocks {
            if finished(&hook) {
                return Ok(None);
            }
            let take = block.layers();
            if skips.len() < take {
                candle_core::bail!(
                    "unet: skip connections exhausted (config inconsistent with weights?)"
                );
            }
            let mine = skips.split_off(skips.len() - take);
            // The upsampler must reproduce the size of the next skip (matters for odd latent sizes).
            let size = match skips.last() {
                Some(next) => {
                    let (_, _, sh, sw) = next.dims4()?;
                    Some((sh, sw))
                }
                None => None,
            };
            h = block.forward(
                &h,
                &mine,
                &emb,
                encoder_hidden_states,
                size,
                hook.as_deref_mut(),
            )?;
        }
        let h = self.conv_norm_out.forward_device(&h, true)?;
        Ok(Some(self.conv_out.forward_device(&h)?.to_cpu()?))
    }
}
