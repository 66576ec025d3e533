//! Network building blocks shared by the UNet, the VAE and CLIP, loaded by diffusers key names: linear
//! and conv loaders, layer/group norm modules, `ResnetBlock2D`, `Downsample2D`/`Upsample2D` and the VAE's
//! `SpatialSelfAttention`.
//!
//! The arithmetic lives in [`crate::kernels`], whose functions pick a fused inference kernel or a
//! differentiable one per call, so the same blocks serve inference and training.

use candle_core::{Module, Result, Tensor};
use candle_nn::VarBuilder;

use crate::kernels;
pub use crate::kernels::Linear;
use crate::kernels::{Addend, DeviceTensor, ProductWeight, Unary};

/// Loads a `nn.Linear` (`weight` [out, in], optional `bias` [out]) under `vb`; its weight is kept as
/// bf16 pairs only when the CPU's products run in bf16 ([`ProductWeight`]).
pub fn linear(in_dim: usize, out_dim: usize, bias: bool, vb: VarBuilder) -> Result<Linear> {
    let weight = linear_weight(in_dim, out_dim, &vb)?;
    let bias = if bias {
        // candle-nn's initialisation, for models trained from scratch (a VarMap).
        let bound = 1.0 / (in_dim as f64).sqrt();
        Some(vb.get_with_hints(
            out_dim,
            "bias",
            candle_nn::Init::Uniform {
                lo: -bound,
                up: bound,
            },
        )?)
    } else {
        None
    };
    Linear::new(weight, bias)
}

/// The f32 `weight` [out, in] of a `nn.Linear` under `vb` (for layers that stack several before
/// keeping them).
pub fn linear_weight(in_dim: usize, out_dim: usize, vb: &VarBuilder) -> Result<Tensor> {
    vb.get_with_hints(
        (out_dim, in_dim),
        "weight",
        candle_nn::init::DEFAULT_KAIMING_NORMAL,
    )
}

/// Loads a square `nn.Conv2d` with bias (`weight` [out, in, k, k], `bias` [out]) under `vb`.
pub fn conv2d(
    in_channels: usize,
    out_channels: usize,
    kernel: usize,
    stride: usize,
    padding: usize,
    vb: VarBuilder,
) -> Result<Conv2d> {
    Conv2d::load(in_channels, out_channels, kernel, stride, padding, true, vb)
}

/// A square-kernel `nn.Conv2d` (no dilation, no groups) with keys `weight` and optional `bias`.
#[derive(Debug, Clone)]
pub struct Conv2d {
    weight: ProductWeight,
    bias: Option<Tensor>,
    stride: usize,
    padding: usize,
}

impl Conv2d {
    /// `weight` [out, in, k, k] (kept as bf16 pairs only when the CPU's products run in bf16),
    /// `bias` [out].
    pub fn new(
        weight: Tensor,
        bias: Option<Tensor>,
        stride: usize,
        padding: usize,
    ) -> Result<Self> {
        Ok(Self {
            weight: ProductWeight::conv(weight)?,
            bias,
            stride,
            padding,
        })
    }

    /// Loads `weight` (and `bias` when `bias` is true) under `vb`.
    pub fn load(
        in_channels: usize,
        out_channels: usize,
        kernel: usize,
        stride: usize,
        padding: usize,
        bias: bool,
        vb: VarBuilder,
    ) -> Result<Self> {
        let weight = vb.get_with_hints(
            (out_channels, in_channels, kernel, kernel),
            "weight",
            candle_nn::init::DEFAULT_KAIMING_NORMAL,
        )?;
        let bias = if bias {
            let bound = 1.0 / ((in_channels * kernel * kernel) as f64).sqrt();
            Some(vb.get_with_hints(
                out_channels,
                "bias",
                candle_nn::Init::Uniform {
                    lo: -bound,
                    up: bound,
                },
            )?)
        } else {
            None
        };
        Self::new(weight, bias, stride, padding)
    }
}

impl Conv2d {
    /// The convolution on the input's device (the CPU branch is [`Module::forward`]'s call).
    pub fn forward_device(&self, x: &kernels::DeviceTensor) -> Result<kernels::DeviceTensor> {
        x.conv2d(&self.weight, self.bias.as_ref(), self.stride, self.padding)
    }

    /// [`Self::forward_device`] plus `addend`, added with the bias (one pass on the GPU).
    pub fn forward_device_add(
        &self,
        x: &kernels::DeviceTensor,
        addend: kernels::Addend<'_, kernels::DeviceTensor>,
    ) -> Result<kernels::DeviceTensor> {
        x.conv2d_add(
            &self.weight,
            self.bias.as_ref(),
            self.stride,
            self.padding,
            addend,
        )
    }
}

