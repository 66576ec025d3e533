//! The UNet's down, mid and up blocks (diffusers `CrossAttnDownBlock2D`, `DownBlock2D`,
//! `UNetMidBlock2DCrossAttn`, `CrossAttnUpBlock2D`, `UpBlock2D`).

use candle_core::Result;
use candle_nn::VarBuilder;

use super::attention::AttentionHook;
use super::transformer::{Transformer2D, Transformer2DConfig};
use crate::kernels::DeviceTensor;
use crate::layers::{Downsample2D, ResnetBlock2D, ResnetConfig, TimeEmbeddingNorm, Upsample2D};

/// Numbers shared by all ResNets of the UNet.
#[derive(Debug, Clone, Copy)]
pub struct ResnetShared {
    pub temb_channels: usize,
    pub groups: usize,
    pub eps: f64,
    pub time_embedding_norm: TimeEmbeddingNorm,
}

impl ResnetShared {
    fn config(&self, cin: usize, cout: usize, output_scale_factor: f64) -> ResnetConfig {
        ResnetConfig {
            output_scale_factor,
            time_embedding_norm: self.time_embedding_norm,
            ..ResnetConfig::new(cin, cout, Some(self.temb_channels), self.groups, self.eps)
        }
    }
}

/// Attention options of one block; `None` in [`DownBlock::load`]/[`UpBlock::load`] means a plain block.
#[derive(Debug, Clone, Copy)]
pub struct BlockAttention {
    pub heads: usize,
    pub transformer_layers: usize,
    pub context_dim: usize,
    pub linear_projection: bool,
    pub only_cross_attention: bool,
}

impl BlockAttention {
    fn transformer(&self, channels: usize, groups: usize) -> Transformer2DConfig {
        Transformer2DConfig {
            channels,
            heads: self.heads,
            layers: self.transformer_layers,
            context_dim: self.context_dim,
            groups,
            linear_projection: self.linear_projection,
            only_cross_attention: self.only_cross_attention,
        }
    }
}

