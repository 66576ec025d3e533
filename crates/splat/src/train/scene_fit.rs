//! Fitting a scene to posed images (the INRIA trainer's recipe on the CPU): load the views, initialise
//! Gaussians from a sparse point cloud or random points in the region the cameras look at, then optimise
//! `(1 − λ)·L1 + λ·D-SSIM` with Adam, raising the SH degree every `sh_degree_interval` steps and densifying
//! with [`DefaultStrategy`].

use crate::cameras::Camera;
use crate::cameras::{crop_window, load_cameras, to_working_resolution, CameraError, PointCloud};
use crate::device::SplatDevice;
use crate::image::Image;
use crate::image::ImageError;
use crate::render::{render, RenderSettings};
use crate::scene::GaussianScene;
use crate::train::densify::{DefaultStrategy, RefineReport};
use crate::train::gpu::L1DssimWeights;
use crate::train::loss::{l1_dssim, psnr, DEFAULT_SSIM_WEIGHT};
use crate::train::optim::LearningRates;
use crate::train::{FitLoss, StepKind, StepOutcome, Trainer};
use crate::train::{RenderedView, TrainState};
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use std::path::{Path, PathBuf};

/// Zeroth-order SH basis constant: colour = 0.5 + C0 · DC.
const SH_C0: f32 = 0.282_094_8;

