//! Stage (c): per-tile front-to-back compositing, with the exact rules of 3DGS/gsplat:
//! - pixel centres at (i + 0.5, j + 0.5); σ = ½(a dx² + c dy²) + b dx dy with d = mean − pixel;
//! - skip when σ < 0 or alpha = min(0.99, o·exp(−σ)) < 1/255;
//! - a pixel is finished (this Gaussian not counted) when T·(1 − alpha) < 1e-4;
//! - otherwise the Gaussian contributes with weight alpha·T and T ← T·(1 − alpha).
//!
//! The traversal is Gaussian-major within a tile: for each Gaussian (front to back) only the rows and,
//! per row, only the span of columns where alpha can reach 1/255 are visited (solved from the conic in
//! closed form, padded by a pixel, then every pixel applies the exact test), and finished pixels drop out
//! of per-row bit masks. The work is thus proportional to the pixel/Gaussian pairs that matter.
//! [`traverse_tile`] is shared by rendering and lifting through the [`Sink`] trait.

use super::project::{Splat, ALPHA_MAX, ALPHA_MIN, TILE, T_MIN};
use super::real::{c, Real};
use super::tiles::{SyncPtr, TileBins};
use rayon::prelude::*;

pub const TILE_PIXELS: usize = (TILE * TILE) as usize;

/// The pixels of one tile inside the image.
#[derive(Clone, Copy, Debug)]
pub struct TileRect {
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
}

/// Receives every (pixel, Gaussian) pair that contributes, in front-to-back order per pixel.
pub trait Sink<R: Real> {
    /// Gaussian `g` contributes to tile pixel `p` (row * 16 + column) with weight `w = alpha * T`.
    fn hit(&mut self, p: usize, g: u32, splat: &Splat<R>, w: R);
}

/// Bits lo..=hi set (both < 32, lo <= hi).
#[inline(always)]
pub fn bit_range(lo: u32, hi: u32) -> u32 {
    let upper = if hi >= 31 {
        u32::MAX
    } else {
        (1u32 << (hi + 1)) - 1
    };
    upper & !((1u32 << lo) - 1)
}

/// Rows of the tile (a bit mask) whose pixel centres may lie in the support of `s`.
#[inline(always)]
pub fn row_mask<R: Real>(s: &Splat<R>, rect: &TileRect) -> u32 {
    let y_base = rect.y0 as f64 + 0.5;
    let my = s.mean[1].to_f64();
    let hh = s.half_height.to_f64() + 1.0;
    let lo = (my - hh - y_base).ceil().max(0.0);
    let hi = (my + hh - y_base).floor().min(rect.h as f64 - 1.0);
    if !(lo <= hi) {
        return 0;
    }
    bit_range(lo as u32, hi as u32)
}

/// Columns (a bit mask) of the row at vertical offset `dy = mean_y − py` where σ ≤ sigma_max may hold.
#[inline(always)]
pub fn column_mask<R: Real>(s: &Splat<R>, dy: R, rect: &TileRect) -> u32 {
    let [a, b, cc] = s.conic;
    // ½a dx² + b dy dx + ½c dy² ≤ σm  ⇔  a dx² + 2 b dy dx + (c dy² − 2σm) ≤ 0.
    let bdy = b * dy;
    let disc = bdy * bdy - a * (cc * dy * dy - c::<R>(2.0) * s.sigma_max);
    if !(disc >= R::ZERO) {
        return 0;
    }
    let sq = disc.sqrt();
    // px = mean_x − dx, column i has px = x0 + i + 0.5.
    let base = s.mean[0] - c::<R>(rect.x0 as f64 + 0.5);
    let lo = (base + (bdy - sq) / a).to_f64() - 1.0;
    let hi = (base + (bdy + sq) / a).to_f64() + 1.0;
    let lo = lo.ceil().max(0.0);
    let hi = hi.floor().min(rect.w as f64 - 1.0);
    if !(lo <= hi) {
        return 0;
    }
    bit_range(lo as u32, hi as u32)
}

