//! The lifting kernels: the forward walk of [`crate::render::gpu::raster`] with T from 1, adding each
//! hit pixel's map values to the Gaussian's sums, per pixel or from a coarse grid.

use ::gpu::cubecl;
use cubecl::prelude::*;

use crate::render::gpu::raster::{
    add_to_bits, cube_busy, falloff, load_batch, tile_range, unit_pixels, MIN_BATCH, STAGE_BITS,
    STAGE_FLOAT,
};
use crate::render::{ALPHA_MAX, ALPHA_MIN, TILE, T_MIN};

/// One Gaussian of a shared-memory batch (its record from `s`: mean, conic, opacity) front to back at
/// the unit's `ppu` pixels (column x, rows y·ppu.. of the cube's tile), with the CPU's rules: skipped at
/// a pixel already done, or where σ < 0 or alpha < 1/255; where T would fall below 1e-4 the pixel is
/// done and the Gaussian does not count; elsewhere it is a hit (unweighted, as in the reference):
/// `hit[q]` = 1 and T ← T·(1 − alpha). Returns the number of hits. The walk of both lifting kernels;
/// the raster forward keeps its own inline (it composites at each hit: split into two loops it ran
/// slower on lavapipe).
#[cube]
fn front_to_back(
    batch: &Shared<[f32]>,
    s: usize,
    done: &mut Array<u32>,
    t: &mut Array<f32>,
    hit: &mut Array<u32>,
    #[comptime] ppu: u32,
) -> u32 {
    let np = comptime!(ppu as usize);
    let (px, py0) = unit_pixels(ppu);
    let fx = px as f32 + 0.5;
    let mx = batch[s];
    let my = batch[s + 1];
    let ca = batch[s + 2];
    let cb = batch[s + 3];
    let cc = batch[s + 4];
    let o = batch[s + 5];
    let mut hits = 0u32;
    #[unroll]
    for q in 0..np {
        hit[q] = 0;
        if done[q] == 0 {
            let fy = (py0 + q as u32) as f32 + 0.5;
            let (sigma, vis, _dx, _dy) = falloff(mx, my, ca, cb, cc, fx, fy);
            let a = f32::min(o * vis, ALPHA_MAX as f32);
            if sigma >= 0.0 && a >= ALPHA_MIN as f32 {
                let next = t[q] * (1.0f32 - a);
                if next < T_MIN as f32 {
                    done[q] = 1;
                } else {
                    hit[q] = 1;
                    hits += 1;
                    t[q] = next;
                }
            }
        }
    }
    hits
}

/// Lifting (GaussianEditor's `apply_weights`, as `crate::lift`): the forward walk with T from 1, and at
/// every hit (an unweighted one) the pixel's C map values are added to the Gaussian's sums and its count
/// goes up by one. Laid out as the raster forward
/// ([`raster_forward`](crate::render::gpu::raster::raster_forward): `ppu` pixels per unit,
/// shared-memory batches, the cube stops when every pixel is done); a unit adds its pixels' hits and
/// sums with one atomic each.
#[cube(launch)]
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
    #[comptime] ppu: u32,
) {
    let units = comptime!(TILE * TILE / ppu);
    let np = comptime!(ppu as usize);
    let c = channels as usize;
    let (start, count) = tile_range(tile_start, tile_end, tiles_x);
    let (px, py0) = unit_pixels(ppu);

    let mut pix = Array::<u32>::new(np);
    let mut done = Array::<u32>::new(np);
    let mut t = Array::<f32>::new(np);
    let mut hit = Array::<u32>::new(np);
    #[unroll]
    for q in 0..np {
        let py = py0 + q as u32;
        pix[q] = 0;
        done[q] = 1;
        t[q] = 1.0;
        if px < width && py < height {
            pix[q] = py * width + px;
            done[q] = 0;
        }
    }

    let batch_len = comptime!(u32::max(units, MIN_BATCH));
    let mut batch = Shared::<[f32]>::new_slice(comptime!((batch_len * 6) as usize));
    let mut batch_ids = Shared::<[u32]>::new_slice(comptime!(batch_len as usize));
    let mut busy = Shared::<[u32]>::new_slice(comptime!(units as usize));
    let mut lo = 0u32;
    while lo < count {
        let size = u32::min(batch_len, count - lo);
        load_batch(
            splats,
            ids,
            start + lo,
            size,
            &mut batch,
            &mut batch_ids,
            6u32,
            units,
        );
        sync_cube();
        for j in 0..size {
            let s = j as usize * 6;
            let hits = front_to_back(&batch, s, &mut done, &mut t, &mut hit, ppu);
            if hits > 0 {
                let gi = batch_ids[j as usize] as usize;
                counts[gi].fetch_add(hits);
                for ch in 0..c {
                    let mut sum = 0.0f32;
                    #[unroll]
                    for q in 0..np {
                        if hit[q] == 1 {
                            sum += map[pix[q] as usize * c + ch];
                        }
                    }
                    sums[gi * c + ch].fetch_add(sum);
                }
            }
        }
        lo += batch_len;
        if !cube_busy(&done, &mut busy, np, units) {
            lo = count;
        }
    }
}

