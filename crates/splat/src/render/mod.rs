//! Differentiable CPU rasteriser for 3D Gaussians, following gsplat/3DGS exactly, in three stages that each
//! have a hand-written backward:
//!
//! 1. `project`: EWA projection (0.3 px low-pass, near plane 0.01, 3σ radius), SH colour, opacity.
//! 2. `tiles`: 16x16 tile binning, lists sorted front to back by camera depth.
//! 3. `raster`: front-to-back alpha compositing per pixel (alpha ≤ 0.99, skip < 1/255, stop at T < 1e-4)
//!    of RGB, alpha, depth and any number of extra per-Gaussian channels in the same pass;
//!    `raster_backward` walks each pixel back to front from the saved final T and last contributor.
//!
//! Both compositing passes (and lifting) work in the units of `segment`: 16x16 tiles and 8-pixel
//! segments. `cpu` picks the AVX2+FMA or portable build of each stage; `simd` holds the hand-written
//! AVX2 segment kernels. The modules stand in layers: segment → simd → raster, raster_backward.
//!
//! `gpu` holds the CubeCL twins of the three stages (with their backward), tested against this CPU
//! renderer.
//!
//! The math is generic over `real::Real` so the gradient tests run the very same code in `f64`; the
//! public API below is `f32`.

// `!(a > b)` is deliberate throughout: it also rejects NaN. Index loops over 2/3/4-element arrays read
// like the formulas they implement.
#![allow(clippy::neg_cmp_op_on_partial_ord, clippy::needless_range_loop)]

pub(crate) mod cpu;
mod frozen;
pub(crate) mod gpu;
pub(crate) mod project;
pub(crate) mod raster;
pub(crate) mod raster_backward;
pub(crate) mod real;
pub(crate) mod segment;
pub(crate) mod sh;
#[cfg(target_arch = "x86_64")]
mod simd;
pub(crate) mod tiles;

#[cfg(test)]
mod gradcheck;

use crate::cameras::Camera;
use crate::scene::GaussianScene;
use cpu::{dispatch, Kernel};
use project::{CameraR, ParamGradsMut, Splat};
use raster::RasterOut;
use raster_backward::{ImageGrads, SavedPixels};
use rayon::prelude::*;
use real::Real;
use tiles::TileBins;

pub use frozen::{FrozenGeometry, FrozenView};
pub use project::{ALPHA_MAX, ALPHA_MIN, LOW_PASS, NEAR_PLANE, TILE, T_MIN};

/// Options of [`render`].
#[derive(Clone, Debug, PartialEq)]
pub struct RenderSettings {
    /// Colour composited behind the Gaussians with the final transmittance.
    pub background: [f32; 3],
}

impl Default for RenderSettings {
    fn default() -> Self {
        Self {
            background: [0.0; 3],
        }
    }
}

/// Extra per-Gaussian channels composited in the same pass as the colour (e.g. 24·L attention channels).
#[derive(Clone, Copy, Debug)]
pub struct ExtraChannels<'a> {
    /// N*C values, Gaussian-major.
    pub values: &'a [f32],
    pub channels: usize,
}

/// Everything [`render`] produces, plus the state [`render_backward`] needs.
#[derive(Clone, Debug)]
pub struct RenderOutput {
    /// The images and radii (what a device render reads back as well).
    pub frame: Frame,
    state: SavedState,
}

/// A rendered view: images and per-Gaussian radii, from any backend.
#[derive(Clone, Debug)]
pub struct Frame {
    pub width: u32,
    pub height: u32,
    /// H*W*3, background composited.
    pub rgb: Vec<f32>,
    /// H*W, 1 − final transmittance.
    pub alpha: Vec<f32>,
    /// H*W, expected camera z = Σ z_i α_i T_i (not divided by alpha).
    pub depth: Vec<f32>,
    /// H*W*C extra channels, composited over 0 (no background).
    pub extra: Vec<f32>,
    /// Number of extra channels C.
    pub channels: usize,
    /// Per Gaussian screen radius in pixels, 0 = not rendered.
    pub radii: Vec<u32>,
}

