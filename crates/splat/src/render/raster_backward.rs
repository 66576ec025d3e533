//! Backward of stage (c), as 3DGS/gsplat do it: per pixel, walk the contributors back to front starting
//! from the saved final transmittance and last-contributor index, recover each T by dividing out
//! (1 − alpha), and keep running sums of what lies behind the current Gaussian.
//!
//! Gradients are accumulated per Gaussian over the pixels of a tile, then added to a buffer owned by the
//! worker thread (no atomics, no contention); the buffers are summed at the end.

use super::project::{Splat, SplatGrad, ALPHA_MAX, ALPHA_MIN, TILE};
use super::raster::{column_mask, row_mask, sigma_at, TileRect, TILE_PIXELS};
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

/// Per-tile scratch reused across tiles of one worker.
struct Scratch<R> {
    trans: [R; TILE_PIXELS],
    buf_rgb: [R; 3 * TILE_PIXELS],
    buf_depth: [R; TILE_PIXELS],
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
                buf_rgb: [R::ZERO; 3 * TILE_PIXELS],
                buf_depth: [R::ZERO; TILE_PIXELS],
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

#[allow(clippy::too_many_arguments)]
#[inline(never)]
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
    // Pixels in decreasing order of their last contributor: a pixel joins the backward walk when the walk
    // reaches its last contributor.
    s.order.clear();
    for r in 0..rect.h as usize {
        for i in 0..rect.w as usize {
            let p = r * TILE as usize + i;
            let gp = rect.global(p, width);
            let last = fwd.last[gp];
            s.trans[p] = fwd.t_final[gp];
            s.buf_rgb[3 * p..3 * p + 3].fill(R::ZERO);
            s.buf_depth[p] = R::ZERO;
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
    let x_base = rect.x0 as f64 + 0.5;
    let y_base = rect.y0 as f64 + 0.5;
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
        let g = list[k] as usize;
        let sp = &splats[g];
        let mut rows = row_mask(sp, rect) & rows_active;
        if rows == 0 {
            continue;
        }
        let [ca, cb, cc] = sp.conic;
        let o = sp.opacity;
        let mut gr = SplatGrad::<R>::default();
        let mut touched = false;
        while rows != 0 {
            let r = rows.trailing_zeros();
            rows &= rows - 1;
            let dy = sp.mean[1] - c(y_base + r as f64);
            let mut cols = column_mask(sp, dy, rect) & active[r as usize];
            while cols != 0 {
                let i = cols.trailing_zeros();
                cols &= cols - 1;
                let dx = sp.mean[0] - c(x_base + i as f64);
                let sigma = sigma_at(&sp.conic, dx, dy);
                if sigma < R::ZERO {
                    continue;
                }
                let vis = (-sigma).exp();
                let raw_alpha = o * vis;
                let alpha = raw_alpha.min(alpha_max);
                if alpha < alpha_min {
                    continue;
                }
                touched = true;
                let p = (r * TILE + i) as usize;
                let gp = rect.global(p, width);
                let ra = R::ONE / (R::ONE - alpha);
                let t = s.trans[p] * ra;
                s.trans[p] = t;
                let fac = alpha * t;

                let v_rgb = &grads.rgb[3 * gp..3 * gp + 3];
                let mut v_alpha = R::ZERO;
                for ch in 0..3 {
                    gr.color[ch] += fac * v_rgb[ch];
                    v_alpha += (sp.color[ch] * t - s.buf_rgb[3 * p + ch] * ra) * v_rgb[ch];
                    s.buf_rgb[3 * p + ch] += sp.color[ch] * fac;
                }
                if let Some(vd) = grads.depth {
                    let vd = vd[gp];
                    gr.depth += fac * vd;
                    v_alpha += (sp.depth * t - s.buf_depth[p] * ra) * vd;
                    s.buf_depth[p] += sp.depth * fac;
                }
                if let Some(ve) = extra_grad {
                    let ve = &ve[gp * channels..(gp + 1) * channels];
                    let vals = &values[g * channels..(g + 1) * channels];
                    let buf = &mut s.buf_extra[p * channels..(p + 1) * channels];
                    let out = &mut acc.extra[g * channels..(g + 1) * channels];
                    let mut va = R::ZERO;
                    for ch in 0..channels {
                        let v = ve[ch];
                        out[ch] += fac * v;
                        va += (vals[ch] * t - buf[ch] * ra) * v;
                        buf[ch] += vals[ch] * fac;
                    }
                    v_alpha += va;
                }
                // The final transmittance (alpha output and background) depends on this alpha too.
                let t_final = fwd.t_final[gp];
                let mut v_t_final =
                    background[0] * v_rgb[0] + background[1] * v_rgb[1] + background[2] * v_rgb[2];
                if let Some(va) = grads.alpha {
                    v_t_final -= va[gp];
                }
                v_alpha -= t_final * ra * v_t_final;

                if raw_alpha <= alpha_max {
                    let v_sigma = -raw_alpha * v_alpha;
                    gr.conic[0] += half * v_sigma * dx * dx;
                    gr.conic[1] += v_sigma * dx * dy;
                    gr.conic[2] += half * v_sigma * dy * dy;
                    gr.mean[0] += v_sigma * (ca * dx + cb * dy);
                    gr.mean[1] += v_sigma * (cb * dx + cc * dy);
                    gr.opacity += vis * v_alpha;
                }
            }
        }
        if touched {
            let a = &mut acc.splats[g];
            for ch in 0..3 {
                a.color[ch] += gr.color[ch];
                a.conic[ch] += gr.conic[ch];
            }
            a.mean[0] += gr.mean[0];
            a.mean[1] += gr.mean[1];
            a.opacity += gr.opacity;
            a.depth += gr.depth;
        }
    }
}
