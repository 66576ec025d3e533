//! (render, caption) pairs: random scenes seen from random orbit views, rendered with splat's renderer.
//!
//! Sample `i` of a stream with seed `s` depends only on (`s`, `i`) and the config, never on the thread
//! count or on which other samples were drawn, so a training run can resume at any index.

use super::build::{build_scene, BuildSettings, BuiltScene};
use super::spec::{GeneratorSettings, SceneSpec};
use super::WorldError;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use splat::cameras::orbit::look_at;
use splat::render::{render, RenderSettings};
use splat::{Camera, Image};
use std::collections::VecDeque;
use std::ops::Range;
use std::path::Path;

/// Ranges of the random orbit views. Cameras look at the centre of the objects' bounds, with +z up.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ViewSampling {
    /// Elevation above the horizontal plane through the centre, degrees.
    pub elevation_deg: [f32; 2],
    pub azimuth_deg: [f32; 2],
    /// Field of view across the shorter image side, degrees.
    pub fov_deg: [f32; 2],
    /// How much of the half field of view the objects' bounding sphere fills.
    pub fill: [f32; 2],
    /// Random shift of the look-at point, as a fraction of the bounding radius.
    pub target_jitter: f32,
}

impl Default for ViewSampling {
    fn default() -> Self {
        Self {
            elevation_deg: [8.0, 45.0],
            azimuth_deg: [0.0, 360.0],
            fov_deg: [35.0, 50.0],
            fill: [0.7, 0.95],
            target_jitter: 0.05,
        }
    }
}

/// Everything that determines a dataset besides its seed.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DatasetConfig {
    pub width: u32,
    pub height: u32,
    pub views: ViewSampling,
    pub generator: GeneratorSettings,
    pub build: BuildSettings,
}

impl Default for DatasetConfig {
    fn default() -> Self {
        Self {
            width: 128,
            height: 128,
            views: ViewSampling::default(),
            generator: GeneratorSettings::default(),
            build: BuildSettings::default(),
        }
    }
}

/// One rendered sample.
#[derive(Clone, Debug)]
pub struct Sample {
    pub index: u64,
    pub spec: SceneSpec,
    pub caption: String,
    pub camera: Camera,
    /// RGB, `width` x `height`.
    pub image: Image,
}

/// SplitMix64 finaliser: decorrelates nearby seeds.
fn mix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// Seeds of sample `index`'s scene and view (separate, so changing the view ranges keeps the scenes).
pub fn sample_seeds(seed: u64, index: u64) -> (u64, u64) {
    let base = mix(seed ^ mix(index));
    (mix(base ^ 1), mix(base ^ 2))
}

/// The bounding sphere (centre, radius) of a scene's objects.
pub fn bounding_sphere(spec: &SceneSpec) -> ([f64; 3], f64) {
    let (lo, hi) = spec.object_bounds();
    let centre = std::array::from_fn(|a| 0.5 * (lo[a] as f64 + hi[a] as f64));
    let radius = 0.5
        * (0..3)
            .map(|a| (hi[a] as f64 - lo[a] as f64).powi(2))
            .sum::<f64>()
            .sqrt();
    (centre, radius.max(1e-3))
}

/// Where a camera sits on the orbit around a bounding sphere.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct OrbitView {
    /// Above the horizontal plane through the sphere's centre, degrees.
    pub elevation_deg: f64,
    /// Around +z from +x, degrees.
    pub azimuth_deg: f64,
    /// Field of view across the shorter image side, degrees.
    pub fov_deg: f64,
    /// How much of the half field of view the sphere fills.
    pub fill: f64,
}

/// A `width` x `height` camera placed by `view` around the sphere (`centre`, `radius`), looking at its
/// centre with +z up, at the distance where the sphere fills `view.fill` of the half field of view.
pub fn orbit_camera(
    name: String,
    centre: [f64; 3],
    radius: f64,
    view: &OrbitView,
    width: u32,
    height: u32,
) -> Camera {
    let half_fov = 0.5 * view.fov_deg.clamp(5.0, 150.0).to_radians();
    let distance = radius / (view.fill.clamp(0.05, 1.0) * half_fov).sin();
    let (el, az) = (
        view.elevation_deg.to_radians(),
        view.azimuth_deg.to_radians(),
    );
    let eye = [
        centre[0] + distance * el.cos() * az.cos(),
        centre[1] + distance * el.cos() * az.sin(),
        centre[2] + distance * el.sin(),
    ];
    let focal = 0.5 * width.min(height) as f64 / half_fov.tan();
    look_at(name, eye, centre, [0.0, 0.0, 1.0], width, height, focal)
}