impl Frame {
    /// Bytes a frame of `pixels` pixels, `gaussians` Gaussians and `extra` channels holds.
    pub fn memory_bytes(pixels: u64, gaussians: u64, extra: u64) -> u64 {
        pixels * (5 + extra) * 4 + gaussians * 4
    }

    /// The RGB image as an [`crate::image::Image`].
    pub fn rgb_image(&self) -> crate::image::Image {
        crate::image::Image::from_data(self.width, self.height, 3, self.rgb.clone())
    }
}

/// A CPU render is its frame plus the state its backward pass needs: it reads as the frame.
impl std::ops::Deref for RenderOutput {
    type Target = Frame;
    fn deref(&self) -> &Frame {
        &self.frame
    }
}

#[derive(Clone, Debug)]
struct SavedState {
    splats: Vec<Splat<f32>>,
    bins: TileBins,
    t_final: Vec<f32>,
    last: Vec<u32>,
}

impl RenderOutput {
    /// The frame, the backward state dropped.
    pub fn into_frame(self) -> Frame {
        self.frame
    }

    /// Number of (tile, Gaussian) pairs the rasteriser visited: a measure of the work done.
    pub fn tile_intersections(&self) -> usize {
        self.state.bins.ids.len()
    }
}

/// Gradients of a scalar loss with respect to the rendered images (same layouts as [`RenderOutput`]).
#[derive(Clone, Copy, Debug)]
pub struct OutputGrads<'a> {
    pub rgb: &'a [f32],
    pub alpha: Option<&'a [f32]>,
    pub depth: Option<&'a [f32]>,
    pub extra: Option<&'a [f32]>,
}

impl<'a> OutputGrads<'a> {
    /// Gradients of the colour alone (a loss on the image only).
    pub fn rgb_only(rgb: &'a [f32]) -> Self {
        Self {
            rgb,
            alpha: None,
            depth: None,
            extra: None,
        }
    }
}

/// Gradients with respect to the scene parameters (same layouts as [`GaussianScene`]).
#[derive(Clone, Debug, Default)]
pub struct SceneGrads {
    pub means: Vec<f32>,
    pub log_scales: Vec<f32>,
    pub quats: Vec<f32>,
    pub opacity_logits: Vec<f32>,
    pub sh: Vec<f32>,
    /// N*C; empty when no extra channels or no extra-channel gradient were given.
    pub extra: Vec<f32>,
    /// dL/d(projected pixel centre) per Gaussian, for densification.
    pub means2d: Vec<[f32; 2]>,
}

/// Peak host memory, in bytes, of one CPU [`render`] of `pixels` pixels of `gaussians` Gaussians with
/// `extra` channels: per pixel the images and the backward state (colour, alpha, depth, extra channels,
/// final transmittance, last index), per Gaussian the projected splat and its tile-list entries
/// (estimated at 16 tiles of 16 bytes each). An estimate for refusing work up front, not a bound.
pub fn render_memory_bytes(pixels: u64, gaussians: u64, extra: u64) -> u64 {
    let per_gaussian = std::mem::size_of::<Splat<f32>>() as u64 + 16 * 16;
    pixels * (7 + extra) * 4 + gaussians * per_gaussian
}

/// Renders `scene` from `camera`.
///
/// # Panics
/// When the scene's arrays have inconsistent lengths ([`GaussianScene::check_shapes`]), its SH degree is
/// above 3, or `extra.values` is not N*C long. These are programming errors: loaders validate files.
pub fn render(
    scene: &GaussianScene,
    camera: &Camera,
    settings: &RenderSettings,
    extra: Option<ExtraChannels<'_>>,
) -> RenderOutput {
    let params = Params::from_scene(scene);
    let extra = extra.map(|e| {
        assert_eq!(
            e.values.len(),
            scene.len() * e.channels,
            "extra channel values must be N*C"
        );
        (e.values, e.channels)
    });
    let fwd = forward(&params, camera, settings.background.map(f64::from), extra);
    RenderOutput::new(camera, fwd, extra.map_or(0, |e| e.1))
}

