//! Lifting 2D maps onto Gaussians: GaussianEditor's `apply_weights` (see docs/algorithm.md §3.1).
//!
//! For every view, the scene is projected and binned exactly as for rendering; then per pixel, front to
//! back with T = 1, each Gaussian is skipped when σ < 0 or alpha < 1/255, the pixel stops (this Gaussian
//! not counted) when T·(1 − alpha) < 1e-4, and otherwise the Gaussian is *hit*: W_j += M(p) (all
//! channels), C_j += 1, T ← T·(1 − alpha). The hit is unweighted by alpha·T, as in the reference.
//! After all views: value_j = W_j / (C_j + 1e-7).
//!
//! Each tile first sums a Gaussian's hits in a small per-tile buffer, then adds them once to a dense N·C
//! buffer owned by a fixed, interleaved set of tiles; the buffers are summed in a fixed order at the end,
//! so results do not depend on thread scheduling.

pub(crate) mod gpu;
mod grid;

pub use grid::{resample, MapGrid, Resample};

pub(crate) use grid::{axis_taps, read_by_resampling, widest_tile};
use grid::{tile_cells, Taps};

use crate::cameras::Camera;
use crate::render::project::{CameraR, Splat};
use crate::render::raster::{traverse_tile, Sink, Traversal};
use crate::render::segment::{TileRect, SEG, TILE_PIXELS};
use crate::render::TILE;
use crate::render::{project_all, tiles, Params};
use crate::scene::GaussianScene;
use rayon::prelude::*;
use std::sync::Mutex;

/// Per-Gaussian averages of the lifted maps.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Lifted {
    /// N*C averages W/(C + 1e-7), Gaussian-major.
    pub values: Vec<f32>,
    /// N hit counts (pixels over all views).
    pub counts: Vec<f32>,
}

struct Accum {
    sums: Vec<f32>,
    counts: Vec<u32>,
}

/// Per-tile partial sums, one row per list entry the tile touches: a Gaussian's hits within a tile are
/// summed here (in cache) and added to its N*C row once per tile instead of once per pixel.
#[derive(Default)]
struct TileSums {
    rows: Vec<f32>,
    counts: Vec<u32>,
    /// List positions touched in the current tile, in first-touch order.
    touched: Vec<u32>,
    /// `seen[k] == epoch` when row k is in use for the current tile.
    seen: Vec<u32>,
    epoch: u32,
}

impl TileSums {
    /// List entry `k`'s row (`len` values; zeroed at its first hit in the tile), its `hits` counted.
    #[inline(always)]
    fn hit_row(&mut self, k: usize, len: usize, hits: u32) -> &mut [f32] {
        if self.seen[k] != self.epoch {
            self.seen[k] = self.epoch;
            self.touched.push(k as u32);
            self.counts[k] = 0;
            self.rows[k * len..(k + 1) * len].fill(0.0);
        }
        self.counts[k] += hits.count_ones();
        &mut self.rows[k * len..(k + 1) * len]
    }

    fn start_tile(&mut self, list_len: usize, channels: usize) {
        if self.seen.len() < list_len {
            self.seen.resize(list_len, 0);
            self.counts.resize(list_len, 0);
            self.rows.resize(list_len * channels, 0.0);
        }
        self.touched.clear();
        self.epoch = self.epoch.wrapping_add(1);
        if self.epoch == 0 {
            self.seen.fill(0);
            self.epoch = 1;
        }
    }
}

struct LiftSink<'a> {
    tile: &'a mut TileSums,
    map: &'a [f32],
    channels: usize,
    rect: TileRect,
    width: u32,
}

impl Sink<f32> for LiftSink<'_> {
    #[inline(always)]
    fn segment(
        &mut self,
        p0: usize,
        k: usize,
        _g: u32,
        _splat: &Splat<f32>,
        _w: &[f32; SEG],
        hits: u32,
    ) {
        let ch = self.channels;
        let sums = self.tile.hit_row(k, ch, hits);
        let mut bits = hits;
        while bits != 0 {
            let l = bits.trailing_zeros() as usize;
            bits &= bits - 1;
            let gp = self.rect.global(p0 + l, self.width);
            for (d, &s) in sums.iter_mut().zip(&self.map[gp * ch..(gp + 1) * ch]) {
                *d += s;
            }
        }
    }
}

