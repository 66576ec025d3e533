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

mod grid;

pub use grid::{resample, MapGrid, Resample};

use crate::render::project::{CameraR, Splat};
use crate::render::raster::{traverse_tile, Sink, Traversal};
use crate::render::segment::{TileRect, SEG, TILE_PIXELS};
use crate::render::{project_all, tiles, Params};
use crate::{Camera, GaussianScene};
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
        let t = &mut *self.tile;
        if t.seen[k] != t.epoch {
            t.seen[k] = t.epoch;
            t.touched.push(k as u32);
            t.counts[k] = 0;
            t.rows[k * ch..(k + 1) * ch].fill(0.0);
        }
        t.counts[k] += hits.count_ones();
        let sums = &mut t.rows[k * ch..(k + 1) * ch];
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
            // More slots than threads balance the interleaved tile sets; each costs N*C floats.
            slots: (0..2 * rayon::current_num_threads().max(1))
                .map(|_| Mutex::new(None))
                .collect(),
        }
    }

    /// Adds one view's map (H*W*C for `cam`).
    ///
    /// # Panics
    /// When the map has the wrong size (a programming error).
    pub fn add_view(&mut self, cam: &Camera, map: &[f32]) {
        let (n, channels) = (self.scene.len(), self.channels);
        let npix = (cam.width * cam.height) as usize;
        assert_eq!(
            map.len(),
            npix * channels,
            "map for camera {:?} must be H*W*C = {}x{}x{channels}",
            cam.name,
            cam.height,
            cam.width
        );
        let camr = CameraR::<f32>::new(cam);
        let splats = project_all(&self.params, &camr, false);
        let (tx, ty) = camr.tiles();
        let bins = tiles::bin(&splats, tx, ty);
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
                sums: vec![0.0; n * channels],
                counts: vec![0; n],
            });
            for tile in (slot..tiles).step_by(stride) {
                let list = bins.list(tile);
                if list.is_empty() {
                    continue;
                }
                let rect = TileRect::new(tile, &bins, cam.width, cam.height);
                tile_sums.start_tile(list.len(), channels);
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
                    for (d, s) in acc.sums[g * channels..(g + 1) * channels]
                        .iter_mut()
                        .zip(src)
                    {
                        *d += s;
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

    #[test]
    fn empty_scene_and_no_views() {
        let scene = GaussianScene::new(0);
        let lifted = lift(&scene, &[], &[], 4);
        assert!(lifted.values.is_empty() && lifted.counts.is_empty());
    }
}
