//! Stage (c) on the GPU: front-to-back compositing per pixel and its backward, with the rules of
//! `render/raster.rs` (pixel centres at +0.5, skip σ < 0 or alpha < 1/255, alpha ≤ 0.99, stop before
//! T < 1e-4). One cube per 16x16 tile, one unit per pixel, each unit walking its tile's depth-sorted list
//! independently: no shared memory and no barriers.
//!
//! The backward walks each pixel's contributors back to front from the saved final T and last index and
//! adds the per-Gaussian gradients with f32 atomics (layout in `project.rs`).

use ::gpu::cubecl;
use cubecl::prelude::*;

use crate::render::{ALPHA_MAX, ALPHA_MIN, TILE, T_MIN};

/// σ of the Gaussian whose record starts at `s` at pixel centre (fx, fy), with d = mean − centre:
/// σ = ½(a dx² + c dy²) + b dx dy (the CPU's `sigma_at`). Returns (σ, dx, dy).
#[cube]
fn sigma_at(splats: &[f32], s: usize, fx: f32, fy: f32) -> (f32, f32, f32) {
    let dx = splats[s] - fx;
    let dy = splats[s + 1] - fy;
    let sigma =
        0.5f32 * (splats[s + 2] * dx * dx + splats[s + 4] * dy * dy) + splats[s + 3] * dx * dy;
    (sigma, dx, dy)
}

/// Forward. `channels` extra channels (`extra_vals` N*C) are composited over 0 into `extra` (H*W*C).
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
pub fn raster_forward(
    splats: &[f32],
    ids: &[u32],
    tile_start: &[u32],
    tile_end: &[u32],
    extra_vals: &[f32],
    width: u32,
    height: u32,
    tiles_x: u32,
    bg_r: f32,
    bg_g: f32,
    bg_b: f32,
    rgb: &mut [f32],
    alpha: &mut [f32],
    depth: &mut [f32],
    extra: &mut [f32],
    t_final: &mut [f32],
    last: &mut [u32],
    #[comptime] channels: u32,
) {
    let px = CUBE_POS_X * TILE + UNIT_POS_X;
    let py = CUBE_POS_Y * TILE + UNIT_POS_Y;
    if px < width && py < height {
        let p = (py * width + px) as usize;
        let c = channels as usize;
        for ch in 0..c {
            extra[p * c + ch] = 0.0;
        }
        let tile = (CUBE_POS_Y * tiles_x + CUBE_POS_X) as usize;
        let start = tile_start[tile];
        let end = tile_end[tile];
        let fx = px as f32 + 0.5;
        let fy = py as f32 + 0.5;
        let mut t = 1.0f32;
        let mut r = 0.0f32;
        let mut g = 0.0f32;
        let mut b = 0.0f32;
        let mut d = 0.0f32;
        let mut n_last = 0u32;
        for k in start..end {
            let s = ids[k as usize] as usize * 10;
            let (sigma, _dx, _dy) = sigma_at(splats, s, fx, fy);
            let a = f32::min(splats[s + 5] * (-sigma).exp(), ALPHA_MAX as f32);
            if sigma >= 0.0 && a >= ALPHA_MIN as f32 {
                let next = t * (1.0f32 - a);
                if next < T_MIN as f32 {
                    break;
                }
                let w = a * t;
                r += w * splats[s + 6];
                g += w * splats[s + 7];
                b += w * splats[s + 8];
                d += w * splats[s + 9];
                let gi = ids[k as usize] as usize;
                for ch in 0..c {
                    extra[p * c + ch] += w * extra_vals[gi * c + ch];
                }
                t = next;
                n_last = k - start + 1;
            }
        }
        rgb[3 * p] = r + t * bg_r;
        rgb[3 * p + 1] = g + t * bg_g;
        rgb[3 * p + 2] = b + t * bg_b;
        alpha[p] = 1.0f32 - t;
        depth[p] = d;
        t_final[p] = t;
        last[p] = n_last;
    }
}

