//! The units the compositing loops work in, shared by the forward pass (`raster.rs`), its backward
//! (`raster_backward.rs`), lifting and the AVX2 kernels (`simd.rs`):
//!
//! - a tile ([`TileRect`]): the 16x16 pixels one list of Gaussians is composited over;
//! - a segment: 8 consecutive pixels of a tile row, processed together over 8 lanes (one AVX2 register of
//!   `f32`), with per-row bit masks of the pixels still in play;
//! - the per-lane state of one segment in the backward pass ([`SegTemps`], [`SegState`], [`LaneGrads`]).

use super::project::{Splat, ALPHA_MAX, ALPHA_MIN, TILE};
use super::real::{c, Real};
use super::tiles::TileBins;

pub(crate) const TILE_PIXELS: usize = (TILE * TILE) as usize;
/// Pixels processed together: half a tile row. 8 f32 lanes fill one AVX2 register.
pub(crate) const SEG: usize = 8;
/// How many list entries ahead the tile loops prefetch splat records (their order in memory is random).
pub(crate) const PREFETCH_AHEAD: usize = 8;

/// The pixels of one tile inside the image.
#[derive(Clone, Copy, Debug)]
pub(crate) struct TileRect {
    pub x0: u32,
    pub y0: u32,
    pub w: u32,
    pub h: u32,
}

impl TileRect {
    pub fn new(tile: usize, bins: &TileBins, width: u32, height: u32) -> Self {
        let tx = tile as u32 % bins.tiles_x;
        let ty = tile as u32 / bins.tiles_x;
        let x0 = tx * TILE;
        let y0 = ty * TILE;
        Self {
            x0,
            y0,
            w: TILE.min(width - x0),
            h: TILE.min(height - y0),
        }
    }

    /// Image pixel index of tile pixel `p` (= row * 16 + column).
    #[inline(always)]
    pub fn global(&self, p: usize, width: u32) -> usize {
        let r = (p / TILE as usize) as u32;
        let i = (p % TILE as usize) as u32;
        ((self.y0 + r) * width + self.x0 + i) as usize
    }

    /// Pixel-centre x coordinates of the two segments of a row.
    #[inline(always)]
    pub fn segment_xs<R: Real>(&self) -> [[R; SEG]; 2] {
        std::array::from_fn(|h| {
            std::array::from_fn(|l| c((self.x0 + (h * SEG + l) as u32) as f64 + 0.5))
        })
    }
}

/// Bits lo..=hi set (both < 32, lo <= hi).
#[inline(always)]
pub(crate) fn bit_range(lo: u32, hi: u32) -> u32 {
    let upper = if hi >= 31 {
        u32::MAX
    } else {
        (1u32 << (hi + 1)) - 1
    };
    upper & !((1u32 << lo) - 1)
}

/// Indices `i` in `0..n` with |centre − (base + i)| ≤ half + 1, as a bit mask (the extra pixel absorbs
/// rounding: the per-pixel test decides exactly).
#[inline(always)]
fn window_bits<R: Real>(centre: R, half: R, base: u32, n: u32) -> u32 {
    let base: R = c(base as f64 + 0.5);
    let lo = (centre - half - R::ONE - base).ceil().max(R::ZERO);
    let hi = (centre + half + R::ONE - base)
        .floor()
        .min(c((n - 1) as f64));
    if !(lo <= hi) {
        return 0;
    }
    bit_range(lo.to_f64() as u32, hi.to_f64() as u32)
}

/// Rows of the tile (bit mask) whose pixel centres may lie in the support of `s`.
#[inline(always)]
pub(crate) fn row_mask<R: Real>(s: &Splat<R>, rect: &TileRect) -> u32 {
    window_bits(s.mean[1], s.half_height, rect.y0, rect.h)
}

/// Columns of the tile (bit mask) whose pixel centres may lie in the support of `s`.
#[inline(always)]
pub(crate) fn column_mask<R: Real>(s: &Splat<R>, rect: &TileRect) -> u32 {
    window_bits(s.mean[0], s.half_width, rect.x0, rect.w)
}

/// σ at pixel offset (dx, dy) = mean − pixel centre. The one definition used by every pass.
#[inline(always)]
pub(crate) fn sigma_at<R: Real>(conic: &[R; 3], dx: R, dy: R) -> R {
    c::<R>(0.5) * (conic[0] * dx * dx + conic[2] * dy * dy) + conic[1] * dx * dy
}

/// What every pass computes per pixel from a splat, the same way (the AVX2 kernels have their own copy,
/// `simd::alpha_lanes`).
#[derive(Clone, Copy)]
pub(crate) struct LaneAlpha<R> {
    /// Splat mean − pixel-centre x.
    pub dx: R,
    /// exp(−σ).
    pub vis: R,
    /// min(0.99, opacity · exp(−σ)).
    pub alpha: R,
    /// σ ≥ 0 and alpha ≥ 1/255: the splat counts at this pixel (if the pixel is still in play).
    pub counts: bool,
}

/// [`LaneAlpha`] of splat `s` at the pixel centred at x (`dy` = mean − pixel-centre y).
#[inline(always)]
pub(crate) fn lane_alpha<R: Real>(s: &Splat<R>, x: R, dy: R) -> LaneAlpha<R> {
    let dx = s.mean[0] - x;
    let sigma = sigma_at(&s.conic, dx, dy);
    let vis = (-sigma).exp_fast();
    let alpha = (s.opacity * vis).min(c(ALPHA_MAX));
    LaneAlpha {
        dx,
        vis,
        alpha,
        counts: sigma >= R::ZERO && alpha >= c(ALPHA_MIN),
    }
}

/// Per-lane intermediate values of one backward segment, shared between its passes.
#[derive(Clone, Copy, Default)]
pub(crate) struct SegTemps<R> {
    pub dx: [R; SEG],
    pub vis: [R; SEG],
    pub alpha: [R; SEG],
    /// 1 / (1 − alpha).
    pub ra: [R; SEG],
    /// T before this Gaussian.
    pub t_new: [R; SEG],
    /// dL/dalpha (without the extra channels' part).
    pub v_alpha: [R; SEG],
}

/// Per-pixel backward state of the 8 pixels of a segment (views into the tile scratch).
pub(crate) struct SegState<'a, R> {
    pub trans: &'a mut [R; SEG],
    pub behind: [&'a mut [R; SEG]; 4],
    pub v_color: [&'a [R; SEG]; 3],
    pub v_depth: &'a [R; SEG],
    pub v_final: &'a [R; SEG],
}

/// Per-lane gradient sums of one Gaussian.
#[derive(Clone, Copy)]
pub(crate) struct LaneGrads<R> {
    pub color: [[R; SEG]; 3],
    pub depth: [R; SEG],
    pub conic: [[R; SEG]; 3],
    pub mean: [[R; SEG]; 2],
    pub opacity: [R; SEG],
}

impl<R: Real> LaneGrads<R> {
    pub fn zero() -> Self {
        Self {
            color: [[R::ZERO; SEG]; 3],
            depth: [R::ZERO; SEG],
            conic: [[R::ZERO; SEG]; 3],
            mean: [[R::ZERO; SEG]; 2],
            opacity: [R::ZERO; SEG],
        }
    }
}