/// σ at pixel offset (dx, dy) = mean − pixel centre.
#[inline(always)]
pub fn sigma_at<R: Real>(conic: &[R; 3], dx: R, dy: R) -> R {
    c::<R>(0.5) * (conic[0] * dx * dx + conic[2] * dy * dy) + conic[1] * dx * dy
}

/// Composites one tile front to back, reporting contributions to `sink`.
///
/// On return `trans[p]` holds the final transmittance of tile pixel `p` and `last[p]` the number of list
/// entries up to and including its last contributor (0 when nothing contributed).
pub fn traverse_tile<R: Real, S: Sink<R>>(
    splats: &[Splat<R>],
    list: &[u32],
    rect: &TileRect,
    sink: &mut S,
    trans: &mut [R; TILE_PIXELS],
    last: &mut [u32; TILE_PIXELS],
) {
    trans.fill(R::ONE);
    last.fill(0);
    let full_row = bit_range(0, rect.w - 1);
    let mut live = [0u32; TILE as usize];
    for row in live.iter_mut().take(rect.h as usize) {
        *row = full_row;
    }
    let mut rows_live = bit_range(0, rect.h - 1);
    let x_base = rect.x0 as f64 + 0.5;
    let y_base = rect.y0 as f64 + 0.5;
    let alpha_max: R = c(ALPHA_MAX);
    let alpha_min: R = c(ALPHA_MIN);
    let t_min: R = c(T_MIN);
    for (k, &g) in list.iter().enumerate() {
        let s = &splats[g as usize];
        let mut rows = row_mask(s, rect) & rows_live;
        while rows != 0 {
            let r = rows.trailing_zeros();
            rows &= rows - 1;
            let dy = s.mean[1] - c(y_base + r as f64);
            let mut cols = column_mask(s, dy, rect) & live[r as usize];
            while cols != 0 {
                let i = cols.trailing_zeros();
                cols &= cols - 1;
                let dx = s.mean[0] - c(x_base + i as f64);
                let sigma = sigma_at(&s.conic, dx, dy);
                if sigma < R::ZERO {
                    continue;
                }
                let alpha = (s.opacity * (-sigma).exp()).min(alpha_max);
                if alpha < alpha_min {
                    continue;
                }
                let p = (r * TILE + i) as usize;
                let t = trans[p];
                let next = t * (R::ONE - alpha);
                if next < t_min {
                    live[r as usize] &= !(1 << i);
                    continue;
                }
                sink.hit(p, g, s, alpha * t);
                trans[p] = next;
                last[p] = k as u32 + 1;
            }
            if live[r as usize] == 0 {
                rows_live &= !(1 << r);
            }
        }
        if rows_live == 0 {
            break;
        }
    }
}

/// Images produced by the forward rasteriser plus the per-pixel state the backward pass needs.
#[derive(Clone, Debug, Default)]
pub struct RasterOut<R> {
    pub rgb: Vec<R>,
    pub alpha: Vec<R>,
    pub depth: Vec<R>,
    pub extra: Vec<R>,
    /// Final transmittance per pixel (kept separately: 1 − alpha loses precision when T is tiny).
    pub t_final: Vec<R>,
    /// Per pixel: index + 1 in its tile list of the last contributing Gaussian (0 = none).
    pub last: Vec<u32>,
}

struct ColorSink<'a, R> {
    rgb: [R; 3 * TILE_PIXELS],
    depth: [R; TILE_PIXELS],
    /// Extra channels: values (N*C), channel count, and the output image written in place.
    values: &'a [R],
    channels: usize,
    extra_out: &'a SyncPtr<R>,
    rect: TileRect,
    width: u32,
}

