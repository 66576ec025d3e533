//! Stage (c) on the GPU: front-to-back compositing per pixel and its backward, with the rules of
//! `render/raster.rs` (pixel centres at +0.5, skip σ < 0 or alpha < 1/255, alpha ≤ 0.99, stop before
//! T < 1e-4). One cube per 16x16 tile; each unit owns a few pixels of one column (`ppu`, a launch-time
//! choice), and the cube walks the tile's depth-sorted list in step, one shared-memory batch of
//! Gaussians at a time (the gsplat/brush structure).
//!
//! The backward walks each pixel's contributors back to front from the saved final T and last index, the
//! tile's units in step over shared-memory batches of Gaussians, and adds the per-Gaussian gradients
//! with f32 atomics, summed over each unit's pixels first (layout in `project.rs`).

use ::gpu::cubecl;
use ::gpu::reduce::cube_max;
use cubecl::prelude::*;

use crate::render::{ALPHA_MAX, ALPHA_MIN, TILE, T_MIN};

/// σ and e^−σ of a Gaussian (mean (mx, my), conic (ca, cb, cc)) at pixel centre (fx, fy), with
/// d = mean − centre: σ = ½(a dx² + c dy²) + b dx dy (the CPU's `sigma_at`). Returns (σ, e^−σ, dx, dy).
#[cube]
pub(crate) fn falloff(
    mx: f32,
    my: f32,
    ca: f32,
    cb: f32,
    cc: f32,
    fx: f32,
    fy: f32,
) -> (f32, f32, f32, f32) {
    let dx = mx - fx;
    let dy = my - fy;
    let sigma = 0.5f32 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy;
    (sigma, (-sigma).exp(), dx, dy)
}

/// The cube's tile: its index in the tile lists, `tiles_x` tiles per row of the image.
#[cube]
pub(crate) fn cube_tile(tiles_x: u32) -> usize {
    (CUBE_POS_Y * tiles_x + CUBE_POS_X) as usize
}

/// The cube's tile's entries of the depth-sorted list: (first entry, entry count).
#[cube]
pub(crate) fn tile_range(tile_start: &[u32], tile_end: &[u32], tiles_x: u32) -> (u32, u32) {
    let tile = cube_tile(tiles_x);
    let start = tile_start[tile];
    (start, tile_end[tile] - start)
}

/// [`tile_range`] of the cube's image (`CUBE_POS_Z`): image 0's lists, or image 1's (`*_b`) in a pair.
#[cube]
fn image_tile_range(
    tile_start: &[u32],
    tile_end: &[u32],
    tile_start_b: &[u32],
    tile_end_b: &[u32],
    tiles_x: u32,
) -> (u32, u32) {
    let tile = cube_tile(tiles_x);
    let second = CUBE_POS_Z != 0;
    let start = select(second, tile_start_b[tile], tile_start[tile]);
    (
        start,
        select(second, tile_end_b[tile], tile_end[tile]) - start,
    )
}

/// The unit's pixels in a tile kernel: column `px` and rows `py0..py0 + ppu` of the image (unit (x, y)
/// of the cube owns column x, rows y·ppu.. of the tile). Returns (px, py0).
#[cube]
pub(crate) fn unit_pixels(#[comptime] ppu: u32) -> (u32, u32) {
    (
        CUBE_POS_X * TILE + UNIT_POS_X,
        CUBE_POS_Y * TILE + UNIT_POS_Y * ppu,
    )
}

/// Loads the tile list entries `first..first + size` into shared memory: ids into `batch_ids`, the first
/// `fields` floats of each splat record into `batch` (`fields` per entry). Each unit loads every
/// `units`-th entry.
#[cube]
pub(crate) fn load_batch(
    splats: &[f32],
    ids: &[u32],
    first: u32,
    size: u32,
    batch: &mut Shared<[f32]>,
    batch_ids: &mut Shared<[u32]>,
    #[comptime] fields: u32,
    #[comptime] units: u32,
) {
    load_batch_of(
        splats, ids, first, size, batch, batch_ids, 0u32, fields, units,
    );
}

