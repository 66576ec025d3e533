//! diffusers' `UNet2DConditionModel` for SD-style configs, written against burn's tensor API with weights
//! by diffusers key names. This is the "second definition" a move to burn would need; it exists only so
//! the stack decision (README, GPU > Stack) is measured on the same network and weights as our own UNet.
//!
//! Covered: `CrossAttnDownBlock2D` / `DownBlock2D` / `UNetMidBlock2DCrossAttn` / `UpBlock2D` /
//! `CrossAttnUpBlock2D`, one transformer layer per block, conv projections, heads from
//! `attention_head_dim` (diffusers' SD naming), an optional LCM `cond_proj`. No attention hook: burn
//! has no place for one, which is part of what is being measured.

use std::collections::HashMap;

use burn::module::Param;
use burn::nn::GroupNorm;
use burn::tensor::activation::{gelu, silu};
use burn::tensor::module::{attention, conv2d, interpolate, layer_norm, linear};
use burn::tensor::ops::{AttentionModuleOptions, ConvOptions, InterpolateMode, InterpolateOptions};
use burn::tensor::{Device, Tensor, TensorData};
use diffusion::unet::{PerBlock, UNetConfig};

/// Host weights by diffusers name: values and shape.
pub type HostWeights = HashMap<String, (Vec<f32>, Vec<usize>)>;

/// The config values this port reads, taken from our parsed `UNetConfig` so both networks are built
/// from one config.
#[derive(Debug, Clone)]
pub struct Config {
    pub block_out_channels: Vec<usize>,
    pub layers_per_block: usize,
    /// Heads per attention layer (diffusers' SD configs name this `attention_head_dim`).
    pub heads: usize,
    pub norm_num_groups: usize,
    pub norm_eps: f64,
    pub down_block_types: Vec<String>,
    pub up_block_types: Vec<String>,
    pub flip_sin_to_cos: bool,
    pub freq_shift: f64,
}

impl Config {
    /// Panics on what this port does not cover (per-block values, linear projections, more
    /// transformer layers): it measures SD-style UNets only.
    pub fn from_ours(c: &UNetConfig) -> Self {
        let one = |v: &PerBlock<usize>, what: &str| match v {
            PerBlock::One(n) => *n,
            PerBlock::Many(_) => panic!("burn unet: per-block {what} not covered"),
        };
        assert!(
            !c.use_linear_projection,
            "burn unet: linear projections not covered"
        );
        assert_eq!(
            one(&c.transformer_layers_per_block, "transformer layers"),
            1
        );
        Self {
            block_out_channels: c.block_out_channels.clone(),
            layers_per_block: one(&c.layers_per_block, "layers_per_block"),
            heads: one(
                c.num_attention_heads
                    .as_ref()
                    .unwrap_or(&c.attention_head_dim),
                "heads",
            ),
            norm_num_groups: c.norm_num_groups.unwrap_or(32),
            norm_eps: c.norm_eps,
            down_block_types: c.down_block_types.clone(),
            up_block_types: c.up_block_types.clone(),
            flip_sin_to_cos: c.flip_sin_to_cos,
            freq_shift: c.freq_shift,
        }
    }
}

struct Loader<'a> {
    weights: &'a HostWeights,
    device: Device,
}

impl Loader<'_> {
    fn tensor<const D: usize>(&self, name: &str) -> Tensor<D> {
        let (values, shape) = self
            .weights
            .get(name)
            .unwrap_or_else(|| panic!("burn unet: missing weight {name}"));
        assert_eq!(shape.len(), D, "burn unet: {name} has shape {shape:?}");
        Tensor::from_data(TensorData::new(values.clone(), shape.clone()), &self.device)
    }

    fn has(&self, name: &str) -> bool {
        self.weights.contains_key(name)
    }

    fn conv(&self, prefix: &str, stride: usize) -> Conv {
        let weight: Tensor<4> = self.tensor(&format!("{prefix}.weight"));
        let padding = weight.dims()[2] / 2;
        Conv {
            weight,
            bias: self.tensor(&format!("{prefix}.bias")),
            options: ConvOptions::new([stride, stride], [padding, padding], [1, 1], 1),
        }
    }

    /// burn's `linear` takes the weight as [in, out], PyTorch stores [out, in].
    fn linear(&self, prefix: &str) -> Linear {
        let weight: Tensor<2> = self.tensor(&format!("{prefix}.weight"));
        let bias = format!("{prefix}.bias");
        Linear {
            weight: weight.transpose(),
            bias: self.has(&bias).then(|| self.tensor(&bias)),
        }
    }

    fn group_norm(&self, prefix: &str, groups: usize, eps: f64) -> GroupNorm {
        let gamma: Tensor<1> = self.tensor(&format!("{prefix}.weight"));
        let channels = gamma.dims()[0];
        GroupNorm {
            gamma: Some(Param::from_tensor(gamma)),
            beta: Some(Param::from_tensor(self.tensor(&format!("{prefix}.bias")))),
            num_groups: groups,
            num_channels: channels,
            epsilon: eps,
            affine: true,
        }
    }

    fn layer_norm(&self, prefix: &str) -> LayerNorm {
        LayerNorm {
            gamma: self.tensor(&format!("{prefix}.weight")),
            beta: self.tensor(&format!("{prefix}.bias")),
        }
    }
}