/// [`render`] with the extra channels composited only where `rows[y]` and `cols[x]` are both non-zero
/// (one flag per image row and column) and 0 elsewhere: what lifting's render-back reads when it
/// resamples the channels to a coarse grid ([`crate::lift::read_by_resampling`]).
///
/// # Panics
/// When the values are not N*C or the flags not one per row and column (programming errors).
pub(crate) fn render_extra_at(
    scene: &GaussianScene,
    camera: &Camera,
    settings: &RenderSettings,
    extra: ExtraChannels<'_>,
    (rows, cols): (&[u32], &[u32]),
) -> RenderOutput {
    let params = Params::from_scene(scene);
    assert_eq!(
        extra.values.len(),
        scene.len() * extra.channels,
        "extra channel values must be N*C"
    );
    let fwd = forward_at(
        &params,
        camera,
        settings.background.map(f64::from),
        Some((extra.values, extra.channels)),
        Some((rows, cols)),
    );
    RenderOutput::new(camera, fwd, extra.channels)
}

impl RenderOutput {
    fn new(camera: &Camera, fwd: Forward<f32>, channels: usize) -> Self {
        let radii = fwd.splats.iter().map(|s| s.radius).collect();
        let RasterOut {
            rgb,
            alpha,
            depth,
            extra,
            t_final,
            last,
        } = fwd.raster;
        RenderOutput {
            frame: Frame {
                width: camera.width,
                height: camera.height,
                rgb,
                alpha,
                depth,
                extra,
                channels,
                radii,
            },
            state: SavedState {
                splats: fwd.splats,
                bins: fwd.bins,
                t_final,
                last,
            },
        }
    }
}

/// Backward pass of [`render`]: gradients of the loss with respect to every parameter, given the gradients
/// with respect to the outputs. `scene`, `camera`, `settings` and `extra` must be those `out` was rendered
/// with.
///
/// # Panics
/// When the gradient images or `out` do not match the scene/camera sizes (programming errors).
pub fn render_backward(
    scene: &GaussianScene,
    camera: &Camera,
    settings: &RenderSettings,
    extra: Option<ExtraChannels<'_>>,
    out: &RenderOutput,
    grads: &OutputGrads<'_>,
) -> SceneGrads {
    backward_of_render(scene, camera, settings, extra, out, grads, true)
}

/// [`render_backward`] (without extra channels) for fits that keep the geometry: the gradients of the
/// opacities, SH coefficients and screen positions (`means2d`, from the rasteriser); those of the means,
/// scales and rotations are left at zero, their part of the projection's backward pass is skipped.
pub fn render_backward_appearance(
    scene: &GaussianScene,
    camera: &Camera,
    settings: &RenderSettings,
    out: &RenderOutput,
    grads: &OutputGrads<'_>,
) -> SceneGrads {
    backward_of_render(scene, camera, settings, None, out, grads, false)
}

fn backward_of_render(
    scene: &GaussianScene,
    camera: &Camera,
    settings: &RenderSettings,
    extra: Option<ExtraChannels<'_>>,
    out: &RenderOutput,
    grads: &OutputGrads<'_>,
    geometry: bool,
) -> SceneGrads {
    let params = Params::from_scene(scene);
    let npix = (camera.width * camera.height) as usize;
    assert_eq!(
        out.state.splats.len(),
        scene.len(),
        "output of another scene"
    );
    assert_eq!((out.width, out.height), (camera.width, camera.height));
    assert_eq!(grads.rgb.len(), 3 * npix, "rgb gradient must be H*W*3");
    if let Some(a) = grads.alpha {
        assert_eq!(a.len(), npix, "alpha gradient must be H*W");
    }
    if let Some(d) = grads.depth {
        assert_eq!(d.len(), npix, "depth gradient must be H*W");
    }
    let extra = extra.map(|e| (e.values, e.channels));
    if let Some(e) = grads.extra {
        assert_eq!(e.len(), npix * out.channels, "extra gradient must be H*W*C");
    }
    let g = backward(
        &params,
        camera,
        settings.background.map(f64::from),
        extra,
        &out.state.splats,
        &out.state.bins,
        SavedPixels {
            t_final: &out.state.t_final,
            last: &out.state.last,
        },
        &ImageGrads {
            rgb: grads.rgb,
            alpha: grads.alpha,
            depth: grads.depth,
            extra: grads.extra,
        },
        geometry,
    );
    SceneGrads {
        means: g.means,
        log_scales: g.log_scales,
        quats: g.quats,
        opacity_logits: g.opacity_logits,
        sh: g.sh,
        extra: g.extra,
        means2d: g.means2d,
    }
}

