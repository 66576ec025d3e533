//! Backward of stage (c), as 3DGS/gsplat do it: per pixel, walk the contributors back to front starting
//! from the saved final transmittance and last-contributor index, recover each T by dividing out
//! (1 − alpha), and keep running sums of what lies behind the current Gaussian.
//!
//! Gradients are accumulated per Gaussian over the pixels of a tile, then added to a buffer owned by the
//! worker thread (no atomics, no contention); the buffers are summed at the end.

use super::project::{Splat, SplatGrad, ALPHA_MAX, ALPHA_MIN, TILE};
use super::raster::{
    column_mask, has_avx2, prefetch, row_mask, sigma_at, TileRect, PREFETCH_AHEAD, SEG, TILE_PIXELS,
};
use super::real::{c, Real};
use super::tiles::TileBins;
use rayon::prelude::*;
use std::sync::Mutex;

/// Gradients of the loss with respect to the rendered images (same layouts as the outputs).
pub struct ImageGrads<'a, R> {
    pub rgb: &'a [R],
    pub alpha: Option<&'a [R]>,
    pub depth: Option<&'a [R]>,
    pub extra: Option<&'a [R]>,
}

/// Per-pixel state saved by the forward pass.
#[derive(Clone, Copy)]
pub struct SavedPixels<'a, R> {
    pub t_final: &'a [R],
    pub last: &'a [u32],
}

/// Gradients with respect to the projected splats, plus the extra channels' values.
pub struct RasterGrads<R> {
    pub splats: Vec<SplatGrad<R>>,
    /// N*C, empty when no extra-channel gradient was given.
    pub extra: Vec<R>,
}

struct ThreadGrads<R> {
    splats: Vec<SplatGrad<R>>,
    extra: Vec<R>,
}

/// Per-tile scratch reused across tiles of one worker (structure of arrays over the 256 tile pixels).
struct Scratch<R> {
    trans: [R; TILE_PIXELS],
    /// Colour (3) and depth composited behind the current Gaussian.
    behind: [[R; TILE_PIXELS]; 4],
    v_color: [[R; TILE_PIXELS]; 3],
    v_depth: [R; TILE_PIXELS],
    /// T_final · dL/dT_final per pixel: each alpha enters the final T.
    v_final: [R; TILE_PIXELS],
    buf_extra: Vec<R>,
    order: Vec<(u32, u16)>,
}

#[allow(clippy::too_many_arguments)]
pub fn rasterize_backward<R: Real>(
    splats: &[Splat<R>],
    bins: &TileBins,
    width: u32,
    height: u32,
    background: [R; 3],
    extra: Option<(&[R], usize)>,
    fwd: SavedPixels<'_, R>,
    grads: &ImageGrads<'_, R>,
) -> RasterGrads<R> {
    let n = splats.len();
    let (values, channels) = extra.unwrap_or((&[], 0));
    let extra_grad = grads.extra.filter(|_| channels > 0);
    let extra_len = if extra_grad.is_some() {
        n * channels
    } else {
        0
    };
    let slots: Vec<Mutex<Option<ThreadGrads<R>>>> = (0..rayon::current_num_threads().max(1))
        .map(|_| Mutex::new(None))
        .collect();

    (0..bins.num_tiles()).into_par_iter().for_each_init(
        || {
            Box::new(Scratch {
                trans: [R::ZERO; TILE_PIXELS],
                behind: [[R::ZERO; TILE_PIXELS]; 4],
                v_color: [[R::ZERO; TILE_PIXELS]; 3],
                v_depth: [R::ZERO; TILE_PIXELS],
                v_final: [R::ZERO; TILE_PIXELS],
                buf_extra: vec![
                    R::ZERO;
                    if extra_grad.is_some() {
                        channels * TILE_PIXELS
                    } else {
                        0
                    }
                ],
                order: Vec::with_capacity(TILE_PIXELS),
            })
        },
        |scratch, tile| {
            let list = bins.list(tile);
            if list.is_empty() {
                return;
            }
            let slot = rayon::current_thread_index().unwrap_or(0) % slots.len();
            // Only this worker ever locks this slot, so the lock is uncontended.
            let mut guard = slots[slot].lock().unwrap_or_else(|e| e.into_inner());
            let acc = guard.get_or_insert_with(|| ThreadGrads {
                splats: vec![SplatGrad::default(); n],
                extra: vec![R::ZERO; extra_len],
            });
            let rect = TileRect::new(tile, bins, width, height);
            backward_tile(
                splats, list, &rect, width, background, values, channels, extra_grad, fwd, grads,
                scratch, acc,
            );
        },
    );

    // Sum the per-thread buffers.
    let mut parts: Vec<ThreadGrads<R>> = slots
        .into_iter()
        .filter_map(|m| m.into_inner().unwrap_or_else(|e| e.into_inner()))
        .collect();
    let Some(mut total) = parts.pop() else {
        return RasterGrads {
            splats: vec![SplatGrad::default(); n],
            extra: vec![R::ZERO; extra_len],
        };
    };
    for part in &parts {
        total
            .splats
            .par_iter_mut()
            .zip(part.splats.par_iter())
            .for_each(|(t, p)| {
                for a in 0..2 {
                    t.mean[a] += p.mean[a];
                }
                for a in 0..3 {
                    t.conic[a] += p.conic[a];
                    t.color[a] += p.color[a];
                }
                t.opacity += p.opacity;
                t.depth += p.depth;
            });
        total
            .extra
            .par_chunks_mut(4096)
            .zip(part.extra.par_chunks(4096))
            .for_each(|(t, p)| {
                for (a, b) in t.iter_mut().zip(p) {
                    *a += *b;
                }
            });
    }
    RasterGrads {
        splats: total.splats,
        extra: total.extra,
    }
}

