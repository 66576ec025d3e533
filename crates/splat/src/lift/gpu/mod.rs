//! Lifting 2D maps onto Gaussians on the GPU, as [`crate::lift`] does on the CPU: per view the scene is
//! projected and binned as for rendering, then one kernel walks every pixel (laid out as the raster
//! forward) and adds its map values to the Gaussians it hits.
//!
//! [`GpuLiftScene::lift_and_render_back`] is the whole 2D → 3D → 2D round of CCM and blend-map
//! consistency on the device: only each view's map on its native grid goes up and comes back. A
//! [`GpuLiftScene`] serves every round of one sampler run (CCM's layers, the blend maps' steps): the scene
//! is uploaded once and each view's projection and tile lists are made once (`render::gpu::frozen`), where a
//! round used to project and bin every view twice, to lift and to render back, each time waiting for
//! the device to size the tile lists. Resampling to and from the
//! render resolution, the averages and the renders of the lifted values stay on the device (at 512² a
//! CCM layer's full-resolution map is 150 MB per view, which used to cross the bus twice and be
//! resampled on one host thread).

mod raster;
#[cfg(test)]
mod tests;

use crate::cameras::Camera;
use crate::lift::{axis_taps, read_by_resampling, widest_tile, Lifted, MapGrid, Resample};
use crate::render::gpu::project::SPLAT_F;
use crate::render::gpu::raster::{STAGE_BITS, STAGE_FLOAT};
use crate::render::gpu::{
    backward_pixels_per_unit, forward_pixels_per_unit, project_and_bin, rasterise_sparse, Binned,
    GpuFrozenGeometry, GpuScene,
};
use crate::render::{RenderSettings, TILE};
use crate::scene::GaussianScene;
use ::gpu::cubecl;
use ::gpu::cubecl::prelude::*;
use ::gpu::cubecl::server::Handle;
use ::gpu::gpu_call;
use ::gpu::prims::{
    arg, empty32, grid as grid_of, read_f32, read_u32, upload_f32, upload_u32, zeros32,
};
use ::gpu::{F32Buffer, F32Values, GpuContext, GpuError};

/// Lifts per-view maps (`maps[v]` is H*W*C for `cameras[v]`) onto the Gaussians of `scene`.
///
/// # Panics
/// When `maps` and `cameras` differ in length or a map has the wrong size (programming errors).
/// The tests' entry (all views at once); callers lift view by view with [`GpuLiftAccumulator`].
#[cfg(test)]
pub fn lift(
    ctx: &GpuContext,
    scene: &GaussianScene,
    cameras: &[Camera],
    maps: &[&[f32]],
    channels: usize,
) -> Result<Lifted, GpuError> {
    lift_with(
        ctx,
        scene,
        cameras,
        maps,
        channels,
        lift_pixels_per_unit(ctx),
    )
}

/// [`lift`] with `ppu` pixels per unit (same counts; sums up to the order of float additions).
#[cfg(test)]
pub(super) fn lift_with(
    ctx: &GpuContext,
    scene: &GaussianScene,
    cameras: &[Camera],
    maps: &[&[f32]],
    channels: usize,
    ppu: u32,
) -> Result<Lifted, GpuError> {
    assert_eq!(cameras.len(), maps.len(), "one map per camera");
    let mut acc = GpuLiftAccumulator::with_layout(ctx, scene, channels, ppu);
    for (cam, map) in cameras.iter().zip(maps) {
        acc.add_view(ctx, cam, map)?;
    }
    acc.finish(ctx)
}

/// Lifting one view at a time (the GPU twin of [`crate::lift::LiftAccumulator`]): the scene and the
/// per-Gaussian sums stay on the device, so only one view's map is ever held on the host.
pub struct GpuLiftAccumulator {
    scene: GpuScene,
    n: usize,
    channels: usize,
    sums: Handle,
    counts: Handle,
    /// Pixels per unit of the accumulation kernel (laid out as the raster forward).
    ppu: u32,
}

impl GpuLiftAccumulator {
    /// Uploads `scene` with zeroed sums for `channels` channels.
    pub fn new(ctx: &GpuContext, scene: &GaussianScene, channels: usize) -> Self {
        Self::with_layout(ctx, scene, channels, lift_pixels_per_unit(ctx))
    }