/// SH coefficients per colour channel for a degree.
#[inline]
pub(crate) fn sh_coeffs_of(degree: u32) -> usize {
    ((degree + 1) * (degree + 1)) as usize
}

/// Borrowed scene parameters in the working float type.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Params<'a, R> {
    pub sh_degree: u32,
    pub means: &'a [R],
    pub log_scales: &'a [R],
    pub quats: &'a [R],
    pub opacity_logits: &'a [R],
    pub sh: &'a [R],
}

impl<'a> Params<'a, f32> {
    pub fn from_scene(scene: &'a GaussianScene) -> Self {
        if let Err(e) = scene.check_shapes() {
            panic!("inconsistent scene: {e}");
        }
        assert!(
            scene.sh_degree <= sh::MAX_DEGREE,
            "SH degree {} is not supported (at most {})",
            scene.sh_degree,
            sh::MAX_DEGREE
        );
        Params {
            sh_degree: scene.sh_degree,
            means: &scene.means,
            log_scales: &scene.log_scales,
            quats: &scene.quats,
            opacity_logits: &scene.opacity_logits,
            sh: &scene.sh,
        }
    }
}

impl<R> Params<'_, R> {
    pub fn len(&self) -> usize {
        self.opacity_logits.len()
    }
}

/// Forward pass in any float type.
pub(crate) struct Forward<R> {
    pub splats: Vec<Splat<R>>,
    pub bins: TileBins,
    pub raster: RasterOut<R>,
}

/// Stage (a) for all Gaussians in parallel.
pub(crate) fn project_all<R: Real>(
    params: &Params<'_, R>,
    cam: &CameraR<R>,
    with_color: bool,
) -> Vec<Splat<R>> {
    let mut out = vec![Splat::default(); params.len()];
    out.par_chunks_mut(PROJECT_CHUNK)
        .enumerate()
        .for_each(|(c, chunk)| {
            dispatch(ProjectChunk {
                params,
                cam,
                with_color,
                start: c * PROJECT_CHUNK,
                chunk,
            })
        });
    out
}

/// Gaussians per parallel work item of the per-Gaussian stages.
const PROJECT_CHUNK: usize = 512;

/// Stage (a) for the Gaussians from `start` on, one per entry of `chunk` (compiled for AVX2+FMA as well:
/// inline rounding and square roots, wider registers).
struct ProjectChunk<'a, R> {
    params: &'a Params<'a, R>,
    cam: &'a CameraR<R>,
    with_color: bool,
    start: usize,
    chunk: &'a mut [Splat<R>],
}

impl<R: Real> Kernel for ProjectChunk<'_, R> {
    type Output = ();

    #[inline(always)]
    fn run<const SIMD: bool>(self) {
        // Separate arguments tell the compiler the output does not alias the inputs.
        project_chunk(
            self.params,
            self.cam,
            self.with_color,
            self.start,
            self.chunk,
        )
    }
}

#[inline(always)]
fn project_chunk<R: Real>(
    params: &Params<'_, R>,
    cam: &CameraR<R>,
    with_color: bool,
    start: usize,
    chunk: &mut [Splat<R>],
) {
    for (j, s) in chunk.iter_mut().enumerate() {
        *s = project::project_one(params, start + j, cam, with_color);
    }
}

pub(crate) fn forward<R: Real>(
    params: &Params<'_, R>,
    camera: &Camera,
    background: [f64; 3],
    extra: Option<(&[R], usize)>,
) -> Forward<R> {
    forward_at(params, camera, background, extra, None)
}

