//! Backward of stage (c), as 3DGS/gsplat do it: per pixel, walk the contributors back to front starting
//! from the saved final transmittance and last-contributor index, recover each T by dividing out
//! (1 − alpha), and keep running sums of what lies behind the current Gaussian.
//!
//! Gradients are accumulated per Gaussian over the pixels of a tile, then added to a buffer owned by the
//! worker thread (no atomics, no contention); the buffers are summed at the end.

use super::cpu::{dispatch, is_f32, prefetch, Kernel};
use super::project::{Splat, SplatGrad, ALPHA_MAX, TILE};
use super::real::{c, Real};
use super::segment::{
    column_mask, lane_alpha, row_mask, LaneGrads, SegState, SegTemps, TileRect, PREFETCH_AHEAD,
    SEG, TILE_PIXELS,
};
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
    // Each slot owns a fixed, interleaved set of tiles walked in order and the slots are summed in order,
    // so gradients do not depend on thread scheduling (bit-identical reruns; resumable edits rely on it).
    // Twice as many slots as threads keep the interleaved sets balanced.
    let inputs = TileInputs {
        splats,
        width,
        background,
        values,
        channels,
        extra_grad,
        fwd,
        grads,
    };
    let stride = 2 * rayon::current_num_threads().max(1);
    let slots: Vec<Mutex<Option<ThreadGrads<R>>>> = (0..stride).map(|_| Mutex::new(None)).collect();
    let tiles = bins.num_tiles();

    (0..stride).into_par_iter().for_each(|slot| {
        let mut scratch = Box::new(Scratch {
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
        });
        let mut guard = slots[slot].lock().unwrap_or_else(|e| e.into_inner());
        for tile in (slot..tiles).step_by(stride) {
            let list = bins.list(tile);
            if list.is_empty() {
                continue;
            }
            let acc = guard.get_or_insert_with(|| ThreadGrads {
                splats: vec![SplatGrad::default(); n],
                extra: vec![R::ZERO; extra_len],
            });
            dispatch(BackwardTile {
                inputs: &inputs,
                list,
                rect: &TileRect::new(tile, bins, width, height),
                s: &mut scratch,
                acc,
            });
        }
    });

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

/// Views of the tile scratch for the segment starting at tile pixel `p0`.
#[inline(always)]
fn seg_state<R: Real>(s: &mut Scratch<R>, p0: usize) -> SegState<'_, R> {
    fn arr<R>(v: &[R; TILE_PIXELS], p0: usize) -> &[R; SEG] {
        v[p0..p0 + SEG].try_into().unwrap()
    }
    fn arr_mut<R>(v: &mut [R; TILE_PIXELS], p0: usize) -> &mut [R; SEG] {
        (&mut v[p0..p0 + SEG]).try_into().unwrap()
    }
    let [b0, b1, b2, b3] = &mut s.behind;
    SegState {
        trans: arr_mut(&mut s.trans, p0),
        behind: [
            arr_mut(b0, p0),
            arr_mut(b1, p0),
            arr_mut(b2, p0),
            arr_mut(b3, p0),
        ],
        v_color: [
            arr(&s.v_color[0], p0),
            arr(&s.v_color[1], p0),
            arr(&s.v_color[2], p0),
        ],
        v_depth: arr(&s.v_depth, p0),
        v_final: arr(&s.v_final, p0),
    }
}

/// Pass 1 of a backward segment: alphas, the recovered T before this Gaussian and the colour, depth and
/// final-T part of dL/dalpha. Returns the lanes where this Gaussian contributed in the forward pass.
#[inline(always)]
fn pass1<R: Real, const SIMD: bool>(
    sp: &Splat<R>,
    dy: R,
    xs: &[R; SEG],
    active: u32,
    st8: &SegState<'_, R>,
    tmp: &mut SegTemps<R>,
) -> u32 {
    #[cfg(target_arch = "x86_64")]
    if SIMD && is_f32::<R>() {
        // SAFETY: R is f32, so these are the same types; SIMD is only set in code compiled for AVX2+FMA
        // that runs after the CPU check.
        unsafe {
            return super::simd::backward_pass1(
                &*(sp as *const Splat<R> as *const Splat<f32>),
                dy.to_f64() as f32,
                &*(xs as *const [R; SEG] as *const [f32; SEG]),
                active,
                &*(st8 as *const SegState<'_, R> as *const SegState<'_, f32>),
                &mut *(tmp as *mut SegTemps<R> as *mut SegTemps<f32>),
            );
        }
    }
    let mut act_bits = 0u32;
    for l in 0..SEG {
        let a = lane_alpha(sp, xs[l], dy);
        (tmp.dx[l], tmp.vis[l], tmp.alpha[l]) = (a.dx, a.vis, a.alpha);
        let act = (active >> l) & 1 != 0 && a.counts;
        act_bits |= (act as u32) << l;
        tmp.ra[l] = R::ONE / (R::ONE - tmp.alpha[l]);
        let t = st8.trans[l] * tmp.ra[l];
        tmp.t_new[l] = t;
        let ra = tmp.ra[l];
        tmp.v_alpha[l] = (sp.color[0] * t - st8.behind[0][l] * ra) * st8.v_color[0][l]
            + (sp.color[1] * t - st8.behind[1][l] * ra) * st8.v_color[1][l]
            + (sp.color[2] * t - st8.behind[2][l] * ra) * st8.v_color[2][l]
            + (sp.depth * t - st8.behind[3][l] * ra) * st8.v_depth[l]
            + st8.v_final[l] * ra;
    }
    act_bits
}

