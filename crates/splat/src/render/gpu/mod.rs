//! The differentiable renderer on the GPU (CubeCL kernels through `gpu`), with the CPU renderer of
//! [`crate::render`] as the reference it must match.
//!
//! Stages, each one kernel per op:
//! 1. `project`: projection + SH colour per Gaussian (depth keys and covered tile counts included);
//! 2. `tiles`: binning, every tile list sorted by depth, ties by index, as on the CPU;
//! 3. `raster`: compositing of RGB, alpha, depth and extra channels, one cube per tile walking the
//!    tile's list in shared-memory batches, each unit owning a few pixels (`forward_pixels_per_unit`).
//!
//! The backward runs 3 then 1 with the state the forward left on the device.
//!
//! [`GpuScene`] keeps the parameters on the device; [`render_device`] / [`render_backward_device`] work on
//! device buffers only (one 4-byte read: the number of tile intersections), and [`render`] /
//! [`render_backward`] are host-side conveniences with the CPU renderer's types. Lifting
//! (`lift::gpu`) and the device-resident trainer (`train::gpu`) build on these stages.

mod frozen;
pub(crate) mod project;
pub(crate) mod raster;
pub(crate) mod sh;
#[cfg(test)]
pub(crate) mod tests;
mod tiles;

use crate::cameras::Camera;
#[cfg(test)]
use crate::render::OutputGrads;
use crate::render::{ExtraChannels, Frame, RenderSettings, SceneGrads, TILE};
use crate::scene::GaussianScene;
use ::gpu::cubecl::prelude::*;
use ::gpu::cubecl::server::Handle;
use ::gpu::gpu_call;
use ::gpu::prims::{arg, empty32, grid, read_f32, read_u32, upload_f32, zeros32};
use ::gpu::{GpuContext, GpuError};
pub use frozen::GpuFrozenGeometry;
pub(crate) use frozen::{render_kept, render_kept_pair};
use project::{CAM_F, GRAD_F, INFO_U, SPLAT_F};

/// Scene parameters on the device (layouts of [`GaussianScene`]).
pub struct GpuScene {
    pub len: usize,
    pub sh_degree: u32,
    pub means: Handle,
    pub log_scales: Handle,
    pub quats: Handle,
    pub opacity_logits: Handle,
    pub sh: Handle,
}

impl GpuScene {
    /// Uploads `scene`.
    ///
    /// # Panics
    /// When the scene's arrays are inconsistent or its SH degree is above 3 (as [`crate::render::render`]).
    pub fn upload(ctx: &GpuContext, scene: &GaussianScene) -> Self {
        if let Err(e) = scene.check_shapes() {
            panic!("inconsistent scene: {e}");
        }
        assert!(
            scene.sh_degree <= 3,
            "SH degree {} is not supported",
            scene.sh_degree
        );
        let c = &ctx.client;
        Self {
            len: scene.len(),
            sh_degree: scene.sh_degree,
            means: upload_f32(c, &scene.means),
            log_scales: upload_f32(c, &scene.log_scales),
            quats: upload_f32(c, &scene.quats),
            opacity_logits: upload_f32(c, &scene.opacity_logits),
            sh: upload_f32(c, &scene.sh),
        }
    }

    /// Reads the parameters back.
    pub fn download(&self, ctx: &GpuContext) -> Result<GaussianScene, GpuError> {
        let c = &ctx.client;
        let n = self.len;
        let k = crate::scene::sh_coeffs(self.sh_degree);
        Ok(GaussianScene {
            sh_degree: self.sh_degree,
            means: read_f32(c, &self.means, 3 * n)?,
            log_scales: read_f32(c, &self.log_scales, 3 * n)?,
            quats: read_f32(c, &self.quats, 4 * n)?,
            opacity_logits: read_f32(c, &self.opacity_logits, n)?,
            sh: read_f32(c, &self.sh, 3 * k * n)?,
        })
    }
}