impl Conv2d {
    /// [`Self::forward_device_add`] followed by `act` (on the CPU under bf16 products a ReLU is applied
    /// as the sums are stored).
    pub fn forward_device_add_act(
        &self,
        x: &kernels::DeviceTensor,
        addend: kernels::Addend<'_, kernels::DeviceTensor>,
        act: kernels::Unary,
    ) -> Result<kernels::DeviceTensor> {
        x.conv2d_add_act(
            &self.weight,
            self.bias.as_ref(),
            self.stride,
            self.padding,
            addend,
            act,
        )
    }
}

impl Module for Conv2d {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        kernels::conv2d(
            x,
            &self.weight,
            self.bias.as_ref(),
            self.stride,
            self.padding,
        )
    }
}

/// `nn.LayerNorm` over the last dimension with weight and bias (keys `weight`, `bias`).
#[derive(Debug, Clone)]
pub struct LayerNorm {
    weight: Tensor,
    bias: Tensor,
    eps: f64,
}

impl LayerNorm {
    pub fn load(dim: usize, eps: f64, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            // The hints only matter when training from scratch (a VarMap): identity affine map.
            weight: vb.get_with_hints(dim, "weight", candle_nn::Init::Const(1.0))?,
            bias: vb.get_with_hints(dim, "bias", candle_nn::Init::Const(0.0))?,
            eps,
        })
    }

    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        kernels::layer_norm(x, &self.weight, &self.bias, self.eps)
    }

    /// [`Self::forward`] on the input's device.
    pub fn forward_device(&self, x: &kernels::DeviceTensor) -> Result<kernels::DeviceTensor> {
        x.layer_norm(&self.weight, &self.bias, self.eps)
    }
}

/// `nn.GroupNorm` with affine weight/bias (keys `weight`, `bias`) over [batch, channels, ...].
#[derive(Debug, Clone)]
pub struct GroupNorm {
    weight: Tensor,
    bias: Tensor,
    num_groups: usize,
    eps: f64,
}

impl GroupNorm {
    pub fn load(num_groups: usize, channels: usize, eps: f64, vb: VarBuilder) -> Result<Self> {
        if num_groups == 0 || !channels.is_multiple_of(num_groups) {
            candle_core::bail!(
                "group norm {}: {channels} channels are not divisible into {num_groups} groups",
                vb.prefix()
            );
        }
        Ok(Self {
            // The hints only matter when training from scratch (a VarMap): identity affine map.
            weight: vb.get_with_hints(channels, "weight", candle_nn::Init::Const(1.0))?,
            bias: vb.get_with_hints(channels, "bias", candle_nn::Init::Const(0.0))?,
            num_groups,
            eps,
        })
    }

    /// Group norm alone (CPU; networks call [`Self::forward_device`]).
    #[cfg(test)]
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        self.run(x, false)
    }

    /// Group norm followed by SiLU (the pairing used throughout ResNet blocks), fused on the fast path.
    #[cfg(test)]
    pub fn forward_silu(&self, x: &Tensor) -> Result<Tensor> {
        self.run(x, true)
    }

    /// Group norm (then SiLU when `with_silu`) on the input's device.
    pub fn forward_device(
        &self,
        x: &kernels::DeviceTensor,
        with_silu: bool,
    ) -> Result<kernels::DeviceTensor> {
        match x {
            kernels::DeviceTensor::Cpu(t) => Ok(self.run(t, with_silu)?.into()),
            kernels::DeviceTensor::Gpu(_) => x.group_norm(
                &self.weight,
                &self.bias,
                self.num_groups,
                self.eps,
                with_silu,
            ),
        }
    }

    fn run(&self, x: &Tensor, with_silu: bool) -> Result<Tensor> {
        if x.rank() < 3 {
            candle_core::bail!(
                "group norm expects [batch, channels, ...], got {:?}",
                x.dims()
            );
        }
        kernels::group_norm(
            x,
            &self.weight,
            &self.bias,
            self.num_groups,
            self.eps,
            with_silu,
        )
    }
}

