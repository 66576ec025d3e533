//! Stage (c): per-tile front-to-back compositing, with the exact rules of 3DGS/gsplat:
//! - pixel centres at (i + 0.5, j + 0.5); σ = ½(a dx² + c dy²) + b dx dy with d = mean − pixel;
//! - skip when σ < 0 or alpha = min(0.99, o·exp(−σ)) < 1/255;
//! - a pixel is finished (this Gaussian not counted) when T·(1 − alpha) < 1e-4;
//! - otherwise the Gaussian contributes with weight alpha·T and T ← T·(1 − alpha).
//!
//! The traversal is Gaussian-major within a tile: for each Gaussian (front to back) only the rows and
//! half-rows ("segments" of 8 pixels) inside the bounding box of its alpha ≥ 1/255 region (padded by a
//! pixel; every pixel then applies the exact test) and still unfinished are visited. A segment is
//! processed branch-free over its 8 lanes so the compiler vectorises it (the tile loops are compiled a
//! second time for AVX2+FMA and picked at run time). Finished pixels drop out of per-row bit masks.
//! [`traverse_tile`] is shared by rendering and lifting through the [`Sink`] trait.

use super::cpu::{dispatch, is_f32, prefetch, Kernel};
use super::project::{Splat, TILE, T_MIN};
use super::real::{c, Real};
use super::segment::{
    bit_range, column_mask, lane_alpha, row_mask, LaneAlpha, TileRect, PREFETCH_AHEAD, SEG,
    TILE_PIXELS,
};
use super::tiles::{SyncPtr, TileBins};
use rayon::prelude::*;

/// Receives the contributions of one Gaussian to one segment (8 pixels of a tile row), front to back.
pub trait Sink<R: Real> {
    /// Tile pixels `p0..p0+8`: lane `l` got weight `w[l] = alpha·T` from Gaussian `g` (entry `k` of the
    /// tile's list) where bit `l` of `hits` is set (`w` is 0 elsewhere).
    fn segment(&mut self, p0: usize, k: usize, g: u32, splat: &Splat<R>, w: &[R; SEG], hits: u32);
}

/// Front-to-back step of one Gaussian over one segment. Updates `trans` and writes the weights; returns
/// (contributing lanes, lanes that just finished).
#[inline(always)]
fn forward_segment<R: Real, const SIMD: bool>(
    s: &Splat<R>,
    dy: R,
    xs: &[R; SEG],
    trans: &mut [R; SEG],
    live: u32,
    w: &mut [R; SEG],
) -> (u32, u32) {
    #[cfg(target_arch = "x86_64")]
    if SIMD && is_f32::<R>() {
        // SAFETY: R is f32, so the casts are between identical types; SIMD is only set in code compiled
        // for AVX2+FMA that runs after the CPU check.
        unsafe {
            return super::simd::forward_segment(
                &*(s as *const Splat<R> as *const Splat<f32>),
                dy.to_f64() as f32,
                &*(xs as *const [R; SEG] as *const [f32; SEG]),
                &mut *(trans as *mut [R; SEG] as *mut [f32; SEG]),
                live,
                &mut *(w as *mut [R; SEG] as *mut [f32; SEG]),
            );
        }
    }
    let t_min: R = c(T_MIN);
    let mut hits = 0u32;
    let mut stops = 0u32;
    for l in 0..SEG {
        let LaneAlpha { alpha, counts, .. } = lane_alpha(s, xs[l], dy);
        let valid = (live >> l) & 1 != 0 && counts;
        let t = trans[l];
        let next = t * (R::ONE - alpha);
        let stop = valid && next < t_min;
        let hit = valid && !stop;
        w[l] = if hit { alpha * t } else { R::ZERO };
        trans[l] = if hit { next } else { t };
        hits |= (hit as u32) << l;
        stops |= (stop as u32) << l;
    }
    (hits, stops)
}

/// One tile composited front to back, reporting contributions to `sink` (run by [`traverse_tile`]).
///
/// On return `trans[p]` holds the final transmittance of tile pixel `p` and `last[p]` the number of list
/// entries up to and including its last contributor (0 when nothing contributed).
pub(crate) struct Traversal<'a, R, S> {
    pub splats: &'a [Splat<R>],
    /// The tile's list, front to back.
    pub list: &'a [u32],
    pub rect: &'a TileRect,
    pub sink: &'a mut S,
    pub trans: &'a mut [R; TILE_PIXELS],
    pub last: &'a mut [u32; TILE_PIXELS],
}