/// A frame rendered on the device, with the state its backward needs.
pub struct GpuFrame {
    pub width: u32,
    pub height: u32,
    pub channels: usize,
    /// H*W*3, H*W, H*W, H*W*C: as [`crate::render::RenderOutput`].
    pub rgb: Handle,
    pub alpha: Handle,
    pub depth: Handle,
    pub extra: Handle,
    /// Number of (tile, Gaussian) pairs.
    pub intersections: usize,
    splats: Handle,
    pub(crate) info: Handle,
    ids: Handle,
    tile_start: Handle,
    t_final: Handle,
    last: Handle,
    cam: Handle,
    tiles_x: u32,
    tiles_y: u32,
    /// Whether the backward computes the geometry's gradients: false for a frame rendered from a kept
    /// geometry ([`frozen`]), whose backward gives the opacity and SH gradients alone.
    geometry_grads: bool,
    /// 1, or 2 for a pair of fits' images ([`render_kept_pair`]): image 1's pixels follow image 0's in
    /// every per-pixel buffer, its Gaussians' records (`splats`, `info`) follow image 0's `pair.offset`.
    images: u32,
    pair: PairImage,
}

/// The second image of a frame: its view's tile lists and camera, and where its Gaussians' records
/// start (image 0's own again, offset 0, in a one-image frame).
#[derive(Clone)]
pub(crate) struct PairImage {
    ids: Handle,
    tile_start: Handle,
    tile_end: Handle,
    intersections: usize,
    cam: Handle,
    offset: u32,
}

impl PairImage {
    /// Image 1 of a pair: `binned`'s lists, its Gaussians `offset` records after image 0's.
    pub(crate) fn of(binned: &Binned, offset: usize) -> Self {
        Self {
            ids: binned.ids.clone(),
            tile_start: binned.tile_start.clone(),
            tile_end: binned.tile_end.clone(),
            intersections: binned.intersections,
            cam: binned.cam.clone(),
            offset: offset as u32,
        }
    }
}

impl GpuFrame {
    /// Tile intersections of all its images.
    fn all_intersections(&self) -> usize {
        match self.images {
            1 => self.intersections,
            _ => self.intersections + self.pair.intersections,
        }
    }

    /// The pixels of all its images.
    fn all_pixels(&self) -> usize {
        self.images as usize * (self.width * self.height) as usize
    }
}

/// Camera values in the kernels' layout, computed as `CameraR::<f32>` does (f64, then rounded).
fn camera_values(cam: &Camera) -> [f32; CAM_F] {
    let (w, h) = (cam.width as f64, cam.height as f64);
    let tan_x = 0.5 * w / cam.fx;
    let tan_y = 0.5 * h / cam.fy;
    let centre = cam.center();
    let mut v = vec![cam.fx, cam.fy, cam.cx, cam.cy];
    v.extend(cam.rotation.iter().flatten());
    v.extend(cam.translation);
    v.extend(centre);
    v.extend([
        cam.cx / cam.fx + 0.3 * tan_x,
        (w - cam.cx) / cam.fx + 0.3 * tan_x,
        cam.cy / cam.fy + 0.3 * tan_y,
        (h - cam.cy) / cam.fy + 0.3 * tan_y,
    ]);
    std::array::from_fn(|i| v[i] as f32)
}

/// Renders a device scene. `extra`: per-Gaussian values on the device (N*C) and C.
pub fn render_device(
    ctx: &GpuContext,
    scene: &GpuScene,
    camera: &Camera,
    settings: &RenderSettings,
    extra: Option<(&Handle, usize)>,
) -> Result<GpuFrame, GpuError> {
    let ppu = forward_pixels_per_unit(ctx, extra.map_or(0, |e| e.1));
    gpu_call(|| render_device_inner(ctx, scene, camera, settings, extra, ppu))
}

/// Projected and binned Gaussians of one view (stages 1 and 2).
#[derive(Clone)]
pub(crate) struct Binned {
    pub(crate) width: u32,
    pub(crate) height: u32,
    pub(crate) splats: Handle,
    pub(crate) info: Handle,
    pub(crate) ids: Handle,
    pub(crate) tile_start: Handle,
    pub(crate) tile_end: Handle,
    pub(crate) intersections: usize,
    pub(crate) cam: Handle,
    pub(crate) tiles_x: u32,
    pub(crate) tiles_y: u32,
}