#[derive(Debug, thiserror::Error)]
pub enum FitError {
    #[error(transparent)]
    Cameras(#[from] CameraError),
    #[error(transparent)]
    Image(#[from] ImageError),
    #[error("{}: {msg}", path.display())]
    Dataset { path: PathBuf, msg: String },
}

/// One posed training or test image.
#[derive(Clone, Debug)]
pub struct View {
    pub camera: Camera,
    /// H*W*3 RGB in [0, 1], alpha already composited on the background.
    pub image: Vec<f32>,
}

/// Posed images split into training and held-out views.
#[derive(Clone, Debug)]
pub struct Dataset {
    pub train: Vec<View>,
    pub test: Vec<View>,
    /// Sparse points for initialisation (COLMAP `points3D`), when the source has them.
    pub points: Option<PointCloud>,
}

/// How to read a dataset.
#[derive(Clone, Debug, PartialEq)]
pub struct DatasetOptions {
    /// Working resolution (centre-crop to its aspect, then resample); `None` keeps the images' size.
    pub size: Option<(u32, u32)>,
    /// Hold out views 0, k, 2k, ... (the INRIA trainer's `llffhold` convention); 0 = none.
    pub holdout_every: usize,
    /// Colour transparent pixels are composited on (must match the render background).
    pub background: [f32; 3],
}

/// Loads posed images from a folder or file understood by [`load_cameras`].
pub fn load_dataset(path: &Path, opts: &DatasetOptions) -> Result<Dataset, FitError> {
    let set = load_cameras(path)?;
    let bad = |msg: String| FitError::Dataset {
        path: path.to_path_buf(),
        msg,
    };
    if set.cameras.is_empty() {
        return Err(bad("no views".into()));
    }
    let views: Vec<Result<View, FitError>> = set
        .cameras
        .par_iter()
        .zip(&set.image_paths)
        .map(|(cam, img_path)| {
            let img_path = img_path.as_ref().ok_or_else(|| FitError::Dataset {
                path: path.to_path_buf(),
                msg: format!("camera '{}' names no image", cam.name),
            })?;
            let img = Image::load(img_path)?;
            load_view(cam, &img, opts).map_err(|msg| FitError::Dataset {
                path: img_path.clone(),
                msg,
            })
        })
        .collect();
    let mut train = Vec::new();
    let mut test = Vec::new();
    for (i, v) in views.into_iter().enumerate() {
        let v = v?;
        if opts.holdout_every > 0 && i % opts.holdout_every == 0 {
            test.push(v);
        } else {
            train.push(v);
        }
    }
    if train.is_empty() {
        return Err(bad(format!(
            "no training views left after holding out every {}th of {}",
            opts.holdout_every,
            set.cameras.len()
        )));
    }
    Ok(Dataset {
        train,
        test,
        points: set.points,
    })
}

/// Adapts a camera and its image to the working resolution and composites alpha.
fn load_view(cam: &Camera, img: &Image, opts: &DatasetOptions) -> Result<View, String> {
    let (iw, ih) = (img.width, img.height);
    // The camera may describe the image at another resolution (e.g. downscaled copies): same aspect only.
    let cam = if (cam.width, cam.height) != (iw, ih) {
        let a = cam.width as f64 / cam.height as f64;
        let b = iw as f64 / ih as f64;
        if (a - b).abs() > 0.01 * a {
            return Err(format!(
                "image is {iw}x{ih} but its camera is {}x{}",
                cam.width, cam.height
            ));
        }
        to_working_resolution(cam, iw, ih)
    } else {
        cam.clone()
    };
    let rgb = composite(img, opts.background)?;
    let (w, h) = opts.size.unwrap_or((iw, ih));
    if (w, h) == (iw, ih) {
        return Ok(View {
            camera: cam,
            image: rgb,
        });
    }
    let window = crop_window(iw, ih, w, h);
    Ok(View {
        camera: to_working_resolution(&cam, w, h),
        image: resample_area(
            &rgb,
            iw as usize,
            ih as usize,
            window,
            w as usize,
            h as usize,
        ),
    })
}

/// RGB(A) image to RGB composited on `background` (non-premultiplied alpha, as PNG stores it).
fn composite(img: &Image, background: [f32; 3]) -> Result<Vec<f32>, String> {
    match img.channels {
        3 => Ok(img.data.clone()),
        4 => Ok(img
            .data
            .chunks_exact(4)
            .flat_map(|p| {
                let a = p[3];
                [0, 1, 2].map(|c| p[c] * a + background[c] * (1.0 - a))
            })
            .collect()),
        c => Err(format!("{c}-channel images are not supported")),
    }
}

/// Resamples the window (x0, y0, w, h) of an RGB image to `ow` x `oh` by exact area averaging (each output
/// pixel is the mean of the source area it covers, partial pixels weighted by coverage).
fn resample_area(
    src: &[f32],
    sw: usize,
    sh: usize,
    window: [f64; 4],
    ow: usize,
    oh: usize,
) -> Vec<f32> {
    let [x0, y0, cw, ch] = window;
    // Per output column/row: covered source pixels and their weights.
    let spans = |start: f64, len: f64, n_out: usize, n_src: usize| -> Vec<Vec<(usize, f32)>> {
        (0..n_out)
            .map(|o| {
                let a = start + len * o as f64 / n_out as f64;
                let b = start + len * (o + 1) as f64 / n_out as f64;
                let mut v = Vec::new();
                let first = a.floor().max(0.0) as usize;
                let last = (b.ceil() as usize).min(n_src);
                for s in first..last {
                    let cover = (b.min(s as f64 + 1.0) - a.max(s as f64)).max(0.0);
                    if cover > 0.0 {
                        v.push((s, (cover / (b - a)) as f32));
                    }
                }
                if v.is_empty() {
                    v.push(((a.floor().max(0.0) as usize).min(n_src - 1), 1.0));
                }
                v
            })
            .collect()
    };
    let xs = spans(x0, cw, ow, sw);
    let ys = spans(y0, ch, oh, sh);
    let mut out = vec![0.0f32; ow * oh * 3];
    out.par_chunks_mut(ow * 3)
        .enumerate()
        .for_each(|(oy, row)| {
            for (ox, px) in row.chunks_exact_mut(3).enumerate() {
                let mut acc = [0.0f32; 3];
                for &(sy, wy) in &ys[oy] {
                    for &(sx, wx) in &xs[ox] {
                        let w = wx * wy;
                        let p = &src[(sy * sw + sx) * 3..(sy * sw + sx) * 3 + 3];
                        for c in 0..3 {
                            acc[c] += w * p[c];
                        }
                    }
                }
                px.copy_from_slice(&acc);
            }
        });
    out
}

/// Scene extent as the INRIA trainer computes it (1.1 × the largest distance of a camera centre from
/// their mean) and that mean.
pub(crate) fn camera_extent(cameras: &[Camera]) -> ([f32; 3], f32) {
    let set = crate::cameras::CameraSet {
        cameras: cameras.to_vec(),
        ..Default::default()
    };
    match set.camera_extent() {
        Some((c, r)) => (c.map(|v| v as f32), (r as f32).max(1e-6)),
        None => ([0.0; 3], 1.0),
    }
}

/// Settings of [`fit`].
#[derive(Clone, Debug)]
pub struct FitConfig {
    pub steps: u64,
    pub background: [f32; 3],
    pub seed: u64,
    /// Highest SH degree; the degree rises by one every `sh_degree_interval` steps up to it.
    pub sh_degree: u32,
    pub sh_degree_interval: u64,
    /// λ of `(1 − λ)·L1 + λ·D-SSIM`.
    pub ssim_weight: f32,
    /// Learning rates; the position schedule's `max_steps` is set to `steps` by [`fit`].
    pub rates: LearningRates,
    pub strategy: DefaultStrategy,
    /// Random points when the dataset has no point cloud. The INRIA trainer uses 100k; densification fills
    /// in from far fewer, and the first (most overlapped) steps get 5x cheaper on the CPU.
    pub init_points: usize,
    pub init_opacity: f32,
    /// Evaluate held-out PSNR every this many steps (0 = only at the end).
    pub eval_every: u64,
}

impl Default for FitConfig {
    fn default() -> Self {
        Self {
            steps: 30_000,
            background: [0.0; 3],
            seed: 0,
            sh_degree: 3,
            sh_degree_interval: 1000,
            ssim_weight: DEFAULT_SSIM_WEIGHT,
            rates: LearningRates::inria(30_000),
            strategy: DefaultStrategy::default(),
            init_points: 20_000,
            init_opacity: 0.1,
            eval_every: 0,
        }
    }
}

impl FitConfig {
    /// The INRIA schedule compressed to `steps`: densification stops halfway (as 15k of 30k does), capped
    /// at the trainer's 15000; the position rate decays over `steps`.
    pub fn for_steps(steps: u64) -> Self {
        let default = Self::default();
        Self {
            steps,
            rates: LearningRates::inria(steps),
            strategy: DefaultStrategy {
                refine_stop: (steps / 2).min(default.strategy.refine_stop),
                ..default.strategy.clone()
            },
            ..default
        }
    }
}

/// How often a device-resident step of [`fit`] reads its loss back. Reading it waits for everything
/// queued before it, so reading every step leaves the GPU idle while the host queues the next step
/// (the only other wait of a step is the binning's pair count).
pub const LOSS_READ_EVERY: u64 = 10;

/// Progress reported by [`fit`] after every step.
#[derive(Clone, Debug)]
pub struct FitProgress {
    /// Steps done.
    pub step: u64,
    pub steps: u64,
    /// Training loss of this step, where it was read: every step that runs on the host, and every
    /// [`LOSS_READ_EVERY`]-th step and the last on a device (a read waits for the device to finish).
    pub loss: Option<f32>,
    pub gaussians: usize,
    /// Mean held-out PSNR when it was evaluated at this step.
    pub test_psnr: Option<f64>,
    /// What densification did at this step.
    pub refine: Option<RefineReport>,
}

/// Result of [`fit`].
#[derive(Clone, Debug)]
pub struct FitResult {
    pub scene: GaussianScene,
    /// Mean PSNR over the held-out views at the end (`None` without held-out views).
    pub test_psnr: Option<f64>,
    /// Mean PSNR over the training views at the end.
    pub train_psnr: f64,
    /// Seconds per phase: rendering, loss, backward, optimiser + densification.
    pub seconds: StageTimes,
}

/// Wall-clock seconds spent per stage of the training loop.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StageTimes {
    pub render: f64,
    pub loss: f64,
    pub backward: f64,
    pub optimise: f64,
    pub densify: f64,
    pub eval: f64,
    /// Reads from the device during the fit (pair counts, losses, state downloads) and the seconds the
    /// host waited in them: of a resident step's time, what the device took beyond the host's launching.
    pub device_reads: u64,
    pub device_wait: f64,
}

/// Initial Gaussians: the dataset's points if it has some, else `count` random points in the region the
/// training cameras look at. Isotropic scales from the mean squared distance to the 3 nearest neighbours
/// (INRIA `create_from_pcd`), identity rotations, opacity `opacity`, SH degree 0.
pub fn initial_scene<R: Rng>(
    dataset: &Dataset,
    count: usize,
    opacity: f32,
    rng: &mut R,
) -> GaussianScene {
    let (positions, colors) = match &dataset.points {
        Some(p) if !p.positions.is_empty() => (p.positions.clone(), p.colors.clone()),
        _ => {
            let cams: Vec<&Camera> = dataset.train.iter().map(|v| &v.camera).collect();
            let positions = random_points_in_view(&cams, count, rng);
            let colors = (0..positions.len())
                .map(|_| [rng.gen(), rng.gen(), rng.gen()])
                .collect();
            (positions, colors)
        }
    };
    let n = positions.len();
    let d2 = mean_sq_dist_3nn(&positions);
    let logit = (opacity / (1.0 - opacity)).ln();
    GaussianScene {
        sh_degree: 0,
        means: positions.iter().flatten().copied().collect(),
        log_scales: d2
            .iter()
            .flat_map(|&d| [0.5 * d.max(1e-7).ln(); 3])
            .collect(),
        quats: (0..n).flat_map(|_| [1.0, 0.0, 0.0, 0.0]).collect(),
        opacity_logits: vec![logit; n],
        sh: colors
            .iter()
            .flat_map(|c| c.map(|v| (v - 0.5) / SH_C0))
            .collect(),
    }
}

/// Uniform random points in the box the cameras look at, kept when they project inside at least half
/// of the cameras' images. The box is centred on the point closest (least squares) to all optical axes,
/// with a half-size that fills the average camera's field of view at its distance.
fn random_points_in_view<R: Rng>(cams: &[&Camera], count: usize, rng: &mut R) -> Vec<[f32; 3]> {
    // Focus: minimise Σ |(I − d dᵀ)(p − c)|² over camera axes (c, d).
    let mut a = [[0.0f64; 3]; 3];
    let mut b = [0.0f64; 3];
    let mut axes = Vec::with_capacity(cams.len());
    for cam in cams {
        let c = cam.center();
        let d = cam.rotation[2]; // third row of world-to-camera = optical axis in world
        axes.push((c, d));
        for i in 0..3 {
            for j in 0..3 {
                let m = if i == j { 1.0 } else { 0.0 } - d[i] * d[j];
                a[i][j] += m;
                b[i] += m * c[j];
            }
        }
    }
    let focus = solve3(a, b).unwrap_or_else(|| {
        // Parallel axes (e.g. one camera): a point in front of the mean camera.
        let (c, d) = axes[0];
        [c[0] + d[0], c[1] + d[1], c[2] + d[2]]
    });
    let mut half = 0.0f64;
    for cam in cams {
        let q = cam.world_to_camera(focus);
        let depth = q[2].abs().max(1e-3);
        let hx = depth * cam.width as f64 / (2.0 * cam.fx);
        let hy = depth * cam.height as f64 / (2.0 * cam.fy);
        half += hx.max(hy);
    }
    half /= cams.len() as f64;
    let visible_in_half = |p: [f64; 3]| {
        let seen = cams
            .iter()
            .filter(|cam| {
                let q = cam.world_to_camera(p);
                if q[2] <= 1e-3 {
                    return false;
                }
                let u = cam.fx * q[0] / q[2] + cam.cx;
                let v = cam.fy * q[1] / q[2] + cam.cy;
                u >= 0.0 && v >= 0.0 && u < cam.width as f64 && v < cam.height as f64
            })
            .count();
        2 * seen >= cams.len()
    };
    let mut out = Vec::with_capacity(count);
    // Bounded tries so a degenerate rig cannot loop forever.
    for _ in 0..count.saturating_mul(20) {
        if out.len() == count {
            break;
        }
        let p: [f64; 3] = std::array::from_fn(|i| focus[i] + half * (2.0 * rng.gen::<f64>() - 1.0));
        if visible_in_half(p) {
            out.push(p.map(|v| v as f32));
        }
    }
    out
}

/// Solves a 3x3 linear system by Cramer's rule; `None` when (nearly) singular.
fn solve3(a: [[f64; 3]; 3], b: [f64; 3]) -> Option<[f64; 3]> {
    let det = |m: [[f64; 3]; 3]| {
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
            - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    };
    let d = det(a);
    let scale = a
        .iter()
        .flatten()
        .map(|v| v.abs())
        .fold(0.0, f64::max)
        .powi(3);
    if d.abs() <= 1e-9 * scale.max(1e-300) {
        return None;
    }
    Some(std::array::from_fn(|k| {
        let mut m = a;
        for i in 0..3 {
            m[i][k] = b[i];
        }
        det(m) / d
    }))
}

/// Mean squared distance of each point to its 3 nearest other points (the INRIA trainer's `distCUDA2`),
/// via a uniform grid searched in growing shells.
fn mean_sq_dist_3nn(points: &[[f32; 3]]) -> Vec<f32> {
    let n = points.len();
    if n < 2 {
        return vec![0.01; n];
    }
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    for p in points {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    // About 2 points per cell on average.
    let volume: f32 = (0..3).map(|a| (hi[a] - lo[a]).max(1e-6)).product();
    let cell = (2.0 * volume / n as f32).cbrt().max(1e-6);
    let dims: [usize; 3] =
        std::array::from_fn(|a| (((hi[a] - lo[a]) / cell) as usize + 1).min(1 << 10));
    let cell_of = |p: &[f32; 3]| -> [usize; 3] {
        std::array::from_fn(|a| (((p[a] - lo[a]) / cell) as usize).min(dims[a] - 1))
    };
    let flat = |c: [usize; 3]| (c[2] * dims[1] + c[1]) * dims[0] + c[0];
    // Counting sort of the points by cell.
    let mut starts = vec![0usize; dims[0] * dims[1] * dims[2] + 1];
    for p in points {
        starts[flat(cell_of(p)) + 1] += 1;
    }
    for i in 1..starts.len() {
        starts[i] += starts[i - 1];
    }
    let mut fill = starts.clone();
    let mut order = vec![0usize; n];
    for (i, p) in points.iter().enumerate() {
        let f = flat(cell_of(p));
        order[fill[f]] = i;
        fill[f] += 1;
    }
    let k = 3.min(n - 1);
    let max_shell = dims.iter().copied().max().unwrap_or(1);
    (0..n)
        .into_par_iter()
        .map(|i| {
            let p = points[i];
            let c = cell_of(&p);
            let mut best = [f32::INFINITY; 3];
            for shell in 0..=max_shell {
                // Everything within shell·cell of p has been seen once the shell is done.
                let lo_c: [isize; 3] = std::array::from_fn(|a| c[a] as isize - shell as isize);
                let hi_c: [isize; 3] = std::array::from_fn(|a| c[a] as isize + shell as isize);
                for z in lo_c[2].max(0)..=hi_c[2].min(dims[2] as isize - 1) {
                    for y in lo_c[1].max(0)..=hi_c[1].min(dims[1] as isize - 1) {
                        for x in lo_c[0].max(0)..=hi_c[0].min(dims[0] as isize - 1) {
                            let on_shell = [x, y, z]
                                .iter()
                                .zip(lo_c.iter().zip(&hi_c))
                                .any(|(&v, (&l, &h))| v == l || v == h);
                            if !on_shell {
                                continue;
                            }
                            let f = flat([x as usize, y as usize, z as usize]);
                            for &j in &order[starts[f]..starts[f + 1]] {
                                if j == i {
                                    continue;
                                }
                                let q = points[j];
                                let d2 = (p[0] - q[0]).powi(2)
                                    + (p[1] - q[1]).powi(2)
                                    + (p[2] - q[2]).powi(2);
                                if d2 < best[k - 1] {
                                    let mut pos = k - 1;
                                    while pos > 0 && best[pos - 1] > d2 {
                                        best[pos] = best[pos - 1];
                                        pos -= 1;
                                    }
                                    best[pos] = d2;
                                }
                            }
                        }
                    }
                }
                let reach = shell as f32 * cell;
                if best[k - 1] <= reach * reach {
                    break;
                }
            }
            best[..k].iter().sum::<f32>() / k as f32
        })
        .collect()
}

/// Mean PSNR of `scene` over `views`.
pub fn evaluate(scene: &GaussianScene, views: &[View], background: [f32; 3]) -> f64 {
    if views.is_empty() {
        return f64::NAN;
    }
    let settings = RenderSettings { background };
    let total: f64 = views
        .iter()
        .map(|v| psnr(&render(scene, &v.camera, &settings, None).rgb, &v.image))
        .sum();
    total / views.len() as f64
}

/// The scene fit's loss: `(1 − ssim_weight)·L1 + ssim_weight·D-SSIM` against the training images.
struct SceneFitLoss<'a> {
    views: &'a [View],
    ssim_weight: f32,
}

impl FitLoss for SceneFitLoss<'_> {
    type Error = ::gpu::GpuError;