/// Configuration of a [`ResnetBlock2D`] (diffusers `ResnetBlock2D` arguments that SD 1.x uses).
#[derive(Debug, Clone)]
pub struct ResnetConfig {
    pub in_channels: usize,
    pub out_channels: usize,
    /// Width of the time embedding; `None` for blocks without `time_emb_proj` (VAE).
    pub temb_channels: Option<usize>,
    pub groups: usize,
    /// Groups of `norm2`; defaults to `groups`.
    pub groups_out: Option<usize>,
    pub eps: f64,
    /// The sum `shortcut + residual` is divided by this (UNet mid block: `mid_block_scale_factor`).
    pub output_scale_factor: f64,
    /// `"default"` adds the projected embedding; `"scale_shift"` applies it as FiLM after `norm2`.
    pub time_embedding_norm: TimeEmbeddingNorm,
}

impl ResnetConfig {
    /// The common case: `groups` groups, eps, scale factor 1, additive time embedding.
    pub fn new(
        in_channels: usize,
        out_channels: usize,
        temb_channels: Option<usize>,
        groups: usize,
        eps: f64,
    ) -> Self {
        Self {
            in_channels,
            out_channels,
            temb_channels,
            groups,
            groups_out: None,
            eps,
            output_scale_factor: 1.0,
            time_embedding_norm: TimeEmbeddingNorm::Default,
        }
    }
}

/// How a ResNet block injects the time embedding (`resnet_time_scale_shift` in UNet configs).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TimeEmbeddingNorm {
    Default,
    ScaleShift,
}

/// diffusers `ResnetBlock2D`: keys `norm1`, `conv1`, `time_emb_proj`, `norm2`, `conv2`, `conv_shortcut`.
#[derive(Debug, Clone)]
pub struct ResnetBlock2D {
    norm1: GroupNorm,
    conv1: Conv2d,
    time_emb_proj: Option<Linear>,
    norm2: GroupNorm,
    conv2: Conv2d,
    conv_shortcut: Option<Conv2d>,
    output_scale_factor: f64,
    time_embedding_norm: TimeEmbeddingNorm,
}

impl ResnetBlock2D {
    pub fn load(cfg: &ResnetConfig, vb: VarBuilder) -> Result<Self> {
        let (cin, cout) = (cfg.in_channels, cfg.out_channels);
        let time_emb_proj = match cfg.temb_channels {
            Some(t) => {
                let width = match cfg.time_embedding_norm {
                    TimeEmbeddingNorm::Default => cout,
                    TimeEmbeddingNorm::ScaleShift => 2 * cout,
                };
                Some(linear(t, width, true, vb.pp("time_emb_proj"))?)
            }
            None => None,
        };
        // diffusers adds the 1x1 shortcut exactly when the channel count changes.
        let conv_shortcut = if cin != cout {
            Some(conv2d(cin, cout, 1, 1, 0, vb.pp("conv_shortcut"))?)
        } else {
            None
        };
        Ok(Self {
            norm1: GroupNorm::load(cfg.groups, cin, cfg.eps, vb.pp("norm1"))?,
            conv1: conv2d(cin, cout, 3, 1, 1, vb.pp("conv1"))?,
            time_emb_proj,
            norm2: GroupNorm::load(
                cfg.groups_out.unwrap_or(cfg.groups),
                cout,
                cfg.eps,
                vb.pp("norm2"),
            )?,
            conv2: conv2d(cout, cout, 3, 1, 1, vb.pp("conv2"))?,
            conv_shortcut,
            output_scale_factor: cfg.output_scale_factor,
            time_embedding_norm: cfg.time_embedding_norm,
        })
    }

