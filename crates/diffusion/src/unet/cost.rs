//! How much arithmetic a UNet call does, from the config alone: multiply-adds of the convolutions, the
//! linear layers and the attention products. A call timed at a small latent size is scaled to the size a
//! run uses by the ratio of these counts (self-attention grows with the square of the pixels, so a
//! pixel ratio would understate a large call many times over).
//!
//! Counted: every 3×3 and 1×1 convolution (ResNet blocks, shortcuts, down- and upsamplers, conv_in and
//! conv_out), the transformers' projections, Q/K/V/out, the GEGLU feed-forward, and the attention's two
//! products (scores and the weighted sum). Not counted: norms, activations, softmax, the time embedding
//! (per call, not per pixel); a few percent at the sizes that matter.

use super::config::{BlockKind, UNetConfig};
use super::UNetError;

impl UNetConfig {
    /// Multiply-adds of one call on `batch` latents of `height`×`width` with `context_tokens` text tokens.
    /// Scales linearly with `batch`.
    pub fn multiply_adds(
        &self,
        batch: usize,
        height: usize,
        width: usize,
        context_tokens: usize,
    ) -> Result<u64, UNetError> {
        let r = self.resolve().map_err(UNetError::Unsupported)?;
        let ch = &self.block_out_channels;
        let n = ch.len();
        let mut pixels = Vec::with_capacity(n);
        let (mut h, mut w) = (height as u64, width as u64);
        for _ in 0..n {
            pixels.push(h * w);
            h = h.div_ceil(2);
            w = w.div_ceil(2);
        }
        let t = context_tokens as u64;
        let resnet = |cin: u64, c: u64, s: u64| {
            let shortcut = if cin != c { cin * c * s } else { 0 };
            9 * cin * c * s + 9 * c * c * s + shortcut
        };
        // One transformer (proj_in, `depth` blocks, proj_out) of `c` channels at `s` pixels.
        let transformer = |l: usize, c: u64, s: u64| {
            let cd = r.cross_attention_dim[l] as u64;
            let cross = 2 * c * c * s + 2 * t * cd * c + 2 * s * t * c;
            let first = if r.only_cross_attention[l] {
                cross
            } else {
                4 * c * c * s + 2 * s * s * c
            };
            let feed_forward = 8 * c * c * s + 4 * c * c * s;
            2 * c * c * s + r.transformer_layers[l] as u64 * (first + cross + feed_forward)
        };
        let c0 = ch[0] as u64;
        let io = self.in_channels as u64 + self.out_channels as u64;
        let mut total = 9 * io * c0 * pixels[0];
        // Down path, with the channels of every skip it leaves for the up path.
        let mut skips = vec![c0];
        let mut cin = c0;
        for l in 0..n {
            let (c, s) = (ch[l] as u64, pixels[l]);
            for _ in 0..r.layers[l] {
                total += resnet(cin, c, s);
                if r.down[l] == BlockKind::CrossAttn {
                    total += transformer(l, c, s);
                }
                cin = c;
                skips.push(c);
            }
            if l + 1 < n {
                total += 9 * c * c * pixels[l + 1];
                skips.push(c);
            }
        }
        // Mid block: ResNet, transformer, ResNet at the last level.
        let (c, s) = (ch[n - 1] as u64, pixels[n - 1]);
        total += 2 * resnet(c, c, s) + transformer(n - 1, c, s);
        // Up path: each ResNet takes the previous output concatenated with the latest skip.
        for (i, l) in (0..n).rev().enumerate() {
            let (c, s) = (ch[l] as u64, pixels[l]);
            for _ in 0..=r.layers[l] {
                let skip = skips.pop().unwrap_or(c);
                total += resnet(cin + skip, c, s);
                if r.up[i] == BlockKind::CrossAttn {
                    total += transformer(l, c, s);
                }
                cin = c;
            }
            if l > 0 {
                total += 9 * c * c * pixels[l - 1];
            }
        }
        Ok(total * batch as u64)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sd15_at_512_is_about_the_known_count_and_attention_makes_it_grow_faster_than_pixels() {
        let cfg = UNetConfig::sd15();
        let full = cfg.multiply_adds(1, 64, 64, 77).unwrap() as f64;
        // SD 1.5's UNet is commonly put at about 0.4 T multiply-adds per 64² latent.
        assert!((3.0e11..5.0e11).contains(&full), "{full:e}");
        let quarter = cfg.multiply_adds(1, 32, 32, 77).unwrap() as f64;
        let ratio = full / quarter;
        // Four times the pixels, more than four times the work: the first level's self-attention.
        assert!((4.3..8.0).contains(&ratio), "{ratio}");
        assert_eq!(
            cfg.multiply_adds(6, 32, 32, 77).unwrap(),
            6 * cfg.multiply_adds(1, 32, 32, 77).unwrap()
        );
    }

    #[test]
    fn only_cross_attention_drops_the_quadratic_term() {
        let mut cfg = UNetConfig::sd15();
        let plain = cfg.multiply_adds(1, 64, 64, 77).unwrap();
        cfg.only_cross_attention = super::super::PerBlock::One(true);
        let cross = cfg.multiply_adds(1, 64, 64, 77).unwrap();
        assert!(cross < plain);
    }
}
