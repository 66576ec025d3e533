//! An estimate of the device memory a UNet call's activations need, from the config alone, so a caller
//! can choose how many views to put in one call before running it (the weights are extra:
//! [`GpuDevice::weight_bytes`](crate::device::GpuDevice::weight_bytes) once uploaded, about
//! parameters × 2 bytes with f16 weights).
//!
//! Assumptions (how the GPU path of `forward_on` allocates; f32 activations, 4 bytes each):
//! - the skip connections of the down path stay alive until the up path consumes them; the estimate
//!   counts all of them at once (they are all alive at the bottom of the UNet);
//! - on top of that, the largest working set of a single layer, taken over all levels:
//!   - a ResNet block (the first one of an up block is the worst: its input concatenates the previous
//!     level's output and a skip): the input, its group norm, the im2col buffer of the 3×3 convolution
//!     (9 × input channels × pixels), the convolution's output, plus the tensor the concatenation read
//!     (about 12 × input channels + output channels, per pixel);
//!   - a transformer block: the residual stream, its norm, Q/K/V and their head-split copies, and the
//!     feed-forward's GEGLU projection (8 × channels) and its output (4 × channels): 17 × channels per
//!     pixel; plus self-attention's scores and probabilities (2 × heads × pixels², 4 bytes each), held
//!     in chunks of whole heads of at most `ops::TRANSIENT_CAP_BYTES` (at least one head: 64 MiB at 64²;
//!     see `ops::attention`);
//!   - with a hook, Q/K/V also make a round trip through the CPU (3 more copies) and the cross-attention
//!     layers hold their scores and probabilities (2 × heads × pixels × context tokens). Self-attention
//!     probabilities are assumed not requested (InfEdit's controller and the blend masks read
//!     cross-attention maps only); a hook that asks for them at 64² latents needs gigabytes more;
//! - the counts are a little above the true live set (the two terms peak at different layers), so
//!   [`ActivationEstimate::total`] bounds the bytes in use; CubeCL's pools carve allocations out of pages
//!   sized to the largest allocation and keep freed pages, so they reserve more. Measured on lavapipe
//!   (the SD 1.5 blocks with channels [64, 128, 256, 256], `vcedit bench unet --small --device gpu`): the
//!   pools reserved, beyond the weights and ~16 MB of fixed pages, 3, 11, 31 and 70 MB where the estimate
//!   says 3, 11 (16², 32²), 22 (32², batch 2) and 44 MB (32² batch 4, and 64²). Check
//!   [`ActivationEstimate::budget`] (1.75 × the estimate) against the adapter's free memory.

use super::config::UNetConfig;
use super::UNetError;
use crate::kernels::gpu::ops::TRANSIENT_CAP_BYTES;

/// Bytes a UNet call's activations occupy on the device (see the module documentation).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ActivationEstimate {
    /// Skip connections held from the down path to the up path.
    pub skips: usize,
    /// The largest single layer's working set (im2col buffers, attention and feed-forward tensors).
    pub working: usize,
    /// Cross-attention scores and probabilities held for a hook (0 without one).
    pub probabilities: usize,
}

impl ActivationEstimate {
    /// The estimated peak of the bytes in use.
    pub fn total(&self) -> usize {
        self.skips + self.working + self.probabilities
    }

    /// What the memory pools may reserve for that peak (see the module documentation): the figure to
    /// check against the adapter's free memory, beside the weights.
    pub fn budget(&self) -> usize {
        self.total() / 4 * 7
    }
}

const F32_BYTES: usize = 4;