/// With `keep_faint`, Gaussians below 1/255 opacity are binned too (see `project::project_forward`).
pub(crate) fn project_and_bin(
    ctx: &GpuContext,
    scene: &GpuScene,
    camera: &Camera,
    keep_faint: bool,
) -> Result<Binned, GpuError> {
    let c = &ctx.client;
    let n = scene.len;
    let tiles_x = camera.width.div_ceil(TILE);
    let tiles_y = camera.height.div_ceil(TILE);
    let num_tiles = (tiles_x * tiles_y) as usize;
    let cam = upload_f32(c, &camera_values(camera));

    // 1. Projection.
    let splats = empty32(c, SPLAT_F * n);
    let info = empty32(c, INFO_U * n);
    if n > 0 {
        let (count, dim) = grid(n);
        project::project_forward::launch(
            c,
            count,
            dim,
            arg(&scene.means, 3 * n),
            arg(&scene.log_scales, 3 * n),
            arg(&scene.quats, 4 * n),
            arg(&scene.opacity_logits, n),
            arg(&scene.sh, 3 * crate::scene::sh_coeffs(scene.sh_degree) * n),
            arg(&cam, CAM_F),
            n as u32,
            tiles_x,
            tiles_y,
            arg(&splats, SPLAT_F * n),
            arg(&info, INFO_U * n),
            scene.sh_degree,
            keep_faint,
        );
    }

    // 2. Binning.
    let (ids, tile_start, tile_end, intersections) =
        tiles::bin(ctx, &info, n, tiles_x, num_tiles.max(1))?;
    Ok(Binned {
        width: camera.width,
        height: camera.height,
        splats,
        info,
        ids,
        tile_start,
        tile_end,
        intersections,
        cam,
        tiles_x,
        tiles_y,
    })
}

fn render_device_inner(
    ctx: &GpuContext,
    scene: &GpuScene,
    camera: &Camera,
    settings: &RenderSettings,
    extra: Option<(&Handle, usize)>,
    ppu: u32,
) -> Result<GpuFrame, GpuError> {
    let binned = project_and_bin(ctx, scene, camera, false)?;
    Ok(rasterise(
        ctx, scene.len, binned, settings, extra, ppu, true,
    ))
}

/// Stage 3 on a view's projected and binned `n` Gaussians; `geometry_grads` goes to the frame.
pub(crate) fn rasterise(
    ctx: &GpuContext,
    n: usize,
    binned: Binned,
    settings: &RenderSettings,
    extra: Option<(&Handle, usize)>,
    ppu: u32,
    geometry_grads: bool,
) -> GpuFrame {
    rasterise_sparse(ctx, n, binned, settings, extra, ppu, geometry_grads, None)
}

/// [`rasterise`], compositing the extra channels only at the pixels whose row and column `needed`
/// flags (one u32 per row, one per column: 1 or 0); zero at the others.
#[allow(clippy::too_many_arguments)]
pub(crate) fn rasterise_sparse(
    ctx: &GpuContext,
    n: usize,
    binned: Binned,
    settings: &RenderSettings,
    extra: Option<(&Handle, usize)>,
    ppu: u32,
    geometry_grads: bool,
    needed: Option<(&Handle, &Handle)>,
) -> GpuFrame {
    rasterise_images(
        ctx,
        n,
        binned,
        None,
        settings,
        extra,
        ppu,
        geometry_grads,
        needed,
    )
}