    fn eval(&mut self, rgb: &[f32], v: usize) -> Result<(f32, Vec<f32>), Self::Error> {
        let view = &self.views[v];
        let (w, h) = (view.camera.width as usize, view.camera.height as usize);
        let loss = l1_dssim(rgb, &view.image, w, h, 3, self.ssim_weight);
        Ok((loss.value, loss.grad))
    }

    fn device_weights(&self) -> Option<L1DssimWeights> {
        Some(L1DssimWeights::blend(self.ssim_weight))
    }
}

/// Whether step `step` must run with the state on the host: it densifies, resets opacities, evaluates
/// or is the last one (the conditions of `DefaultStrategy::after_backward`, taken broadly).
fn host_step(config: &FitConfig, step: u64) -> bool {
    let s = &config.strategy;
    let done = step + 1;
    let refine = step < s.refine_stop
        && step > s.refine_start
        && s.refine_every > 0
        && step.is_multiple_of(s.refine_every);
    let reset = (s.reset_every > 0 && step > 0 && step.is_multiple_of(s.reset_every))
        || (s.reset_at_refine_start && step == s.refine_start);
    let eval = config.eval_every > 0 && done.is_multiple_of(config.eval_every);
    refine || reset || eval || done == config.steps
}

/// Trains a scene on `dataset.train`; `progress` is called after every step.
pub fn fit(
    dataset: &Dataset,
    config: &FitConfig,
    progress: &mut dyn FnMut(&FitProgress),
) -> FitResult {
    match fit_on(dataset, config, &SplatDevice::Cpu, progress) {
        Ok(r) => r,
        Err(e) => unreachable!("the CPU path has no device to fail: {e}"),
    }
}