/// A view's map given on its grid rather than at the image's resolution: an upsampled pixel is a weighted
/// sum of at most four cells, so a Gaussian's sum over its hit pixels in a tile is the tile's cells
/// weighted by the summed weights of those pixels. Per hit pixel this sink adds four weights to the
/// Gaussian's row of the tile's cells (`span.0 × span.1` from `base`), where [`LiftSink`] adds every
/// channel; the channels are added once per Gaussian and tile, from the cells its pixels read.
struct GridSink<'a> {
    tile: &'a mut TileSums,
    rows: &'a [Taps],
    cols: &'a [Taps],
    rect: TileRect,
    /// The tile's first cell (row, column) and the cells its pixels read along each axis.
    base: (u32, u32),
    span: (usize, usize),
}

impl Sink<f32> for GridSink<'_> {
    #[inline(always)]
    fn segment(
        &mut self,
        p0: usize,
        k: usize,
        _g: u32,
        _splat: &Splat<f32>,
        _w: &[f32; SEG],
        hits: u32,
    ) {
        let weights = self.tile.hit_row(k, self.span.0 * self.span.1, hits);
        let mut bits = hits;
        while bits != 0 {
            let l = bits.trailing_zeros() as usize;
            bits &= bits - 1;
            let p = p0 + l;
            let ty = self.rows[(self.rect.y0 as usize) + p / TILE as usize];
            let tx = self.cols[(self.rect.x0 as usize) + p % TILE as usize];
            for a in 0..2 {
                let row = (ty.cells[a] - self.base.0) as usize * self.span.1;
                for b in 0..2 {
                    weights[row + (tx.cells[b] - self.base.1) as usize] +=
                        ty.weights[a] * tx.weights[b];
                }
            }
        }
    }
}

/// Cells per tile side beyond which [`LiftAccumulator::add_view_on_grid`] upsamples the map and lifts
/// per pixel: with fine grids a Gaussian's pixels in a tile read nearly as many cells as there are
/// pixels, and the per-tile weight rows only add work.
const MAX_GRID_SPAN: usize = 8;

/// Lifts per-view maps (`maps[v]` is H*W*C for `cameras[v]`, row-major, channel-interleaved) onto the
/// Gaussians of `scene`.
///
/// # Panics
/// When `maps` and `cameras` differ in length, a map has the wrong size, or the scene is inconsistent
/// (programming errors).
pub fn lift(scene: &GaussianScene, cameras: &[Camera], maps: &[&[f32]], channels: usize) -> Lifted {
    assert_eq!(cameras.len(), maps.len(), "one map per camera");
    let mut acc = LiftAccumulator::new(scene, channels);
    for (cam, map) in cameras.iter().zip(maps) {
        acc.add_view(cam, map);
    }
    acc.finish()
}

/// One view's map as [`LiftAccumulator`] takes it.
enum ViewMap<'m> {
    /// At the camera's resolution (H*W*C).
    Full(&'m [f32]),
    /// On a grid (cells row-major, `grid_width` per row, channels interleaved), with each image row's and
    /// column's taps and the most cells a tile reads along each axis.
    Grid {
        map: &'m [f32],
        grid_width: usize,
        rows: &'m [Taps],
        cols: &'m [Taps],
        span: (usize, usize),
    },
}

/// `len` zeros written into fresh memory rather than allocated zeroed. The sums are read before they are
/// first written, and a zeroed allocation's page that is read first maps the shared zero page: each page
/// then faults twice, the second time copying and flushing the TLB of every core. With hundreds of
/// channels that was a third of a lifting round's time, in the kernel (perf, 2026-12-07).
fn written_zeros(len: usize) -> Vec<f32> {
    let mut v = Vec::with_capacity(len);
    v.resize(len, 0.0);
    v
}

/// `dst += w · src`, elementwise.
#[inline(always)]
fn add_to(dst: &mut [f32], src: &[f32], w: f32) {
    for (d, &s) in dst.iter_mut().zip(src) {
        *d += w * s;
    }
}

/// [`lift`] one view at a time, so callers never hold every view's (possibly many-channel, full-resolution)
/// map at once: the sums and counts are accumulated as views are added.
pub struct LiftAccumulator<'s> {
    scene: &'s GaussianScene,
    params: Params<'s, f32>,
    channels: usize,
    slots: Vec<Mutex<Option<Accum>>>,
}