/// [`rasterise_sparse`] of one image, or of two of the same size in one launch (`second`: image 1's
/// lists, its Gaussians' records after image 0's in `binned`'s `splats`, `n` records in all).
#[allow(clippy::too_many_arguments)]
pub(crate) fn rasterise_images(
    ctx: &GpuContext,
    n: usize,
    binned: Binned,
    second: Option<PairImage>,
    settings: &RenderSettings,
    extra: Option<(&Handle, usize)>,
    ppu: u32,
    geometry_grads: bool,
    needed: Option<(&Handle, &Handle)>,
) -> GpuFrame {
    assert!(
        ppu.is_power_of_two() && ppu <= TILE,
        "pixels per unit must be a power of two ≤ {TILE}"
    );
    let c = &ctx.client;
    let Binned {
        width,
        height,
        splats,
        info,
        ids,
        tile_start,
        tile_end,
        intersections,
        cam,
        tiles_x,
        tiles_y,
    } = binned;
    // A pair's second half is differentiated through its camera's colours only (`project_backward`).
    assert!(
        second.is_none() || !geometry_grads,
        "a pair of images renders kept geometry only"
    );
    let images = if second.is_some() { 2 } else { 1 };
    let pair = second.unwrap_or_else(|| PairImage {
        ids: ids.clone(),
        tile_start: tile_start.clone(),
        tile_end: tile_end.clone(),
        intersections,
        cam: cam.clone(),
        offset: 0,
    });
    // Every per-pixel buffer holds all the images.
    let npix = images as usize * (width * height) as usize;
    let num_tiles = (tiles_x * tiles_y) as usize;

    // 3. Rasterisation.
    let channels = extra.map_or(0, |e| e.1);
    let extra_vals = extra.map_or_else(|| empty32(c, 1), |e| e.0.clone());
    let rgb = empty32(c, 3 * npix);
    let alpha = empty32(c, npix);
    let depth = empty32(c, npix);
    let extra_img = empty32(c, channels * npix);
    let t_final = empty32(c, npix);
    let last = empty32(c, npix);
    if npix > 0 {
        let bg = settings.background;
        raster::raster_forward::launch(
            c,
            CubeCount::new_3d(tiles_x, tiles_y, images),
            CubeDim::new_2d(TILE, TILE / ppu),
            arg(&splats, SPLAT_F * n),
            arg(&ids, intersections),
            arg(&tile_start, num_tiles),
            arg(&tile_end, num_tiles),
            arg(&pair.ids, pair.intersections),
            arg(&pair.tile_start, num_tiles),
            arg(&pair.tile_end, num_tiles),
            pair.offset,
            arg(&extra_vals, channels * n),
            arg(
                needed.map_or(&extra_vals, |f| f.0),
                needed.map_or(1, |_| height as usize),
            ),
            arg(
                needed.map_or(&extra_vals, |f| f.1),
                needed.map_or(1, |_| width as usize),
            ),
            width,
            height,
            tiles_x,
            bg[0],
            bg[1],
            bg[2],
            arg(&rgb, 3 * npix),
            arg(&alpha, npix),
            arg(&depth, npix),
            arg(&extra_img, channels * npix),
            arg(&t_final, npix),
            arg(&last, npix),
            channels as u32,
            ppu,
            needed.is_some(),
        );
    }
    GpuFrame {
        width,
        height,
        channels,
        rgb,
        alpha,
        depth,
        extra: extra_img,
        intersections,
        splats,
        info,
        ids,
        tile_start,
        t_final,
        last,
        cam,
        tiles_x,
        tiles_y,
        geometry_grads,
        images,
        pair,
    }
}

/// Gradients of the loss with respect to a device frame's outputs (device buffers, same layouts).
pub struct GpuOutputGrads<'a> {
    pub rgb: &'a Handle,
    pub alpha: Option<&'a Handle>,
    pub depth: Option<&'a Handle>,
    pub extra: Option<&'a Handle>,
}

impl<'a> GpuOutputGrads<'a> {
    /// Gradients of the colour alone (a loss on the image only).
    pub fn rgb_only(rgb: &'a Handle) -> Self {
        Self {
            rgb,
            alpha: None,
            depth: None,
            extra: None,
        }
    }
}

/// Parameter gradients on the device (layouts of [`SceneGrads`]); `splat` holds the per-Gaussian screen
/// gradients (mean x, y first: the densification statistics read them).
pub struct GpuSceneGrads {
    pub means: Handle,
    pub log_scales: Handle,
    pub quats: Handle,
    pub opacity_logits: Handle,
    pub sh: Handle,
    /// N*C, present when an extra-channel gradient was given.
    pub extra: Option<Handle>,
    pub splat: Handle,
}

/// Pixels each unit of the raster forward owns (a power of two dividing `TILE`) when it composites
/// `channels` extra channels. Hardware: one per unit (gsplat's layout, 256 units per tile). Software
/// (lavapipe runs a cube on one CPU thread, 8 units per SIMD step): 16, as fast as the per-pixel kernel
/// there and fewer barriers per Gaussian; but 4 above 16 channels, since Mesa 22.3's lavapipe mis-runs
/// the 16-pixel kernel with more than 32 (colours and alpha wrong too; Mesa 25 is exact, as 4 is on
/// both; `the_render_back_is_right_where_the_grid_reads_it`). On Mesa 25 the 4-pixel kernel costs
/// 5–10 % of a 144-channel render.
pub(crate) fn forward_pixels_per_unit(ctx: &GpuContext, channels: usize) -> u32 {
    match (ctx.software, channels) {
        (false, _) => 1,
        (true, 0..=16) => 16,
        (true, _) => 4,
    }
}