/// [`forward`], compositing the extra channels only at `extra_at`'s pixels when given.
fn forward_at<R: Real>(
    params: &Params<'_, R>,
    camera: &Camera,
    background: [f64; 3],
    extra: Option<(&[R], usize)>,
    extra_at: Option<raster::ExtraAt<'_>>,
) -> Forward<R> {
    let cam = CameraR::<R>::new(camera);
    assert!(
        cam.tiles().0 <= u16::MAX as u32 && cam.tiles().1 <= u16::MAX as u32,
        "image too large: {}x{}",
        camera.width,
        camera.height
    );
    let splats = project_all(params, &cam, true);
    let (tx, ty) = cam.tiles();
    let bins = tiles::bin(&splats, tx, ty);
    let raster = raster::rasterize(
        &splats,
        &bins,
        camera.width,
        camera.height,
        background.map(R::from_f64),
        extra,
        extra_at,
    );
    Forward {
        splats,
        bins,
        raster,
    }
}

/// Parameter gradients in any float type.
pub(crate) struct Grads<R> {
    pub means: Vec<R>,
    pub log_scales: Vec<R>,
    pub quats: Vec<R>,
    pub opacity_logits: Vec<R>,
    pub sh: Vec<R>,
    pub extra: Vec<R>,
    pub means2d: Vec<[R; 2]>,
}

pub(crate) fn backward<R: Real>(
    params: &Params<'_, R>,
    camera: &Camera,
    background: [f64; 3],
    extra: Option<(&[R], usize)>,
    splats: &[Splat<R>],
    bins: &TileBins,
    saved: SavedPixels<'_, R>,
    grads: &ImageGrads<'_, R>,
    geometry: bool,
) -> Grads<R> {
    let cam = CameraR::<R>::new(camera);
    let n = params.len();
    let rg = raster_backward::rasterize_backward(
        splats,
        bins,
        camera.width,
        camera.height,
        background.map(R::from_f64),
        extra,
        saved,
        grads,
    );
    let mut out = Grads::zeros(n, params.sh_degree);
    out.extra = rg.extra;
    out.means2d = rg.splats.iter().map(|g| g.mean).collect();
    project_backward_all(params, &cam, splats, &rg.splats, &mut out, geometry);
    out
}

impl<R: Real> Grads<R> {
    fn zeros(n: usize, sh_degree: u32) -> Self {
        Grads {
            means: vec![R::ZERO; 3 * n],
            log_scales: vec![R::ZERO; 3 * n],
            quats: vec![R::ZERO; 4 * n],
            opacity_logits: vec![R::ZERO; n],
            sh: vec![R::ZERO; 3 * sh_coeffs_of(sh_degree) * n],
            extra: vec![],
            means2d: vec![],
        }
    }
}

/// Backward of stage (a) for all Gaussians in parallel, writing the parameter gradients of `out`
/// (without `geometry`, those of the opacities and SH coefficients only).
fn project_backward_all<R: Real>(
    params: &Params<'_, R>,
    cam: &CameraR<R>,
    splats: &[Splat<R>],
    splat_grads: &[project::SplatGrad<R>],
    out: &mut Grads<R>,
    geometry: bool,
) {
    let k3 = 3 * sh_coeffs_of(params.sh_degree);
    let n = PROJECT_CHUNK;
    (
        out.means.par_chunks_mut(3 * n),
        out.log_scales.par_chunks_mut(3 * n),
        out.quats.par_chunks_mut(4 * n),
        out.opacity_logits.par_chunks_mut(n),
        out.sh.par_chunks_mut(k3 * n),
    )
        .into_par_iter()
        .enumerate()
        .for_each(|(c, (mean, log_scale, quat, opacity_logit, sh))| {
            dispatch(ProjectBackwardChunk {
                params,
                cam,
                splats,
                splat_grads,
                geometry,
                out: GradChunk {
                    start: c * n,
                    mean,
                    log_scale,
                    quat,
                    opacity_logit,
                    sh,
                },
            })
        });
}

/// Output slices of one chunk of Gaussians, starting at Gaussian `start`.
struct GradChunk<'a, R> {
    start: usize,
    mean: &'a mut [R],
    log_scale: &'a mut [R],
    quat: &'a mut [R],
    opacity_logit: &'a mut [R],
    sh: &'a mut [R],
}