impl<'s> LiftAccumulator<'s> {
    pub fn new(scene: &'s GaussianScene, channels: usize) -> Self {
        Self {
            scene,
            params: Params::from_scene(scene),
            channels,
            slots: (0..Self::slot_count()).map(|_| Mutex::new(None)).collect(),
        }
    }

    /// The partial sums an accumulator keeps, each N*C floats: more slots than threads balance the
    /// interleaved tile sets.
    pub fn slot_count() -> usize {
        2 * rayon::current_num_threads().max(1)
    }

    /// Adds one view's map (H*W*C for `cam`).
    ///
    /// # Panics
    /// When the map has the wrong size (a programming error).
    pub fn add_view(&mut self, cam: &Camera, map: &[f32]) {
        let channels = self.channels;
        let npix = (cam.width * cam.height) as usize;
        assert_eq!(
            map.len(),
            npix * channels,
            "map for camera {:?} must be H*W*C = {}x{}x{channels}",
            cam.name,
            cam.height,
            cam.width
        );
        self.add(cam, &ViewMap::Full(map));
    }

    /// Adds one view's map given on `grid` (`grid.len()` values), as [`Self::add_view`] adds it upsampled
    /// to the camera's resolution (`grid.up`), equal to float rounding, without making the upsampled map:
    /// see `GridSink`. Grids finer than `MAX_GRID_SPAN` cells per tile side are upsampled.
    ///
    /// # Panics
    /// When the map has the wrong size or `grid.channels` is not the accumulator's (programming errors).
    pub fn add_view_on_grid(&mut self, cam: &Camera, map: &[f32], grid: &MapGrid) {
        assert_eq!(map.len(), grid.len(), "map must be on the grid");
        assert_eq!(grid.channels, self.channels, "grid channels");
        let full = (cam.height as usize, cam.width as usize);
        if full.0 * full.1 == 0 {
            return;
        }
        let rows = axis_taps(full.0, grid.height, grid.up);
        let cols = axis_taps(full.1, grid.width, grid.up);
        let span = (widest_tile(&rows), widest_tile(&cols));
        if span.0.max(span.1) > MAX_GRID_SPAN {
            let native = (grid.height, grid.width);
            let up = resample(map, native, full, grid.channels, grid.up);
            return self.add_view(cam, &up);
        }
        self.add(
            cam,
            &ViewMap::Grid {
                map,
                grid_width: grid.width,
                rows: &rows,
                cols: &cols,
                span,
            },
        );
    }

    fn add(&mut self, cam: &Camera, view: &ViewMap<'_>) {
        let (n, channels) = (self.scene.len(), self.channels);
        let camr = CameraR::<f32>::new(cam);
        let splats = project_all(&self.params, &camr, false);
        let (tx, ty) = camr.tiles();
        let bins = tiles::bin(&splats, tx, ty);
        let row_len = match view {
            ViewMap::Full(_) => channels,
            ViewMap::Grid { span, .. } => span.0 * span.1,
        };
        // Each slot owns a fixed, interleaved subset of the tiles and walks it in order, so the sums do not
        // depend on thread scheduling: the same inputs give bit-identical results (resumable runs rely on it).
        let slots = &self.slots;
        let stride = slots.len();
        let tiles = bins.num_tiles();
        (0..stride).into_par_iter().for_each(|slot| {
            let mut trans = Box::new([0f32; TILE_PIXELS]);
            let mut last = Box::new([0u32; TILE_PIXELS]);
            let mut tile_sums = TileSums::default();
            let mut guard = slots[slot].lock().unwrap_or_else(|e| e.into_inner());
            let acc = guard.get_or_insert_with(|| Accum {
                sums: written_zeros(n * channels),
                counts: vec![0; n],
            });
            for tile in (slot..tiles).step_by(stride) {
                let list = bins.list(tile);
                if list.is_empty() {
                    continue;
                }
                let rect = TileRect::new(tile, &bins, cam.width, cam.height);
                tile_sums.start_tile(list.len(), row_len);
                match *view {
                    ViewMap::Full(map) => {
                        let mut sink = LiftSink {
                            tile: &mut tile_sums,
                            map,
                            channels,
                            rect,
                            width: cam.width,
                        };
                        traverse_tile(Traversal {
                            splats: &splats,
                            list,
                            rect: &rect,
                            sink: &mut sink,
                            trans: &mut trans,
                            last: &mut last,
                        });
                        for &k in &tile_sums.touched {
                            let k = k as usize;
                            let g = list[k] as usize;
                            acc.counts[g] += tile_sums.counts[k];
                            let src = &tile_sums.rows[k * channels..(k + 1) * channels];
                            add_to(&mut acc.sums[g * channels..(g + 1) * channels], src, 1.0);
                        }
                    }
                    ViewMap::Grid {
                        map,
                        grid_width,
                        rows,
                        cols,
                        span,
                    } => {
                        let base = (
                            tile_cells(rows, rect.y0 as usize).0,
                            tile_cells(cols, rect.x0 as usize).0,
                        );
                        let mut sink = GridSink {
                            tile: &mut tile_sums,
                            rows,
                            cols,
                            rect,
                            base,
                            span,
                        };
                        traverse_tile(Traversal {
                            splats: &splats,
                            list,
                            rect: &rect,
                            sink: &mut sink,
                            trans: &mut trans,
                            last: &mut last,
                        });
                        let len = span.0 * span.1;
                        for &k in &tile_sums.touched {
                            let k = k as usize;
                            let g = list[k] as usize;
                            acc.counts[g] += tile_sums.counts[k];
                            let sums = &mut acc.sums[g * channels..(g + 1) * channels];
                            for (c, &w) in tile_sums.rows[k * len..(k + 1) * len].iter().enumerate()
                            {
                                if w != 0.0 {
                                    let cy = base.0 as usize + c / span.1;
                                    let cx = base.1 as usize + c % span.1;
                                    let cell = (cy * grid_width + cx) * channels;
                                    add_to(sums, &map[cell..cell + channels], w);
                                }
                            }
                        }
                    }
                }
            }
        });
    }