/// Composites one tile (see [`Traversal`]).
pub(crate) fn traverse_tile<R: Real, S: Sink<R>>(t: Traversal<'_, R, S>) {
    dispatch(t)
}

impl<R: Real, S: Sink<R>> Kernel for Traversal<'_, R, S> {
    type Output = ();

    #[inline(always)]
    fn run<const SIMD: bool>(self) {
        // The buffers go in as separate arguments: that tells the compiler they do not alias, which
        // struct fields would not.
        traverse::<R, S, SIMD>(
            self.splats,
            self.list,
            self.rect,
            self.sink,
            self.trans,
            self.last,
        )
    }
}

#[inline(always)]
fn traverse<R: Real, S: Sink<R>, const SIMD: bool>(
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
    let xs = rect.segment_xs::<R>();
    let mut w = [R::ZERO; SEG];
    for (k, &g) in list.iter().enumerate() {
        if let Some(&ahead) = list.get(k + PREFETCH_AHEAD) {
            prefetch(&splats[ahead as usize]);
        }
        let s = &splats[g as usize];
        let mut rows = row_mask(s, rect) & rows_live;
        if rows == 0 {
            continue;
        }
        let cols = column_mask(s, rect);
        // The segments of the rows the splat may cover, skipping finished pixels. Written out here and in
        // the backward pass: a shared visitor taking a closure cost ~5% more instructions in both loops.
        while rows != 0 {
            let r = rows.trailing_zeros() as usize;
            rows &= rows - 1;
            let dy = s.mean[1] - c((rect.y0 as usize + r) as f64 + 0.5);
            for h in 0..2 {
                let seg_live = (live[r] & cols) >> (h * SEG) & 0xff;
                if seg_live == 0 {
                    continue;
                }
                let p0 = r * TILE as usize + h * SEG;
                let t: &mut [R; SEG] = (&mut trans[p0..p0 + SEG]).try_into().unwrap();
                let (hits, stops) = forward_segment::<R, SIMD>(s, dy, &xs[h], t, seg_live, &mut w);
                live[r] &= !(stops << (h * SEG));
                if hits != 0 {
                    let lst: &mut [u32; SEG] = (&mut last[p0..p0 + SEG]).try_into().unwrap();
                    let kk = k as u32 + 1;
                    for l in 0..SEG {
                        // Branch-free select (all ones where lane l missed) so this vectorises.
                        let keep = ((hits >> l) & 1).wrapping_sub(1);
                        lst[l] = (lst[l] & keep) | (kk & !keep);
                    }
                    sink.segment(p0, k, g, s, &w, hits);
                }
            }
            if live[r] == 0 {
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

/// Accumulates colour, depth (structure of arrays over the tile) and extra channels.
struct ColorSink<'a, R> {
    r: [R; TILE_PIXELS],
    g: [R; TILE_PIXELS],
    b: [R; TILE_PIXELS],
    d: [R; TILE_PIXELS],
    /// Extra channels: values (N*C), channel count, and the output image written in place.
    values: &'a [R],
    channels: usize,
    extra_out: &'a SyncPtr<R>,
    rect: TileRect,
    width: u32,
    /// Per segment of the tile, the lanes that composite the extra channels (all, unless `ExtraAt`).
    want: [u32; TILE_PIXELS / SEG],
}

/// Image rows and columns (1 or 0 each) at whose crossings [`rasterize`] composites the extra channels;
/// elsewhere they stay 0. Lifting's render-back reads only a few pixels per grid cell.
pub type ExtraAt<'a> = (&'a [u32], &'a [u32]);

impl<R: Real> Sink<R> for ColorSink<'_, R> {
    #[inline(always)]
    fn segment(&mut self, p0: usize, _k: usize, g: u32, s: &Splat<R>, w: &[R; SEG], hits: u32) {
        for l in 0..SEG {
            self.r[p0 + l] += w[l] * s.color[0];
            self.g[p0 + l] += w[l] * s.color[1];
            self.b[p0 + l] += w[l] * s.color[2];
            self.d[p0 + l] += w[l] * s.depth;
        }
        let ch = self.channels;
        if ch > 0 {
            let vals = &self.values[g as usize * ch..(g as usize + 1) * ch];
            let mut bits = hits & self.want[p0 / SEG];
            while bits != 0 {
                let l = bits.trailing_zeros() as usize;
                bits &= bits - 1;
                let gp = self.rect.global(p0 + l, self.width);
                // SAFETY: tile pixels are disjoint between tiles, and one tile is handled by one thread.
                let out = unsafe { self.extra_out.slice_mut(gp * ch, ch) };
                for (o, &v) in out.iter_mut().zip(vals) {
                    *o += w[l] * v;
                }
            }
        }
    }
}

/// Renders all tiles in parallel. `extra` = per-Gaussian values (N*C, Gaussian-major) and C, composited
/// at every pixel or only at `extra_at`'s.
pub fn rasterize<R: Real>(
    splats: &[Splat<R>],
    bins: &TileBins,
    width: u32,
    height: u32,
    background: [R; 3],
    extra: Option<(&[R], usize)>,
    extra_at: Option<ExtraAt<'_>>,
) -> RasterOut<R> {
    if let Some((rows, cols)) = extra_at {
        assert!(
            rows.len() == height as usize && cols.len() == width as usize,
            "one flag per row and column"
        );
    }
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
            Box::new((
                [R::ZERO; TILE_PIXELS],
                [0u32; TILE_PIXELS],
                ColorSink {
                    r: [R::ZERO; TILE_PIXELS],
                    g: [R::ZERO; TILE_PIXELS],
                    b: [R::ZERO; TILE_PIXELS],
                    d: [R::ZERO; TILE_PIXELS],
                    values,
                    channels,
                    extra_out: &extra_ptr,
                    rect: TileRect {
                        x0: 0,
                        y0: 0,
                        w: 0,
                        h: 0,
                    },
                    width,
                    want: [u32::MAX; TILE_PIXELS / SEG],
                },
            ))
        },
        |scratch, tile| {
            let (trans, last, sink) = &mut **scratch;
            let rect = TileRect::new(tile, bins, width, height);
            sink.rect = rect;
            sink.r.fill(R::ZERO);
            sink.g.fill(R::ZERO);
            sink.b.fill(R::ZERO);
            sink.d.fill(R::ZERO);
            if let Some((rows, cols)) = extra_at {
                for (seg, lanes) in sink.want.iter_mut().enumerate() {
                    let (r, i0) = ((seg * SEG) / TILE as usize, (seg * SEG) % TILE as usize);
                    *lanes = 0;
                    if r < rect.h as usize && rows[rect.y0 as usize + r] != 0 {
                        for l in 0..SEG.min((rect.w as usize).saturating_sub(i0)) {
                            if cols[rect.x0 as usize + i0 + l] != 0 {
                                *lanes |= 1 << l;
                            }
                        }
                    }
                }
            }
            traverse_tile(Traversal {
                splats,
                list: bins.list(tile),
                rect: &rect,
                sink,
                trans,
                last,
            });
            for r in 0..rect.h as usize {
                for i in 0..rect.w as usize {
                    let p = r * TILE as usize + i;
                    let gp = rect.global(p, width);
                    let t = trans[p];
                    // SAFETY: pixel `gp` belongs to this tile only.
                    unsafe {
                        rgb_ptr.write(3 * gp, sink.r[p] + t * background[0]);
                        rgb_ptr.write(3 * gp + 1, sink.g[p] + t * background[1]);
                        rgb_ptr.write(3 * gp + 2, sink.b[p] + t * background[2]);
                        alpha_ptr.write(gp, R::ONE - t);
                        depth_ptr.write(gp, sink.d[p]);
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
    use super::super::project::{CameraR, ALPHA_MAX, ALPHA_MIN};
    use super::super::segment::sigma_at;
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
            None,
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
                    let [x0, y0, x1, y1] = s.tile_rect();
                    if tx < x0 || tx >= x1 || ty < y0 || ty >= y1 {
                        continue;
                    }
                    k += 1;
                    let dx = s.mean[0] - (x as f64 + 0.5);
                    let dy = s.mean[1] - (y as f64 + 0.5);
                    let sigma = sigma_at(&s.conic, dx, dy);
                    let alpha = (s.opacity * (-sigma).exp_fast()).min(ALPHA_MAX);
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