impl UNetConfig {
    /// The activation memory of one [`forward_on`](super::UNet2DConditionModel::forward_on) call on the GPU
    /// for `batch` latents of `height`×`width` with `context_tokens` text tokens (77 for CLIP), with or
    /// without an attention hook. Scales linearly with `batch`.
    pub fn activation_estimate(
        &self,
        batch: usize,
        height: usize,
        width: usize,
        context_tokens: usize,
        hooked: bool,
    ) -> Result<ActivationEstimate, UNetError> {
        let r = self.resolve().map_err(UNetError::Unsupported)?;
        let ch = &self.block_out_channels;
        let n = ch.len();
        // Pixels per level: each downsampler (3×3, stride 2, padding 1) halves a side, rounding up.
        let mut pixels = Vec::with_capacity(n);
        let (mut h, mut w) = (height, width);
        for _ in 0..n {
            pixels.push(h * w);
            h = h.div_ceil(2);
            w = w.div_ceil(2);
        }
        // Elements per image (`working` in bytes for the whole batch: the score chunks do not scale
        // with it).
        let mut skips = ch[0] * pixels[0];
        let mut working = 0usize;
        let bytes = |elements: usize| elements * batch * F32_BYTES;
        let mut probabilities = 0usize;
        for l in 0..n {
            let (c, s) = (ch[l], pixels[l]);
            skips += r.layers[l] * c * s;
            if l + 1 < n {
                skips += c * pixels[l + 1];
            }
            let input = ch[(l + 1).min(n - 1)] + c;
            working = working.max(bytes((12 * input + c) * s));
            // The mid block has attention at the last level whatever the block types say.
            let has_attention = r.down[l] == super::config::BlockKind::CrossAttn
                || r.up[n - 1 - l] == super::config::BlockKind::CrossAttn
                || l + 1 == n;
            if has_attention {
                let copies = if hooked { 20 } else { 17 };
                let one_head = s * s * F32_BYTES;
                let scores = bytes(r.heads[l] * s * s).min(one_head.max(TRANSIENT_CAP_BYTES));
                working = working.max(bytes(copies * c * s) + 2 * scores);
                if hooked {
                    probabilities = probabilities.max(2 * r.heads[l] * s * context_tokens);
                }
            }
        }
        Ok(ActivationEstimate {
            skips: bytes(skips),
            working,
            probabilities: bytes(probabilities),
        })
    }
}

/// A map size `(h, w)` and how many recorded cross-attention layers have it.
pub type LayerGrid = ((usize, usize), usize);

impl UNetConfig {
    /// Cross-attention layers of a call on `height`×`width` latents whose maps have at most `max_queries`
    /// pixels (those an attention store records, e.g. CCM's): per level, `layers` per cross-attention down
    /// block and `layers + 1` per up block, each times its transformer depth, plus the mid block's at the
    /// last level. SD 1.5 at 64² latents with 32² queries at most: 11.
    pub fn cross_attention_layers(
        &self,
        height: usize,
        width: usize,
        max_queries: usize,
    ) -> Result<usize, UNetError> {
        Ok(self
            .cross_attention_grids(height, width, max_queries)?
            .iter()
            .map(|&(_, layers)| layers)
            .sum())
    }