    fn with_layout(ctx: &GpuContext, scene: &GaussianScene, channels: usize, ppu: u32) -> Self {
        let n = scene.len();
        Self {
            ppu,
            scene: GpuScene::upload(ctx, scene),
            n,
            channels,
            sums: zeros32(&ctx.client, n * channels),
            counts: zeros32(&ctx.client, n),
        }
    }

    /// Adds `map` (H*W*C) seen from `cam`.
    ///
    /// # Panics
    /// When the map has the wrong size (a programming error).
    pub fn add_view(
        &mut self,
        ctx: &GpuContext,
        cam: &Camera,
        map: &[f32],
    ) -> Result<(), GpuError> {
        let npix = (cam.width * cam.height) as usize;
        assert_eq!(map.len(), npix * self.channels, "map must be H*W*C");
        if npix == 0 || self.n == 0 {
            return Ok(());
        }
        let map = gpu_call(|| Ok(upload_f32(&ctx.client, map)))?;
        self.add_device_view(ctx, cam, &map)
    }

    /// [`Self::add_view`] with the map already on the device (H*W*C values).
    fn add_device_view(
        &mut self,
        ctx: &GpuContext,
        cam: &Camera,
        map: &Handle,
    ) -> Result<(), GpuError> {
        if cam.width * cam.height == 0 || self.n == 0 {
            return Ok(());
        }
        gpu_call(|| {
            let bins = project_and_bin(ctx, &self.scene, cam, false)?;
            accumulate(
                ctx,
                self.n,
                &bins,
                map,
                &self.sums,
                &self.counts,
                self.channels,
                self.ppu,
            );
            Ok(())
        })
    }

    /// The per-Gaussian averages and hit counts, read back.
    pub fn finish(self, ctx: &GpuContext) -> Result<Lifted, GpuError> {
        let c = &ctx.client;
        let (n, channels) = (self.n, self.channels);
        gpu_call(|| {
            let counts: Vec<f32> = read_u32(c, &self.counts, n)?
                .into_iter()
                .map(|k| k as f32)
                .collect();
            let mut values = read_f32(c, &self.sums, n * channels)?;
            if channels > 0 {
                for (row, &k) in values.chunks_mut(channels).zip(&counts) {
                    let inv = 1.0 / (k + 1e-7);
                    for v in row {
                        *v *= inv;
                    }
                }
            }
            Ok(Lifted { values, counts })
        })
    }
}

/// Lifting's pixels per unit: each unit sums its pixels' map values before its one atomic add per hit
/// Gaussian and channel, so the backward's layout (4 on hardware, brush's choice: 4× fewer atomics on
/// the Gaussians a whole tile shares; 16 on lavapipe) rather than the forward's one pixel per unit.
fn lift_pixels_per_unit(ctx: &GpuContext) -> u32 {
    backward_pixels_per_unit(ctx)
}

/// Adds a view's `map` (H*W*C on the device) to the per-Gaussian `sums` (N*C) and hit `counts` (N), over
/// the view's projected and binned `n` Gaussians.
#[allow(clippy::too_many_arguments)]
fn accumulate(
    ctx: &GpuContext,
    n: usize,
    bins: &Binned,
    map: &Handle,
    sums: &Handle,
    counts: &Handle,
    channels: usize,
    ppu: u32,
) {
    let npix = (bins.width * bins.height) as usize;
    if bins.intersections == 0 || npix == 0 {
        return;
    }
    let num_tiles = (bins.tiles_x * bins.tiles_y) as usize;
    raster::lift_accumulate::launch(
        &ctx.client,
        CubeCount::new_2d(bins.tiles_x, bins.tiles_y),
        CubeDim::new_2d(TILE, TILE / ppu),
        arg(&bins.splats, SPLAT_F * n),
        arg(&bins.ids, bins.intersections),
        arg(&bins.tile_start, num_tiles),
        arg(&bins.tile_end, num_tiles),
        arg(map, npix * channels),
        bins.width,
        bins.height,
        bins.tiles_x,
        arg(sums, n * channels),
        arg(counts, n),
        channels as u32,
        ppu,
    );
}

/// Cells per axis the grid lifting stages per tile at most ([`raster::lift_accumulate_grid`]): a map
/// grid finer than about a quarter of the tiles' pixels is lifted per pixel, from its upsampled version.
const MAX_GRID_SPAN: u32 = 6;

