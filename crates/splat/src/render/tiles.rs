//! Stage (b): tile binning. Every drawable Gaussian is listed in each 16x16 tile its 3σ rectangle covers;
//! each tile's list is sorted front to back by camera depth (ties by index, so results are deterministic).

use super::project::Splat;
use super::real::Real;
use rayon::prelude::*;

/// Per-tile Gaussian lists, concatenated: tile `t` owns `ids[offsets[t]..offsets[t+1]]`.
#[derive(Clone, Debug, Default)]
pub struct TileBins {
    pub tiles_x: u32,
    pub tiles_y: u32,
    pub offsets: Vec<u32>,
    pub ids: Vec<u32>,
}

impl TileBins {
    #[inline]
    pub fn list(&self, tile: usize) -> &[u32] {
        &self.ids[self.offsets[tile] as usize..self.offsets[tile + 1] as usize]
    }

    pub fn num_tiles(&self) -> usize {
        (self.tiles_x * self.tiles_y) as usize
    }
}

/// A drawable splat in the depth order, with its tile rectangle inline so binning never goes back to the
/// (large, randomly ordered) splat records.
#[derive(Clone, Copy)]
struct Entry {
    /// Depth bits (depths are > 0, so the IEEE bit pattern orders like the value).
    key: u64,
    index: u32,
    /// x0, y0, x1, y1 in tiles.
    rect: [u16; 4],
}

/// Bins the drawable splats into tiles.
///
/// The splats are sorted by depth once (a parallel sort of N keys instead of one sort per tile), then
/// appended to the tile lists in that order, so every list comes out sorted.
pub fn bin<R: Real>(splats: &[Splat<R>], tiles_x: u32, tiles_y: u32) -> TileBins {
    let mut entries: Vec<Entry> = splats
        .par_iter()
        .enumerate()
        .filter(|(_, s)| s.is_drawable())
        .map(|(i, s)| Entry::of(i, s))
        .collect();
    entries.par_sort_unstable_by_key(|e| (e.key, e.index));
    scatter(&entries, tiles_x, tiles_y)
}

impl Entry {
    #[inline]
    fn of<R: Real>(i: usize, s: &Splat<R>) -> Self {
        Entry {
            key: s.depth.to_f64().to_bits(),
            index: i as u32,
            rect: s.tiles,
        }
    }
}

/// The tile lists of every splat that is on screen, whatever its opacity: where only opacities change
/// between renders (fits with frozen geometry), [`DepthOrder::bin`] makes [`bin`]'s lists from them by
/// dropping the splats that are not drawable, without sorting or scattering again.
#[derive(Clone, Default)]
pub struct DepthOrder {
    lists: TileBins,
}

impl DepthOrder {
    pub fn new<R: Real>(splats: &[Splat<R>], tiles_x: u32, tiles_y: u32) -> Self {
        let mut entries: Vec<Entry> = splats
            .par_iter()
            .enumerate()
            .filter(|(_, s)| s.radius > 0)
            .map(|(i, s)| Entry::of(i, s))
            .collect();
        entries.par_sort_unstable_by_key(|e| (e.key, e.index));
        DepthOrder {
            lists: scatter(&entries, tiles_x, tiles_y),
        }
    }

    /// [`bin`] of `splats`, which must have the geometry (and tile counts) this order was made from: each
    /// tile's list keeps its drawable splats in order, which is what [`bin`] lists (the depth sort's key
    /// is unique).
    pub fn bin<R: Real>(&self, splats: &[Splat<R>]) -> TileBins {
        let all = &self.lists;
        let drawable: Vec<bool> = splats.iter().map(Splat::is_drawable).collect();
        if all.ids.iter().all(|&g| drawable[g as usize]) {
            return all.clone();
        }
        let mut offsets = Vec::with_capacity(all.offsets.len());
        let mut ids = Vec::with_capacity(all.ids.len());
        offsets.push(0);
        for t in 0..all.num_tiles() {
            ids.extend(
                all.list(t)
                    .iter()
                    .copied()
                    .filter(|&g| drawable[g as usize]),
            );
            offsets.push(ids.len() as u32);
        }
        TileBins {
            tiles_x: all.tiles_x,
            tiles_y: all.tiles_y,
            offsets,
            ids,
        }
    }

    /// Bytes the kept lists take.
    pub fn bytes(&self) -> usize {
        (self.lists.ids.len() + self.lists.offsets.len()) * std::mem::size_of::<u32>()
    }

    /// Bytes per Gaussian on screen assumed before the lists exist: 4 tiles each.
    pub const ENTRY_BYTES: usize = 4 * std::mem::size_of::<u32>();
}