/// A random view of `spec` drawn from `views`.
pub fn random_view<R: Rng>(
    spec: &SceneSpec,
    views: &ViewSampling,
    width: u32,
    height: u32,
    rng: &mut R,
) -> Camera {
    let (centre, radius) = bounding_sphere(spec);
    let mut draw = |r: [f32; 2]| {
        if r[1] > r[0] {
            rng.gen_range(r[0]..r[1]) as f64
        } else {
            r[0] as f64
        }
    };
    let elevation = draw(views.elevation_deg);
    let azimuth = draw(views.azimuth_deg);
    let fov = draw(views.fov_deg);
    let fill = draw(views.fill);
    let j = views.target_jitter as f64 * radius;
    let target = centre.map(|c| c + if j > 0.0 { rng.gen_range(-j..j) } else { 0.0 });
    let view = OrbitView {
        elevation_deg: elevation,
        azimuth_deg: azimuth,
        fov_deg: fov,
        fill,
    };
    orbit_camera("view".into(), target, radius, &view, width, height)
}

/// `n` evenly spaced views on a ring around the scene (the demo's cameras): fixed elevation, the first at
/// azimuth `start_deg`, a 40° field of view, the objects filling 85% of it.
pub fn ring_views(
    spec: &SceneSpec,
    n: usize,
    width: u32,
    height: u32,
    elevation_deg: f64,
    start_deg: f64,
) -> Vec<Camera> {
    let (centre, radius) = bounding_sphere(spec);
    (0..n)
        .map(|k| {
            let azimuth = start_deg + 360.0 * k as f64 / n.max(1) as f64;
            let view = OrbitView {
                elevation_deg,
                azimuth_deg: azimuth,
                fov_deg: 40.0,
                fill: 0.85,
            };
            orbit_camera(format!("view_{k:03}"), centre, radius, &view, width, height)
        })
        .collect()
}

/// Renders a built scene (RGB over the spec's background).
pub fn render_view(built: &BuiltScene, camera: &Camera) -> Image {
    let settings = RenderSettings {
        background: built.spec.background,
    };
    render(&built.scene, camera, &settings, None).rgb_image()
}

/// Sample `index` of the stream `seed`.
pub fn sample(config: &DatasetConfig, seed: u64, index: u64) -> Sample {
    let (scene_seed, view_seed) = sample_seeds(seed, index);
    let spec = SceneSpec::random(scene_seed, &config.generator);
    let built = build_scene(&spec, &config.build);
    let mut rng = ChaCha8Rng::seed_from_u64(view_seed);
    let mut camera = random_view(&spec, &config.views, config.width, config.height, &mut rng);
    camera.name = format!("sample_{index:08}");
    let image = render_view(&built, &camera);
    Sample {
        index,
        caption: spec.caption(),
        spec,
        camera,
        image,
    }
}

/// Samples `indices` of the stream `seed`, rendered in parallel, in index order.
pub fn samples(config: &DatasetConfig, seed: u64, indices: Range<u64>) -> Vec<Sample> {
    indices
        .into_par_iter()
        .map(|i| sample(config, seed, i))
        .collect()
}

/// An iterator over samples `start..end` of the stream `seed`, rendered in parallel batches.
pub struct SampleStream {
    config: DatasetConfig,
    seed: u64,
    next: u64,
    end: u64,
    batch: usize,
    ready: VecDeque<Sample>,
}

/// Streams samples `start..start + n` of `seed`, rendering `batch` at a time in parallel.
pub fn stream(config: DatasetConfig, seed: u64, start: u64, n: u64, batch: usize) -> SampleStream {
    SampleStream {
        config,
        seed,
        next: start,
        end: start.saturating_add(n),
        batch: batch.max(1),
        ready: VecDeque::new(),
    }
}