/// How [`raster::lift_accumulate_grid`] runs for one grid and view size.
#[derive(Clone, Copy, Debug)]
struct GridLayout {
    /// Cells per axis a tile stages (comptime).
    span: u32,
    staging: u32,
    ppu: u32,
}

/// The grid lifting's layout for maps on `grid` lifted at `full` (rows, columns), or None where the
/// per-pixel kernel lifts them: a grid too fine for [`MAX_GRID_SPAN`], or `VCEDIT_GPU_LIFT=pixels`
/// (the A/B switch of gpu-check). `VCEDIT_GPU_LIFT=float` stages in shared float atomics on the SPIR-V
/// compiler; by default the weights' bits are swapped in, which every compiler has.
fn grid_layout(ctx: &GpuContext, grid: &MapGrid, full: (usize, usize)) -> Option<GridLayout> {
    static ASKED: std::sync::OnceLock<Option<String>> = std::sync::OnceLock::new();
    let asked = ASKED.get_or_init(|| {
        std::env::var("VCEDIT_GPU_LIFT")
            .ok()
            .map(|v| v.trim().to_string())
    });
    if asked.as_deref() == Some("pixels") {
        return None;
    }
    let staging = if asked.as_deref() == Some("float") && ctx.on_spirv() {
        STAGE_FLOAT
    } else {
        STAGE_BITS
    };
    GridLayout::new(ctx, grid, full, staging)
}

impl GridLayout {
    /// The layout for maps on `grid` lifted at `full` with `staging`; None where the grid is too fine.
    fn new(ctx: &GpuContext, grid: &MapGrid, full: (usize, usize), staging: u32) -> Option<Self> {
        if grid.channels == 0 {
            return None;
        }
        let span =
            grid_span(full.0, grid.height, grid.up)?.max(grid_span(full.1, grid.width, grid.up)?);
        Some(Self {
            span,
            staging,
            ppu: lift_pixels_per_unit(ctx),
        })
    }
}

/// The most cells one tile's pixels read along an axis of `full` pixels upsampled from `cells` cells
/// (`resample_map` takes the host's f32 scale, so its taps are the CPU's), plus one for a device that
/// rounds a pixel's position differently; None beyond [`MAX_GRID_SPAN`].
pub(super) fn grid_span(full: usize, cells: usize, mode: Resample) -> Option<u32> {
    if full == 0 || cells == 0 {
        return None;
    }
    let span = widest_tile(&axis_taps(full, cells, mode)) as u32 + 1;
    (span <= MAX_GRID_SPAN).then_some(span)
}

/// The tests' entry to both lifting kernels: `maps[v]` on `grid` lifted over `cameras`, through the grid
/// kernel with `staging` (with the span the host would pick), or per pixel from the upsampled maps when
/// `staging` is None.
#[cfg(test)]
pub(super) fn lift_on_grid(
    ctx: &GpuContext,
    scene: &GaussianScene,
    cameras: &[Camera],
    maps: &[Vec<f32>],
    grid: &MapGrid,
    staging: Option<u32>,
) -> Result<Lifted, GpuError> {
    let ppu = lift_pixels_per_unit(ctx);
    let acc = GpuLiftAccumulator::with_layout(ctx, scene, grid.channels, ppu);
    for (cam, map) in cameras.iter().zip(maps) {
        let full = (cam.height as usize, cam.width as usize);
        let bins = project_and_bin(ctx, &acc.scene, cam, false)?;
        let small = upload_f32(&ctx.client, map);
        match staging {
            Some(staging) => {
                let layout = GridLayout::new(ctx, grid, full, staging).expect("a coarse grid");
                accumulate_grid(
                    ctx,
                    acc.n,
                    &bins,
                    &small,
                    grid,
                    layout,
                    &acc.sums,
                    &acc.counts,
                );
            }
            None => {
                let native = (grid.height, grid.width);
                let up = resample_on_device(ctx, &small, native, full, grid.channels, grid.up);
                accumulate(
                    ctx,
                    acc.n,
                    &bins,
                    &up,
                    &acc.sums,
                    &acc.counts,
                    grid.channels,
                    ppu,
                );
            }
        }
    }
    acc.finish(ctx)
}