/// [`load_batch`] for an image of a pair: its list's ids are `offset` below its Gaussians' records in
/// `splats` (the second image's Gaussians follow the first's), and `batch_ids` gets the records' ids.
#[cube]
#[allow(clippy::too_many_arguments)]
fn load_batch_of(
    splats: &[f32],
    ids: &[u32],
    first: u32,
    size: u32,
    batch: &mut Shared<[f32]>,
    batch_ids: &mut Shared<[u32]>,
    offset: u32,
    #[comptime] fields: u32,
    #[comptime] units: u32,
) {
    let mut e = UNIT_POS;
    while e < size {
        let gi = ids[(first + e) as usize] + offset;
        batch_ids[e as usize] = gi;
        let src = gi as usize * 10;
        let dst = (e * fields) as usize;
        #[unroll]
        for f in 0..fields {
            batch[dst + f as usize] = splats[src + f as usize];
        }
        e += units;
    }
}

/// [`load_batch_of`] from the cube's image's list (`CUBE_POS_Z`: `ids`, or `ids_b` in a pair), the
/// second image's Gaussians `offset` records after the first's.
#[cube]
#[allow(clippy::too_many_arguments)]
fn load_image_batch(
    splats: &[f32],
    ids: &[u32],
    ids_b: &[u32],
    first: u32,
    size: u32,
    batch: &mut Shared<[f32]>,
    batch_ids: &mut Shared<[u32]>,
    offset: u32,
    #[comptime] units: u32,
) {
    if CUBE_POS_Z == 0 {
        load_batch_of(
            splats, ids, first, size, batch, batch_ids, 0u32, 10u32, units,
        );
    } else {
        load_batch_of(
            splats, ids_b, first, size, batch, batch_ids, offset, 10u32, units,
        );
    }
}

/// Whether any unit of the cube still has a pixel compositing (`done[q]` = 0). Every unit gets the same
/// answer; `busy` is one flag per unit. Includes a barrier: the batch just walked may be overwritten
/// after it.
#[cube]
pub(crate) fn cube_busy(
    done: &Array<u32>,
    busy: &mut Shared<[u32]>,
    #[comptime] np: usize,
    #[comptime] units: u32,
) -> bool {
    let mut mine = 0u32;
    #[unroll]
    for q in 0..np {
        if done[q] == 0 {
            mine = 1;
        }
    }
    busy[UNIT_POS as usize] = mine;
    sync_cube();
    let mut any = 0u32;
    for u in 0..units {
        any |= busy[u as usize];
    }
    any != 0
}

/// Gaussians per shared-memory batch at least (each unit loads several when the cube has fewer units):
/// fewer barriers per Gaussian.
pub(crate) const MIN_BATCH: u32 = 64;

/// The raster backward's `staging`: global atomics per unit and Gaussian; shared float atomics per
/// batch, then global ones (SPIR-V); the same with the floats' bits swapped in (any compiler).
pub(crate) const STAGE_NONE: u32 = 0;
pub(crate) const STAGE_FLOAT: u32 = 1;
pub(crate) const STAGE_BITS: u32 = 2;