/// Backward. `channels` is the extra channel count when their gradient is wanted, else 0;
/// `behind` is per-pixel scratch (H*W*C) for the extra channels composited behind the current Gaussian.
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
pub fn raster_backward(
    splats: &[f32],
    ids: &[u32],
    tile_start: &[u32],
    extra_vals: &[f32],
    width: u32,
    height: u32,
    tiles_x: u32,
    bg_r: f32,
    bg_g: f32,
    bg_b: f32,
    t_final: &[f32],
    last: &[u32],
    v_rgb: &[f32],
    v_alpha_out: &[f32],
    v_depth: &[f32],
    v_extra: &[f32],
    behind: &mut [f32],
    grads: &mut [Atomic<f32>],
    g_extra: &mut [Atomic<f32>],
    #[comptime] channels: u32,
) {
    let px = CUBE_POS_X * TILE + UNIT_POS_X;
    let py = CUBE_POS_Y * TILE + UNIT_POS_Y;
    if px < width && py < height {
        let p = (py * width + px) as usize;
        let c = channels as usize;
        for ch in 0..c {
            behind[p * c + ch] = 0.0;
        }
        let tile = (CUBE_POS_Y * tiles_x + CUBE_POS_X) as usize;
        let start = tile_start[tile];
        let fx = px as f32 + 0.5;
        let fy = py as f32 + 0.5;
        let mut t = t_final[p];
        let vr = v_rgb[3 * p];
        let vg = v_rgb[3 * p + 1];
        let vb = v_rgb[3 * p + 2];
        let vd = v_depth[p];
        // Every alpha also changes the final T: d out/d T_final = background·v_rgb − v_alpha.
        let v_final = t * (v_alpha_out[p] - bg_r * vr - bg_g * vg - bg_b * vb);
        let mut br = 0.0f32;
        let mut bgc = 0.0f32;
        let mut bb = 0.0f32;
        let mut bd = 0.0f32;
        let n_last = last[p];
        for j in 0..n_last {
            let k = (start + n_last - 1 - j) as usize;
            let gi = ids[k] as usize;
            let s = gi * 10;
            let (sigma, dx, dy) = sigma_at(splats, s, fx, fy);
            let ca = splats[s + 2];
            let cb = splats[s + 3];
            let cc = splats[s + 4];
            let o = splats[s + 5];
            let vis = (-sigma).exp();
            let a = f32::min(o * vis, ALPHA_MAX as f32);
            if sigma >= 0.0 && a >= ALPHA_MIN as f32 {
                let ra = 1.0f32 / (1.0f32 - a);
                let tn = t * ra;
                let cr = splats[s + 6];
                let cg = splats[s + 7];
                let cbl = splats[s + 8];
                let dep = splats[s + 9];
                let fac = a * tn;
                let mut v_alpha = (cr * tn - br * ra) * vr
                    + (cg * tn - bgc * ra) * vg
                    + (cbl * tn - bb * ra) * vb
                    + (dep * tn - bd * ra) * vd
                    + v_final * ra;
                for ch in 0..c {
                    let v = v_extra[p * c + ch];
                    let val = extra_vals[gi * c + ch];
                    g_extra[gi * c + ch].fetch_add(fac * v);
                    v_alpha += (val * tn - behind[p * c + ch] * ra) * v;
                    behind[p * c + ch] += val * fac;
                }
                t = tn;
                br += cr * fac;
                bgc += cg * fac;
                bb += cbl * fac;
                bd += dep * fac;
                grads[s + 6].fetch_add(fac * vr);
                grads[s + 7].fetch_add(fac * vg);
                grads[s + 8].fetch_add(fac * vb);
                grads[s + 9].fetch_add(fac * vd);
                // Where alpha was clamped at 0.99 it depends on neither σ nor the opacity.
                if o * vis <= ALPHA_MAX as f32 {
                    let v_sigma = -(o * vis) * v_alpha;
                    grads[s].fetch_add(v_sigma * (ca * dx + cb * dy));
                    grads[s + 1].fetch_add(v_sigma * (cb * dx + cc * dy));
                    grads[s + 2].fetch_add(0.5f32 * v_sigma * dx * dx);
                    grads[s + 3].fetch_add(v_sigma * dx * dy);
                    grads[s + 4].fetch_add(0.5f32 * v_sigma * dy * dy);
                    grads[s + 5].fetch_add(vis * v_alpha);
                }
            }
        }
    }
}