/// The tests' entry to the render-back: `values` (N*C) composited over `cam` at full resolution, densely
/// or only at the pixels that resampling to `grid` reads ([`read_by_resampling`]'s rows and columns).
#[cfg(test)]
pub(super) fn render_back_pixels(
    ctx: &GpuContext,
    scene: &GaussianScene,
    cam: &Camera,
    values: &[f32],
    grid: &MapGrid,
    sparse: bool,
) -> Result<Vec<f32>, GpuError> {
    let c = &ctx.client;
    let gpu_scene = GpuScene::upload(ctx, scene);
    let (h, w) = (cam.height as usize, cam.width as usize);
    let rows = read_by_resampling(h, grid.height, grid.down);
    let cols = read_by_resampling(w, grid.width, grid.down);
    let bins = project_and_bin(ctx, &gpu_scene, cam, false)?;
    let extra = upload_f32(c, values);
    let flags = sparse.then(|| (upload_u32(c, &rows), upload_u32(c, &cols)));
    let frame = rasterise_sparse(
        ctx,
        scene.len(),
        bins,
        &RenderSettings::default(),
        Some((&extra, grid.channels)),
        forward_pixels_per_unit(ctx, grid.channels),
        true,
        flags.as_ref().map(|(r, k)| (r, k)),
    );
    read_f32(c, &frame.extra, h * w * grid.channels)
}

/// Adds a view's map, given on `grid` (`small`, grid.len() values on the device), to the per-Gaussian
/// `sums` and `counts` as [`accumulate`] adds its upsampled version (see
/// [`raster::lift_accumulate_grid`]).
#[allow(clippy::too_many_arguments)]
fn accumulate_grid(
    ctx: &GpuContext,
    n: usize,
    bins: &Binned,
    small: &Handle,
    grid: &MapGrid,
    layout: GridLayout,
    sums: &Handle,
    counts: &Handle,
) {
    let npix = (bins.width * bins.height) as usize;
    if bins.intersections == 0 || npix == 0 {
        return;
    }
    let num_tiles = (bins.tiles_x * bins.tiles_y) as usize;
    let channels = grid.channels;
    raster::lift_accumulate_grid::launch(
        &ctx.client,
        CubeCount::new_2d(bins.tiles_x, bins.tiles_y),
        CubeDim::new_2d(TILE, TILE / layout.ppu),
        arg(&bins.splats, SPLAT_F * n),
        arg(&bins.ids, bins.intersections),
        arg(&bins.tile_start, num_tiles),
        arg(&bins.tile_end, num_tiles),
        arg(small, grid.len()),
        bins.width,
        bins.height,
        bins.tiles_x,
        grid.width as u32,
        grid.height as u32,
        // The axis scales in f32 from the host, as `resample_on_device` passes them.
        grid.width as f32 / bins.width as f32,
        grid.height as f32 / bins.height as f32,
        u32::from(grid.up == Resample::Bilinear),
        arg(sums, n * channels),
        arg(counts, n),
        channels as u32,
        layout.ppu,
        layout.span,
        layout.staging,
    );
}

/// One scene's lifting rounds on the device (see the module documentation): the scene uploaded once,
/// each view's projection and tile lists kept within [`crate::render::FrozenGeometry::DEFAULT_BUDGET`]
/// (views beyond it are projected and binned for each use, as before).
pub struct GpuLiftScene {
    scene: GpuScene,
    views: GpuFrozenGeometry,
}

impl GpuLiftScene {
    /// Uploads `scene`.
    pub fn new(ctx: &GpuContext, scene: &GaussianScene) -> Self {
        Self::with_budget(ctx, scene, crate::render::FrozenGeometry::DEFAULT_BUDGET)
    }

    /// [`Self::new`] with views kept within `budget` bytes.
    pub(super) fn with_budget(ctx: &GpuContext, scene: &GaussianScene, budget: usize) -> Self {
        Self {
            scene: GpuScene::upload(ctx, scene),
            views: GpuFrozenGeometry::fixed_opacities(budget),
        }
    }

    /// Device bytes of the kept views.
    #[cfg(test)]
    pub(super) fn kept_bytes(&self) -> usize {
        self.views.bytes()
    }

    /// View `v`'s projected and binned Gaussians: the kept ones, else made for this use.
    fn bins(&mut self, ctx: &GpuContext, cam: &Camera, v: usize) -> Result<Binned, GpuError> {
        match self.views.view(ctx, &self.scene, cam, v)? {
            Some(bins) => Ok(bins.clone()),
            None => gpu_call(|| project_and_bin(ctx, &self.scene, cam, false)),
        }
    }