/// Forward. `channels` extra channels (`extra_vals` N*C) are composited over 0 into `extra` (H*W*C).
///
/// One cube per tile with `TILE * TILE / ppu` units, unit (x, y) owning the `ppu` pixels of column x,
/// rows y·ppu.. of the tile (as the backward). The cube walks the tile's list front to back in batches
/// of one Gaussian per unit loaded into shared memory, and stops once every pixel of the tile is done.
/// Per pixel the arithmetic is that of the CPU renderer, in the same order.
/// With `sparse`, the extra channels are composited only at the pixels whose row and column are flagged
/// in `needed_rows` / `needed_cols` (lifting's render-back reads a few pixels per grid cell) and are zero
/// elsewhere; without it those two arrays are not read.
///
/// A launch renders one image, or two of the same size (a pair of fits, `CUBE_POS_Z` the image): image 1
/// walks its own lists (`ids_b`, `tile_start_b`, `tile_end_b`; image 0's again for one image) whose ids
/// are `gauss_offset` below its Gaussians' records in `splats`, and its pixels follow image 0's in every
/// output.
#[cube(launch)]
pub fn raster_forward(
    splats: &[f32],
    ids: &[u32],
    tile_start: &[u32],
    tile_end: &[u32],
    ids_b: &[u32],
    tile_start_b: &[u32],
    tile_end_b: &[u32],
    gauss_offset: u32,
    extra_vals: &[f32],
    needed_rows: &[u32],
    needed_cols: &[u32],
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
    #[comptime] ppu: u32,
    #[comptime] sparse: bool,
) {
    let units = comptime!(TILE * TILE / ppu);
    let np = comptime!(ppu as usize);
    let c = channels as usize;
    let (start, count) = image_tile_range(tile_start, tile_end, tile_start_b, tile_end_b, tiles_x);
    let offset = CUBE_POS_Z * gauss_offset;
    let pix_offset = CUBE_POS_Z * width * height;
    let (px, py0) = unit_pixels(ppu);
    let fx = px as f32 + 0.5;

    // Whether each pixel composites the extra channels.
    let mut wants = Array::<u32>::new(np);
    let mut pix = Array::<u32>::new(np);
    let mut done = Array::<u32>::new(np);
    let mut t = Array::<f32>::new(np);
    let mut r = Array::<f32>::new(np);
    let mut g = Array::<f32>::new(np);
    let mut b = Array::<f32>::new(np);
    let mut d = Array::<f32>::new(np);
    let mut n_last = Array::<u32>::new(np);
    #[unroll]
    for q in 0..np {
        let py = py0 + q as u32;
        pix[q] = 0;
        // Pixels outside the image are done from the start.
        done[q] = 1;
        t[q] = 1.0;
        r[q] = 0.0;
        g[q] = 0.0;
        b[q] = 0.0;
        d[q] = 0.0;
        n_last[q] = 0;
        wants[q] = 1;
        if px < width && py < height {
            let p = pix_offset + py * width + px;
            pix[q] = p;
            done[q] = 0;
            if comptime!(sparse) {
                wants[q] = needed_rows[py as usize] * needed_cols[px as usize];
            }
            for ch in 0..c {
                extra[p as usize * c + ch] = 0.0;
            }
        }
    }

    let batch_len = comptime!(u32::max(units, MIN_BATCH));
    let mut batch = Shared::<[f32]>::new_slice(comptime!((batch_len * 10) as usize));
    let mut batch_ids = Shared::<[u32]>::new_slice(comptime!(batch_len as usize));
    // Per unit: 1 while it has a pixel still compositing (read by every unit to stop together).
    let mut busy = Shared::<[u32]>::new_slice(comptime!(units as usize));
    let mut lo = 0u32;
    while lo < count {
        let size = u32::min(batch_len, count - lo);
        load_image_batch(
            splats,
            ids,
            ids_b,
            start + lo,
            size,
            &mut batch,
            &mut batch_ids,
            offset,
            units,
        );
        sync_cube();
        for j in 0..size {
            let s = j as usize * 10;
            let mx = batch[s];
            let my = batch[s + 1];
            let ca = batch[s + 2];
            let cb = batch[s + 3];
            let cc = batch[s + 4];
            let o = batch[s + 5];
            #[unroll]
            for q in 0..np {
                if done[q] == 0 {
                    let fy = (py0 + q as u32) as f32 + 0.5;
                    let (sigma, vis, _dx, _dy) = falloff(mx, my, ca, cb, cc, fx, fy);
                    let a = f32::min(o * vis, ALPHA_MAX as f32);
                    if sigma >= 0.0 && a >= ALPHA_MIN as f32 {
                        let next = t[q] * (1.0f32 - a);
                        if next < T_MIN as f32 {
                            done[q] = 1;
                        } else {
                            let w = a * t[q];
                            r[q] += w * batch[s + 6];
                            g[q] += w * batch[s + 7];
                            b[q] += w * batch[s + 8];
                            d[q] += w * batch[s + 9];
                            if c > 0 && wants[q] != 0 {
                                let gi = batch_ids[j as usize] as usize;
                                let p = pix[q] as usize;
                                for ch in 0..c {
                                    extra[p * c + ch] += w * extra_vals[gi * c + ch];
                                }
                            }
                            t[q] = next;
                            n_last[q] = lo + j + 1;
                        }
                    }
                }
            }
        }
        lo += batch_len;
        if !cube_busy(&done, &mut busy, np, units) {
            lo = count;
        }
    }
    #[unroll]
    for q in 0..np {
        if px < width && py0 + (q as u32) < height {
            let p = pix[q] as usize;
            rgb[3 * p] = r[q] + t[q] * bg_r;
            rgb[3 * p + 1] = g[q] + t[q] * bg_g;
            rgb[3 * p + 2] = b[q] + t[q] * bg_b;
            alpha[p] = 1.0f32 - t[q];
            depth[p] = d[q];
            t_final[p] = t[q];
            last[p] = n_last[q];
        }
    }
}