    /// The per-Gaussian averages W / (C + 1e-7) and counts over all views added.
    pub fn finish(self) -> Lifted {
        let (n, channels) = (self.scene.len(), self.channels);
        let mut parts: Vec<Accum> = self
            .slots
            .into_iter()
            .filter_map(|m| m.into_inner().unwrap_or_else(|e| e.into_inner()))
            .collect();
        let mut total = parts.pop().unwrap_or_else(|| Accum {
            sums: vec![0.0; n * channels],
            counts: vec![0; n],
        });
        for part in &parts {
            total
                .sums
                .par_iter_mut()
                .zip(part.sums.par_iter())
                .for_each(|(a, b)| *a += b);
            for (a, b) in total.counts.iter_mut().zip(&part.counts) {
                *a += b;
            }
        }
        let counts: Vec<f32> = total.counts.iter().map(|&c| c as f32).collect();
        let mut values = total.sums;
        if channels > 0 {
            values
                .par_chunks_mut(channels)
                .zip(counts.par_iter())
                .for_each(|(row, &c)| {
                    let inv = 1.0 / (c + 1e-7);
                    for v in row {
                        *v *= inv;
                    }
                });
        }
        Lifted { values, counts }
    }
}

/// `width` channels of each of `cells` cells copied from one interleaved map to another: from channel
/// `from.1` of a map of `from.0` channels per cell to channel `to.1` of one of `to.0`.
#[derive(Clone, Copy, Debug)]
pub(crate) struct ChannelSlice {
    pub cells: usize,
    pub width: usize,
    pub from: (usize, usize),
    pub to: (usize, usize),
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::real::Real;
    use crate::render::segment::sigma_at;
    use crate::render::{ALPHA_MAX, ALPHA_MIN};

    /// A camera at the origin looking down +z.
    fn cam(width: u32, height: u32, f: f64, tx: f64) -> Camera {
        Camera {
            name: "v".into(),
            width,
            height,
            fx: f,
            fy: f,
            cx: width as f64 / 2.0,
            cy: height as f64 / 2.0,
            rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            translation: [tx, 0.0, 0.0],
        }
    }

    /// Adds an isotropic Gaussian at world position `m` with world std `s` and opacity `o`.
    fn push(scene: &mut GaussianScene, m: [f32; 3], s: f32, o: f32) {
        scene.means.extend_from_slice(&m);
        scene.log_scales.extend_from_slice(&[s.ln(); 3]);
        scene.quats.extend_from_slice(&[1.0, 0.0, 0.0, 0.0]);
        scene.opacity_logits.push((o / (1.0 - o)).ln());
        scene.sh.extend_from_slice(&[0.0; 3]);
    }