    /// `x` [batch, in, h, w]; `temb` [batch, temb_channels] on the same device (ignored by blocks loaded
    /// without one).
    pub fn forward_device(
        &self,
        x: &DeviceTensor,
        temb: Option<&DeviceTensor>,
    ) -> Result<DeviceTensor> {
        let emb = match (&self.time_emb_proj, temb) {
            (Some(proj), Some(t)) => {
                let e = t.unary(Unary::Silu)?.linear(proj)?;
                if e.dims().len() != 2 {
                    candle_core::bail!("time embedding {:?} is not [batch, channels]", e.dims());
                }
                Some(e)
            }
            _ => None,
        };
        let normed = self.norm1.forward_device(x, true)?;
        let h = match (self.time_embedding_norm, emb) {
            (TimeEmbeddingNorm::ScaleShift, Some(emb)) => {
                let h = self.conv1.forward_device(&normed)?;
                let (b, c) = (emb.dims()[0], emb.dims()[1]);
                let emb = emb.reshape(&[b, c, 1, 1])?;
                let half = c / 2;
                let (scale, shift) = (emb.narrow(1, 0, half)?, emb.narrow(1, half, half)?);
                let normed = self.norm2.forward_device(&h, false)?;
                normed
                    .broadcast_mul(&scale.add_scalar(1.0)?)?
                    .broadcast_add(&shift)?
                    .unary(Unary::Silu)?
            }
            // The time embedding joins conv1's bias (one pass over conv1's output on the GPU).
            (_, Some(emb)) => {
                let h = self
                    .conv1
                    .forward_device_add(&normed, Addend::PerChannel(&emb))?;
                self.norm2.forward_device(&h, true)?
            }
            (_, None) => self
                .norm2
                .forward_device(&self.conv1.forward_device(&normed)?, true)?,
        };
        let shortcut = match &self.conv_shortcut {
            Some(conv) => conv.forward_device(x)?,
            None => x.clone(),
        };
        // The skip connection joins conv2's bias (`shortcut + conv2(h)` before: two terms commute exactly).
        let out = self
            .conv2
            .forward_device_add(&h, Addend::Residual(&shortcut))?;
        if self.output_scale_factor == 1.0 {
            Ok(out)
        } else {
            out.div_scalar(self.output_scale_factor)
        }
    }
}

/// diffusers `Downsample2D` with a convolution (key `conv`): 3x3, stride 2. With `padding == 0` the input is
/// padded by one zero row/column at the bottom/right first, as diffusers does.
#[derive(Debug, Clone)]
pub struct Downsample2D {
    conv: Conv2d,
    padding: usize,
}

impl Downsample2D {
    pub fn load(
        in_channels: usize,
        out_channels: usize,
        padding: usize,
        vb: VarBuilder,
    ) -> Result<Self> {
        Ok(Self {
            conv: conv2d(in_channels, out_channels, 3, 2, padding, vb.pp("conv"))?,
            padding,
        })
    }

    /// The downsampling on the input's device.
    pub fn forward_device(&self, x: &DeviceTensor) -> Result<DeviceTensor> {
        if self.padding == 0 {
            let x = x.pad_bottom_right_with_zeros()?;
            self.conv.forward_device(&x)
        } else {
            self.conv.forward_device(x)
        }
    }
}

/// diffusers `Upsample2D` with a convolution (key `conv`): nearest-neighbour resize then 3x3 conv.
#[derive(Debug, Clone)]
pub struct Upsample2D {
    conv: Conv2d,
}

impl Upsample2D {
    pub fn load(in_channels: usize, out_channels: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            conv: conv2d(in_channels, out_channels, 3, 1, 1, vb.pp("conv"))?,
        })
    }

    /// Doubles the spatial size, or resizes to `size` = (h, w) when given (the UNet passes the skip
    /// connection's size when the latent is not a multiple of the total downsampling factor).
    pub fn forward_device(
        &self,
        x: &DeviceTensor,
        size: Option<(usize, usize)>,
    ) -> Result<DeviceTensor> {
        let (_, _, h, w) = x.dims4()?;
        let (th, tw) = size.unwrap_or((2 * h, 2 * w));
        self.conv.forward_device(&x.upsample_nearest2d(th, tw)?)
    }
}

/// diffusers `Attention` as used by the VAE mid block: group norm over [B, C, H, W], single- or multi-head
/// self-attention over the H·W positions, output projection, residual added.
///
/// Keys: `group_norm`, `to_q`, `to_k`, `to_v`, `to_out.0` (older checkpoints: `query`, `key`, `value`,
/// `proj_attn`, which diffusers converts on load; accepted here too).
#[derive(Debug, Clone)]
pub struct SpatialSelfAttention {
    group_norm: GroupNorm,
    to_q: Linear,
    to_k: Linear,
    to_v: Linear,
    to_out: Linear,
    heads: usize,
    rescale_output_factor: f64,
}

impl SpatialSelfAttention {
    /// `head_dim` is diffusers' `attention_head_dim` (the VAE passes the channel count: one head).
    pub fn load(
        channels: usize,
        head_dim: usize,
        groups: usize,
        eps: f64,
        vb: VarBuilder,
    ) -> Result<Self> {
        if head_dim == 0 || !channels.is_multiple_of(head_dim) {
            candle_core::bail!(
                "attention {}: {channels} channels not divisible by head dim {head_dim}",
                vb.prefix()
            );
        }
        let legacy = !vb.contains_tensor("to_q.weight") && vb.contains_tensor("query.weight");
        let names = if legacy {
            ["query", "key", "value", "proj_attn"]
        } else {
            ["to_q", "to_k", "to_v", "to_out.0"]
        };
        Ok(Self {
            group_norm: GroupNorm::load(groups, channels, eps, vb.pp("group_norm"))?,
            to_q: linear(channels, channels, true, vb.pp(names[0]))?,
            to_k: linear(channels, channels, true, vb.pp(names[1]))?,
            to_v: linear(channels, channels, true, vb.pp(names[2]))?,
            to_out: linear(channels, channels, true, vb.pp(names[3]))?,
            heads: channels / head_dim,
            rescale_output_factor: 1.0,
        })
    }