/// Pixels each unit of the raster backward owns (a power of two dividing `TILE`): its gradients are
/// summed over them before the atomics. Hardware: 4 (brush's choice: 64 units per tile, 4x fewer
/// atomics). Software: 16, measured fastest on lavapipe (125k Gaussians at 512²: ppu 1 / 2 / 4 / 8 / 16
/// took 3.6 / 1.9 / 1.2 / 0.78 / 0.61 s).
pub(crate) fn backward_pixels_per_unit(ctx: &GpuContext) -> u32 {
    if ctx.software {
        16
    } else {
        4
    }
}

/// Backward of [`render_device`]: `scene`, `camera`, `settings` and `extra` must be those of `frame`.
pub fn render_backward_device(
    ctx: &GpuContext,
    scene: &GpuScene,
    settings: &RenderSettings,
    extra: Option<(&Handle, usize)>,
    frame: &GpuFrame,
    grads: &GpuOutputGrads<'_>,
) -> Result<GpuSceneGrads, GpuError> {
    let layout = BackwardLayout::of(ctx);
    render_backward_device_with(ctx, scene, settings, extra, frame, grads, layout)
}

/// How the raster backward sums its gradients (every layout gives the same gradients up to the order
/// of float sums; the tests try each).
#[derive(Clone, Copy, Debug)]
struct BackwardLayout {
    /// Pixels per unit (a power of two ≤ `TILE`).
    ppu: u32,
    /// Plane reductions before the atomics.
    plane: bool,
    /// Shared-memory sums per batch before the global atomics (`raster::STAGE_*`).
    staging: u32,
}

impl BackwardLayout {
    /// The adapter's layout.
    fn of(ctx: &GpuContext) -> Self {
        let ppu = backward_pixels_per_unit(ctx);
        Self {
            ppu,
            plane: plane_sums(ctx, ppu),
            staging: backward_staging(ctx),
        }
    }
}

/// How the raster backward stages each batch's gradients in shared memory before its global atomics
/// (`raster::raster_backward`'s `staging`). Not by default: `VCEDIT_GPU_STAGED_BACKWARD=on` stages in
/// shared float atomics on the SPIR-V compiler and in swapped bits on WGSL (which has no float atomics in
/// shared memory), `=bits` in swapped bits on either. It is meant for SPIR-V, whose atomics are
/// acquire-release ones (the backward was 5.5× slower there than on WGSL on an H200, 2026-11-28), and
/// stays off until a card has measured it: gpu-check's `fit-ab` compares the variants.
fn backward_staging(ctx: &GpuContext) -> u32 {
    static ASKED: std::sync::OnceLock<Option<String>> = std::sync::OnceLock::new();
    let asked = ASKED.get_or_init(|| {
        std::env::var("VCEDIT_GPU_STAGED_BACKWARD")
            .ok()
            .map(|v| v.trim().to_string())
    });
    let spirv = ctx.on_spirv();
    match asked.as_deref() {
        Some("bits") => raster::STAGE_BITS,
        Some("on" | "1" | "true") if spirv => raster::STAGE_FLOAT,
        Some("on" | "1" | "true") => raster::STAGE_BITS,
        _ => raster::STAGE_NONE,
    }
}

/// Whether the raster backward with `ppu` pixels per unit sums each plane's gradients: asked for, offered
/// by the adapter, whole planes, and the SPIR-V compiler (on an H200 the WGSL kernel with plane sums
/// failed to build, 2026-11-28; cubecl registers plane operations there all the same).
fn plane_sums(ctx: &GpuContext, ppu: u32) -> bool {
    plane_sums_asked() && ctx.on_spirv() && plane_reductions(ctx) && plane_fits(ctx, ppu)
}