/// [`fit`] on `device` when one is given: ordinary steps keep the scene, Adam moments and densification
/// statistics on the device; densification, opacity resets, SH degree changes and evaluations run on the
/// host (the render and its backward still on the device). Errors only come from the device.
pub fn fit_on(
    dataset: &Dataset,
    config: &FitConfig,
    device: &SplatDevice,
    progress: &mut dyn FnMut(&FitProgress),
) -> Result<FitResult, ::gpu::GpuError> {
    let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
    let cams: Vec<Camera> = dataset.train.iter().map(|v| v.camera.clone()).collect();
    let (_, extent) = camera_extent(&cams);
    let scene = initial_scene(dataset, config.init_points, config.init_opacity, &mut rng);
    let mut rates = config.rates.clone();
    rates.means.max_steps = config.steps;
    let mut state = TrainState::new(scene, rates, extent);
    let mut times = StageTimes::default();
    let reads_before = ::gpu::prims::read_waits();
    let mut order: Vec<usize> = Vec::new();
    let clock = std::time::Instant::now;
    let mut fit_loss = SceneFitLoss {
        views: &dataset.train,
        ssim_weight: config.ssim_weight,
    };
    // Ordinary steps run resident on a device; steps that change the scene's structure or read it
    // (densification, opacity reset, SH degree change, evaluation, the last step) run on the host state.
    let mut trainer = Trainer::new(
        device,
        &fit_loss,
        dataset.train.iter().map(|v| v.image.as_slice()),
        config.background,
    );
    for step in 0..config.steps {
        if order.is_empty() {
            order = (0..dataset.train.len()).collect();
            order.shuffle(&mut rng);
        }
        let view_index = order.pop().expect("refilled");
        let view = &dataset.train[view_index];
        let degree = ((step / config.sh_degree_interval.max(1)) as u32).min(config.sh_degree);
        let kind = if degree != state.scene.sh_degree || host_step(config, step) {
            trainer.sync(&mut state)?;
            state.set_sh_degree(degree);
            StepKind::Host
        } else {
            StepKind::Ordinary {
                track_stats: step < config.strategy.refine_stop,
                read_loss: (step + 1) % LOSS_READ_EVERY == 0 || step + 1 == config.steps,
            }
        };
        state.adam.set_iteration(step);
        let t = clock();
        let (loss, grads, radii) =
            match trainer.step(&mut state, &view.camera, view_index, &mut fit_loss, kind)? {
                StepOutcome::Resident { loss } => {
                    times.render += t.elapsed().as_secs_f64();
                    progress(&FitProgress {
                        step: step + 1,
                        steps: config.steps,
                        loss,
                        gaussians: state.len(),
                        test_psnr: None,
                        refine: None,
                    });
                    continue;
                }
                StepOutcome::Host {
                    loss,
                    grads,
                    radii,
                    seconds,
                } => {
                    times.render += seconds.render;
                    times.loss += seconds.loss;
                    times.backward += seconds.backward;
                    times.optimise += seconds.optimise;
                    (loss, grads, radii)
                }
            };
        let t = clock();
        let refine = config.strategy.after_backward(
            &mut state,
            step,
            &RenderedView::new(&grads, &radii, &view.camera),
            &mut rng,
        );
        times.densify += t.elapsed().as_secs_f64();

        let done = step + 1;
        let test_psnr =
            if config.eval_every > 0 && done % config.eval_every == 0 && done < config.steps {
                let t = clock();
                let p = evaluate(&state.scene, &dataset.test, config.background);
                times.eval += t.elapsed().as_secs_f64();
                (!dataset.test.is_empty()).then_some(p)
            } else {
                None
            };
        progress(&FitProgress {
            step: done,
            steps: config.steps,
            loss: Some(loss),
            gaussians: state.len(),
            test_psnr,
            refine,
        });
    }
    let t = clock();
    let test_psnr = (!dataset.test.is_empty())
        .then(|| evaluate(&state.scene, &dataset.test, config.background));
    let train_psnr = evaluate(&state.scene, &dataset.train, config.background);
    times.eval += t.elapsed().as_secs_f64();
    let reads_after = ::gpu::prims::read_waits();
    times.device_reads = reads_after.0 - reads_before.0;
    times.device_wait = (reads_after.1 - reads_before.1).as_secs_f64();
    Ok(FitResult {
        scene: state.scene,
        test_psnr,
        train_psnr,
        seconds: times,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nearest_neighbours_match_brute_force() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let mut pts: Vec<[f32; 3]> = (0..700)
            .map(|_| {
                [
                    rng.gen::<f32>() * 3.0,
                    rng.gen::<f32>(),
                    rng.gen::<f32>() * 0.2,
                ]
            })
            .collect();
        // A far outlier and a duplicate.
        pts.push([40.0, -3.0, 2.0]);
        pts.push(pts[0]);
        let got = mean_sq_dist_3nn(&pts);
        for (i, p) in pts.iter().enumerate() {
            let mut d: Vec<f32> = pts
                .iter()
                .enumerate()
                .filter(|&(j, _)| j != i)
                .map(|(_, q)| (0..3).map(|a| (p[a] - q[a]).powi(2)).sum())
                .collect();
            d.sort_by(f32::total_cmp);
            let want = (d[0] + d[1] + d[2]) / 3.0;
            assert!(
                (got[i] - want).abs() <= 1e-5 * want.max(1e-6),
                "{i}: {} vs {want}",
                got[i]
            );
        }
    }

    #[test]
    fn area_resampling_preserves_mean_and_handles_crop() {
        let (sw, sh) = (9usize, 6usize);
        let src: Vec<f32> = (0..sw * sh * 3).map(|i| (i % 11) as f32 / 10.0).collect();
        let out = resample_area(&src, sw, sh, [0.0, 0.0, 9.0, 6.0], 3, 2);
        // Each output pixel is the mean of a 3x3 block.
        for c in 0..3 {
            let mut want = 0.0;
            for y in 0..3 {
                for x in 0..3 {
                    want += src[(y * sw + x) * 3 + c];
                }
            }
            assert!((out[c] - want / 9.0).abs() < 1e-6);
        }
        // Identity window copies.
        let same = resample_area(&src, sw, sh, [0.0, 0.0, 9.0, 6.0], 9, 6);
        for (a, b) in same.iter().zip(&src) {
            assert!((a - b).abs() < 1e-6);
        }
        // Centre crop 9x6 → 6x6 square starting at x = 1.5: first output pixel covers [1.5, 2.5).
        let crop = resample_area(&src, sw, sh, crop_window(9, 6, 6, 6), 6, 6);
        let want = 0.5 * src[3] + 0.5 * src[6];
        assert!((crop[0] - want).abs() < 1e-6);
    }

    #[test]
    fn composite_uses_alpha() {
        let img = Image::from_data(1, 2, 4, vec![1.0, 0.0, 0.0, 0.25, 0.0, 1.0, 0.0, 1.0]);
        let rgb = composite(&img, [1.0, 1.0, 1.0]).unwrap();
        assert_eq!(rgb, vec![1.0, 0.75, 0.75, 0.0, 1.0, 0.0]);
    }

    fn look_at_origin(from: [f64; 3], name: &str) -> Camera {
        crate::cameras::orbit::look_at(name.into(), from, [0.0; 3], [0.0, 0.0, 1.0], 40, 30, 35.0)
    }

    #[test]
    fn random_init_lies_in_the_viewed_region() {
        let cams: Vec<Camera> = (0..8)
            .map(|i| {
                let a = i as f64 * std::f64::consts::TAU / 8.0;
                look_at_origin([4.0 * a.cos() + 1.0, 4.0 * a.sin() - 2.0, 1.0], "c")
            })
            .collect();
        let refs: Vec<&Camera> = cams.iter().collect();
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let pts = random_points_in_view(&refs, 500, &mut rng);
        assert_eq!(pts.len(), 500);
        for p in &pts {
            let seen = cams
                .iter()
                .filter(|c| {
                    let q = c.world_to_camera(p.map(|v| v as f64));
                    q[2] > 0.0
                })
                .count();
            assert!(seen >= 4);
        }
    }
}