    /// Pixels of `cam` where a lone Gaussian `i` passes the alpha tests (what it must be hit on when
    /// nothing occludes it), computed by brute force over all pixels and tiles.
    fn brute_force_hits(scene: &GaussianScene, cam: &Camera, i: usize) -> u32 {
        let camr = CameraR::<f32>::new(cam);
        let s = crate::render::project::project_one(&Params::from_scene(scene), i, &camr, false);
        if s.radius == 0 {
            return 0;
        }
        let mut hits = 0;
        for y in 0..cam.height {
            for x in 0..cam.width {
                let (tx, ty) = (x / 16, y / 16);
                let [x0, y0, x1, y1] = s.tile_rect();
                if tx < x0 || tx >= x1 || ty < y0 || ty >= y1 {
                    continue;
                }
                let dx = s.mean[0] - (x as f32 + 0.5);
                let dy = s.mean[1] - (y as f32 + 0.5);
                let sigma = sigma_at(&s.conic, dx, dy);
                let alpha = (s.opacity * (-sigma).exp_fast()).min(ALPHA_MAX as f32);
                if sigma >= 0.0 && alpha >= ALPHA_MIN as f32 {
                    hits += 1;
                }
            }
        }
        hits
    }

    #[test]
    fn left_and_right_gaussians_get_their_half_of_the_map() {
        // 64x16 view; Gaussians at pixel x = 16 and x = 48 with a 3 px std: their support (alpha ≥ 1/255
        // reaches ~3.3σ ≈ 10 px) stays inside their own half.
        let c = cam(64, 16, 32.0, 0.0);
        let mut scene = GaussianScene::new(0);
        push(&mut scene, [-1.0, 0.0, 2.0], 3.0 * 2.0 / 32.0, 0.95);
        push(&mut scene, [1.0, 0.0, 2.0], 3.0 * 2.0 / 32.0, 0.95);
        let map: Vec<f32> = (0..64 * 16)
            .map(|p| if p % 64 < 32 { 1.0 } else { 0.0 })
            .collect();
        let lifted = lift(&scene, std::slice::from_ref(&c), &[&map], 1);
        assert!((lifted.values[0] - 1.0).abs() < 1e-6, "{:?}", lifted.values);
        assert_eq!(lifted.values[1], 0.0);
        for i in 0..2 {
            assert_eq!(lifted.counts[i] as u32, brute_force_hits(&scene, &c, i));
            assert!(lifted.counts[i] > 50.0);
        }
    }

    #[test]
    fn occluded_gaussian_gets_no_hits() {
        let c = cam(32, 32, 32.0, 0.0);
        let mut scene = GaussianScene::new(0);
        // Small Gaussian at the back (index 0), four wide near-opaque layers in front of it: where the small
        // one reaches alpha ≥ 1/255 the layers leave T·(1 − alpha) < 1e-4, so every pixel stops first.
        push(&mut scene, [0.0, 0.0, 4.0], 1.0 * 4.0 / 32.0, 0.9);
        for k in 0..4 {
            let z = 2.0 + 0.2 * k as f32;
            push(&mut scene, [0.0, 0.0, z], 8.0 * z / 32.0, 0.999);
        }
        let map = vec![1.0f32; 32 * 32];
        let lifted = lift(&scene, std::slice::from_ref(&c), &[&map], 1);
        assert_eq!(lifted.counts[0], 0.0, "{:?}", lifted.counts);
        assert_eq!(lifted.values[0], 0.0);
        assert!(
            brute_force_hits(&scene, &c, 0) > 0,
            "the back Gaussian is on screen"
        );
        assert!(lifted.counts[1] > 100.0);
        assert!((lifted.values[1] - 1.0).abs() < 1e-6);
    }