struct Conv {
    weight: Tensor<4>,
    bias: Tensor<1>,
    options: ConvOptions<2>,
}

impl Conv {
    fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        conv2d(
            x,
            self.weight.clone(),
            Some(self.bias.clone()),
            self.options.clone(),
        )
    }
}

struct Linear {
    weight: Tensor<2>,
    bias: Option<Tensor<1>>,
}

impl Linear {
    fn forward<const D: usize>(&self, x: Tensor<D>) -> Tensor<D> {
        linear(x, self.weight.clone(), self.bias.clone())
    }
}

struct LayerNorm {
    gamma: Tensor<1>,
    beta: Tensor<1>,
}

impl LayerNorm {
    fn forward(&self, x: Tensor<3>) -> Tensor<3> {
        layer_norm(x, self.gamma.clone(), Some(self.beta.clone()), 1e-5)
    }
}

struct Resnet {
    norm1: GroupNorm,
    conv1: Conv,
    time_emb_proj: Linear,
    norm2: GroupNorm,
    conv2: Conv,
    shortcut: Option<Conv>,
}

impl Resnet {
    fn load(l: &Loader, p: &str, cfg: &Config) -> Self {
        let (g, eps) = (cfg.norm_num_groups, cfg.norm_eps);
        let shortcut = format!("{p}.conv_shortcut.weight");
        Self {
            norm1: l.group_norm(&format!("{p}.norm1"), g, eps),
            conv1: l.conv(&format!("{p}.conv1"), 1),
            time_emb_proj: l.linear(&format!("{p}.time_emb_proj")),
            norm2: l.group_norm(&format!("{p}.norm2"), g, eps),
            conv2: l.conv(&format!("{p}.conv2"), 1),
            shortcut: l
                .has(&shortcut)
                .then(|| l.conv(&format!("{p}.conv_shortcut"), 1)),
        }
    }

    fn forward(&self, x: Tensor<4>, temb: &Tensor<2>) -> Tensor<4> {
        let h = self.conv1.forward(silu(self.norm1.forward(x.clone())));
        let t: Tensor<2> = self.time_emb_proj.forward(silu(temb.clone()));
        let [b, c] = t.dims();
        let h = h + t.reshape([b, c, 1, 1]);
        let h = self.conv2.forward(silu(self.norm2.forward(h)));
        let skip = match &self.shortcut {
            Some(conv) => conv.forward(x),
            None => x,
        };
        skip + h
    }
}

struct Attention {
    to_q: Linear,
    to_k: Linear,
    to_v: Linear,
    to_out: Linear,
    heads: usize,
}

impl Attention {
    fn load(l: &Loader, p: &str, heads: usize) -> Self {
        Self {
            to_q: l.linear(&format!("{p}.to_q")),
            to_k: l.linear(&format!("{p}.to_k")),
            to_v: l.linear(&format!("{p}.to_v")),
            to_out: l.linear(&format!("{p}.to_out.0")),
            heads,
        }
    }

    /// [b, n, c] → [b, heads, n, c / heads].
    fn split_heads(&self, x: Tensor<3>) -> Tensor<4> {
        let [b, n, c] = x.dims();
        x.reshape([b, n, self.heads, c / self.heads])
            .swap_dims(1, 2)
    }

    fn forward(&self, x: Tensor<3>, context: Option<&Tensor<3>>) -> Tensor<3> {
        let kv = context.cloned().unwrap_or_else(|| x.clone());
        let q = self.split_heads(self.to_q.forward(x));
        let k = self.split_heads(self.to_k.forward(kv.clone()));
        let v = self.split_heads(self.to_v.forward(kv));
        let out = attention(q, k, v, None, None, AttentionModuleOptions::default());
        let [b, h, n, d] = out.dims();
        self.to_out
            .forward(out.swap_dims(1, 2).reshape([b, n, h * d]))
    }
}