/// Whether `VCEDIT_GPU_PLANE_SUMS=on` asks the raster backward to sum each plane's gradients before its
/// atomics. Off by default until a hardware run has checked it: cubecl registers plane operations only
/// on hardware adapters, so the tests here (lavapipe) cannot run that path; `tools/gpu-check`'s `fit-ab`
/// compares a fit with and without it (time and held-out PSNR).
fn plane_sums_asked() -> bool {
    static ASKED: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *ASKED.get_or_init(|| {
        matches!(
            std::env::var("VCEDIT_GPU_PLANE_SUMS")
                .as_deref()
                .map(str::trim),
            Ok("on" | "1" | "true")
        )
    })
}

/// Whether the adapter offers plane (subgroup) reductions to the raster backward: cubecl registers
/// them on hardware adapters with subgroups, not on software ones (lavapipe has subgroups, but cubecl's
/// compiler refuses plane operations there).
fn plane_reductions(ctx: &GpuContext) -> bool {
    ctx.client
        .properties()
        .features
        .plane
        .contains(::gpu::cubecl::ir::features::Plane::Ops)
}

/// Whether the raster backward's `TILE * TILE / ppu` units split into whole planes.
fn plane_fits(ctx: &GpuContext, ppu: u32) -> bool {
    let (units, plane) = (TILE * TILE / ppu, ctx.limits.plane_size);
    plane > 0 && plane <= units && units % plane == 0
}

/// [`render_backward_device`] with the raster backward's `layout`.
fn render_backward_device_with(
    ctx: &GpuContext,
    scene: &GpuScene,
    settings: &RenderSettings,
    extra: Option<(&Handle, usize)>,
    frame: &GpuFrame,
    grads: &GpuOutputGrads<'_>,
    layout: BackwardLayout,
) -> Result<GpuSceneGrads, GpuError> {
    let BackwardLayout {
        ppu,
        plane,
        staging,
    } = layout;
    assert!(
        ppu.is_power_of_two() && ppu <= TILE,
        "pixels per unit must be a power of two ≤ {TILE}"
    );
    assert!(
        !plane || plane_fits(ctx, ppu),
        "{ppu} pixels per unit: no whole planes"
    );
    gpu_call(|| {
        let c = &ctx.client;
        let n = scene.len;
        let npix = frame.all_pixels();
        let k = crate::scene::sh_coeffs(scene.sh_degree);
        let num_tiles = (frame.tiles_x * frame.tiles_y) as usize;
        let splat = zeros32(c, GRAD_F * n);
        let channels = match (extra, grads.extra) {
            (Some((_, ch)), Some(_)) if ch > 0 => ch,
            _ => 0,
        };
        let g_extra = (channels > 0).then(|| zeros32(c, channels * n));
        if npix > 0 && frame.all_intersections() > 0 {
            let zeros_pix =
                (grads.alpha.is_none() || grads.depth.is_none()).then(|| zeros32(c, npix));
            let v_alpha = grads.alpha.or(zeros_pix.as_ref()).unwrap();
            let v_depth = grads.depth.or(zeros_pix.as_ref()).unwrap();
            let dummy = empty32(c, 1);
            let extra_vals = extra.filter(|_| channels > 0).map_or(&dummy, |e| e.0);
            let v_extra = grads.extra.filter(|_| channels > 0).unwrap_or(&dummy);
            let behind = empty32(c, channels * npix);
            let bg = settings.background;
            let pair = &frame.pair;
            raster::raster_backward::launch(
                c,
                CubeCount::new_3d(frame.tiles_x, frame.tiles_y, frame.images),
                CubeDim::new_2d(TILE, TILE / ppu),
                arg(&frame.splats, SPLAT_F * n),
                arg(&frame.ids, frame.intersections),
                arg(&frame.tile_start, num_tiles),
                arg(&pair.ids, pair.intersections),
                arg(&pair.tile_start, num_tiles),
                pair.offset,
                arg(extra_vals, channels * n),
                frame.width,
                frame.height,
                frame.tiles_x,
                bg[0],
                bg[1],
                bg[2],
                arg(&frame.t_final, npix),
                arg(&frame.last, npix),
                arg(grads.rgb, 3 * npix),
                arg(v_alpha, npix),
                arg(v_depth, npix),
                arg(v_extra, channels * npix),
                arg(&behind, channels * npix),
                arg(&splat, GRAD_F * n),
                arg(g_extra.as_ref().unwrap_or(&dummy), channels * n),
                channels as u32,
                ppu,
                plane,
                staging,
            );
        }
        let out = GpuSceneGrads {
            means: empty32(c, 3 * n),
            log_scales: empty32(c, 3 * n),
            quats: empty32(c, 4 * n),
            opacity_logits: empty32(c, n),
            sh: empty32(c, 3 * k * n),
            extra: g_extra,
            splat,
        };
        if n > 0 {
            let (count, dim) = grid(n);
            // The second image's Gaussians, from `half` on, are seen from its camera.
            let half = match frame.images {
                1 => n as u32,
                _ => frame.pair.offset,
            };
            project::project_backward::launch(
                c,
                count,
                dim,
                arg(&scene.means, 3 * n),
                arg(&scene.log_scales, 3 * n),
                arg(&scene.quats, 4 * n),
                arg(&scene.sh, 3 * k * n),
                arg(&frame.cam, CAM_F),
                arg(&frame.pair.cam, CAM_F),
                half,
                n as u32,
                arg(&frame.splats, SPLAT_F * n),
                arg(&frame.info, INFO_U * n),
                arg(&out.splat, GRAD_F * n),
                arg(&out.means, 3 * n),
                arg(&out.log_scales, 3 * n),
                arg(&out.quats, 4 * n),
                arg(&out.opacity_logits, n),
                arg(&out.sh, 3 * k * n),
                scene.sh_degree,
                frame.geometry_grads,
            );
        }
        Ok(out)
    })
}