/// Appends the depth-sorted `entries` to the lists of the tiles they cover.
fn scatter(entries: &[Entry], tiles_x: u32, tiles_y: u32) -> TileBins {
    let num_tiles = (tiles_x * tiles_y) as usize;
    // Chunks of the sorted order are scattered in parallel, each into slots reserved for it in every tile.
    let chunks = rayon::current_num_threads().max(1) * 4;
    let chunk_len = entries.len().div_ceil(chunks).max(1);
    // counts[chunk][tile]
    let counts: Vec<Vec<u32>> = entries
        .par_chunks(chunk_len)
        .map(|chunk| {
            let mut counts = vec![0u32; num_tiles];
            for e in chunk {
                let [x0, y0, x1, y1] = e.rect.map(usize::from);
                for ty in y0..y1 {
                    let row = ty * tiles_x as usize;
                    for c in &mut counts[row + x0..row + x1] {
                        *c += 1;
                    }
                }
            }
            counts
        })
        .collect();

    // Tile offsets, and each chunk's first slot within each tile.
    let mut offsets = vec![0u32; num_tiles + 1];
    let mut starts: Vec<Vec<u32>> = vec![vec![0u32; num_tiles]; counts.len()];
    let mut total = 0u64;
    for t in 0..num_tiles {
        offsets[t] = total as u32;
        for (ch, cnt) in counts.iter().enumerate() {
            starts[ch][t] = total as u32;
            total += cnt[t] as u64;
        }
    }
    offsets[num_tiles] = total as u32;
    assert!(total <= u32::MAX as u64, "too many tile intersections");

    let mut ids = vec![0u32; total as usize];
    let ids_ptr = SyncPtr(ids.as_mut_ptr());
    entries
        .par_chunks(chunk_len)
        .zip(starts.par_iter_mut())
        .for_each(|(chunk, next)| {
            let ptr = &ids_ptr;
            for e in chunk {
                let [x0, y0, x1, y1] = e.rect.map(usize::from);
                for ty in y0..y1 {
                    let row = ty * tiles_x as usize;
                    for slot in &mut next[row + x0..row + x1] {
                        // SAFETY: every (chunk, tile) pair owns the disjoint slot range
                        // [starts[chunk][tile], starts[chunk][tile] + counts[chunk][tile]) inside `ids`;
                        // each chunk advances only its own cursors.
                        unsafe { ptr.write(*slot as usize, e.index) };
                        *slot += 1;
                    }
                }
            }
        });
    TileBins {
        tiles_x,
        tiles_y,
        offsets,
        ids,
    }
}

/// A raw pointer that parallel workers may share when they provably write disjoint elements.
pub(crate) struct SyncPtr<T>(pub *mut T);
unsafe impl<T: Send> Send for SyncPtr<T> {}
unsafe impl<T: Send> Sync for SyncPtr<T> {}

impl<T> SyncPtr<T> {
    /// # Safety
    /// `idx` must be in bounds of the allocation and no other thread may access that element concurrently.
    #[inline(always)]
    pub unsafe fn write(&self, idx: usize, v: T) {
        unsafe { self.0.add(idx).write(v) }
    }

    /// # Safety
    /// `start..start+len` must be in bounds and not accessed by any other thread while the slice lives.
    #[inline(always)]
    #[allow(clippy::mut_from_ref)]
    pub unsafe fn slice_mut(&self, start: usize, len: usize) -> &mut [T] {
        unsafe { std::slice::from_raw_parts_mut(self.0.add(start), len) }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn splat(depth: f32, tiles: [u32; 4]) -> Splat<f32> {
        Splat {
            depth,
            radius: 1,
            tiles: tiles.map(|t| t as u16),
            opacity: 0.5,
            ..Default::default()
        }
    }

    #[test]
    fn lists_are_complete_and_sorted_by_depth() {
        let splats = vec![
            splat(3.0, [0, 0, 2, 1]),
            splat(1.0, [1, 0, 2, 2]),
            splat(2.0, [0, 0, 1, 2]),
            Splat::default(), // culled
            splat(0.5, [0, 1, 2, 2]),
        ];
        let bins = bin(&splats, 2, 2);
        assert_eq!(bins.list(0), &[2, 0]);
        assert_eq!(bins.list(1), &[1, 0]);
        assert_eq!(bins.list(2), &[4, 2]);
        assert_eq!(bins.list(3), &[4, 1]);
    }

    #[test]
    fn many_splats_match_naive_binning() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let splats: Vec<Splat<f32>> = (0..3000)
            .map(|_| {
                let x0 = rng.gen_range(0..7);
                let y0 = rng.gen_range(0..5);
                splat(
                    rng.gen_range(0.1..10.0),
                    [x0, y0, rng.gen_range(x0 + 1..=7), rng.gen_range(y0 + 1..=5)],
                )
            })
            .collect();
        let bins = bin(&splats, 7, 5);
        for t in 0..35u32 {
            let (tx, ty) = (t % 7, t / 7);
            let mut want: Vec<u32> = (0..splats.len() as u32)
                .filter(|&i| {
                    let r = splats[i as usize].tile_rect();
                    tx >= r[0] && tx < r[2] && ty >= r[1] && ty < r[3]
                })
                .collect();
            want.sort_by(|&a, &b| {
                splats[a as usize]
                    .depth
                    .partial_cmp(&splats[b as usize].depth)
                    .unwrap()
                    .then(a.cmp(&b))
            });
            assert_eq!(bins.list(t as usize), &want[..]);
        }
    }
}