/// Per-tile list ranges from the tile-sorted keys: tile `t` owns `ids[start[t]..end[t]]` (both arrays
/// must be zeroed first).
#[cube(launch)]
pub fn tile_ranges(keys: &[u32], m: u32, start: &mut [u32], end: &mut [u32]) {
    let i = ABSOLUTE_POS as u32;
    if i < m {
        let t = keys[i as usize];
        if i == 0 || keys[(i - 1) as usize] != t {
            start[t as usize] = i;
        }
        if i + 1 == m || keys[(i + 1) as usize] != t {
            end[t as usize] = i + 1;
        }
    }
}

/// One (tile, Gaussian) pair per covered tile, Gaussians taken in depth order (`order`), written from
/// each Gaussian's offset: after a stable sort by tile, every tile's list is sorted by depth.
#[cube(launch)]
pub fn emit_pairs(
    order: &[u32],
    info: &[u32],
    offsets: &[u32],
    n: u32,
    tiles_x: u32,
    tile_keys: &mut [u32],
    ids: &mut [u32],
) {
    let j = ABSOLUTE_POS;
    if j < n as usize {
        let gi = order[j];
        let f = gi as usize * 8;
        if info[f + 6] > 0 {
            let mut o = offsets[j] as usize;
            for ty in info[f + 2]..info[f + 4] {
                for tx in info[f + 1]..info[f + 3] {
                    tile_keys[o] = ty * tiles_x + tx;
                    ids[o] = gi;
                    o += 1;
                }
            }
        }
    }
}

/// Gathers per-Gaussian values in depth order: `out[j] = info[order[j]].field`.
#[cube(launch)]
pub fn gather_info(order: &[u32], info: &[u32], n: u32, field: u32, out: &mut [u32]) {
    let j = ABSOLUTE_POS;
    if j < n as usize {
        out[j] = info[order[j] as usize * 8 + field as usize];
    }
}

/// Depth sort keys and identity values for the drawable Gaussians.
#[cube(launch)]
pub fn depth_keys(info: &[u32], n: u32, keys: &mut [u32], vals: &mut [u32]) {
    let i = ABSOLUTE_POS;
    if i < n as usize {
        keys[i] = info[i * 8 + 7];
        vals[i] = i as u32;
    }
}

/// Lifting (GaussianEditor's `apply_weights`, as `crate::lift`): the forward walk with T from 1, and at
/// every hit (an unweighted one) the pixel's C map values are added to the Gaussian's sums and its count
/// goes up by one.
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
pub fn lift_accumulate(
    splats: &[f32],
    ids: &[u32],
    tile_start: &[u32],
    tile_end: &[u32],
    map: &[f32],
    width: u32,
    height: u32,
    tiles_x: u32,
    sums: &mut [Atomic<f32>],
    counts: &mut [Atomic<u32>],
    #[comptime] channels: u32,
) {
    let px = CUBE_POS_X * TILE + UNIT_POS_X;
    let py = CUBE_POS_Y * TILE + UNIT_POS_Y;
    if px < width && py < height {
        let p = (py * width + px) as usize;
        let c = channels as usize;
        let tile = (CUBE_POS_Y * tiles_x + CUBE_POS_X) as usize;
        let fx = px as f32 + 0.5;
        let fy = py as f32 + 0.5;
        let mut t = 1.0f32;
        for k in tile_start[tile]..tile_end[tile] {
            let gi = ids[k as usize] as usize;
            let s = gi * 10;
            let (sigma, _dx, _dy) = sigma_at(splats, s, fx, fy);
            let a = f32::min(splats[s + 5] * (-sigma).exp(), ALPHA_MAX as f32);
            if sigma >= 0.0 && a >= ALPHA_MIN as f32 {
                let next = t * (1.0f32 - a);
                if next < T_MIN as f32 {
                    break;
                }
                counts[gi].fetch_add(1u32);
                for ch in 0..c {
                    sums[gi * c + ch].fetch_add(map[p * c + ch]);
                }
                t = next;
            }
        }
    }
}