    /// Lifts per-view maps given on `grid` onto the Gaussians and renders them back to that grid, as
    /// [`crate::device::SplatDevice::lift_and_render_back`] describes. The maps rendered back stay on the
    /// device; of the maps lifted, only those given on the host cross the bus.
    ///
    /// # Panics
    /// When a map from `map_of` is not `grid.len()` long (a programming error).
    pub fn lift_and_render_back<E: From<GpuError>>(
        &mut self,
        ctx: &GpuContext,
        cameras: &[Camera],
        grid: &MapGrid,
        map_of: &mut dyn FnMut(usize) -> Result<F32Values, E>,
        sink: &mut dyn FnMut(usize, F32Values) -> Result<(), E>,
    ) -> Result<(), E> {
        let c = &ctx.client;
        let (n, channels) = (self.scene.len, grid.channels);
        let native = (grid.height, grid.width);
        let ppu = lift_pixels_per_unit(ctx);
        let (sums, counts) = gpu_call(|| Ok((zeros32(c, n * channels), zeros32(c, n))))?;
        for (v, cam) in cameras.iter().enumerate() {
            let map = map_of(v)?;
            assert_eq!(map.len(), grid.len(), "map {v} must be on the grid");
            if cam.width * cam.height == 0 || n == 0 {
                continue;
            }
            let bins = self.bins(ctx, cam, v)?;
            let full = (cam.height as usize, cam.width as usize);
            gpu_call(|| {
                let small = match &map {
                    F32Values::Host(map) => upload_f32(c, map),
                    F32Values::Device(buffer) => buffer.handle().clone(),
                };
                match grid_layout(ctx, grid, full) {
                    Some(layout) => {
                        accumulate_grid(ctx, n, &bins, &small, grid, layout, &sums, &counts)
                    }
                    None => {
                        let full_map =
                            resample_on_device(ctx, &small, native, full, channels, grid.up);
                        accumulate(ctx, n, &bins, &full_map, &sums, &counts, channels, ppu);
                    }
                }
                Ok(())
            })?;
        }
        gpu_call(|| {
            if n * channels > 0 {
                let (count, dim) = grid_of(n * channels);
                lift_average::launch(
                    c,
                    count,
                    dim,
                    arg(&sums, n * channels),
                    arg(&counts, n),
                    (n * channels) as u32,
                    channels as u32,
                );
            }
            Ok(())
        })?;
        let settings = RenderSettings::default();
        let forward_ppu = forward_pixels_per_unit(ctx, channels);
        for (v, cam) in cameras.iter().enumerate() {
            let full = (cam.height as usize, cam.width as usize);
            let bins = self.bins(ctx, cam, v)?;
            let back = gpu_call(|| {
                // Only the pixels the resampling to the grid reads composite the lifted channels.
                let flags = sparse_back().then(|| {
                    (
                        upload_u32(c, &read_by_resampling(full.0, grid.height, grid.down)),
                        upload_u32(c, &read_by_resampling(full.1, grid.width, grid.down)),
                    )
                });
                let frame = rasterise_sparse(
                    ctx,
                    n,
                    bins,
                    &settings,
                    Some((&sums, channels)),
                    forward_ppu,
                    true,
                    flags.as_ref().map(|(rows, cols)| (rows, cols)),
                );
                let small =
                    resample_on_device(ctx, &frame.extra, full, native, channels, grid.down);
                F32Buffer::new(small, grid.len())
                    .map(F32Values::Device)
                    .map_err(GpuError::BufferTooSmall)
            })?;
            sink(v, back)?;
        }
        Ok(())
    }
}

/// Whether the render-back composites the lifted channels only where the grid reads them (the default;
/// `VCEDIT_GPU_SPARSE_BACK=off` composites every pixel, the A/B; read once per process).
fn sparse_back() -> bool {
    static ON: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *ON.get_or_init(|| std::env::var("VCEDIT_GPU_SPARSE_BACK").map_or(true, |v| v.trim() != "off"))
}

/// [`super::ChannelSlice`] `part` of `src` copied into `dst` on the device (a round's channels
/// split into passes and put back together).
pub(crate) fn copy_channels(
    ctx: &GpuContext,
    src: &Handle,
    dst: &Handle,
    part: super::ChannelSlice,
) {
    let len = part.cells * part.width;
    if len == 0 {
        return;
    }
    let (count, dim) = grid_of(len);
    copy_channel_slice::launch(
        &ctx.client,
        count,
        dim,
        arg(src, part.cells * part.from.0),
        arg(dst, part.cells * part.to.0),
        part.from.0 as u32,
        part.from.1 as u32,
        part.to.0 as u32,
        part.to.1 as u32,
        part.width as u32,
        len as u32,
    );
}