/// Runs the transformer when present and passes the hook on.
fn attend(
    attention: Option<&Transformer2D>,
    h: DeviceTensor,
    context: &DeviceTensor,
    hook: Option<&mut (dyn AttentionHook + '_)>,
) -> Result<DeviceTensor> {
    match attention {
        Some(t) => t.forward(&h, context, hook),
        None => Ok(h),
    }
}

/// A down block: `layers` × (ResNet [+ transformer]) then an optional stride-2 downsampler.
#[derive(Debug, Clone)]
pub struct DownBlock {
    resnets: Vec<ResnetBlock2D>,
    attentions: Vec<Transformer2D>,
    downsampler: Option<Downsample2D>,
}

impl DownBlock {
    pub fn load(
        cin: usize,
        cout: usize,
        layers: usize,
        shared: &ResnetShared,
        output_scale_factor: f64,
        attention: Option<BlockAttention>,
        downsample_padding: Option<usize>,
        vb: VarBuilder,
    ) -> Result<Self> {
        let mut resnets = Vec::with_capacity(layers);
        let mut attentions = Vec::new();
        for i in 0..layers {
            let input = if i == 0 { cin } else { cout };
            let cfg = shared.config(input, cout, output_scale_factor);
            resnets.push(ResnetBlock2D::load(&cfg, vb.pp(format!("resnets.{i}")))?);
            if let Some(a) = &attention {
                let t = a.transformer(cout, shared.groups);
                attentions.push(Transformer2D::load(&t, vb.pp(format!("attentions.{i}")))?);
            }
        }
        let downsampler = match downsample_padding {
            Some(p) => Some(Downsample2D::load(cout, cout, p, vb.pp("downsamplers.0"))?),
            None => None,
        };
        Ok(Self {
            resnets,
            attentions,
            downsampler,
        })
    }

    /// Returns the block output and the skip connections it produced (one per layer, plus the
    /// downsampled output).
    pub fn forward(
        &self,
        x: &DeviceTensor,
        temb: &DeviceTensor,
        context: &DeviceTensor,
        mut hook: Option<&mut (dyn AttentionHook + '_)>,
    ) -> Result<(DeviceTensor, Vec<DeviceTensor>)> {
        let mut h = x.clone();
        let mut skips = Vec::with_capacity(self.resnets.len() + 1);
        for (i, resnet) in self.resnets.iter().enumerate() {
            h = resnet.forward_device(&h, Some(temb))?;
            h = attend(self.attentions.get(i), h, context, hook.as_deref_mut())?;
            skips.push(h.clone());
        }
        if let Some(down) = &self.downsampler {
            h = down.forward_device(&h)?;
            skips.push(h.clone());
        }
        Ok((h, skips))
    }
}

/// `UNetMidBlock2DCrossAttn`: ResNet, transformer(s), ResNet.
#[derive(Debug, Clone)]
pub struct MidBlock {
    resnets: Vec<ResnetBlock2D>,
    attentions: Vec<Transformer2D>,
}

impl MidBlock {
    pub fn load(
        channels: usize,
        shared: &ResnetShared,
        output_scale_factor: f64,
        attention: BlockAttention,
        vb: VarBuilder,
    ) -> Result<Self> {
        let cfg = shared.config(channels, channels, output_scale_factor);
        let t = attention.transformer(channels, shared.groups);
        Ok(Self {
            resnets: vec![
                ResnetBlock2D::load(&cfg, vb.pp("resnets.0"))?,
                ResnetBlock2D::load(&cfg, vb.pp("resnets.1"))?,
            ],
            attentions: vec![Transformer2D::load(&t, vb.pp("attentions.0"))?],
        })
    }

    pub fn forward(
        &self,
        x: &DeviceTensor,
        temb: &DeviceTensor,
        context: &DeviceTensor,
        hook: Option<&mut (dyn AttentionHook + '_)>,
    ) -> Result<DeviceTensor> {
        let h = self.resnets[0].forward_device(x, Some(temb))?;
        let h = self.attentions[0].forward(&h, context, hook)?;
        self.resnets[1].forward_device(&h, Some(temb))
    }
}

/// An up block: `layers` × (concat skip, ResNet [+ transformer]) then an optional upsampler.
#[derive(Debug, Clone)]
pub struct UpBlock {
    resnets: Vec<ResnetBlock2D>,
    attentions: Vec<Transformer2D>,
    upsampler: Option<Upsample2D>,
}

impl UpBlock {
    /// `skip_channels[i]` is the width of the skip connection consumed by layer i.
    pub fn load(
        prev_out: usize,
        cout: usize,
        skip_channels: &[usize],
        shared: &ResnetShared,
        output_scale_factor: f64,
        attention: Option<BlockAttention>,
        upsample: bool,
        vb: VarBuilder,
    ) -> Result<Self> {
        let mut resnets = Vec::with_capacity(skip_channels.len());
        let mut attentions = Vec::new();
        for (i, &skip) in skip_channels.iter().enumerate() {
            let input = if i == 0 { prev_out } else { cout };
            let cfg = shared.config(input + skip, cout, output_scale_factor);
            resnets.push(ResnetBlock2D::load(&cfg, vb.pp(format!("resnets.{i}")))?);
            if let Some(a) = &attention {
                let t = a.transformer(cout, shared.groups);
                attentions.push(Transformer2D::load(&t, vb.pp(format!("attentions.{i}")))?);
            }
        }
        let upsampler = if upsample {
            Some(Upsample2D::load(cout, cout, vb.pp("upsamplers.0"))?)
        } else {
            None
        };
        Ok(Self {
            resnets,
            attentions,
            upsampler,
        })
    }

    /// Number of skip connections this block consumes.
    pub fn layers(&self) -> usize {
        self.resnets.len()
    }

    /// `skips` in the order they were produced (the last one is consumed first); `upsample_size` is the
    /// spatial size the upsampler must produce.
    pub fn forward(
        &self,
        x: &DeviceTensor,
        skips: &[DeviceTensor],
        temb: &DeviceTensor,
        context: &DeviceTensor,
        upsample_size: Option<(usize, usize)>,
        mut hook: Option<&mut (dyn AttentionHook + '_)>,
    ) -> Result<DeviceTensor> {
        let mut h = x.clone();
        for (i, resnet) in self.resnets.iter().enumerate() {
            let skip = &skips[skips.len() - 1 - i];
            h = resnet.forward_device(&DeviceTensor::cat(&[&h, skip], 1)?, Some(temb))?;
            h = attend(self.attentions.get(i), h, context, hook.as_deref_mut())?;
        }
        match &self.upsampler {
            Some(up) => up.forward_device(&h, upsample_size),
            None => Ok(h),
        }
    }
}