struct Transformer {
    norm: GroupNorm,
    proj_in: Conv,
    norm1: LayerNorm,
    attn1: Attention,
    norm2: LayerNorm,
    attn2: Attention,
    norm3: LayerNorm,
    ff_in: Linear,
    ff_out: Linear,
    proj_out: Conv,
}

impl Transformer {
    fn load(l: &Loader, p: &str, cfg: &Config) -> Self {
        let b = format!("{p}.transformer_blocks.0");
        let heads = cfg.heads;
        Self {
            // diffusers' Transformer2DModel normalises with eps 1e-6 whatever the config says.
            norm: l.group_norm(&format!("{p}.norm"), cfg.norm_num_groups, 1e-6),
            proj_in: l.conv(&format!("{p}.proj_in"), 1),
            norm1: l.layer_norm(&format!("{b}.norm1")),
            attn1: Attention::load(l, &format!("{b}.attn1"), heads),
            norm2: l.layer_norm(&format!("{b}.norm2")),
            attn2: Attention::load(l, &format!("{b}.attn2"), heads),
            norm3: l.layer_norm(&format!("{b}.norm3")),
            ff_in: l.linear(&format!("{b}.ff.net.0.proj")),
            ff_out: l.linear(&format!("{b}.ff.net.2")),
            proj_out: l.conv(&format!("{p}.proj_out"), 1),
        }
    }

    fn forward(&self, x: Tensor<4>, context: &Tensor<3>) -> Tensor<4> {
        let [b, c, h, w] = x.dims();
        let tokens = self
            .proj_in
            .forward(self.norm.forward(x.clone()))
            .reshape([b, c, h * w])
            .swap_dims(1, 2);
        let tokens = tokens.clone() + self.attn1.forward(self.norm1.forward(tokens), None);
        let tokens = tokens.clone()
            + self
                .attn2
                .forward(self.norm2.forward(tokens), Some(context));
        // GEGLU: the projection's first half gated by GELU of its second half.
        let projected = self.ff_in.forward(self.norm3.forward(tokens.clone()));
        let inner = projected.dims()[2] / 2;
        let gated = projected.clone().narrow(2, 0, inner) * gelu(projected.narrow(2, inner, inner));
        let tokens = tokens + self.ff_out.forward(gated);
        let spatial = tokens.swap_dims(1, 2).reshape([b, c, h, w]);
        self.proj_out.forward(spatial) + x
    }
}

struct Block {
    resnets: Vec<Resnet>,
    attentions: Vec<Transformer>,
    /// Downsampler (stride 2) or upsampler (nearest ×2, then conv).
    resample: Option<Conv>,
}

impl Block {
    fn load(l: &Loader, p: &str, cfg: &Config, layers: usize, cross: bool, resample: bool) -> Self {
        let down = p.starts_with("down");
        Self {
            resnets: (0..layers)
                .map(|j| Resnet::load(l, &format!("{p}.resnets.{j}"), cfg))
                .collect(),
            attentions: if cross {
                (0..layers)
                    .map(|j| Transformer::load(l, &format!("{p}.attentions.{j}"), cfg))
                    .collect()
            } else {
                Vec::new()
            },
            resample: resample.then(|| {
                if down {
                    l.conv(&format!("{p}.downsamplers.0.conv"), 2)
                } else {
                    l.conv(&format!("{p}.upsamplers.0.conv"), 1)
                }
            }),
        }
    }
}

pub struct BurnUNet {
    config: Config,
    time_cond_proj: Option<Linear>,
    time_linear_1: Linear,
    time_linear_2: Linear,
    conv_in: Conv,
    down: Vec<Block>,
    mid_resnets: [Resnet; 2],
    mid_attention: Transformer,
    up: Vec<Block>,
    norm_out: GroupNorm,
    conv_out: Conv,
    device: Device,
}