/// Backward. `channels` is the extra channel count when their gradient is wanted, else 0;
/// `behind` is per-pixel scratch (H*W*C) for the extra channels composited behind the current Gaussian.
///
/// One cube per tile with `TILE * TILE / ppu` units; unit (x, y) owns the `ppu` pixels of column x,
/// rows y·ppu.. of the tile. The whole cube walks the tile's list back to front in step, from the
/// largest `last` of its pixels, in batches of one Gaussian per unit loaded into shared memory; each
/// pixel skips the Gaussians at or after its own `last`. A unit sums its pixels' gradients for the
/// current Gaussian in registers: `ppu` times fewer global atomics than one per pixel, without barriers
/// per Gaussian. With `plane` (adapters with plane reductions, on request: `plane_sums_asked`) the
/// units of a plane sum their values and one of them adds them (32x fewer atomics on NVIDIA).
///
/// With `staging` the ten sums go to shared slots of the batch's Gaussians, and after the batch the
/// units add each slot to `grads` with one global atomic, spread over the units. It is for SPIR-V:
/// cubecl-spirv 0.11.3 gives every atomic acquire-release semantics at its pointer's scope, so a
/// global one waits for the device-wide fence, and a cube that adds ten per Gaussian in turn waits ten
/// times per Gaussian (on an H200 the backward took 3.0 ms per lego step against 0.55 ms on WGSL, whose
/// atomics are relaxed, and plane sums did not help: one unit still waits ten times); a shared atomic
/// only orders the cube's own memory. Per pixel the arithmetic is that of the CPU backward, in the
/// same order.
///
/// Two images in one launch as in [`raster_forward`] (`CUBE_POS_Z`, `ids_b`, `tile_start_b`,
/// `gauss_offset`; every per-pixel buffer holds image 1 after image 0).
#[cube(launch)]
pub fn raster_backward(
    splats: &[f32],
    ids: &[u32],
    tile_start: &[u32],
    ids_b: &[u32],
    tile_start_b: &[u32],
    gauss_offset: u32,
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
    #[comptime] ppu: u32,
    #[comptime] plane: bool,
    #[comptime] staging: u32,
) {
    let units = comptime!(TILE * TILE / ppu);
    let np = comptime!(ppu as usize);
    let c = channels as usize;
    let tile = cube_tile(tiles_x);
    let start = select(CUBE_POS_Z != 0, tile_start_b[tile], tile_start[tile]);
    let offset = CUBE_POS_Z * gauss_offset;
    let pix_offset = CUBE_POS_Z * width * height;
    let (px, py0) = unit_pixels(ppu);
    let fx = px as f32 + 0.5;

    // Per-pixel state: index, contributor count, T, output gradients and what lies behind.
    let mut pix = Array::<u32>::new(np);
    let mut n_last = Array::<u32>::new(np);
    let mut t = Array::<f32>::new(np);
    let mut vr = Array::<f32>::new(np);
    let mut vg = Array::<f32>::new(np);
    let mut vb = Array::<f32>::new(np);
    let mut vd = Array::<f32>::new(np);
    let mut v_final = Array::<f32>::new(np);
    let mut br = Array::<f32>::new(np);
    let mut bgc = Array::<f32>::new(np);
    let mut bb = Array::<f32>::new(np);
    let mut bd = Array::<f32>::new(np);
    // Per-pixel values for the current Gaussian.
    let mut hit = Array::<u32>::new(np);
    let mut fac = Array::<f32>::new(np);
    let mut tn = Array::<f32>::new(np);
    let mut ra = Array::<f32>::new(np);
    let mut v_alpha = Array::<f32>::new(np);
    let mut dxs = Array::<f32>::new(np);
    let mut dys = Array::<f32>::new(np);
    let mut vis = Array::<f32>::new(np);
    let mut unit_last = 0u32;
    #[unroll]
    for q in 0..np {
        let py = py0 + q as u32;
        pix[q] = 0;
        n_last[q] = 0;
        t[q] = 0.0;
        vr[q] = 0.0;
        vg[q] = 0.0;
        vb[q] = 0.0;
        vd[q] = 0.0;
        v_final[q] = 0.0;
        br[q] = 0.0;
        bgc[q] = 0.0;
        bb[q] = 0.0;
        bd[q] = 0.0;
        if px < width && py < height {
            let p = pix_offset + py * width + px;
            let pu = p as usize;
            pix[q] = p;
            n_last[q] = last[pu];
            t[q] = t_final[pu];
            vr[q] = v_rgb[3 * pu];
            vg[q] = v_rgb[3 * pu + 1];
            vb[q] = v_rgb[3 * pu + 2];
            vd[q] = v_depth[pu];
            // Every alpha also changes the final T: d out/d T_final = background·v_rgb − v_alpha.
            v_final[q] = t[q] * (v_alpha_out[pu] - bg_r * vr[q] - bg_g * vg[q] - bg_b * vb[q]);
            for ch in 0..c {
                behind[pu * c + ch] = 0.0;
            }
            unit_last = u32::max(unit_last, n_last[q]);
        }
    }
    let count = cube_max::<u32>(unit_last, units);

    let batch_len = comptime!(u32::max(units, MIN_BATCH));
    let mut batch = Shared::<[f32]>::new_slice(comptime!((batch_len * 10) as usize));
    let mut batch_ids = Shared::<[u32]>::new_slice(comptime!(batch_len as usize));
    // With staging, the batch's ten sums per Gaussian (one slot each, in the cube's shared memory): as
    // floats ([`STAGE_FLOAT`]) or as their bits ([`STAGE_BITS`]).
    let stage_len = comptime!(batch_len * 10);
    let stage = Shared::<[Atomic<f32>]>::new_slice(comptime!(
        (if staging == STAGE_FLOAT { stage_len } else { 1 }) as usize
    ));
    let stage_bits = Shared::<[Atomic<u32>]>::new_slice(comptime!(
        (if staging == STAGE_BITS { stage_len } else { 1 }) as usize
    ));
    // Spelt out: `div_ceil` is not part of CubeCL's kernel language.
    #[allow(clippy::manual_div_ceil)]
    let batches = (count + batch_len - 1) / batch_len;
    let mut hi = count;
    for _ in 0..batches {
        // Spelt out: `saturating_sub` is not part of CubeCL's kernel language.
        #[allow(clippy::implicit_saturating_sub)]
        let lo = if hi > batch_len { hi - batch_len } else { 0u32 };
        let size = hi - lo;
        // The previous batch is consumed (and a staged one added to `grads`) before it is overwritten.
        sync_cube();
        load_image_batch(
            splats,
            ids,
            ids_b,
            start + lo,
            size,
            &mut batch,
            &mut batch_ids,
            offset,
            units,
        );
        if comptime!(staging != STAGE_NONE) {
            let mut e = UNIT_POS;
            while e < size * 10 {
                if comptime!(staging == STAGE_FLOAT) {
                    stage[e as usize].store(0.0f32);
                } else {
                    stage_bits[e as usize].store(0u32);
                }
                e += units;
            }
        }
        sync_cube();
        for j in 0..size {
            let local = size - 1 - j;
            let rel = lo + local;
            let s = local as usize * 10;
            let mx = batch[s];
            let my = batch[s + 1];
            let ca = batch[s + 2];
            let cb = batch[s + 3];
            let cc = batch[s + 4];
            let o = batch[s + 5];
            let cr = batch[s + 6];
            let cg = batch[s + 7];
            let cbl = batch[s + 8];
            let dep = batch[s + 9];
            let mut any_hit = false;
            let mut g_r = 0.0f32;
            let mut g_g = 0.0f32;
            let mut g_b = 0.0f32;
            let mut g_d = 0.0f32;
            #[unroll]
            for q in 0..np {
                hit[q] = 0;
                if rel < n_last[q] {
                    let fy = (py0 + q as u32) as f32 + 0.5;
                    let (sigma, vv, dx, dy) = falloff(mx, my, ca, cb, cc, fx, fy);
                    let a = f32::min(o * vv, ALPHA_MAX as f32);
                    if sigma >= 0.0 && a >= ALPHA_MIN as f32 {
                        hit[q] = 1;
                        any_hit = true;
                        let r_a = 1.0f32 / (1.0f32 - a);
                        let t_n = t[q] * r_a;
                        let f = a * t_n;
                        v_alpha[q] = (cr * t_n - br[q] * r_a) * vr[q]
                            + (cg * t_n - bgc[q] * r_a) * vg[q]
                            + (cbl * t_n - bb[q] * r_a) * vb[q]
                            + (dep * t_n - bd[q] * r_a) * vd[q]
                            + v_final[q] * r_a;
                        t[q] = t_n;
                        br[q] += cr * f;
                        bgc[q] += cg * f;
                        bb[q] += cbl * f;
                        bd[q] += dep * f;
                        g_r += f * vr[q];
                        g_g += f * vg[q];
                        g_b += f * vb[q];
                        g_d += f * vd[q];
                        fac[q] = f;
                        tn[q] = t_n;
                        ra[q] = r_a;
                        dxs[q] = dx;
                        dys[q] = dy;
                        vis[q] = vv;
                    }
                }
            }
            // With plane reductions every unit of a plane that has a hit takes part (a unit without
            // one sums zeros), and one unit per plane adds the plane's sums.
            let take_part = if comptime!(plane) {
                plane_any(any_hit)
            } else {
                any_hit
            };
            if take_part {
                let gi = batch_ids[local as usize] as usize;
                for ch in 0..c {
                    let val = extra_vals[gi * c + ch];
                    let mut g_ch = 0.0f32;
                    #[unroll]
                    for q in 0..np {
                        if hit[q] == 1 {
                            let e = pix[q] as usize * c + ch;
                            let v = v_extra[e];
                            g_ch += fac[q] * v;
                            v_alpha[q] += (val * tn[q] - behind[e] * ra[q]) * v;
                            behind[e] += val * fac[q];
                        }
                    }
                    if comptime!(plane) {
                        let sum = plane_sum(g_ch);
                        if UNIT_POS_PLANE == 0 {
                            g_extra[gi * c + ch].fetch_add(sum);
                        }
                    } else {
                        g_extra[gi * c + ch].fetch_add(g_ch);
                    }
                }
                let mut g_mx = 0.0f32;
                let mut g_my = 0.0f32;
                let mut g_ca = 0.0f32;
                let mut g_cb = 0.0f32;
                let mut g_cc = 0.0f32;
                let mut g_o = 0.0f32;
                #[unroll]
                for q in 0..np {
                    // Where alpha was clamped at 0.99 it depends on neither σ nor the opacity.
                    if hit[q] == 1 && o * vis[q] <= ALPHA_MAX as f32 {
                        let dx = dxs[q];
                        let dy = dys[q];
                        let v_sigma = -(o * vis[q]) * v_alpha[q];
                        g_mx += v_sigma * (ca * dx + cb * dy);
                        g_my += v_sigma * (cb * dx + cc * dy);
                        g_ca += 0.5f32 * v_sigma * dx * dx;
                        g_cb += v_sigma * dx * dy;
                        g_cc += 0.5f32 * v_sigma * dy * dy;
                        g_o += vis[q] * v_alpha[q];
                    }
                }
                let mut sums = Array::<f32>::new(10usize);
                sums[0] = g_mx;
                sums[1] = g_my;
                sums[2] = g_ca;
                sums[3] = g_cb;
                sums[4] = g_cc;
                sums[5] = g_o;
                sums[6] = g_r;
                sums[7] = g_g;
                sums[8] = g_b;
                sums[9] = g_d;
                // With plane sums one unit per plane adds them.
                let mut adds = true;
                if comptime!(plane) {
                    #[unroll]
                    for k in 0..10usize {
                        sums[k] = plane_sum(sums[k]);
                    }
                    adds = UNIT_POS_PLANE == 0;
                }
                if adds {
                    #[unroll]
                    for k in 0..10usize {
                        if comptime!(staging == STAGE_NONE) {
                            grads[gi * 10 + k].fetch_add(sums[k]);
                        } else if comptime!(staging == STAGE_FLOAT) {
                            stage[local as usize * 10 + k].fetch_add(sums[k]);
                        } else {
                            add_to_bits(&stage_bits[local as usize * 10 + k], sums[k]);
                        }
                    }
                }
            }
        }
        if comptime!(staging != STAGE_NONE) {
            // One global atomic per Gaussian of the batch and parameter, spread over the units.
            sync_cube();
            let mut e = UNIT_POS;
            while e < size * 10 {
                let v = if comptime!(staging == STAGE_FLOAT) {
                    stage[e as usize].load()
                } else {
                    f32::reinterpret(stage_bits[e as usize].load())
                };
                if v != 0.0f32 {
                    let gi = batch_ids[(e / 10) as usize] as usize;
                    grads[gi * 10 + (e % 10) as usize].fetch_add(v);
                }
                e += units;
            }
        }
        hi = lo;
    }
}

/// Adds `v` to the float whose bits `slot` holds, by compare-and-swap: staging where the compiler has no
/// float atomics in shared memory (WGSL: naga allows them in storage buffers only). The swap returns
/// only the old value; WGSL's weak swap is a strong one on Vulkan (naga emits OpAtomicCompareExchange),
/// so seeing the expected value means it swapped. The tests run staging this way on lavapipe.
#[cube]
pub(crate) fn add_to_bits(slot: &Atomic<u32>, v: f32) {
    let mut old = slot.load();
    loop {
        let new = u32::reinterpret(f32::reinterpret(old) + v);
        let seen = slot.compare_exchange_weak(old, new);
        if seen == old {
            break;
        }
        old = seen;
    }
}