impl Iterator for SampleStream {
    type Item = Sample;

    fn next(&mut self) -> Option<Sample> {
        if self.ready.is_empty() && self.next < self.end {
            let stop = self.next.saturating_add(self.batch as u64).min(self.end);
            self.ready
                .extend(samples(&self.config, self.seed, self.next..stop));
            self.next = stop;
        }
        self.ready.pop_front()
    }

    fn size_hint(&self) -> (usize, Option<usize>) {
        let left = self.ready.len() + (self.end - self.next) as usize;
        (left, Some(left))
    }
}

/// Tiles images (all the same size) into a `cols`-wide grid with a 2-pixel white gap.
pub fn tile_grid(images: &[Image], cols: usize) -> Image {
    let cols = cols.max(1);
    let rows = images.len().div_ceil(cols).max(1);
    let (w, h) = images
        .first()
        .map_or((1, 1), |i| (i.width as usize, i.height as usize));
    let gap = 2;
    let gw = cols * w + (cols + 1) * gap;
    let gh = rows * h + (rows + 1) * gap;
    let mut out = Image::from_data(gw as u32, gh as u32, 3, vec![1.0; gw * gh * 3]);
    for (k, img) in images.iter().enumerate() {
        let (x0, y0) = (gap + (k % cols) * (w + gap), gap + (k / cols) * (h + gap));
        let c = img.channels as usize;
        for y in 0..h.min(img.height as usize) {
            for x in 0..w.min(img.width as usize) {
                let src = &img.data[(y * img.width as usize + x) * c..][..3.min(c)];
                let dst = ((y0 + y) * gw + x0 + x) * 3;
                out.data[dst..dst + src.len()].copy_from_slice(src);
            }
        }
    }
    out
}