impl BurnUNet {
    pub fn load(config: &Config, weights: &HostWeights, device: &Device) -> Self {
        let l = Loader {
            weights,
            device: device.clone(),
        };
        let n = config.block_out_channels.len();
        let cross = |t: &str| t.starts_with("CrossAttn");
        let down = config
            .down_block_types
            .iter()
            .enumerate()
            .map(|(i, t)| {
                let p = format!("down_blocks.{i}");
                Block::load(&l, &p, config, config.layers_per_block, cross(t), i + 1 < n)
            })
            .collect();
        let up = config
            .up_block_types
            .iter()
            .enumerate()
            .map(|(i, t)| {
                let p = format!("up_blocks.{i}");
                Block::load(
                    &l,
                    &p,
                    config,
                    config.layers_per_block + 1,
                    cross(t),
                    i + 1 < n,
                )
            })
            .collect();
        Self {
            config: config.clone(),
            time_cond_proj: l
                .has("time_embedding.cond_proj.weight")
                .then(|| l.linear("time_embedding.cond_proj")),
            time_linear_1: l.linear("time_embedding.linear_1"),
            time_linear_2: l.linear("time_embedding.linear_2"),
            conv_in: l.conv("conv_in", 1),
            down,
            mid_resnets: [
                Resnet::load(&l, "mid_block.resnets.0", config),
                Resnet::load(&l, "mid_block.resnets.1", config),
            ],
            mid_attention: Transformer::load(&l, "mid_block.attentions.0", config),
            up,
            norm_out: l.group_norm("conv_norm_out", config.norm_num_groups, config.norm_eps),
            conv_out: l.conv("conv_out", 1),
            device: device.clone(),
        }
    }

    pub fn device(&self) -> &Device {
        &self.device
    }

    /// The sinusoidal timestep embedding (diffusers' `Timesteps`), computed on the host like ours.
    fn timestep_embedding(&self, timesteps: &[f32]) -> Tensor<2> {
        let dim = self.config.block_out_channels[0];
        let half = dim / 2;
        let mut rows: Vec<f32> = Vec::with_capacity(timesteps.len() * dim);
        for &t in timesteps {
            let args: Vec<f64> = (0..half)
                .map(|i| {
                    let exponent =
                        -(10000f64).ln() * i as f64 / (half as f64 - self.config.freq_shift);
                    t as f64 * exponent.exp()
                })
                .collect();
            let (sin, cos): (Vec<f32>, Vec<f32>) = args
                .iter()
                .map(|a| (a.sin() as f32, a.cos() as f32))
                .unzip();
            if self.config.flip_sin_to_cos {
                rows.extend(cos.iter().chain(&sin));
            } else {
                rows.extend(sin.iter().chain(&cos));
            }
        }
        Tensor::from_data(TensorData::new(rows, [timesteps.len(), dim]), &self.device)
    }

    /// `timesteps` holds one value per batch item.
    pub fn forward(
        &self,
        sample: Tensor<4>,
        timesteps: &[f32],
        context: Tensor<3>,
        timestep_cond: Option<Tensor<2>>,
    ) -> Tensor<4> {
        let mut temb = self.timestep_embedding(timesteps);
        if let (Some(proj), Some(cond)) = (&self.time_cond_proj, timestep_cond) {
            temb = temb + proj.forward(cond);
        }
        let temb = self
            .time_linear_2
            .forward(silu(self.time_linear_1.forward(temb)));

        let mut x = self.conv_in.forward(sample);
        let mut skips = vec![x.clone()];
        for block in &self.down {
            for (j, resnet) in block.resnets.iter().enumerate() {
                x = resnet.forward(x, &temb);
                if let Some(attn) = block.attentions.get(j) {
                    x = attn.forward(x, &context);
                }
                skips.push(x.clone());
            }
            if let Some(conv) = &block.resample {
                x = conv.forward(x);
                skips.push(x.clone());
            }
        }
        x = self.mid_resnets[0].forward(x, &temb);
        x = self.mid_attention.forward(x, &context);
        x = self.mid_resnets[1].forward(x, &temb);
        for block in &self.up {
            for (j, resnet) in block.resnets.iter().enumerate() {
                let skip = skips.pop().expect("one skip per up resnet");
                x = resnet.forward(Tensor::cat(vec![x, skip], 1), &temb);
                if let Some(attn) = block.attentions.get(j) {
                    x = attn.forward(x, &context);
                }
            }
            if let Some(conv) = &block.resample {
                let [_, _, h, w] = x.dims();
                let up = InterpolateOptions::new(InterpolateMode::Nearest)
                    .with_output_size([2 * h, 2 * w]);
                x = conv.forward(interpolate(x, up));
            }
        }
        self.conv_out.forward(silu(self.norm_out.forward(x)))
    }
}