    /// [`Self::cross_attention_layers`] by map size: `((h, w), layers)` per level that has any, finest
    /// first. SD 1.5 at 64² latents with 32² queries at most: 32² (5), 16² (5), 8² (1).
    pub fn cross_attention_grids(
        &self,
        height: usize,
        width: usize,
        max_queries: usize,
    ) -> Result<Vec<LayerGrid>, UNetError> {
        use super::config::BlockKind::CrossAttn;
        let r = self.resolve().map_err(UNetError::Unsupported)?;
        let n = self.block_out_channels.len();
        let (mut h, mut w) = (height, width);
        let mut grids = Vec::new();
        for l in 0..n {
            if h * w <= max_queries {
                let depth = r.transformer_layers[l];
                let mut layers = 0;
                if r.down[l] == CrossAttn {
                    layers += r.layers[l] * depth;
                }
                if r.up[n - 1 - l] == CrossAttn {
                    layers += (r.layers[l] + 1) * depth;
                }
                if l + 1 == n {
                    layers += depth;
                }
                if layers > 0 {
                    grids.push(((h, w), layers));
                }
            }
            h = h.div_ceil(2);
            w = w.div_ceil(2);
        }
        Ok(grids)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sd15_estimate_is_dominated_by_the_first_level_and_scales_with_the_batch() {
        let cfg = UNetConfig::sd15();
        let one = cfg.activation_estimate(1, 64, 64, 77, false).unwrap();
        // The first level's transformer at 64²: 17 copies of 320 channels plus the scores and
        // probabilities of its self-attention, in chunks of the cap (8 heads of 4096² are 512 MiB).
        assert_eq!(one.working, 17 * 320 * 4096 * 4 + 2 * TRANSIENT_CAP_BYTES);
        // Six images' activations scale, their scores' chunks do not: the first up block's ResNet
        // ((12 × (640 + 320) + 320) × 4096 per image) is now the larger.
        let six_plain = cfg.activation_estimate(6, 64, 64, 77, false).unwrap();
        let transformer = 6 * 17 * 320 * 4096 * 4 + 2 * TRANSIENT_CAP_BYTES;
        let resnet = 6 * (12 * 960 + 320) * 4096 * 4;
        assert!(resnet > transformer);
        assert_eq!(six_plain.working, resnet);
        // At 32² one image's 8 heads of 1024² (32 MiB) fit in one chunk.
        let small = cfg.activation_estimate(1, 32, 32, 77, false).unwrap();
        assert!(small.working >= 2 * 8 * 1024 * 1024 * 4);
        assert!(small.working < 2 * TRANSIENT_CAP_BYTES);
        assert_eq!(one.probabilities, 0);
        // Skips: conv_in + 2 per level + 3 downsamplers, in f32.
        let skips = 320 * 4096 * 3
            + 320 * 1024
            + 640 * 1024 * 2
            + 640 * 256
            + 1280 * 256 * 2
            + 1280 * 64
            + 1280 * 64 * 2;
        assert_eq!(one.skips, skips * 4);
        let six = cfg.activation_estimate(6, 64, 64, 77, true).unwrap();
        assert_eq!(six.skips, 6 * one.skips);
        // Cross-attention maps at 64²: scores and probabilities, 8 heads × 4096 × 77, per image.
        assert_eq!(six.probabilities, 6 * 2 * 8 * 4096 * 77 * 4);
        // About 1.35 GiB for one 512² view's six hooked branches: a view batch of 8 fits in 24 GB.
        assert!((1 << 30..3 << 29).contains(&six.total()), "{six:?}");
    }

    #[test]
    fn recorded_cross_attention_layers_follow_the_query_limit() {
        let cfg = UNetConfig::sd15();
        // 64² latents: 32² (5 layers), 16² (5) and the mid block at 8² (1).
        assert_eq!(cfg.cross_attention_layers(64, 64, 32 * 32).unwrap(), 11);
        // 32² latents: the first level is 32² too.
        assert_eq!(cfg.cross_attention_layers(32, 32, 32 * 32).unwrap(), 16);
        assert_eq!(cfg.cross_attention_layers(64, 64, 1).unwrap(), 0);
        // Every layer: 2 + 2 + 2 down, 3 + 3 + 3 up, 1 mid.
        assert_eq!(cfg.cross_attention_layers(64, 64, usize::MAX).unwrap(), 16);
        assert_eq!(
            cfg.cross_attention_grids(64, 64, 32 * 32).unwrap(),
            [((32, 32), 5), ((16, 16), 5), ((8, 8), 1)]
        );
    }

    #[test]
    fn odd_latent_sizes_round_up_per_level() {
        let cfg = UNetConfig::sd15();
        let odd = cfg.activation_estimate(1, 63, 65, 77, false).unwrap();
        let even = cfg.activation_estimate(1, 64, 64, 77, false).unwrap();
        assert!(odd.total() > 0 && odd.total().abs_diff(even.total()) < even.total() / 20);
    }
}