/// Renders `cols * rows` samples of stream `seed` into one PNG at `path` and their captions, one per line
/// in row-major order, into the same path with extension `txt`. Returns the captions.
pub fn write_sample_grid(
    path: &Path,
    config: &DatasetConfig,
    seed: u64,
    cols: usize,
    rows: usize,
) -> Result<Vec<String>, WorldError> {
    let batch = samples(config, seed, 0..(cols * rows) as u64);
    let images: Vec<Image> = batch.iter().map(|s| s.image.clone()).collect();
    let captions: Vec<String> = batch.into_iter().map(|s| s.caption).collect();
    let write_err = |p: &Path, msg: String| WorldError::Write {
        path: p.to_path_buf(),
        msg,
    };
    tile_grid(&images, cols)
        .save_png(path)
        .map_err(|e| write_err(path, e.reason().to_string()))?;
    let txt = path.with_extension("txt");
    let mut text = captions.join("\n");
    text.push('\n');
    files::atomic_write(&txt, text.as_bytes()).map_err(|e| write_err(&txt, e.to_string()))?;
    Ok(captions)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::world::caption::Appearance;
    use crate::world::palette::{lab_distance, ColorName};
    use crate::world::pattern::PatternKind;
    use crate::world::shape::{Shape, ShapeKind};

    fn window_colour(img: &Image, at: [f64; 2], half: i64) -> [f32; 3] {
        let (cx, cy) = (at[0].floor() as i64, at[1].floor() as i64);
        let mut sum = [0.0; 3];
        let mut n = 0.0;
        for y in cy - half..cy + half.max(1) {
            for x in cx - half..cx + half.max(1) {
                let p = img.pixel(x as u32, y as u32);
                (0..3).for_each(|k| sum[k] += p[k]);
                n += 1.0;
            }
        }
        sum.map(|s| s / n)
    }

    fn project(cam: &Camera, p: [f64; 3]) -> [f64; 2] {
        let q = cam.world_to_camera(p);
        [cam.fx * q[0] / q[2] + cam.cx, cam.fy * q[1] / q[2] + cam.cy]
    }

    fn normalize2(v: [f64; 2]) -> [f64; 2] {
        let n = (v[0] * v[0] + v[1] * v[1]).sqrt();
        [v[0] / n, v[1] / n]
    }

    #[test]
    fn every_shape_renders_its_colour_in_the_centre() {
        let gen = GeneratorSettings::default();
        let build = BuildSettings::default();
        for shape in ShapeKind::ALL {
            for color in [ColorName::Red, ColorName::Blue, ColorName::Yellow] {
                let app = Appearance {
                    shape,
                    colors: [color, ColorName::White],
                    pattern: PatternKind::Solid,
                    on_table: false,
                };
                let spec = SceneSpec::from_appearance(&app, 4, &gen);
                let built = build_scene(&spec, &build);
                // A view from the side, slightly above, looking at the object's middle.
                let cams = ring_views(&spec, 1, 64, 64, 15.0, 30.0);
                let img = render_view(&built, &cams[0]);
                // The torus' centre is its hole: look at the top of its near side instead.
                let c = if let Shape::Torus { major, minor } = spec.main.shape {
                    let eye = cams[0].center();
                    let d = normalize2([eye[0], eye[1]]);
                    let p = [major as f64 * d[0], major as f64 * d[1], 1.8 * minor as f64];
                    window_colour(&img, project(&cams[0], p), 1)
                } else {
                    window_colour(&img, [32.0, 32.0], 3)
                };
                assert!(
                    lab_distance(c, spec.main.colors[0].rgb) < 12.0,
                    "{shape:?} {color:?}: centre {c:?} vs {:?}",
                    spec.main.colors[0].rgb
                );
                // Not empty: the object covers a good part of the frame.
                let differs = img
                    .data
                    .chunks_exact(3)
                    .filter(|p| lab_distance([p[0], p[1], p[2]], spec.main.colors[0].rgb) < 15.0)
                    .count();
                assert!(differs > 64 * 64 / 20, "{shape:?}: {differs} object pixels");
            }
        }
    }

    #[test]
    fn samples_are_deterministic_and_independent_of_batching() {
        let config = DatasetConfig {
            width: 32,
            height: 32,
            ..Default::default()
        };
        let a = samples(&config, 5, 3..7);
        let b: Vec<Sample> = stream(config.clone(), 5, 0, 7, 3).skip(3).collect();
        assert_eq!(a.len(), 4);
        for (x, y) in a.iter().zip(&b) {
            assert_eq!(x.index, y.index);
            assert_eq!(x.caption, y.caption);
            assert_eq!(x.image, y.image);
            assert_eq!(x.camera, y.camera);
        }
        let c = samples(&config, 6, 3..4);
        assert_ne!(c[0].image, a[0].image);
        // The caption describes the spec.
        for s in &a {
            assert_eq!(
                crate::world::parse_caption(&s.caption).unwrap(),
                s.spec.appearance()
            );
        }
    }

    #[test]
    fn random_views_look_at_the_objects() {
        let spec = SceneSpec::random(1, &GeneratorSettings::default());
        let (centre, radius) = bounding_sphere(&spec);
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let views = ViewSampling::default();
        for _ in 0..20 {
            let cam = random_view(&spec, &views, 64, 48, &mut rng);
            let p = cam.world_to_camera(centre);
            assert!(p[2] > radius, "centre in front, beyond the bounding sphere");
            let u = cam.fx * p[0] / p[2] + cam.cx;
            let v = cam.fy * p[1] / p[2] + cam.cy;
            assert!((u - 32.0).abs() < 8.0 && (v - 24.0).abs() < 8.0, "{u} {v}");
            let c = cam.center();
            let el = ((c[2] - centre[2])
                / (0..3)
                    .map(|a| (c[a] - centre[a]).powi(2))
                    .sum::<f64>()
                    .sqrt())
            .asin();
            assert!(el.to_degrees() > 7.0 && el.to_degrees() < 46.0);
        }
    }

    #[test]
    fn grid_has_the_tiles_and_captions() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("grid.png");
        let config = DatasetConfig {
            width: 24,
            height: 24,
            ..Default::default()
        };
        let caps = write_sample_grid(&path, &config, 1, 3, 2).unwrap();
        assert_eq!(caps.len(), 6);
        let img = Image::load(&path).unwrap();
        assert_eq!((img.width, img.height), (3 * 24 + 8, 2 * 24 + 6));
        let txt = std::fs::read_to_string(path.with_extension("txt")).unwrap();
        assert_eq!(txt.lines().collect::<Vec<_>>(), caps);
    }
}