    /// The attention block on the input's device.
    pub fn forward_device(&self, x: &DeviceTensor) -> Result<DeviceTensor> {
        let (b, c, h, w) = x.dims4()?;
        let normed = self.group_norm.forward_device(x, false)?;
        let tokens = normed
            .reshape(&[b, c, h * w])?
            .permute_contiguous(&[0, 2, 1])?;
        let head_dim = c / self.heads;
        let split = |t: DeviceTensor| -> Result<DeviceTensor> {
            t.reshape(&[b, h * w, self.heads, head_dim])?
                .permute_contiguous(&[0, 2, 1, 3])
        };
        let q = split(tokens.linear(&self.to_q)?)?;
        let k = split(tokens.linear(&self.to_k)?)?;
        let v = split(tokens.linear(&self.to_v)?)?;
        let attn = DeviceTensor::attention(&q, &k, &v, 1.0 / (head_dim as f64).sqrt())?;
        let attn = attn
            .permute_contiguous(&[0, 2, 1, 3])?
            .reshape(&[b, h * w, c])?;
        let out = attn.linear(&self.to_out)?;
        let out = out.permute_contiguous(&[0, 2, 1])?.reshape(&[b, c, h, w])?;
        let out = out.add(x)?;
        if self.rescale_output_factor == 1.0 {
            Ok(out)
        } else {
            out.div_scalar(self.rescale_output_factor)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::test_support::max_diff;
    use candle_core::{DType, Device, Var};

    #[test]
    fn group_norm_module_paths_agree() {
        let dev = Device::Cpu;
        let x = Tensor::randn(0f32, 1.0, (2, 8, 5, 3), &dev)
            .unwrap()
            .affine(3.0, 1.5)
            .unwrap();
        let w = Tensor::randn(1f32, 0.2, 8, &dev).unwrap();
        let b = Tensor::randn(0f32, 0.2, 8, &dev).unwrap();
        let module = |w: &Tensor, b: &Tensor| GroupNorm {
            weight: w.clone(),
            bias: b.clone(),
            num_groups: 4,
            eps: 1e-5,
        };
        let (gn, f64_of) = (module(&w, &b), |t: &Tensor| t.to_dtype(DType::F64).unwrap());
        // f64 runs the composite ops: the reference for the fused f32 kernel.
        let gn64 = module(&f64_of(&w), &f64_of(&b));
        let f32_of = |t: Tensor| t.to_dtype(DType::F32).unwrap();
        let want = f32_of(gn64.forward(&f64_of(&x)).unwrap());
        let want_silu = f32_of(gn64.forward_silu(&f64_of(&x)).unwrap());
        assert!(max_diff(&gn.forward(&x).unwrap(), &want) < 1e-5);
        assert!(max_diff(&gn.forward_silu(&x).unwrap(), &want_silu) < 1e-5);
        // Through a Var the training kernel runs and gradients flow.
        let xv = Var::from_tensor(&x).unwrap();
        let y = gn.forward_silu(xv.as_tensor()).unwrap();
        assert!(max_diff(&y, &want_silu) < 1e-5);
        let grads = y.sum_all().unwrap().backward().unwrap();
        assert!(grads.get(xv.as_tensor()).is_some());
    }

    #[test]
    fn layer_norm_paths_agree() {
        let dev = Device::Cpu;
        let x = Tensor::randn(0f32, 2.0, (2, 7, 16), &dev).unwrap();
        let ln = LayerNorm {
            weight: Tensor::randn(1f32, 0.1, 16, &dev).unwrap(),
            bias: Tensor::randn(0f32, 0.1, 16, &dev).unwrap(),
            eps: 1e-5,
        };
        let fast = ln.forward(&x).unwrap();
        let xv = Var::from_tensor(&x).unwrap();
        let slow = ln.forward(xv.as_tensor()).unwrap();
        assert!(max_diff(&fast, &slow) < 1e-5);
    }
}
