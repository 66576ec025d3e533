//! diffusers `Transformer2DModel` (continuous input) and `BasicTransformerBlock`.

use candle_core::Result;
use candle_nn::VarBuilder;

use super::attention::{Attention, AttentionHook};
use crate::kernels::{Addend, DeviceTensor};
use crate::layers::{conv2d, linear, Conv2d, GroupNorm, LayerNorm, Linear};

/// diffusers `GEGLU` + output linear (`ff.net.0.proj`, `ff.net.2`): `W2 (h ⊙ gelu(g))` with `[h, g] = W1 x`.
#[derive(Debug, Clone)]
pub struct FeedForward {
    proj: Linear,
    out: Linear,
}

impl FeedForward {
    pub fn load(dim: usize, mult: usize, vb: VarBuilder) -> Result<Self> {
        let inner = dim * mult;
        Ok(Self {
            proj: linear(dim, inner * 2, true, vb.pp("net.0.proj"))?,
            out: linear(inner, dim, true, vb.pp("net.2"))?,
        })
    }

    /// The feed-forward of `x`, plus `residual` (added with the output layer's bias).
    pub fn forward_device(
        &self,
        x: &DeviceTensor,
        residual: &DeviceTensor,
    ) -> Result<DeviceTensor> {
        // diffusers uses the exact (erf) GELU here.
        x.linear(&self.proj)?
            .geglu()?
            .linear_add(&self.out, residual)
    }
}

/// Self-attention, cross-attention and GEGLU feed-forward, each pre-normed with a residual.
#[derive(Debug, Clone)]
pub struct BasicTransformerBlock {
    norm1: LayerNorm,
    attn1: Attention,
    norm2: LayerNorm,
    attn2: Attention,
    norm3: LayerNorm,
    ff: FeedForward,
    only_cross_attention: bool,
}

impl BasicTransformerBlock {
    pub fn load(
        dim: usize,
        heads: usize,
        head_dim: usize,
        context_dim: usize,
        only_cross_attention: bool,
        vb: VarBuilder,
    ) -> Result<Self> {
        let attn1_context = only_cross_attention.then_some(context_dim);
        Ok(Self {
            norm1: LayerNorm::load(dim, 1e-5, vb.pp("norm1"))?,
            attn1: Attention::load(dim, attn1_context, heads, head_dim, vb.pp("attn1"))?,
            norm2: LayerNorm::load(dim, 1e-5, vb.pp("norm2"))?,
            attn2: Attention::load(dim, Some(context_dim), heads, head_dim, vb.pp("attn2"))?,
            norm3: LayerNorm::load(dim, 1e-5, vb.pp("norm3"))?,
            ff: FeedForward::load(dim, 4, vb.pp("ff"))?,
            only_cross_attention,
        })
    }

    pub fn forward(
        &self,
        x: &DeviceTensor,
        context: &DeviceTensor,
        size: (usize, usize),
        mut hook: Option<&mut (dyn AttentionHook + '_)>,
    ) -> Result<DeviceTensor> {
        // Each residual is added in its output projection's bias pass.
        let attn1_context = self.only_cross_attention.then_some(context);
        let x = self.attn1.forward_device(
            &self.norm1.forward_device(x)?,
            attn1_context,
            size,
            hook.as_deref_mut(),
            x,
        )?;
        let x = self.attn2.forward_device(
            &self.norm2.forward_device(&x)?,
            Some(context),
            size,
            hook,
            &x,
        )?;
        self.ff.forward_device(&self.norm3.forward_device(&x)?, &x)
    }
}

#[derive(Debug, Clone)]
enum Projection {
    Conv(Conv2d),
    Linear(Linear),
}

/// diffusers `Transformer2DModel` for image latents: group norm, `proj_in` (1x1 conv or linear per
/// `use_linear_projection`), transformer blocks, `proj_out`, residual.
#[derive(Debug, Clone)]
pub struct Transformer2D {
    norm: GroupNorm,
    proj_in: Projection,
    blocks: Vec<BasicTransformerBlock>,
    proj_out: Projection,
}

/// Shape and options of one [`Transformer2D`].
#[derive(Debug, Clone, Copy)]
pub struct Transformer2DConfig {
    pub channels: usize,
    pub heads: usize,
    pub layers: usize,
    pub context_dim: usize,
    pub groups: usize,
    pub linear_projection: bool,
    pub only_cross_attention: bool,
}

impl Transformer2D {
    pub fn load(cfg: &Transformer2DConfig, vb: VarBuilder) -> Result<Self> {
        let c = cfg.channels;
        let head_dim = c / cfg.heads;
        let projection = |vb: VarBuilder| -> Result<Projection> {
            Ok(if cfg.linear_projection {
                Projection::Linear(linear(c, c, true, vb)?)
            } else {
                Projection::Conv(conv2d(c, c, 1, 1, 0, vb)?)
            })
        };
        let blocks = (0..cfg.layers)
            .map(|i| {
                BasicTransformerBlock::load(
                    c,
                    cfg.heads,
                    head_dim,
                    cfg.context_dim,
                    cfg.only_cross_attention,
                    vb.pp(format!("transformer_blocks.{i}")),
                )
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Self {
            norm: GroupNorm::load(cfg.groups, c, 1e-6, vb.pp("norm"))?,
            proj_in: projection(vb.pp("proj_in"))?,
            blocks,
            proj_out: projection(vb.pp("proj_out"))?,
        })
    }

    /// `x` [batch, channels, h, w]; `context` [batch, tokens, context_dim].
    pub fn forward(
        &self,
        x: &DeviceTensor,
        context: &DeviceTensor,
        mut hook: Option<&mut (dyn AttentionHook + '_)>,
    ) -> Result<DeviceTensor> {
        let (b, c, h, w) = x.dims4()?;
        let normed = self.norm.forward_device(x, false)?;
        let to_tokens = |t: &DeviceTensor| -> Result<DeviceTensor> {
            t.reshape(&[b, c, h * w])?.permute_contiguous(&[0, 2, 1])
        };
        let mut tokens = match &self.proj_in {
            Projection::Conv(conv) => to_tokens(&conv.forward_device(&normed)?)?,
            Projection::Linear(lin) => to_tokens(&normed)?.linear(lin)?,
        };
        for block in &self.blocks {
            tokens = block.forward(&tokens, context, (h, w), hook.as_deref_mut())?;
        }
        let to_image = |t: &DeviceTensor| -> Result<DeviceTensor> {
            t.permute_contiguous(&[0, 2, 1])?.reshape(&[b, c, h, w])
        };
        match &self.proj_out {
            // The residual joins the bias's pass.
            Projection::Conv(conv) => {
                conv.forward_device_add(&to_image(&tokens)?, Addend::Residual(x))
            }
            Projection::Linear(lin) => to_image(&tokens.linear(lin)?)?.add(x),
        }
    }
}
