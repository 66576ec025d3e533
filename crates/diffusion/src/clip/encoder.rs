//! The transformer encoder layer both CLIP towers use (transformers' `CLIPEncoderLayer`): pre-LayerNorm
//! multi-head self-attention and a two-layer MLP, each with a residual.
//!
//! Keys under the layer: `layer_norm1`, `self_attn.{q,k,v,out}_proj`, `layer_norm2`, `mlp.fc1`, `mlp.fc2`.

use candle_core::{Result, Tensor};
use candle_nn::VarBuilder;
use serde::Deserialize;

use crate::kernels::{DeviceTensor, Unary};
use crate::layers::{linear, LayerNorm, Linear};

/// `hidden_act` of a CLIP config.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ClipActivation {
    /// x·σ(1.702x), OpenAI CLIP's approximation (SD 1.x).
    QuickGelu,
    /// Exact erf GELU (SD 2.x / OpenCLIP).
    Gelu,
    /// tanh-approximated GELU.
    GeluNew,
    GeluPytorchTanh,
    Relu,
}

impl ClipActivation {
    fn apply(self, x: &DeviceTensor) -> Result<DeviceTensor> {
        match self {
            ClipActivation::QuickGelu => x.unary(Unary::QuickGelu),
            ClipActivation::Gelu => x.unary(Unary::GeluErf),
            ClipActivation::GeluNew | ClipActivation::GeluPytorchTanh => x.unary(Unary::GeluTanh),
            ClipActivation::Relu => x.relu(),
        }
    }
}

/// The sizes of one encoder layer (the fields both towers' configs share).
#[derive(Debug, Clone, Copy)]
pub(super) struct EncoderLayerConfig {
    pub hidden_size: usize,
    pub intermediate_size: usize,
    pub num_attention_heads: usize,
    pub layer_norm_eps: f64,
    pub hidden_act: ClipActivation,
}

#[derive(Debug, Clone)]
struct SelfAttention {
    q_proj: Linear,
    k_proj: Linear,
    v_proj: Linear,
    out_proj: Linear,
    heads: usize,
    head_dim: usize,
}

impl SelfAttention {
    fn load(vb: VarBuilder, c: &EncoderLayerConfig) -> Result<Self> {
        let d = c.hidden_size;
        Ok(Self {
            q_proj: linear(d, d, true, vb.pp("q_proj"))?,
            k_proj: linear(d, d, true, vb.pp("k_proj"))?,
            v_proj: linear(d, d, true, vb.pp("v_proj"))?,
            out_proj: linear(d, d, true, vb.pp("out_proj"))?,
            heads: c.num_attention_heads,
            head_dim: d / c.num_attention_heads,
        })
    }

    /// x [B, S, D] → `residual` + attention output; `mask` [S, S] is added to the scores (−∞ hides a
    /// position). The residual is added by the output projection's product (no pass of its own).
    fn forward(
        &self,
        x: &DeviceTensor,
        mask: Option<&Tensor>,
        residual: &DeviceTensor,
    ) -> Result<DeviceTensor> {
        let &[b, s, d] = x.dims() else {
            candle_core::bail!(
                "CLIP attention expects [batch, seq, dim], got {:?}",
                x.dims()
            );
        };
        let split = |t: DeviceTensor| -> Result<DeviceTensor> {
            t.reshape(&[b, s, self.heads, self.head_dim])?
                .permute_contiguous(&[0, 2, 1, 3])
        };
        let scale = (self.head_dim as f64).powf(-0.5);
        let q = split(x.linear(&self.q_proj)?.mul_scalar(scale)?)?;
        let k = split(x.linear(&self.k_proj)?)?;
        let v = split(x.linear(&self.v_proj)?)?;
        let scores = q.matmul_t(&k)?;
        let scores = match mask {
            Some(mask) => scores.broadcast_add_tensor(mask)?,
            None => scores,
        };
        // The kernel softmax has a backward pass, so the towers can be trained (the demo's text encoder is).
        let probs = scores.softmax_last_dim()?;
        let out = probs
            .matmul(&v)?
            .permute_contiguous(&[0, 2, 1, 3])?
            .reshape(&[b, s, d])?;
        out.linear_add(&self.out_proj, residual)
    }
}

/// One `CLIPEncoderLayer`.
#[derive(Debug, Clone)]
pub(super) struct EncoderLayer {
    layer_norm1: LayerNorm,
    self_attn: SelfAttention,
    layer_norm2: LayerNorm,
    fc1: Linear,
    fc2: Linear,
    act: ClipActivation,
}

impl EncoderLayer {
    pub fn load(vb: VarBuilder, c: &EncoderLayerConfig) -> Result<Self> {
        let eps = c.layer_norm_eps;
        Ok(Self {
            layer_norm1: LayerNorm::load(c.hidden_size, eps, vb.pp("layer_norm1"))?,
            self_attn: SelfAttention::load(vb.pp("self_attn"), c)?,
            layer_norm2: LayerNorm::load(c.hidden_size, eps, vb.pp("layer_norm2"))?,
            fc1: linear(
                c.hidden_size,
                c.intermediate_size,
                true,
                vb.pp("mlp").pp("fc1"),
            )?,
            fc2: linear(
                c.intermediate_size,
                c.hidden_size,
                true,
                vb.pp("mlp").pp("fc2"),
            )?,
            act: c.hidden_act,
        })
    }

    /// x [B, S, D] → [B, S, D]; `mask` as in self-attention.
    pub fn forward(&self, x: &Tensor, mask: Option<&Tensor>) -> Result<Tensor> {
        self.forward_device(&x.clone().into(), mask)?.to_cpu()
    }

    /// [`Self::forward`] on the input's device.
    pub fn forward_device(&self, x: &DeviceTensor, mask: Option<&Tensor>) -> Result<DeviceTensor> {
        let x = self
            .self_attn
            .forward(&self.layer_norm1.forward_device(x)?, mask, x)?;
        let h = self.layer_norm2.forward_device(&x)?.linear(&self.fc1)?;
        self.act.apply(&h)?.linear_add(&self.fc2, &x)
    }
}
