//! Multi-head attention of the UNet transformer blocks and the attention hook interface.
//!
//! The hook is the one place where editing logic touches the UNet: every attention call reports its layer,
//! whether it is self- or cross-attention, the spatial size of its queries and the batch/head counts, and
//! the hook may replace Q/K/V before the softmax and read or replace the probabilities after it.

use candle_core::Result;
use candle_nn::{Linear, VarBuilder};

use crate::kernels::DeviceTensor;
use crate::layers::linear;

/// Self-attention (keys from the image tokens) or cross-attention (keys from the text embedding).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AttnKind {
    SelfAttn,
    CrossAttn,
}

/// What one attention call tells its hook.
#[derive(Debug, Clone, Copy)]
pub struct AttnCall<'a> {
    /// diffusers module path, e.g. `"down_blocks.1.attentions.0.transformer_blocks.0.attn2"`.
    pub layer: &'a str,
    pub kind: AttnKind,
    /// Spatial size of the queries: `height * width` query tokens, row-major.
    pub height: usize,
    pub width: usize,
    /// Batch size of the UNet call (the caller knows its layout, e.g. InfEdit's `[S_u,T_u,M_u,S_c,T_c,M_c]`).
    pub batch: usize,
    pub heads: usize,
}

/// Observes and rewrites attention inside the UNet. All methods have pass-through defaults.
///
/// The tensors live where the UNet runs ([`DeviceTensor`]: a candle tensor on the CPU, a buffer on the
/// GPU), so a hook that only rearranges or mixes them (InfEdit's controller) costs no transfers; a hook
/// that must read values on the host calls [`DeviceTensor::to_cpu`] itself, for just what it reads.
pub trait AttentionHook {
    /// May replace Q, K, V (each [batch, heads, tokens, head_dim]) before the scores are computed.
    fn qkv(
        &mut self,
        call: &AttnCall,
        q: DeviceTensor,
        k: DeviceTensor,
        v: DeviceTensor,
    ) -> Result<(DeviceTensor, DeviceTensor, DeviceTensor)> {
        let _ = call;
        Ok((q, k, v))
    }

    /// Whether [`AttentionHook::probs`] must see this call's probabilities. When false the memory-bounded
    /// fused path runs (recommended for 64×64 self-attention, whose full maps take gigabytes).
    fn wants_probs(&self, call: &AttnCall) -> bool {
        let _ = call;
        true
    }

    /// May read/replace the probabilities [batch, heads, q_len, k_len] after the softmax.
    fn probs(&mut self, call: &AttnCall, probs: DeviceTensor) -> Result<DeviceTensor> {
        let _ = call;
        Ok(probs)
    }
}

/// diffusers `Attention` inside `BasicTransformerBlock` (keys `to_q`, `to_k`, `to_v` without bias,
/// `to_out.0` with bias).
#[derive(Debug, Clone)]
pub struct Attention {
    to_q: Linear,
    to_k: Linear,
    to_v: Linear,
    to_out: Linear,
    heads: usize,
    head_dim: usize,
    kind: AttnKind,
    name: String,
}

impl Attention {
    /// `context_dim` is the cross-attention width (`None` for self-attention).
    pub fn load(
        query_dim: usize,
        context_dim: Option<usize>,
        heads: usize,
        head_dim: usize,
        vb: VarBuilder,
    ) -> Result<Self> {
        let inner = heads * head_dim;
        let kv_dim = context_dim.unwrap_or(query_dim);
        Ok(Self {
            to_q: linear(query_dim, inner, false, vb.pp("to_q"))?,
            to_k: linear(kv_dim, inner, false, vb.pp("to_k"))?,
            to_v: linear(kv_dim, inner, false, vb.pp("to_v"))?,
            to_out: linear(inner, query_dim, true, vb.pp("to_out.0"))?,
            heads,
            head_dim,
            kind: if context_dim.is_some() {
                AttnKind::CrossAttn
            } else {
                AttnKind::SelfAttn
            },
            name: vb.prefix(),
        })
    }

    /// `x` [batch, h·w, query_dim]; `context` [batch, tokens, context_dim] for cross-attention, on one
    /// device. Without a hook, or when the hook does not read this call's probabilities, the flash kernel
    /// runs (no probability matrix); the hook sees the tensors on the device they are on.
    pub fn forward_device(
        &self,
        x: &DeviceTensor,
        context: Option<&DeviceTensor>,
        (height, width): (usize, usize),
        hook: Option<&mut (dyn AttentionHook + '_)>,
    ) -> Result<DeviceTensor> {
        let &[batch, tokens, _] = x.dims() else {
            candle_core::bail!(
                "{}: expected [batch, tokens, dim], got {:?}",
                self.name,
                x.dims()
            );
        };
        let kv_source = match self.kind {
            AttnKind::CrossAttn => context.ok_or_else(|| {
                candle_core::Error::Msg(format!(
                    "{}: cross-attention called without encoder hidden states",
                    self.name
                ))
            })?,
            AttnKind::SelfAttn => x,
        };
        let split = |t: DeviceTensor| -> Result<DeviceTensor> {
            let n = t.dims()[1];
            t.reshape(&[batch, n, self.heads, self.head_dim])?
                .permute_contiguous(&[0, 2, 1, 3])
        };
        let q = split(x.linear(&self.to_q)?)?;
        let k = split(kv_source.linear(&self.to_k)?)?;
        let v = split(kv_source.linear(&self.to_v)?)?;
        let scale = 1.0 / (self.head_dim as f64).sqrt();
        let out = match hook {
            None => DeviceTensor::attention(&q, &k, &v, scale)?,
            Some(hook) => {
                let call = AttnCall {
                    layer: &self.name,
                    kind: self.kind,
                    height,
                    width,
                    batch,
                    heads: self.heads,
                };
                let (q, k, v) = hook.qkv(&call, q, k, v)?;
                if hook.wants_probs(&call) {
                    let scores = q.matmul_t(&k)?.mul_scalar(scale)?;
                    let probs = hook.probs(&call, scores.softmax_last_dim()?)?;
                    probs.matmul(&v)?
                } else {
                    DeviceTensor::attention(&q, &k, &v, scale)?
                }
            }
        };
        out.permute_contiguous(&[0, 2, 1, 3])?
            .reshape(&[batch, tokens, self.heads * self.head_dim])?
            .linear(&self.to_out)
    }
}