    #[test]
    fn two_views_average_weighted_by_pixel_counts() {
        let mut scene = GaussianScene::new(0);
        push(&mut scene, [0.0, 0.0, 3.0], 0.2, 0.8);
        // Two views at different resolutions and positions see it with different pixel counts.
        let v1 = cam(48, 40, 40.0, 0.1);
        let v2 = cam(32, 32, 20.0, -0.3);
        let n1 = brute_force_hits(&scene, &v1, 0) as f32;
        let n2 = brute_force_hits(&scene, &v2, 0) as f32;
        assert!(n1 > 0.0 && n2 > 0.0 && n1 != n2);
        let ones = vec![1.0f32; 48 * 40];
        let zeros = vec![0.0f32; 32 * 32];
        let lifted = lift(&scene, &[v1, v2], &[&ones, &zeros], 1);
        assert_eq!(lifted.counts[0], n1 + n2);
        let want = n1 / (n1 + n2 + 1e-7);
        assert!(
            (lifted.values[0] - want).abs() < 1e-6,
            "{} vs {want}",
            lifted.values[0]
        );
    }

    #[test]
    fn many_channels_average_pixel_coordinates() {
        // Channels: x, y of the pixel centre and a constant. A symmetric footprint averages to its centre.
        let c = cam(40, 36, 30.0, 0.0);
        let mut scene = GaussianScene::new(0);
        push(&mut scene, [0.0, 0.0, 2.5], 0.25, 0.7);
        let mut map = Vec::new();
        for y in 0..36 {
            for x in 0..40 {
                map.extend_from_slice(&[x as f32 + 0.5, y as f32 + 0.5, 2.0]);
            }
        }
        let lifted = lift(&scene, &[c], &[&map], 3);
        assert!(
            (lifted.values[0] - 20.0).abs() < 1e-3,
            "{:?}",
            lifted.values
        );
        assert!((lifted.values[1] - 18.0).abs() < 1e-3);
        assert!((lifted.values[2] - 2.0).abs() < 1e-5);
    }

    /// Lifting a map on its grid equals lifting it upsampled: the same hit counts, the values to float
    /// rounding; odd ratios, a grid coarser than a tile, one finer than [`MAX_GRID_SPAN`] (upsampled).
    #[test]
    fn lifting_on_the_grid_matches_lifting_upsampled_maps() {
        let mut scene = GaussianScene::new(0);
        let mut state = 12345u64;
        let mut next = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 40) as f32 / (1u64 << 24) as f32
        };
        for _ in 0..400 {
            let m = [next() * 3.0 - 1.5, next() * 3.0 - 1.5, 2.0 + next() * 2.0];
            push(&mut scene, m, 0.02 + 0.25 * next(), 0.05 + 0.9 * next());
        }
        let channels = 5;
        for ((w, h), (gh, gw)) in [
            ((40, 34), (9, 10)),
            ((128, 128), (16, 16)),
            ((70, 50), (3, 5)),
            ((64, 64), (64, 64)),
        ] {
            for mode in [Resample::Bilinear, Resample::Nearest] {
                let grid = MapGrid {
                    height: gh,
                    width: gw,
                    channels,
                    up: mode,
                    down: mode,
                };
                let cams = [
                    cam(w, h, w as f64 * 0.6, 0.0),
                    cam(w, h, w as f64 * 0.8, 0.4),
                ];
                let maps: Vec<Vec<f32>> = (0..2)
                    .map(|v| {
                        (0..grid.len())
                            .map(|i| ((i * 7 + v * 3) % 11) as f32 / 10.0)
                            .collect()
                    })
                    .collect();
                let mut on_grid = LiftAccumulator::new(&scene, channels);
                let mut upsampled = LiftAccumulator::new(&scene, channels);
                for (c, map) in cams.iter().zip(&maps) {
                    on_grid.add_view_on_grid(c, map, &grid);
                    let full = (h as usize, w as usize);
                    upsampled.add_view(c, &resample(map, (gh, gw), full, channels, mode));
                }
                let (got, want) = (on_grid.finish(), upsampled.finish());
                assert_eq!(got.counts, want.counts, "{w}x{h} on {gh}x{gw} {mode:?}");
                assert!(want.counts.iter().filter(|&&c| c > 0.0).count() > 100);
                let worst = got
                    .values
                    .iter()
                    .zip(&want.values)
                    .map(|(a, b)| (a - b).abs())
                    .fold(0.0f32, f32::max);
                assert!(
                    worst < 1e-5,
                    "{w}x{h} on {gh}x{gw} {mode:?}: off by {worst}"
                );
            }
        }
    }

    #[test]
    fn empty_scene_and_no_views() {
        let scene = GaussianScene::new(0);
        let lifted = lift(&scene, &[], &[], 4);
        assert!(lifted.values.is_empty() && lifted.counts.is_empty());
    }
}