/// Per-lane sums of one Gaussian's gradients over the segments it touches in a tile.
#[derive(Clone, Copy)]
struct LaneGrads<R> {
    color: [[R; SEG]; 3],
    depth: [R; SEG],
    conic: [[R; SEG]; 3],
    mean: [[R; SEG]; 2],
    opacity: [R; SEG],
}

impl<R: Real> LaneGrads<R> {
    fn zero() -> Self {
        Self {
            color: [[R::ZERO; SEG]; 3],
            depth: [R::ZERO; SEG],
            conic: [[R::ZERO; SEG]; 3],
            mean: [[R::ZERO; SEG]; 2],
            opacity: [R::ZERO; SEG],
        }
    }
}

#[inline(always)]
fn lane_sum<R: Real>(v: &[R; SEG]) -> R {
    let mut s = R::ZERO;
    for x in v {
        s += *x;
    }
    s
}

#[allow(clippy::too_many_arguments)]
fn backward_tile<R: Real>(
    splats: &[Splat<R>],
    list: &[u32],
    rect: &TileRect,
    width: u32,
    background: [R; 3],
    values: &[R],
    channels: usize,
    extra_grad: Option<&[R]>,
    fwd: SavedPixels<'_, R>,
    grads: &ImageGrads<'_, R>,
    s: &mut Scratch<R>,
    acc: &mut ThreadGrads<R>,
) {
    #[cfg(target_arch = "x86_64")]
    if has_avx2() {
        // SAFETY: the CPU supports the features `backward_tile_avx2` is compiled for.
        return unsafe {
            backward_tile_avx2(
                splats, list, rect, width, background, values, channels, extra_grad, fwd, grads, s,
                acc,
            )
        };
    }
    backward_tile_impl(
        splats, list, rect, width, background, values, channels, extra_grad, fwd, grads, s, acc,
    )
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[allow(clippy::too_many_arguments)]
unsafe fn backward_tile_avx2<R: Real>(
    splats: &[Splat<R>],
    list: &[u32],
    rect: &TileRect,
    width: u32,
    background: [R; 3],
    values: &[R],
    channels: usize,
    extra_grad: Option<&[R]>,
    fwd: SavedPixels<'_, R>,
    grads: &ImageGrads<'_, R>,
    s: &mut Scratch<R>,
    acc: &mut ThreadGrads<R>,
) {
    backward_tile_impl(
        splats, list, rect, width, background, values, channels, extra_grad, fwd, grads, s, acc,
    )
}

#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn backward_tile_impl<R: Real>(
    splats: &[Splat<R>],
    list: &[u32],
    rect: &TileRect,
    width: u32,
    background: [R; 3],
    values: &[R],
    channels: usize,
    extra_grad: Option<&[R]>,
    fwd: SavedPixels<'_, R>,
    grads: &ImageGrads<'_, R>,
    s: &mut Scratch<R>,
    acc: &mut ThreadGrads<R>,
) {
    // Per-pixel state in structure-of-arrays form. Pixels join the backward walk when it reaches their
    // last contributor, so they are ordered by decreasing last index.
    s.order.clear();
    for r in 0..TILE as usize {
        for i in 0..TILE as usize {
            let p = r * TILE as usize + i;
            s.behind[0][p] = R::ZERO;
            s.behind[1][p] = R::ZERO;
            s.behind[2][p] = R::ZERO;
            s.behind[3][p] = R::ZERO;
            if r >= rect.h as usize || i >= rect.w as usize {
                s.trans[p] = R::ONE;
                s.v_color[0][p] = R::ZERO;
                s.v_color[1][p] = R::ZERO;
                s.v_color[2][p] = R::ZERO;
                s.v_depth[p] = R::ZERO;
                s.v_final[p] = R::ZERO;
                continue;
            }
            let gp = rect.global(p, width);
            let t_final = fwd.t_final[gp];
            s.trans[p] = t_final;
            let v = &grads.rgb[3 * gp..3 * gp + 3];
            s.v_color[0][p] = v[0];
            s.v_color[1][p] = v[1];
            s.v_color[2][p] = v[2];
            s.v_depth[p] = grads.depth.map_or(R::ZERO, |d| d[gp]);
            // Every alpha also changes the final T: d out/d T_final = background·v_rgb − v_alpha.
            let v_alpha_out = grads.alpha.map_or(R::ZERO, |a| a[gp]);
            s.v_final[p] = t_final
                * (v_alpha_out
                    - background[0] * v[0]
                    - background[1] * v[1]
                    - background[2] * v[2]);
            let last = fwd.last[gp];
            if last > 0 {
                s.order.push((last, p as u16));
            }
        }
    }
    if s.order.is_empty() {
        return;
    }
    if extra_grad.is_some() {
        s.buf_extra.fill(R::ZERO);
    }
    s.order.sort_unstable_by(|a, b| b.cmp(a));
    let mut next_join = 0;
    let mut active = [0u32; TILE as usize];
    let mut rows_active = 0u32;
    let xs = rect.segment_xs::<R>();
    let alpha_max: R = c(ALPHA_MAX);
    let alpha_min: R = c(ALPHA_MIN);
    let half: R = c(0.5);
    let max_last = s.order[0].0 as usize;

    for k in (0..max_last).rev() {
        while next_join < s.order.len() && s.order[next_join].0 as usize > k {
            let p = s.order[next_join].1 as u32;
            active[(p / TILE) as usize] |= 1 << (p % TILE);
            rows_active |= 1 << (p / TILE);
            next_join += 1;
        }
        if k >= PREFETCH_AHEAD {
            prefetch(&splats[list[k - PREFETCH_AHEAD] as usize]);
        }
        let g = list[k] as usize;
        let sp = &splats[g];
        let mut rows = row_mask(sp, rect) & rows_active;
        if rows == 0 {
            continue;
        }
        let cols = column_mask(sp, rect);
        let [ca, cb, cc] = sp.conic;
        let o = sp.opacity;
        let mut lg = LaneGrads::<R>::zero();
        let mut touched = false;
        while rows != 0 {
            let r = rows.trailing_zeros() as usize;
            rows &= rows - 1;
            let dy = sp.mean[1] - c((rect.y0 as usize + r) as f64 + 0.5);
            for h in 0..2 {
                let seg_active = (active[r] & cols) >> (h * SEG) & 0xff;
                if seg_active == 0 {
                    continue;
                }
                let p0 = r * TILE as usize + h * SEG;
                let x = &xs[h];
                // Pass 1: alphas, recovered T and the colour/depth/background part of dL/dalpha.
                let mut dx = [R::ZERO; SEG];
                let mut vis = [R::ZERO; SEG];
                let mut alpha = [R::ZERO; SEG];
                let mut ra = [R::ZERO; SEG];
                let mut t_new = [R::ZERO; SEG];
                let mut v_alpha = [R::ZERO; SEG];
                let mut act_bits = 0u32;
                for l in 0..SEG {
                    let p = p0 + l;
                    dx[l] = sp.mean[0] - x[l];
                    let sigma = sigma_at(&sp.conic, dx[l], dy);
                    vis[l] = (-sigma).exp_fast();
                    alpha[l] = (o * vis[l]).min(alpha_max);
                    let act =
                        (seg_active >> l) & 1 != 0 && sigma >= R::ZERO && alpha[l] >= alpha_min;
                    act_bits |= (act as u32) << l;
                    ra[l] = R::ONE / (R::ONE - alpha[l]);
                    t_new[l] = s.trans[p] * ra[l];
                    v_alpha[l] = (sp.color[0] * t_new[l] - s.behind[0][p] * ra[l])
                        * s.v_color[0][p]
                        + (sp.color[1] * t_new[l] - s.behind[1][p] * ra[l]) * s.v_color[1][p]
                        + (sp.color[2] * t_new[l] - s.behind[2][p] * ra[l]) * s.v_color[2][p]
                        + (sp.depth * t_new[l] - s.behind[3][p] * ra[l]) * s.v_depth[p]
                        + s.v_final[p] * ra[l];
                }
                if act_bits == 0 {
                    continue;
                }
                touched = true;
                // Pass 2 (only with extra channels): their part of dL/dalpha and their gradients.
                if let Some(ve) = extra_grad {
                    let vals = &values[g * channels..(g + 1) * channels];
                    let mut bits = act_bits;
                    while bits != 0 {
                        let l = bits.trailing_zeros() as usize;
                        bits &= bits - 1;
                        let p = p0 + l;
                        let gp = rect.global(p, width);
                        let ve = &ve[gp * channels..(gp + 1) * channels];
                        let buf = &mut s.buf_extra[p * channels..(p + 1) * channels];
                        let out = &mut acc.extra[g * channels..(g + 1) * channels];
                        let fac = alpha[l] * t_new[l];
                        let mut va = R::ZERO;
                        for ch in 0..channels {
                            let v = ve[ch];
                            out[ch] += fac * v;
                            va += (vals[ch] * t_new[l] - buf[ch] * ra[l]) * v;
                            buf[ch] += vals[ch] * fac;
                        }
                        v_alpha[l] += va;
                    }
                }
                // Pass 3: state updates and gradient sums, masked to the active lanes.
                for l in 0..SEG {
                    let p = p0 + l;
                    let act = (act_bits >> l) & 1 != 0;
                    let fac = alpha[l] * t_new[l];
                    s.trans[p] = if act { t_new[l] } else { s.trans[p] };
                    let fac = if act { fac } else { R::ZERO };
                    for ch in 0..3 {
                        s.behind[ch][p] += sp.color[ch] * fac;
                        lg.color[ch][l] += fac * s.v_color[ch][p];
                    }
                    s.behind[3][p] += sp.depth * fac;
                    lg.depth[l] += fac * s.v_depth[p];
                    // Where alpha was clamped at 0.99 it does not depend on σ or the opacity.
                    let free = act && o * vis[l] <= alpha_max;
                    let v_sigma = if free {
                        -(o * vis[l]) * v_alpha[l]
                    } else {
                        R::ZERO
                    };
                    let d = dx[l];
                    lg.conic[0][l] += v_sigma * d * d;
                    lg.conic[1][l] += v_sigma * d * dy;
                    lg.conic[2][l] += v_sigma * dy * dy;
                    lg.mean[0][l] += v_sigma * (ca * d + cb * dy);
                    lg.mean[1][l] += v_sigma * (cb * d + cc * dy);
                    lg.opacity[l] += if free { vis[l] * v_alpha[l] } else { R::ZERO };
                }
            }
        }
        if touched {
            let a = &mut acc.splats[g];
            for ch in 0..3 {
                a.color[ch] += lane_sum(&lg.color[ch]);
            }
            a.depth += lane_sum(&lg.depth);
            a.conic[0] += half * lane_sum(&lg.conic[0]);
            a.conic[1] += lane_sum(&lg.conic[1]);
            a.conic[2] += half * lane_sum(&lg.conic[2]);
            a.mean[0] += lane_sum(&lg.mean[0]);
            a.mean[1] += lane_sum(&lg.mean[1]);
            a.opacity += lane_sum(&lg.opacity);
        }
    }
}