/// Backward of stage (a) for one chunk of Gaussians (compiled for AVX2+FMA as well).
struct ProjectBackwardChunk<'a, R> {
    params: &'a Params<'a, R>,
    cam: &'a CameraR<R>,
    splats: &'a [Splat<R>],
    splat_grads: &'a [project::SplatGrad<R>],
    geometry: bool,
    out: GradChunk<'a, R>,
}

impl<R: Real> Kernel for ProjectBackwardChunk<'_, R> {
    type Output = ();

    #[inline(always)]
    fn run<const SIMD: bool>(self) {
        // Separate arguments tell the compiler the outputs do not alias the inputs.
        project_backward_chunk(
            self.params,
            self.cam,
            self.splats,
            self.splat_grads,
            self.geometry,
            self.out,
        )
    }
}

#[inline(always)]
fn project_backward_chunk<R: Real>(
    params: &Params<'_, R>,
    cam: &CameraR<R>,
    splats: &[Splat<R>],
    splat_grads: &[project::SplatGrad<R>],
    geometry: bool,
    c: GradChunk<'_, R>,
) {
    let k3 = 3 * sh_coeffs_of(params.sh_degree);
    for (j, opacity_logit) in c.opacity_logit.iter_mut().enumerate() {
        let i = c.start + j;
        // Occluded or off-screen Gaussians (most of a dense scene) got no gradient: their outputs are
        // already zero.
        if splat_grads[i].is_zero() {
            continue;
        }
        if !geometry {
            // The outputs start at zero, which is what a culled splat gets.
            if splats[i].radius > 0 {
                let sh = &mut c.sh[k3 * j..k3 * (j + 1)];
                let s = (&splats[i], &splat_grads[i]);
                project::appearance_backward(params, i, cam, s.0, s.1, opacity_logit, sh);
            }
            continue;
        }
        project::project_one_backward(
            params,
            i,
            cam,
            &splats[i],
            &splat_grads[i],
            ParamGradsMut {
                mean: &mut c.mean[3 * j..3 * j + 3],
                log_scale: &mut c.log_scale[3 * j..3 * j + 3],
                quat: &mut c.quat[4 * j..4 * j + 4],
                opacity_logit,
                sh: &mut c.sh[k3 * j..k3 * (j + 1)],
            },
        );
    }
}