/// One value of [`copy_channels`] per unit.
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn copy_channel_slice(
    src: &[f32],
    dst: &mut [f32],
    src_channels: u32,
    src_first: u32,
    dst_channels: u32,
    dst_first: u32,
    width: u32,
    len: u32,
) {
    let i = ABSOLUTE_POS as u32;
    if i < len {
        let cell = i / width;
        let j = i % width;
        dst[(cell * dst_channels + dst_first + j) as usize] =
            src[(cell * src_channels + src_first + j) as usize];
    }
}

/// [`crate::lift::resample`] on the device: `src` (h*w*C) to a new (out_h*out_w*C) buffer; `src`
/// itself when the sizes agree.
pub(super) fn resample_on_device(
    ctx: &GpuContext,
    src: &Handle,
    (h, w): (usize, usize),
    (out_h, out_w): (usize, usize),
    channels: usize,
    mode: Resample,
) -> Handle {
    if (h, w) == (out_h, out_w) {
        return src.clone();
    }
    let len = out_h * out_w * channels;
    let out = empty32(&ctx.client, len);
    if len == 0 {
        return out;
    }
    let (count, dim) = grid_of(len);
    resample_map::launch(
        &ctx.client,
        count,
        dim,
        arg(src, h * w * channels),
        arg(&out, len),
        h as u32,
        w as u32,
        out_h as u32,
        out_w as u32,
        channels as u32,
        // The axis scales in f32 from the host, as the CPU computes them (a device division may round
        // differently).
        h as f32 / out_h as f32,
        w as f32 / out_w as f32,
        u32::from(mode == Resample::Bilinear),
    );
    out
}

/// One output value of [`resample_on_device`] per unit (the CPU's `resample`, same arithmetic).
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn resample_map(
    src: &[f32],
    out: &mut [f32],
    h: u32,
    w: u32,
    out_h: u32,
    out_w: u32,
    channels: u32,
    scale_y: f32,
    scale_x: f32,
    bilinear: u32,
) {
    let i = ABSOLUTE_POS as u32;
    if i < out_h * out_w * channels {
        let ch = i % channels;
        let p = i / channels;
        let ox = p % out_w;
        let oy = p / out_w;
        if bilinear == 1 {
            let fy = f32::max((oy as f32 + 0.5) * scale_y - 0.5, 0.0);
            let y0 = u32::min(fy as u32, h - 1);
            let y1 = u32::min(y0 + 1, h - 1);
            let ty = fy - y0 as f32;
            let fx = f32::max((ox as f32 + 0.5) * scale_x - 0.5, 0.0);
            let x0 = u32::min(fx as u32, w - 1);
            let x1 = u32::min(x0 + 1, w - 1);
            let tx = fx - x0 as f32;
            let a = src[((y0 * w + x0) * channels + ch) as usize];
            let b = src[((y0 * w + x1) * channels + ch) as usize];
            let c = src[((y1 * w + x0) * channels + ch) as usize];
            let d = src[((y1 * w + x1) * channels + ch) as usize];
            let top = a * (1.0 - tx) + b * tx;
            let bot = c * (1.0 - tx) + d * tx;
            out[i as usize] = top * (1.0 - ty) + bot * ty;
        } else {
            // torch's nearest, floor(dst * in / out), in exact integer arithmetic as on the CPU.
            let y = u32::min(oy * h / out_h, h - 1);
            let x = u32::min(ox * w / out_w, w - 1);
            out[i as usize] = src[((y * w + x) * channels + ch) as usize];
        }
    }
}

/// In place: `sums[i] *= 1 / (counts[i / C] + 1e-7)`, the CPU's `LiftAccumulator::finish`.
#[cube(launch)]
fn lift_average(sums: &mut [f32], counts: &[u32], len: u32, channels: u32) {
    let i = ABSOLUTE_POS as u32;
    if i < len {
        let inv = 1.0f32 / (counts[(i / channels) as usize] as f32 + 1e-7f32);
        sums[i as usize] *= inv;
    }
}