/// The grid cells a pixel row or column `o` (of `full`) reads when a map of `cells` cells is upsampled to
/// `full` as `resample_map` does (bilinear, or torch's nearest): (first cell, second cell, their weights).
/// At the clamped far edge both cells are the last one, and the weights still sum to one.
#[cube]
fn axis_cells(o: u32, full: u32, cells: u32, scale: f32, bilinear: u32) -> (u32, u32, f32, f32) {
    let mut c0 = u32::min(o * cells / full, cells - 1);
    let mut c1 = c0;
    let mut w0 = 1.0f32;
    let mut w1 = 0.0f32;
    if bilinear == 1 {
        let f = f32::max((o as f32 + 0.5) * scale - 0.5, 0.0);
        c0 = u32::min(f as u32, cells - 1);
        c1 = u32::min(c0 + 1, cells - 1);
        w1 = f - c0 as f32;
        w0 = 1.0f32 - w1;
    }
    (c0, c1, w0, w1)
}

/// Lifting a map given on a coarse grid (`grid_h` × `grid_w` cells, C channels) as [`lift_accumulate`]
/// lifts its upsampled full-resolution version, without making that version: a pixel's upsampled value is
/// a weighted sum of at most four cells, so a Gaussian's sum over its hit pixels is the cells' values
/// weighted by the summed weights of those pixels. Per batch, the units add their hit pixels' cell weights
/// (at most `span` × `span` cells per tile, from the tile's first cell) and hit counts into the cube's
/// shared memory — one unit's pixels share a column, so it adds its rows' weights per cell row — and after
/// the batch one global atomic per hit Gaussian and channel adds the weighted cells. Where the per-pixel
/// kernel does C global atomics per unit and hit Gaussian (144 for a CCM layer) and reads C values per
/// hit pixel, this does a few shared ones; the sums agree up to the order of float additions.
/// `staging` is [`STAGE_FLOAT`] (shared float atomics: SPIR-V) or [`STAGE_BITS`] (any compiler).
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
pub fn lift_accumulate_grid(
    splats: &[f32],
    ids: &[u32],
    tile_start: &[u32],
    tile_end: &[u32],
    grid_map: &[f32],
    width: u32,
    height: u32,
    tiles_x: u32,
    grid_w: u32,
    grid_h: u32,
    scale_x: f32,
    scale_y: f32,
    bilinear: u32,
    sums: &mut [Atomic<f32>],
    counts: &mut [Atomic<u32>],
    #[comptime] channels: u32,
    #[comptime] ppu: u32,
    #[comptime] span: u32,
    #[comptime] staging: u32,
) {
    let units = comptime!(TILE * TILE / ppu);
    let np = comptime!(ppu as usize);
    let cells = comptime!(span * span);
    let c = channels as usize;
    let (start, count) = tile_range(tile_start, tile_end, tiles_x);
    let (px, py0) = unit_pixels(ppu);

    // Every pixel of the tile reads cells in [base, base + span) on each axis (the host checked `span`).
    let (xbase, _, _, _) = axis_cells(CUBE_POS_X * TILE, width, grid_w, scale_x, bilinear);
    let (ybase, _, _, _) = axis_cells(CUBE_POS_Y * TILE, height, grid_h, scale_y, bilinear);
    let (cx0, cx1, wx0, wx1) =
        axis_cells(u32::min(px, width - 1), width, grid_w, scale_x, bilinear);
    let rx0 = cx0 - xbase;
    let rx1 = cx1 - xbase;

    let mut done = Array::<u32>::new(np);
    let mut t = Array::<f32>::new(np);
    let mut ry0 = Array::<u32>::new(np);
    let mut ry1 = Array::<u32>::new(np);
    let mut wy0 = Array::<f32>::new(np);
    let mut wy1 = Array::<f32>::new(np);
    // Per pixel: whether the Gaussian at hand hits it.
    let mut hit = Array::<u32>::new(np);
    #[unroll]
    for q in 0..np {
        let py = py0 + q as u32;
        done[q] = 1;
        t[q] = 1.0;
        ry0[q] = 0;
        ry1[q] = 0;
        wy0[q] = 0.0;
        wy1[q] = 0.0;
        if px < width && py < height {
            done[q] = 0;
            let (cy0, cy1, w0, w1) = axis_cells(py, height, grid_h, scale_y, bilinear);
            ry0[q] = cy0 - ybase;
            ry1[q] = cy1 - ybase;
            wy0[q] = w0;
            wy1[q] = w1;
        }
    }
    // This unit's hit weight per cell row, for the Gaussian at hand.
    let mut rows = Array::<f32>::new(comptime!(span as usize));

    let batch_len = comptime!(u32::max(units, MIN_BATCH));
    let mut batch = Shared::<[f32]>::new_slice(comptime!((batch_len * 6) as usize));
    let mut batch_ids = Shared::<[u32]>::new_slice(comptime!(batch_len as usize));
    let mut busy = Shared::<[u32]>::new_slice(comptime!(units as usize));
    let stage_len = comptime!(batch_len * cells);
    let stage = Shared::<[Atomic<f32>]>::new_slice(comptime!(
        (if staging == STAGE_FLOAT { stage_len } else { 1 }) as usize
    ));
    let stage_bits = Shared::<[Atomic<u32>]>::new_slice(comptime!(
        (if staging == STAGE_BITS { stage_len } else { 1 }) as usize
    ));
    let hits_of = Shared::<[Atomic<u32>]>::new_slice(comptime!(batch_len as usize));
    let mut lo = 0u32;
    while lo < count {
        let size = u32::min(batch_len, count - lo);
        load_batch(
            splats,
            ids,
            start + lo,
            size,
            &mut batch,
            &mut batch_ids,
            6u32,
            units,
        );
        let mut e = UNIT_POS;
        while e < size * cells {
            if comptime!(staging == STAGE_FLOAT) {
                stage[e as usize].store(0.0f32);
            } else {
                stage_bits[e as usize].store(0u32);
            }
            e += units;
        }
        let mut e = UNIT_POS;
        while e < size {
            hits_of[e as usize].store(0u32);
            e += units;
        }
        sync_cube();
        for j in 0..size {
            let s = j as usize * 6;
            let hits = front_to_back(&batch, s, &mut done, &mut t, &mut hit, ppu);
            #[unroll]
            for r in 0..span {
                rows[r as usize] = 0.0;
            }
            #[unroll]
            for q in 0..np {
                if hit[q] == 1 {
                    rows[ry0[q] as usize] += wy0[q];
                    rows[ry1[q] as usize] += wy1[q];
                }
            }
            if hits > 0 {
                hits_of[j as usize].fetch_add(hits);
                #[unroll]
                for r in 0..span {
                    let v = rows[r as usize];
                    if v != 0.0f32 {
                        let row = (j * cells + r * span) as usize;
                        if comptime!(staging == STAGE_FLOAT) {
                            stage[row + rx0 as usize].fetch_add(v * wx0);
                            if wx1 != 0.0f32 {
                                stage[row + rx1 as usize].fetch_add(v * wx1);
                            }
                        } else {
                            add_to_bits(&stage_bits[row + rx0 as usize], v * wx0);
                            if wx1 != 0.0f32 {
                                add_to_bits(&stage_bits[row + rx1 as usize], v * wx1);
                            }
                        }
                    }
                }
            }
        }
        sync_cube();
        // One global atomic per hit Gaussian of the batch and channel, spread over the units.
        let mut e = UNIT_POS;
        while e < size * channels {
            let j = e / channels;
            if hits_of[j as usize].load() > 0 {
                let ch = (e % channels) as usize;
                let mut sum = 0.0f32;
                #[unroll]
                for r in 0..span {
                    #[unroll]
                    for x in 0..span {
                        let slot = (j * cells + r * span + x) as usize;
                        let w = if comptime!(staging == STAGE_FLOAT) {
                            stage[slot].load()
                        } else {
                            f32::reinterpret(stage_bits[slot].load())
                        };
                        if w != 0.0f32 {
                            let cell = ((ybase + r) * grid_w + xbase + x) as usize;
                            sum += w * grid_map[cell * c + ch];
                        }
                    }
                }
                let gi = batch_ids[j as usize] as usize;
                sums[gi * c + ch].fetch_add(sum);
            }
            e += units;
        }
        let mut e = UNIT_POS;
        while e < size {
            let k = hits_of[e as usize].load();
            if k > 0 {
                counts[batch_ids[e as usize] as usize].fetch_add(k);
            }
            e += units;
        }
        lo += batch_len;
        // Its barrier also keeps the next batch's loads and zeroing behind these reads.
        if !cube_busy(&done, &mut busy, np, units) {
            lo = count;
        }
    }
}