/// Reads a device frame back.
pub fn download(ctx: &GpuContext, frame: &GpuFrame, n: usize) -> Result<Frame, GpuError> {
    let c = &ctx.client;
    let npix = (frame.width * frame.height) as usize;
    let info = read_u32(c, &frame.info, INFO_U * n)?;
    Ok(Frame {
        width: frame.width,
        height: frame.height,
        rgb: read_f32(c, &frame.rgb, 3 * npix)?,
        alpha: read_f32(c, &frame.alpha, npix)?,
        depth: read_f32(c, &frame.depth, npix)?,
        extra: read_f32(c, &frame.extra, frame.channels * npix)?,
        channels: frame.channels,
        radii: info.chunks(INFO_U).map(|r| r[0]).collect(),
    })
}

/// Host convenience: uploads, renders and reads back, like [`crate::render::render`].
pub fn render(
    ctx: &GpuContext,
    scene: &GaussianScene,
    camera: &Camera,
    settings: &RenderSettings,
    extra: Option<ExtraChannels<'_>>,
) -> Result<Frame, GpuError> {
    render_with(
        ctx,
        scene,
        camera,
        settings,
        extra,
        forward_pixels_per_unit(ctx, extra.map_or(0, |e| e.channels)),
    )
}

/// [`render`] with `ppu` pixels per raster forward unit (every layout gives the same image, bit for
/// bit: per pixel the operations are the same; the tests try each).
fn render_with(
    ctx: &GpuContext,
    scene: &GaussianScene,
    camera: &Camera,
    settings: &RenderSettings,
    extra: Option<ExtraChannels<'_>>,
    ppu: u32,
) -> Result<Frame, GpuError> {
    let dev = GpuScene::upload(ctx, scene);
    let extra_dev = extra.map(|e| {
        assert_eq!(
            e.values.len(),
            scene.len() * e.channels,
            "extra channel values must be N*C"
        );
        (upload_f32(&ctx.client, e.values), e.channels)
    });
    let extra_ref = extra_dev.as_ref().map(|(h, c)| (h, *c));
    let frame = gpu_call(|| render_device_inner(ctx, &dev, camera, settings, extra_ref, ppu))?;
    download(ctx, &frame, scene.len())
}

/// Host convenience: forward and backward on the device, gradients read back, like
/// [`crate::render::render_backward`] (which needs the forward's output; here the forward is rerun).
/// The tests' entry; the fits go through [`render_with_loss`] or the resident trainer.
#[cfg(test)]
pub fn render_backward(
    ctx: &GpuContext,
    scene: &GaussianScene,
    camera: &Camera,
    settings: &RenderSettings,
    extra: Option<ExtraChannels<'_>>,
    grads: &OutputGrads<'_>,
) -> Result<SceneGrads, GpuError> {
    render_backward_with(
        ctx,
        scene,
        camera,
        settings,
        extra,
        grads,
        BackwardLayout::of(ctx),
    )
}

