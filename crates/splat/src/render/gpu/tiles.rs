//! Stage 2 on the GPU, the twin of [`crate::render::tiles`]: a stable radix sort of the drawable
//! Gaussians by depth, an exclusive scan of their tile counts in that order, one (tile, Gaussian) pair
//! per covered tile, a stable radix sort of the pairs by tile and the per-tile ranges. Every tile list
//! comes out sorted by depth, ties by index, as on the CPU.

use super::project::INFO_U;
use ::gpu::cubecl;
use ::gpu::cubecl::prelude::*;
use ::gpu::cubecl::server::Handle;
use ::gpu::prims::{arg, empty32, exclusive_scan, grid, read_u32, sort_pairs, zeros32};
use ::gpu::{GpuContext, GpuError};

/// Tile lists: (ids, start, end, number of pairs).
pub(super) fn bin(
    ctx: &GpuContext,
    info: &Handle,
    n: usize,
    tiles_x: u32,
    num_tiles: usize,
) -> Result<(Handle, Handle, Handle, usize), GpuError> {
    let c = &ctx.client;
    let tile_start = zeros32(c, num_tiles);
    let tile_end = zeros32(c, num_tiles);
    if n == 0 {
        return Ok((empty32(c, 1), tile_start, tile_end, 0));
    }
    let (count, dim) = grid(n);
    let keys = empty32(c, n);
    let vals = empty32(c, n);
    depth_keys::launch(
        c,
        count.clone(),
        dim,
        arg(info, INFO_U * n),
        n as u32,
        arg(&keys, n),
        arg(&vals, n),
    );
    let (_, order) = sort_pairs(c, keys, vals, n, 32);
    let counts = empty32(c, n);
    gather_info::launch(
        c,
        count.clone(),
        dim,
        arg(&order, n),
        arg(info, INFO_U * n),
        n as u32,
        6,
        arg(&counts, n),
    );
    let (offsets, total) = exclusive_scan(c, &counts, n);
    // The one read of the forward pass: the pair count sizes the next buffers.
    let m = read_u32(c, &total, 1)?[0] as usize;
    if m == 0 {
        return Ok((empty32(c, 1), tile_start, tile_end, 0));
    }
    let tile_keys = empty32(c, m);
    let ids = empty32(c, m);
    emit_pairs::launch(
        c,
        count,
        dim,
        arg(&order, n),
        arg(info, INFO_U * n),
        arg(&offsets, n),
        n as u32,
        tiles_x,
        arg(&tile_keys, m),
        arg(&ids, m),
    );
    let tile_bits = u32::BITS - (num_tiles as u32 - 1).leading_zeros();
    let (tile_keys, ids) = sort_pairs(c, tile_keys, ids, m, tile_bits);
    let (count, dim) = grid(m);
    tile_ranges::launch(
        c,
        count,
        dim,
        arg(&tile_keys, m),
        m as u32,
        arg(&tile_start, num_tiles),
        arg(&tile_end, num_tiles),
    );
    Ok((ids, tile_start, tile_end, m))
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