/// Pass 3 of a backward segment: state updates (T, what lies behind) and the Gaussian's gradient sums,
/// masked to the contributing lanes.
#[inline(always)]
fn pass3<R: Real, const SIMD: bool>(
    sp: &Splat<R>,
    dy: R,
    act_bits: u32,
    st8: &mut SegState<'_, R>,
    tmp: &SegTemps<R>,
    lg: &mut LaneGrads<R>,
) {
    #[cfg(target_arch = "x86_64")]
    if SIMD && is_f32::<R>() {
        // SAFETY: as in `pass1`.
        unsafe {
            return super::simd::backward_pass3(
                &*(sp as *const Splat<R> as *const Splat<f32>),
                dy.to_f64() as f32,
                act_bits,
                &mut *(st8 as *mut SegState<'_, R> as *mut SegState<'_, f32>),
                &*(tmp as *const SegTemps<R> as *const SegTemps<f32>),
                &mut *(lg as *mut LaneGrads<R> as *mut LaneGrads<f32>),
            );
        }
    }
    let alpha_max: R = c(ALPHA_MAX);
    let o = sp.opacity;
    let [ca, cb, cc] = sp.conic;
    for l in 0..SEG {
        let act = (act_bits >> l) & 1 != 0;
        let fac = tmp.alpha[l] * tmp.t_new[l];
        st8.trans[l] = if act { tmp.t_new[l] } else { st8.trans[l] };
        let fac = if act { fac } else { R::ZERO };
        for ch in 0..3 {
            st8.behind[ch][l] += sp.color[ch] * fac;
            lg.color[ch][l] += fac * st8.v_color[ch][l];
        }
        st8.behind[3][l] += sp.depth * fac;
        lg.depth[l] += fac * st8.v_depth[l];
        // Where alpha was clamped at 0.99 it depends on neither σ nor the opacity.
        let free = act && o * tmp.vis[l] <= alpha_max;
        let v_sigma = if free {
            -(o * tmp.vis[l]) * tmp.v_alpha[l]
        } else {
            R::ZERO
        };
        let d = tmp.dx[l];
        lg.conic[0][l] += v_sigma * d * d;
        lg.conic[1][l] += v_sigma * d * dy;
        lg.conic[2][l] += v_sigma * dy * dy;
        lg.mean[0][l] += v_sigma * (ca * d + cb * dy);
        lg.mean[1][l] += v_sigma * (cb * d + cc * dy);
        lg.opacity[l] += if free {
            tmp.vis[l] * tmp.v_alpha[l]
        } else {
            R::ZERO
        };
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

/// What the backward pass of every tile reads.
#[derive(Clone, Copy)]
struct TileInputs<'a, R> {
    splats: &'a [Splat<R>],
    width: u32,
    background: [R; 3],
    /// Extra channels' values (N*C) and C (0 without extra channels).
    values: &'a [R],
    channels: usize,
    /// dL/d(extra image), when given and there are extra channels.
    extra_grad: Option<&'a [R]>,
    fwd: SavedPixels<'a, R>,
    grads: &'a ImageGrads<'a, R>,
}

/// The backward pass of one tile, adding its gradients to `acc`.
struct BackwardTile<'a, R> {
    inputs: &'a TileInputs<'a, R>,
    /// The tile's list, front to back.
    list: &'a [u32],
    rect: &'a TileRect,
    s: &'a mut Scratch<R>,
    acc: &'a mut ThreadGrads<R>,
}

impl<R: Real> Kernel for BackwardTile<'_, R> {
    type Output = ();

    #[inline(always)]
    fn run<const SIMD: bool>(self) {
        let i = self.inputs;
        // The buffers go in as separate arguments: that tells the compiler they do not alias, which
        // struct fields would not.
        backward_tile::<R, SIMD>(
            i.splats,
            self.list,
            self.rect,
            i.values,
            i.extra_grad,
            i,
            self.s,
            self.acc,
        )
    }
}

#[inline(always)]
fn backward_tile<R: Real, const SIMD: bool>(
    splats: &[Splat<R>],
    list: &[u32],
    rect: &TileRect,
    values: &[R],
    extra_grad: Option<&[R]>,
    inputs: &TileInputs<'_, R>,
    s: &mut Scratch<R>,
    acc: &mut ThreadGrads<R>,
) {
    let TileInputs {
        width,
        background,
        channels,
        fwd,
        grads,
        ..
    } = *inputs;
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
    let half: R = c(0.5);
    let max_last = s.order[0].0 as usize;
    let mut tmp = SegTemps::<R>::default();

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
        let mut lg = LaneGrads::<R>::zero();
        let mut touched = false;
        // The segments of the rows the splat may cover (the same walk as the forward pass's).
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
                let act_bits = {
                    let st8 = seg_state(s, p0);
                    pass1::<R, SIMD>(sp, dy, &xs[h], seg_active, &st8, &mut tmp)
                };
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
                        let (t_new, ra) = (tmp.t_new[l], tmp.ra[l]);
                        let fac = tmp.alpha[l] * t_new;
                        let mut va = R::ZERO;
                        for ch in 0..channels {
                            let v = ve[ch];
                            out[ch] += fac * v;
                            va += (vals[ch] * t_new - buf[ch] * ra) * v;
                            buf[ch] += vals[ch] * fac;
                        }
                        tmp.v_alpha[l] += va;
                    }
                }
                let mut st8 = seg_state(s, p0);
                pass3::<R, SIMD>(sp, dy, act_bits, &mut st8, &tmp, &mut lg);
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