impl<R: Real> Sink<R> for ColorSink<'_, R> {
    #[inline(always)]
    fn hit(&mut self, p: usize, g: u32, s: &Splat<R>, w: R) {
        self.rgb[3 * p] += w * s.color[0];
        self.rgb[3 * p + 1] += w * s.color[1];
        self.rgb[3 * p + 2] += w * s.color[2];
        self.depth[p] += w * s.depth;
        let ch = self.channels;
        if ch > 0 {
            let gp = self.rect.global(p, self.width);
            // SAFETY: tile pixels are disjoint between tiles, and one tile is handled by one thread.
            let out = unsafe { self.extra_out.slice_mut(gp * ch, ch) };
            let vals = &self.values[g as usize * ch..(g as usize + 1) * ch];
            for (o, &v) in out.iter_mut().zip(vals) {
                *o += w * v;
            }
        }
    }
}

/// Renders all tiles in parallel. `extra` = per-Gaussian values (N*C, Gaussian-major) and C.
pub fn rasterize<R: Real>(
    splats: &[Splat<R>],
    bins: &TileBins,
    width: u32,
    height: u32,
    background: [R; 3],
    extra: Option<(&[R], usize)>,
) -> RasterOut<R> {
    let npix = (width * height) as usize;
    let (values, channels) = extra.unwrap_or((&[], 0));
    let mut out = RasterOut {
        rgb: vec![R::ZERO; 3 * npix],
        alpha: vec![R::ZERO; npix],
        depth: vec![R::ZERO; npix],
        extra: vec![R::ZERO; channels * npix],
        t_final: vec![R::ZERO; npix],
        last: vec![0; npix],
    };
    let rgb_ptr = SyncPtr(out.rgb.as_mut_ptr());
    let alpha_ptr = SyncPtr(out.alpha.as_mut_ptr());
    let depth_ptr = SyncPtr(out.depth.as_mut_ptr());
    let extra_ptr = SyncPtr(out.extra.as_mut_ptr());
    let t_ptr = SyncPtr(out.t_final.as_mut_ptr());
    let last_ptr = SyncPtr(out.last.as_mut_ptr());
    (0..bins.num_tiles()).into_par_iter().for_each_init(
        || {
            (
                Box::new([R::ZERO; TILE_PIXELS]),
                Box::new([0u32; TILE_PIXELS]),
            )
        },
        |(trans, last), tile| {
            let rect = TileRect::new(tile, bins, width, height);
            let mut sink = ColorSink {
                rgb: [R::ZERO; 3 * TILE_PIXELS],
                depth: [R::ZERO; TILE_PIXELS],
                values,
                channels,
                extra_out: &extra_ptr,
                rect,
                width,
            };
            traverse_tile(splats, bins.list(tile), &rect, &mut sink, trans, last);
            for r in 0..rect.h as usize {
                for i in 0..rect.w as usize {
                    let p = r * TILE as usize + i;
                    let gp = rect.global(p, width);
                    let t = trans[p];
                    // SAFETY: pixel `gp` belongs to this tile only.
                    unsafe {
                        for ch in 0..3 {
                            rgb_ptr.write(3 * gp + ch, sink.rgb[3 * p + ch] + t * background[ch]);
                        }
                        alpha_ptr.write(gp, R::ONE - t);
                        depth_ptr.write(gp, sink.depth[p]);
                        t_ptr.write(gp, t);
                        last_ptr.write(gp, last[p]);
                    }
                }
            }
        },
    );
    out
}

#[cfg(test)]
mod tests {
    use super::super::gradcheck::camera;
    use super::super::project::CameraR;
    use super::super::{project_all, tiles, Params};
    use super::*;
    use rand::{Rng, SeedableRng};