/// Wall-clock time of each stage of one forward + backward pass (for benchmarks and profiling).
#[doc(hidden)]
pub fn profile_stages(
    scene: &GaussianScene,
    camera: &Camera,
    settings: &RenderSettings,
) -> Vec<(&'static str, std::time::Duration)> {
    use std::time::Instant;
    let params = Params::from_scene(scene);
    let cam = CameraR::<f32>::new(camera);
    let bg = settings.background;
    let mut times = vec![];
    let t = Instant::now();
    let splats = project_all(&params, &cam, true);
    times.push(("project", t.elapsed()));
    let t = Instant::now();
    let (tx, ty) = cam.tiles();
    let bins = tiles::bin(&splats, tx, ty);
    times.push(("bin", t.elapsed()));
    let t = Instant::now();
    let raster = raster::rasterize(&splats, &bins, camera.width, camera.height, bg, None, None);
    times.push(("rasterize", t.elapsed()));
    let grad_rgb: Vec<f32> = raster.rgb.iter().map(|v| v - 0.5).collect();
    let t = Instant::now();
    let rg = raster_backward::rasterize_backward(
        &splats,
        &bins,
        camera.width,
        camera.height,
        bg,
        None,
        SavedPixels {
            t_final: &raster.t_final,
            last: &raster.last,
        },
        &ImageGrads {
            rgb: &grad_rgb,
            alpha: None,
            depth: None,
            extra: None,
        },
    );
    times.push(("rasterize backward", t.elapsed()));
    let t = Instant::now();
    let mut grads = Grads::zeros(params.len(), params.sh_degree);
    project_backward_all(&params, &cam, &splats, &rg.splats, &mut grads, true);
    times.push(("project backward", t.elapsed()));
    times
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera(width: u32, height: u32) -> Camera {
        Camera {
            name: "c".into(),
            width,
            height,
            fx: 20.0,
            fy: 20.0,
            cx: width as f64 / 2.0,
            cy: height as f64 / 2.0,
            rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            translation: [0.0, 0.0, 0.0],
        }
    }

    fn push(s: &mut GaussianScene, m: [f32; 3], log_scale: f32, q: [f32; 4], logit: f32) {
        s.means.extend_from_slice(&m);
        s.log_scales.extend_from_slice(&[log_scale; 3]);
        s.quats.extend_from_slice(&q);
        s.opacity_logits.push(logit);
        s.sh.extend_from_slice(&[0.3, -0.2, 0.1]);
    }

    #[test]
    fn empty_scene_shows_the_background() {
        let scene = GaussianScene::new(0);
        let settings = RenderSettings {
            background: [1.0, 0.5, 0.25],
        };
        let out = render(&scene, &camera(20, 7), &settings, None);
        assert!(out.rgb.chunks(3).all(|p| p == [1.0, 0.5, 0.25]));
        assert!(out.alpha.iter().all(|&a| a == 0.0));
        let g = render_backward(
            &scene,
            &camera(20, 7),
            &settings,
            None,
            &out,
            &OutputGrads::rgb_only(&vec![1.0; 20 * 7 * 3]),
        );
        assert!(g.means.is_empty() && g.means2d.is_empty());
    }

    /// Non-finite, degenerate and out-of-view Gaussians are culled without panics, and the valid one is
    /// still rendered with finite outputs and gradients.
    #[test]
    fn degenerate_gaussians_are_culled() {
        let mut s = GaussianScene::new(0);
        push(&mut s, [0.0, 0.0, 3.0], -1.0, [1.0, 0.0, 0.0, 0.0], 2.0); // valid
        push(
            &mut s,
            [f32::NAN, 0.0, 3.0],
            -1.0,
            [1.0, 0.0, 0.0, 0.0],
            2.0,
        );
        push(
            &mut s,
            [0.0, 0.0, 3.0],
            f32::INFINITY,
            [1.0, 0.0, 0.0, 0.0],
            2.0,
        );
        push(&mut s, [0.0, 0.0, 3.0], f32::NAN, [1.0, 0.0, 0.0, 0.0], 2.0);
        push(&mut s, [0.0, 0.0, 3.0], -1.0, [0.0; 4], 2.0); // zero quaternion
        push(&mut s, [0.0, 0.0, 3.0], -1.0, [f32::NAN; 4], 2.0);
        push(
            &mut s,
            [0.0, 0.0, 3.0],
            -1.0,
            [1.0, 0.0, 0.0, 0.0],
            f32::NAN,
        );
        push(&mut s, [0.0, 0.0, -3.0], -1.0, [1.0, 0.0, 0.0, 0.0], 2.0); // behind
        push(&mut s, [0.0, 0.0, 0.001], -1.0, [1.0, 0.0, 0.0, 0.0], 2.0); // inside the near plane
        push(&mut s, [1e30, 0.0, 3.0], -1.0, [1.0, 0.0, 0.0, 0.0], 2.0); // far off screen
        push(&mut s, [0.0, 0.0, 3.0], 40.0, [1.0, 0.0, 0.0, 0.0], 2.0); // astronomically large
        push(&mut s, [0.0, 0.0, 3.0], -60.0, [1.0, 0.0, 0.0, 0.0], 2.0); // vanishingly small
        for (w, h) in [(0, 0), (1, 1), (17, 33)] {
            let cam = camera(w, h);
            let settings = RenderSettings::default();
            let out = render(&s, &cam, &settings, None);
            assert!(out.rgb.iter().all(|v| v.is_finite()));
            for i in 1..10 {
                assert_eq!(out.radii[i], 0, "Gaussian {i} at {w}x{h}");
            }
            let npix = (w * h) as usize;
            let g = render_backward(
                &s,
                &cam,
                &settings,
                None,
                &out,
                &OutputGrads {
                    rgb: &vec![1.0; 3 * npix],
                    alpha: Some(&vec![1.0; npix]),
                    depth: Some(&vec![1.0; npix]),
                    extra: None,
                },
            );
            assert!(g.means[..3].iter().all(|v| v.is_finite()));
            if w == 17 {
                assert!(out.radii[0] > 0 && out.alpha.iter().any(|&a| a > 0.5));
                assert!(g.opacity_logits[0] != 0.0);
            }
        }
    }

    /// Extra channels without a gradient for them: the other gradients are those of a render without
    /// extra channels, and no extra gradient is returned.
    #[test]
    fn extra_channels_without_their_gradient() {
        let mut s = GaussianScene::new(0);
        push(&mut s, [0.0, 0.0, 3.0], -1.0, [1.0, 0.2, 0.0, 0.0], 1.0);
        push(&mut s, [0.1, 0.1, 4.0], -0.8, [1.0, 0.0, 0.3, 0.0], 0.5);
        let cam = camera(24, 20);
        let settings = RenderSettings::default();
        let values = vec![0.5, 1.0, 2.0, -1.0];
        let extra = ExtraChannels {
            values: &values,
            channels: 2,
        };
        let rgb_grad = vec![0.7; 24 * 20 * 3];
        let grads = OutputGrads::rgb_only(&rgb_grad);
        let with = render(&s, &cam, &settings, Some(extra));
        assert_eq!(with.extra.len(), 24 * 20 * 2);
        let g_with = render_backward(&s, &cam, &settings, Some(extra), &with, &grads);
        let without = render(&s, &cam, &settings, None);
        let g_without = render_backward(&s, &cam, &settings, None, &without, &grads);
        assert_eq!(with.rgb, without.rgb);
        assert!(g_with.extra.is_empty());
        assert_eq!(g_with.means, g_without.means);
        assert_eq!(g_with.sh, g_without.sh);
        // Extra channel 0 of Gaussian 0 is 0.5 and of Gaussian 1 is 2.0: the composite lies between.
        let e = &with.extra;
        let centre = (10 * 24 + 12) * 2;
        assert!(e[centre] > 0.4 && e[centre] < 2.0, "{}", e[centre]);
    }

    /// Extra channels composited only at flagged rows × columns equal the full render's there and are 0
    /// elsewhere; colours, alpha and depth are the full render's. Tiles cut by the image's edge included.
    #[test]
    fn extra_channels_only_where_asked() {
        let mut s = GaussianScene::new(0);
        for k in 0..40 {
            let t = k as f32 * 0.37;
            let m = [
                0.6 * t.sin(),
                0.5 * (1.3 * t).cos(),
                2.5 + (k % 5) as f32 * 0.3,
            ];
            push(
                &mut s,
                m,
                -1.8 + 0.02 * k as f32,
                [1.0, 0.1 * t.cos(), 0.0, 0.2],
                0.5,
            );
        }
        let (w, h) = (37u32, 29u32);
        let cam = camera(w, h);
        let settings = RenderSettings::default();
        let channels = 3;
        let values: Vec<f32> = (0..40 * channels)
            .map(|i| (i % 7) as f32 * 0.3 - 0.5)
            .collect();
        let extra = ExtraChannels {
            values: &values,
            channels,
        };
        let rows: Vec<u32> = (0..h).map(|y| u32::from(y % 3 == 1 || y == 17)).collect();
        let cols: Vec<u32> = (0..w)
            .map(|x| u32::from(x % 5 == 0 || x == 11 || x > 33))
            .collect();
        let full = render(&s, &cam, &settings, Some(extra));
        let some = render_extra_at(&s, &cam, &settings, extra, (&rows, &cols));
        assert_eq!(some.rgb, full.rgb);
        assert_eq!(some.alpha, full.alpha);
        assert_eq!(some.depth, full.depth);
        let mut kept = 0;
        for y in 0..h as usize {
            for x in 0..w as usize {
                let p = (y * w as usize + x) * channels;
                let asked = rows[y] * cols[x] == 1;
                for c in 0..channels {
                    let want = if asked { full.extra[p + c] } else { 0.0 };
                    assert_eq!(some.extra[p + c], want, "pixel ({x}, {y}) channel {c}");
                    kept += usize::from(asked && want != 0.0);
                }
            }
        }
        assert!(kept > 20, "{kept} composited values checked");
    }
}