/// [`render_backward`] with the raster backward's `layout`.
#[cfg(test)]
fn render_backward_with(
    ctx: &GpuContext,
    scene: &GaussianScene,
    camera: &Camera,
    settings: &RenderSettings,
    extra: Option<ExtraChannels<'_>>,
    grads: &OutputGrads<'_>,
    layout: BackwardLayout,
) -> Result<SceneGrads, GpuError> {
    let c = &ctx.client;
    let n = scene.len();
    let npix = (camera.width * camera.height) as usize;
    assert_eq!(grads.rgb.len(), 3 * npix, "rgb gradient must be H*W*3");
    let dev = GpuScene::upload(ctx, scene);
    let extra_dev = extra.map(|e| (upload_f32(c, e.values), e.channels));
    let extra_ref = extra_dev.as_ref().map(|(h, ch)| (h, *ch));
    let frame = render_device(ctx, &dev, camera, settings, extra_ref)?;
    let rgb = upload_f32(c, grads.rgb);
    let alpha = grads.alpha.map(|a| upload_f32(c, a));
    let depth = grads.depth.map(|d| upload_f32(c, d));
    let ext = grads.extra.map(|e| upload_f32(c, e));
    let g = render_backward_device_with(
        ctx,
        &dev,
        settings,
        extra_ref,
        &frame,
        &GpuOutputGrads {
            rgb: &rgb,
            alpha: alpha.as_ref(),
            depth: depth.as_ref(),
            extra: ext.as_ref(),
        },
        layout,
    )?;
    read_grads(ctx, &g, n, scene.sh_degree, extra_ref.map(|e| e.1))
}

/// One training pass with the loss on the host: uploads `scene`, renders on the device, reads the RGB
/// image back, lets `loss` turn it into (its value, dL/d rgb), and runs the backward on the device.
/// Returns the screen radii (densification uses them), the loss value and the parameter gradients.
pub fn render_with_loss<L>(
    ctx: &GpuContext,
    scene: &GaussianScene,
    camera: &Camera,
    settings: &RenderSettings,
    loss: impl FnOnce(&[f32]) -> (L, Vec<f32>),
) -> Result<(Vec<u32>, L, SceneGrads), GpuError> {
    let c = &ctx.client;
    let n = scene.len();
    let npix = (camera.width * camera.height) as usize;
    let dev = GpuScene::upload(ctx, scene);
    let frame = render_device(ctx, &dev, camera, settings, None)?;
    let rgb = read_f32(c, &frame.rgb, 3 * npix)?;
    let (value, grad) = loss(&rgb);
    assert_eq!(grad.len(), 3 * npix, "rgb gradient must be H*W*3");
    let grad = upload_f32(c, &grad);
    let g = render_backward_device(
        ctx,
        &dev,
        settings,
        None,
        &frame,
        &GpuOutputGrads::rgb_only(&grad),
    )?;
    let info = read_u32(c, &frame.info, INFO_U * n)?;
    let grads = read_grads(ctx, &g, n, scene.sh_degree, None)?;
    Ok((info.chunks(INFO_U).map(|r| r[0]).collect(), value, grads))
}

/// Reads device gradients back into the CPU renderer's type.
pub(crate) fn read_grads(
    ctx: &GpuContext,
    g: &GpuSceneGrads,
    n: usize,
    sh_degree: u32,
    channels: Option<usize>,
) -> Result<SceneGrads, GpuError> {
    let c = &ctx.client;
    let k = crate::scene::sh_coeffs(sh_degree);
    let splat = read_f32(c, &g.splat, GRAD_F * n)?;
    Ok(SceneGrads {
        means: read_f32(c, &g.means, 3 * n)?,
        log_scales: read_f32(c, &g.log_scales, 3 * n)?,
        quats: read_f32(c, &g.quats, 4 * n)?,
        opacity_logits: read_f32(c, &g.opacity_logits, n)?,
        sh: read_f32(c, &g.sh, 3 * k * n)?,
        extra: match (&g.extra, channels) {
            (Some(h), Some(ch)) => read_f32(c, h, ch * n)?,
            _ => vec![],
        },
        means2d: splat.chunks(GRAD_F).map(|s| [s[0], s[1]]).collect(),
    })
}