    /// The tile renderer with its row/span culling must equal a brute-force compositor that visits every
    /// Gaussian covering a pixel's tile, in depth order, with the same rules.
    #[test]
    fn matches_brute_force_compositing() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(21);
        let cam = camera(53, 37, 40.0, [0.1, 0.05, 0.2]);
        let n = 400;
        let channels = 2;
        let mut means = vec![];
        let mut log_scales = vec![];
        let mut quats = vec![];
        let mut logits = vec![];
        let mut sh = vec![];
        for _ in 0..n {
            means.extend([
                rng.gen_range(-2.0..2.0),
                rng.gen_range(-1.5..1.5),
                rng.gen_range(-1.0..6.0),
            ]);
            for _ in 0..3 {
                log_scales.push(rng.gen_range(-4.0f64..-0.5));
            }
            for _ in 0..4 {
                quats.push(rng.gen_range(-1.0..1.0));
            }
            logits.push(rng.gen_range(-6.0..5.0));
            for _ in 0..12 {
                sh.push(rng.gen_range(-0.6..0.6));
            }
        }
        let extra: Vec<f64> = (0..n * channels).map(|_| rng.gen_range(0.0..1.0)).collect();
        let params = Params {
            sh_degree: 1,
            means: &means,
            log_scales: &log_scales,
            quats: &quats,
            opacity_logits: &logits,
            sh: &sh,
        };
        let camr = CameraR::<f64>::new(&cam);
        let splats = project_all(&params, &camr, true);
        let (tx, ty) = camr.tiles();
        let bins = tiles::bin(&splats, tx, ty);
        let bg = [0.1, 0.2, 0.3];
        let out = rasterize(
            &splats,
            &bins,
            cam.width,
            cam.height,
            bg,
            Some((&extra, channels)),
        );
        let mut order: Vec<usize> = (0..n).filter(|&i| splats[i].is_drawable()).collect();
        order.sort_by(|&a, &b| {
            splats[a]
                .depth
                .partial_cmp(&splats[b].depth)
                .unwrap()
                .then(a.cmp(&b))
        });
        let mut contributing_pairs = 0;
        for y in 0..cam.height {
            for x in 0..cam.width {
                let (tx, ty) = (x / TILE, y / TILE);
                let mut t = 1.0f64;
                let mut rgb = [0.0; 3];
                let mut depth = 0.0;
                let mut ex = vec![0.0; channels];
                let mut last = 0;
                let mut k = 0;
                for &i in &order {
                    let s = &splats[i];
                    if tx < s.tiles[0] || tx >= s.tiles[2] || ty < s.tiles[1] || ty >= s.tiles[3] {
                        continue;
                    }
                    k += 1;
                    let dx = s.mean[0] - (x as f64 + 0.5);
                    let dy = s.mean[1] - (y as f64 + 0.5);
                    let sigma = sigma_at(&s.conic, dx, dy);
                    let alpha = (s.opacity * (-sigma).exp()).min(ALPHA_MAX);
                    if sigma < 0.0 || alpha < ALPHA_MIN {
                        continue;
                    }
                    if t * (1.0 - alpha) < T_MIN {
                        break;
                    }
                    let w = alpha * t;
                    for c in 0..3 {
                        rgb[c] += w * s.color[c];
                    }
                    depth += w * s.depth;
                    for c in 0..channels {
                        ex[c] += w * extra[i * channels + c];
                    }
                    t *= 1.0 - alpha;
                    last = k;
                    contributing_pairs += 1;
                }
                let p = (y * cam.width + x) as usize;
                assert_eq!(out.last[p], last, "last contributor at ({x},{y})");
                assert!((out.t_final[p] - t).abs() < 1e-12);
                assert!((out.alpha[p] - (1.0 - t)).abs() < 1e-12);
                assert!((out.depth[p] - depth).abs() < 1e-12);
                for c in 0..3 {
                    assert!((out.rgb[3 * p + c] - (rgb[c] + t * bg[c])).abs() < 1e-12);
                }
                for c in 0..channels {
                    assert!((out.extra[channels * p + c] - ex[c]).abs() < 1e-12);
                }
            }
        }
        // The scene must exercise the interesting cases: many contributions, some saturated pixels.
        assert!(contributing_pairs > 5000, "{contributing_pairs}");
        assert!(out.t_final.iter().filter(|&&t| t < 1e-3).count() > 20);
        assert!(out.t_final.iter().filter(|&&t| t > 0.5).count() > 20);
    }
}
