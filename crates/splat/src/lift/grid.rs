//! Maps on a coarse grid (CCM's 16² attention maps, the 64² local-blend maps): how they are resampled to
//! the cameras' resolution before lifting and back to their grid after rendering. The CPU functions here
//! are the reference the GPU's resampling kernel is tested against.

use crate::render::TILE;
use rayon::prelude::*;

/// How maps are resampled between their native grid and the render resolution.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Resample {
    /// torch `interpolate(mode="nearest")`.
    Nearest,
    /// torch `interpolate(mode="bilinear", align_corners=False)` (no antialiasing).
    Bilinear,
}

/// The grid per-view maps are given on (row-major, `channels` interleaved) and how they travel to the
/// cameras' resolution (`up`, before lifting) and back (`down`, after rendering).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MapGrid {
    pub height: usize,
    pub width: usize,
    pub channels: usize,
    pub up: Resample,
    pub down: Resample,
}

impl MapGrid {
    /// Values in one map.
    pub fn len(&self) -> usize {
        self.height * self.width * self.channels
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// Nearest source index along one axis: torch's `floor(dst * in / out)`, in exact integer arithmetic
/// (the same on the GPU).
#[inline]
fn nearest_index(dst: usize, src_len: usize, dst_len: usize) -> usize {
    (dst * src_len / dst_len).min(src_len - 1)
}

/// Bilinear source indices and weight along one axis (align_corners = false, edge-clamped), from the
/// axis scale `src_len / dst_len` computed once in f32 (the GPU kernel receives the same value).
#[inline]
fn bilinear_taps(dst: usize, scale: f32, src_len: usize) -> (usize, usize, f32) {
    let f = ((dst as f32 + 0.5) * scale - 0.5).max(0.0);
    let i0 = (f as usize).min(src_len - 1);
    let i1 = (i0 + 1).min(src_len - 1);
    (i0, i1, f - i0 as f32)
}

/// The two cells (of `cells`) an image row or column (of `full`) reads when a map is upsampled with
/// `mode`, and their weights (the nearest cell twice, weights 1 and 0).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Taps {
    pub cells: [u32; 2],
    pub weights: [f32; 2],
}

/// [`Taps`] of every row (or column) of `full` pixels upsampled from `cells`, in [`resample`]'s arithmetic.
pub(crate) fn axis_taps(full: usize, cells: usize, mode: Resample) -> Vec<Taps> {
    let scale = cells as f32 / full as f32;
    (0..full)
        .map(|o| match mode {
            Resample::Nearest => {
                let k = nearest_index(o, cells, full) as u32;
                Taps {
                    cells: [k, k],
                    weights: [1.0, 0.0],
                }
            }
            Resample::Bilinear => {
                let (i0, i1, t) = bilinear_taps(o, scale, cells);
                Taps {
                    cells: [i0 as u32, i1 as u32],
                    weights: [1.0 - t, t],
                }
            }
        })
        .collect()
}

/// Flags (1 or 0) of the `full` rows (or columns) that [`resample`] reads when it takes them to `cells`,
/// each with its neighbours, so a device that rounds a position differently still reads flagged pixels.
pub(crate) fn read_by_resampling(full: usize, cells: usize, mode: Resample) -> Vec<u32> {
    let mut flags = vec![0u32; full];
    if full == 0 {
        return flags;
    }
    let scale = full as f32 / cells as f32;
    for o in 0..cells {
        let (first, second) = match mode {
            Resample::Nearest => {
                let k = nearest_index(o, full, cells);
                (k, k)
            }
            Resample::Bilinear => {
                let (i0, i1, _) = bilinear_taps(o, scale, full);
                (i0, i1)
            }
        };
        for flag in &mut flags[first.saturating_sub(1)..=(second + 1).min(full - 1)] {
            *flag = 1;
        }
    }
    flags
}

/// The first cell and the number of cells the pixels `first..first + TILE` (clamped to the axis) read.
pub(crate) fn tile_cells(taps: &[Taps], first: usize) -> (u32, usize) {
    let last = (first + TILE as usize).min(taps.len()) - 1;
    let base = taps[first].cells[0];
    (base, (taps[last].cells[1] - base) as usize + 1)
}

/// The most cells any tile reads along an axis of `taps` (the CPU's and the GPU's grid lifting).
pub(crate) fn widest_tile(taps: &[Taps]) -> usize {
    (0..taps.len())
        .step_by(TILE as usize)
        .map(|first| tile_cells(taps, first).1)
        .max()
        .unwrap_or(1)
}

/// Resamples a row-major, channel-interleaved map from (h, w) to (out_h, out_w), rows in parallel.
pub fn resample(
    src: &[f32],
    (h, w): (usize, usize),
    (out_h, out_w): (usize, usize),
    channels: usize,
    mode: Resample,
) -> Vec<f32> {
    assert_eq!(src.len(), h * w * channels, "map must be H*W*C");
    if (h, w) == (out_h, out_w) {
        return src.to_vec();
    }
    let mut out = vec![0.0f32; out_h * out_w * channels];
    if out.is_empty() {
        return out;
    }
    let (sy, sx) = (h as f32 / out_h as f32, w as f32 / out_w as f32);
    out.par_chunks_mut(out_w * channels)
        .enumerate()
        .for_each(|(oy, row)| match mode {
            Resample::Nearest => {
                let y = nearest_index(oy, h, out_h);
                for (ox, px) in row.chunks_exact_mut(channels).enumerate() {
                    let s = (y * w + nearest_index(ox, w, out_w)) * channels;
                    px.copy_from_slice(&src[s..s + channels]);
                }
            }
            Resample::Bilinear => {
                let (y0, y1, ty) = bilinear_taps(oy, sy, h);
                for (ox, px) in row.chunks_exact_mut(channels).enumerate() {
                    let (x0, x1, tx) = bilinear_taps(ox, sx, w);
                    let at = |y: usize, x: usize| &src[(y * w + x) * channels..][..channels];
                    let (a, b, c, d) = (at(y0, x0), at(y0, x1), at(y1, x0), at(y1, x1));
                    for (k, o) in px.iter_mut().enumerate() {
                        let top = a[k] * (1.0 - tx) + b[k] * tx;
                        let bot = c[k] * (1.0 - tx) + d[k] * tx;
                        *o = top * (1.0 - ty) + bot * ty;
                    }
                }
            }
        });
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nearest_matches_torch_index_rule() {
        // torch: interpolate([[0, 1, 2]], size=2, mode="nearest") picks floor(i * 3/2) = 0, 1.
        let out = resample(&[0.0, 1.0, 2.0], (1, 3), (1, 2), 1, Resample::Nearest);
        assert_eq!(out, vec![0.0, 1.0]);
        let up = resample(&[0.0, 1.0], (1, 2), (1, 4), 1, Resample::Nearest);
        assert_eq!(up, vec![0.0, 0.0, 1.0, 1.0]);
    }

    #[test]
    fn bilinear_matches_torch_on_a_ramp() {
        // torch: F.interpolate(tensor([[[[0., 1.]]]]), size=(1, 4), mode="bilinear") = [0, .25, .75, 1]
        let out = resample(&[0.0, 1.0], (1, 2), (1, 4), 1, Resample::Bilinear);
        assert_eq!(out, vec![0.0, 0.25, 0.75, 1.0]);
        // Downsampling without antialiasing reads the two middle pixels of each block:
        // F.interpolate(arange(8.).view(1, 1, 1, 8), size=(1, 2), mode="bilinear") = [1.5, 5.5].
        let ramp: Vec<f32> = (0..8).map(|i| i as f32).collect();
        let down = resample(&ramp, (1, 8), (1, 2), 1, Resample::Bilinear);
        assert_eq!(down, vec![1.5, 5.5]);
    }

    #[test]
    fn channels_are_resampled_independently() {
        // Two channels, one constant and one a ramp: the constant stays, the ramp interpolates.
        let src = [7.0, 0.0, 7.0, 1.0];
        let out = resample(&src, (1, 2), (2, 4), 2, Resample::Bilinear);
        let constant: Vec<f32> = out.iter().step_by(2).copied().collect();
        let ramp: Vec<f32> = out.iter().skip(1).step_by(2).copied().collect();
        assert_eq!(constant, vec![7.0; 8]);
        assert_eq!(ramp, vec![0.0, 0.25, 0.75, 1.0, 0.0, 0.25, 0.75, 1.0]);
    }
}
