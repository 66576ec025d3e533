//! The splatting engine's device seam: where renders, their backward passes and liftings run is decided
//! here and nowhere else. [`SplatDevice`] is the CPU (the reference implementation in [`crate::render`] and
//! [`crate::lift`]) or a GPU (the CubeCL kernels in [`crate::render::gpu`] and [`crate::lift::gpu`], tested against the CPU on lavapipe);
//! both produce the same [`Frame`]s, [`SceneGrads`] and [`Lifted`] values.
//!
//! Adding a backend: a variant here, and one arm in each method below (render, render with loss and
//! backward, lifting); callers are unchanged.

use crate::lift::gpu::{GpuLiftAccumulator, GpuLiftScene};
use crate::lift::{read_by_resampling, resample, ChannelSlice, LiftAccumulator, Lifted, MapGrid};
use crate::render::gpu::GpuScene;
use crate::render::{
    render, render_backward, render_backward_appearance, render_extra_at, ExtraChannels, Frame,
    FrozenGeometry, OutputGrads, RenderOutput, RenderSettings, SceneGrads,
};
use ::gpu::prims::read_f32;
use ::gpu::{gpu_call, F32Buffer, F32Values, GpuContext, GpuError};
use rayon::prelude::*;

use crate::cameras::Camera;
use crate::image::Image;
use crate::scene::GaussianScene;

/// Where the splatting engine runs.
// One value per run, passed by reference: the GPU variant's size does not matter.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Debug, Default)]
pub enum SplatDevice {
    #[default]
    Cpu,
    Gpu(GpuContext),
}

impl From<Option<GpuContext>> for SplatDevice {
    fn from(ctx: Option<GpuContext>) -> Self {
        ctx.map_or(SplatDevice::Cpu, SplatDevice::Gpu)
    }
}

impl SplatDevice {
    /// The GPU, for the device-resident trainer and callers that time or synchronise it (`None`: the CPU).
    pub fn gpu(&self) -> Option<&GpuContext> {
        match self {
            SplatDevice::Cpu => None,
            SplatDevice::Gpu(ctx) => Some(ctx),
        }
    }

    pub fn is_cpu(&self) -> bool {
        matches!(self, SplatDevice::Cpu)
    }

    /// Memory one appearance fit's kept views take ([`crate::train::Trainer::freeze_geometry`]): host
    /// memory on the CPU, device memory on a GPU, for `views` views of `width`×`height` pixels and
    /// `gaussians` Gaussians, within the per-fit budget. A GPU view's tile lists are only known once
    /// binned: 4 pairs per Gaussian assumed.
    pub fn kept_views_bytes(&self, gaussians: usize, views: usize, width: u32, height: u32) -> u64 {
        let per_view = match self {
            SplatDevice::Cpu => crate::render::FrozenView::memory_bytes_for(gaussians),
            SplatDevice::Gpu(_) => crate::render::gpu::GpuFrozenGeometry::view_bytes(
                gaussians,
                4 * gaussians,
                width,
                height,
            ),
        };
        views
            .saturating_mul(per_view)
            .min(FrozenGeometry::DEFAULT_BUDGET) as u64
    }

    /// Renders `scene` from `camera`. `extra`: N*C values composited as extra channels.
    pub fn render(
        &self,
        scene: &GaussianScene,
        camera: &Camera,
        settings: &RenderSettings,
        extra: Option<ExtraChannels<'_>>,
    ) -> Result<Frame, GpuError> {
        match self {
            SplatDevice::Cpu => Ok(render(scene, camera, settings, extra).into_frame()),
            SplatDevice::Gpu(ctx) => {
                crate::render::gpu::render(ctx, scene, camera, settings, extra)
            }
        }
    }

    /// Renders `scene` from every camera (the scene is uploaded once on a GPU; on the CPU the views render
    /// in parallel, beside the renderer's own parallelism, which rayon balances).
    pub fn render_views(
        &self,
        scene: &GaussianScene,
        cameras: &[Camera],
        settings: &RenderSettings,
        extra: Option<ExtraChannels<'_>>,
    ) -> Result<Vec<Frame>, GpuError> {
        if self.is_cpu() {
            return Ok(cameras
                .par_iter()
                .map(|c| render(scene, c, settings, extra).into_frame())
                .collect());
        }
        let mut frames = Vec::with_capacity(cameras.len());
        self.for_each_render(scene, cameras, settings, extra, &mut |_, f| {
            frames.push(f);
            Ok(())
        })?;
        Ok(frames)
    }

    /// [`Self::render_views`] one view at a time: `sink(v, frame)` gets each render as it is made, so only
    /// one frame is held (CCM's maps have a channel per token).
    pub fn for_each_render<E: From<GpuError>>(
        &self,
        scene: &GaussianScene,
        cameras: &[Camera],
        settings: &RenderSettings,
        extra: Option<ExtraChannels<'_>>,
        sink: &mut dyn FnMut(usize, Frame) -> Result<(), E>,
    ) -> Result<(), E> {
        match self {
            SplatDevice::Cpu => {
                for (v, c) in cameras.iter().enumerate() {
                    sink(v, render(scene, c, settings, extra).into_frame())?;
                }
            }
            SplatDevice::Gpu(ctx) => {
                let dev = GpuScene::upload(ctx, scene);
                let extra_dev =
                    extra.map(|e| (::gpu::prims::upload_f32(&ctx.client, e.values), e.channels));
                for (v, cam) in cameras.iter().enumerate() {
                    let frame = crate::render::gpu::render_device(
                        ctx,
                        &dev,
                        cam,
                        settings,
                        extra_dev.as_ref().map(|(h, c)| (h, *c)),
                    )?;
                    sink(v, crate::render::gpu::download(ctx, &frame, scene.len())?)?;
                }
            }
        }
        Ok(())
    }

    /// The RGB renders of `scene` from every camera over `background`.
    pub fn render_images(
        &self,
        scene: &GaussianScene,
        cameras: &[Camera],
        background: [f32; 3],
    ) -> Result<Vec<Image>, GpuError> {
        let settings = RenderSettings { background };
        Ok(self
            .render_views(scene, cameras, &settings, None)?
            .iter()
            .map(Frame::rgb_image)
            .collect())
    }

    /// Renders the colour of `scene` from `camera`, evaluates `loss` on it (`rgb` → value and ∂value/∂rgb,
    /// on the host) and back-propagates into scene gradients. Returns the radii, the loss value and the
    /// gradients.
    pub fn render_with_loss<L>(
        &self,
        scene: &GaussianScene,
        camera: &Camera,
        settings: &RenderSettings,
        loss: impl FnOnce(&[f32]) -> (L, Vec<f32>),
    ) -> Result<(Vec<u32>, L, SceneGrads), GpuError> {
        match self {
            SplatDevice::Cpu => {
                let out = render(scene, camera, settings, None);
                Ok(loss_and_backward(scene, camera, settings, out, loss, true))
            }
            SplatDevice::Gpu(ctx) => {
                crate::render::gpu::render_with_loss(ctx, scene, camera, settings, loss)
            }
        }
    }

    /// [`Self::render_with_loss`] of view `v` for fits that keep the geometry (means, scales and
    /// rotations fixed, their gradients not needed). On the CPU the view's projection is kept in `frozen`
    /// across steps and the gradients of the geometry are zero (that part of the backward pass is
    /// skipped); on a GPU, where those passes cost little, it is the ordinary render.
    pub fn render_with_loss_frozen<L>(
        &self,
        scene: &GaussianScene,
        camera: &Camera,
        v: usize,
        frozen: &mut FrozenGeometry,
        settings: &RenderSettings,
        loss: impl FnOnce(&[f32]) -> (L, Vec<f32>),
    ) -> Result<(Vec<u32>, L, SceneGrads), GpuError> {
        match self {
            SplatDevice::Cpu => {
                let out = match frozen.view(scene, camera, v) {
                    Some(view) => view.render(scene, settings),
                    None => render(scene, camera, settings, None),
                };
                Ok(loss_and_backward(scene, camera, settings, out, loss, false))
            }
            SplatDevice::Gpu(_) => self.render_with_loss(scene, camera, settings, loss),
        }
    }

    /// 2D → 3D → 2D, the operation CCM and blend-map consistency rest on: `map_of(v)` gives view v's map
    /// on `grid` (row-major, channels interleaved); every map is resampled to its camera's resolution
    /// (`grid.up`) and lifted onto the Gaussians over all views ([`crate::lift`]); the lifted values are
    /// rendered back from every camera as extra channels (alpha-composited over 0), resampled to the grid
    /// (`grid.down`) and handed to `sink(v, map)`. On a GPU only the grid-sized maps cross the bus, and
    /// none with [`LiftSession::lift_values_and_render_back`] (maps already on the device, results kept
    /// there). One round of a [`LiftSession`]: callers with several rounds over the same scene and
    /// cameras keep one.
    ///
    /// # Panics
    /// When a map is not `grid.len()` long (a programming error).
    pub fn lift_and_render_back<E: From<GpuError>>(
        &self,
        scene: &GaussianScene,
        cameras: &[Camera],
        grid: &MapGrid,
        map_of: &mut dyn FnMut(usize) -> Result<Vec<f32>, E>,
        sink: &mut dyn FnMut(usize, Vec<f32>) -> Result<(), E>,
    ) -> Result<(), E> {
        self.lift_session(scene, cameras)
            .lift_and_render_back(grid, map_of, sink)
    }

    /// Lifting rounds over `scene` seen from `cameras` (CCM's layers and the blend maps' steps of one
    /// sampler run): on a GPU the scene is uploaded once and each view's projection and tile lists are
    /// made once for all rounds (at first use).
    pub fn lift_session<'s>(
        &self,
        scene: &'s GaussianScene,
        cameras: &'s [Camera],
    ) -> LiftSession<'s> {
        LiftSession {
            device: self.clone(),
            scene,
            cameras,
            gpu: None,
            pass_channels: None,
        }
    }

    /// A lifting of per-view maps onto the Gaussians of `scene`, one view at a time.
    pub fn lifter<'s>(&self, scene: &'s GaussianScene, channels: usize) -> Lifter<'s> {
        match self {
            SplatDevice::Cpu => Lifter::Cpu(LiftAccumulator::new(scene, channels)),
            SplatDevice::Gpu(ctx) => Lifter::Gpu(
                ctx.clone(),
                Box::new(GpuLiftAccumulator::new(ctx, scene, channels)),
            ),
        }
    }
}

/// Lifting rounds over one scene and one set of cameras ([`SplatDevice::lift_session`]).
pub struct LiftSession<'s> {
    device: SplatDevice,
    scene: &'s GaussianScene,
    cameras: &'s [Camera],
    /// The uploaded scene and the kept views, made at the first round on a GPU.
    gpu: Option<Box<GpuLiftScene>>,
    /// Channels per pass when set (tests), instead of what the device's bounds allow.
    pass_channels: Option<usize>,
}

/// A view's map on the grid, from its index: on the host, or in a buffer of the session's GPU.
type MapOf<'a, E> = dyn FnMut(usize) -> Result<F32Values, E> + 'a;
/// Where a view's rendered-back map goes: on the host on the CPU, in a device buffer on a GPU.
type MapSink<'a, E> = dyn FnMut(usize, F32Values) -> Result<(), E> + 'a;
/// One pass of a round: a grid's channels lifted and rendered back.
type Pass<'a, E> =
    dyn FnMut(&MapGrid, &mut MapOf<'_, E>, &mut MapSink<'_, E>) -> Result<(), E> + 'a;

impl LiftSession<'_> {
    /// One round of [`SplatDevice::lift_and_render_back`] over the session's scene and cameras, the maps
    /// on the host both ways. A round of more channels than the device's bounds allow in one pass (CCM
    /// stacks all layers of one map size) runs in passes over slices of its channels, with the same
    /// result.
    ///
    /// # Panics
    /// When a map is not `grid.len()` long (a programming error).
    pub fn lift_and_render_back<E: From<GpuError>>(
        &mut self,
        grid: &MapGrid,
        map_of: &mut dyn FnMut(usize) -> Result<Vec<f32>, E>,
        sink: &mut dyn FnMut(usize, Vec<f32>) -> Result<(), E>,
    ) -> Result<(), E> {
        let device = self.device.clone();
        self.lift_values_and_render_back(
            grid,
            &mut |v| Ok(F32Values::Host(map_of(v)?)),
            &mut |v, back| sink(v, device.values_on_host(back)?),
        )
    }

    /// [`Self::lift_and_render_back`] with each map where it is: on a GPU a map in a device buffer (the
    /// networks' attention maps on the same GPU) is lifted from there and the maps rendered back stay
    /// on the device ([`F32Values::Device`]), so a round reads nothing back; on the CPU every map is on
    /// the host ([`F32Values::Host`]; a device buffer there is an error).
    ///
    /// # Panics
    /// When a map is not `grid.len()` long (a programming error).
    pub fn lift_values_and_render_back<E: From<GpuError>>(
        &mut self,
        grid: &MapGrid,
        map_of: &mut MapOf<'_, E>,
        sink: &mut MapSink<'_, E>,
    ) -> Result<(), E> {
        let (scene, cameras) = (self.scene, self.cameras);
        if cameras.is_empty() || grid.is_empty() {
            return Ok(());
        }
        let chunk = self
            .pass_channels
            .unwrap_or_else(|| self.channels_per_pass(grid.channels));
        let device = &self.device;
        let kept = &mut self.gpu;
        in_passes(
            device,
            grid,
            chunk,
            cameras.len(),
            map_of,
            sink,
            &mut |grid, map_of, sink| match device {
                SplatDevice::Cpu => cpu_round(scene, cameras, grid, map_of, sink),
                SplatDevice::Gpu(ctx) => {
                    let lift = match kept {
                        Some(lift) => lift,
                        None => kept.insert(Box::new(::gpu::gpu_call(|| {
                            Ok(GpuLiftScene::new(ctx, scene))
                        })?)),
                    };
                    lift.lift_and_render_back(ctx, cameras, grid, map_of, sink)
                }
            },
        )
    }

    /// Channels one pass takes (at least one): on the CPU within [`CPU_LIFT_PASS_BYTES`]; on a GPU with
    /// each of its per-channel buffers (the sums over the Gaussians, a view's map or frame at full
    /// resolution) within the device's largest buffer.
    fn channels_per_pass(&self, channels: usize) -> usize {
        let pixels = self
            .cameras
            .iter()
            .map(|c| c.width as u64 * c.height as u64)
            .max()
            .unwrap_or(0);
        let gaussians = self.scene.len();
        let fit = |budget: u64, per_channel: u64| {
            ((budget / per_channel.max(1)) as usize).clamp(1, channels.max(1))
        };
        match &self.device {
            SplatDevice::Cpu => fit(
                CPU_LIFT_PASS_BYTES,
                cpu_lift_channel_bytes(gaussians, pixels),
            ),
            SplatDevice::Gpu(ctx) => fit(
                ctx.limits.max_buffer_bytes,
                4 * (gaussians as u64).max(pixels),
            ),
        }
    }

    /// Runs later rounds in passes of `channels` channels, whatever the bounds allow.
    #[cfg(test)]
    fn with_pass_channels(mut self, channels: usize) -> Self {
        self.pass_channels = Some(channels);
        self
    }
}

/// A round in passes of at most `chunk` channels: one pass when they all fit, else passes over slices
/// of the channels (each channel's result does not depend on the others'), the grid-sized maps held
/// meanwhile where they are (a device's maps sliced on the device).
fn in_passes<E: From<GpuError>>(
    device: &SplatDevice,
    grid: &MapGrid,
    chunk: usize,
    views: usize,
    map_of: &mut MapOf<'_, E>,
    sink: &mut MapSink<'_, E>,
    round: &mut Pass<'_, E>,
) -> Result<(), E> {
    if chunk >= grid.channels {
        return round(grid, map_of, sink);
    }
    let chunk = chunk.max(1);
    let maps = (0..views)
        .map(&mut *map_of)
        .collect::<Result<Vec<_>, E>>()?;
    let mut backs = (0..views)
        .map(|_| device.zeroed_values(grid.len()))
        .collect::<Result<Vec<_>, GpuError>>()?;
    let (channels, cells) = (grid.channels, grid.height * grid.width);
    for first in (0..channels).step_by(chunk) {
        let width = chunk.min(channels - first);
        let part = ChannelSlice {
            cells,
            width,
            from: (channels, first),
            to: (width, 0),
        };
        round(
            &MapGrid {
                channels: width,
                ..*grid
            },
            &mut |v| Ok(device.slice_channels(&maps[v], part)?),
            &mut |v, back| {
                let place = ChannelSlice {
                    from: (width, 0),
                    to: (channels, first),
                    ..part
                };
                Ok(device.copy_channels(&back, &mut backs[v], place)?)
            },
        )?;
    }
    for (v, back) in backs.into_iter().enumerate() {
        sink(v, back)?;
    }
    Ok(())
}

impl SplatDevice {
    /// `len` zeros where this device keeps maps: on the host on the CPU, in a device buffer on a GPU.
    fn zeroed_values(&self, len: usize) -> Result<F32Values, GpuError> {
        match self {
            SplatDevice::Cpu => Ok(F32Values::Host(vec![0.0; len])),
            SplatDevice::Gpu(ctx) => gpu_call(|| {
                let zeros = ::gpu::prims::zeros32(&ctx.client, len);
                F32Buffer::new(zeros, len)
                    .map(F32Values::Device)
                    .map_err(GpuError::BufferTooSmall)
            }),
        }
    }

    /// The slice `part` of `src` as a map of its own, where `src` is.
    fn slice_channels(&self, src: &F32Values, part: ChannelSlice) -> Result<F32Values, GpuError> {
        let len = part.cells * part.to.0;
        let mut out = match (src, self) {
            (F32Values::Host(_), _) => F32Values::Host(vec![0.0; len]),
            (F32Values::Device(_), device) => device.zeroed_values(len)?,
        };
        self.copy_channels(src, &mut out, part)?;
        Ok(out)
    }

    /// Copies the slice `part` of `src` into `dst`, on the device when both are there (a host `src`
    /// is uploaded to reach a device `dst`, a device `src` read back to reach a host one).
    fn copy_channels(
        &self,
        src: &F32Values,
        dst: &mut F32Values,
        part: ChannelSlice,
    ) -> Result<(), GpuError> {
        match (src, &mut *dst, self) {
            (F32Values::Host(src), F32Values::Host(dst), _) => {
                let ChannelSlice {
                    width, from, to, ..
                } = part;
                for (s, d) in src.chunks(from.0).zip(dst.chunks_mut(to.0)) {
                    d[to.1..to.1 + width].copy_from_slice(&s[from.1..from.1 + width]);
                }
                Ok(())
            }
            (F32Values::Device(src), F32Values::Device(dst), SplatDevice::Gpu(ctx)) => {
                gpu_call(|| {
                    crate::lift::gpu::copy_channels(ctx, src.handle(), dst.handle(), part);
                    Ok(())
                })
            }
            (F32Values::Host(host), F32Values::Device(_), SplatDevice::Gpu(ctx)) => {
                let uploaded = gpu_call(|| {
                    F32Buffer::new(::gpu::prims::upload_f32(&ctx.client, host), host.len())
                        .map_err(GpuError::BufferTooSmall)
                })?;
                self.copy_channels(&F32Values::Device(uploaded), dst, part)
            }
            (F32Values::Device(_), F32Values::Host(_), _) => {
                let host = F32Values::Host(self.values_on_host(src.clone())?);
                self.copy_channels(&host, dst, part)
            }
            (_, _, SplatDevice::Cpu) => Err(GpuError::BufferOnCpu("lifting")),
        }
    }

    /// `values` on the host: read back from this device's GPU when they are in a device buffer.
    pub fn values_on_host(&self, values: F32Values) -> Result<Vec<f32>, GpuError> {
        match (values, self) {
            (F32Values::Host(values), _) => Ok(values),
            (F32Values::Device(buffer), SplatDevice::Gpu(ctx)) => {
                read_f32(&ctx.client, buffer.handle(), buffer.len())
            }
            (F32Values::Device(_), SplatDevice::Cpu) => Err(GpuError::BufferOnCpu("lifting")),
        }
    }
}

/// Host memory one CPU lifting pass may hold for its per-channel buffers: the per-slot sums over the
/// Gaussians ([`LiftAccumulator`]) and one view's render-back at full resolution. A round of more
/// channels (CCM stacks all layers of one map size) is done in passes over slices of its channels.
pub const CPU_LIFT_PASS_BYTES: u64 = 1 << 30;

/// Host memory a lifting round of `channels` channels holds on the CPU over `gaussians` Gaussians and
/// views of at most `pixels` pixels (a GPU holds only the grid-sized maps on the host: 0 here).
pub fn cpu_lift_round_bytes(gaussians: usize, pixels: u64, channels: usize) -> u64 {
    let per_channel = cpu_lift_channel_bytes(gaussians, pixels);
    (per_channel * channels as u64).min(CPU_LIFT_PASS_BYTES.max(per_channel))
}

fn cpu_lift_channel_bytes(gaussians: usize, pixels: u64) -> u64 {
    4 * (LiftAccumulator::slot_count() as u64 * gaussians as u64 + pixels)
}

/// One lifting round on the CPU, all of `grid`'s channels in one pass.
fn cpu_round<E: From<GpuError>>(
    scene: &GaussianScene,
    cameras: &[Camera],
    grid: &MapGrid,
    map_of: &mut MapOf<'_, E>,
    sink: &mut MapSink<'_, E>,
) -> Result<(), E> {
    let native = (grid.height, grid.width);
    let size = |cam: &Camera| (cam.height as usize, cam.width as usize);
    let mut acc = LiftAccumulator::new(scene, grid.channels);
    for (v, cam) in cameras.iter().enumerate() {
        let map = SplatDevice::Cpu.values_on_host(map_of(v)?)?;
        acc.add_view_on_grid(cam, &map, grid);
    }
    let lifted = acc.finish();
    let extra = ExtraChannels {
        values: &lifted.values,
        channels: grid.channels,
    };
    for (v, cam) in cameras.iter().enumerate() {
        // Only the pixels the resampling to the grid reads composite the lifted channels.
        let (h, w) = size(cam);
        let rows = read_by_resampling(h, grid.height, grid.down);
        let cols = read_by_resampling(w, grid.width, grid.down);
        let settings = RenderSettings::default();
        let out = render_extra_at(scene, cam, &settings, extra, (&rows, &cols));
        sink(
            v,
            F32Values::Host(resample(
                &out.extra,
                size(cam),
                native,
                grid.channels,
                grid.down,
            )),
        )?;
    }
    Ok(())
}

/// The CPU side of [`SplatDevice::render_with_loss`]: the loss of a render and its backward pass (of the
/// appearance only without `geometry`).
fn loss_and_backward<L>(
    scene: &GaussianScene,
    camera: &Camera,
    settings: &RenderSettings,
    out: RenderOutput,
    loss: impl FnOnce(&[f32]) -> (L, Vec<f32>),
    geometry: bool,
) -> (Vec<u32>, L, SceneGrads) {
    let (value, grad) = loss(&out.rgb);
    let grads = OutputGrads {
        rgb: &grad,
        alpha: None,
        depth: None,
        extra: None,
    };
    let grads = if geometry {
        render_backward(scene, camera, settings, None, &out, &grads)
    } else {
        render_backward_appearance(scene, camera, settings, &out, &grads)
    };
    (out.into_frame().radii, value, grads)
}

/// A lifting under way on the CPU or the GPU (see [`SplatDevice::lifter`]).
pub enum Lifter<'s> {
    Cpu(LiftAccumulator<'s>),
    Gpu(GpuContext, Box<GpuLiftAccumulator>),
}

impl Lifter<'_> {
    /// Adds one view's H*W*C map.
    pub fn add_view(&mut self, cam: &Camera, map: &[f32]) -> Result<(), GpuError> {
        match self {
            Lifter::Cpu(acc) => {
                acc.add_view(cam, map);
                Ok(())
            }
            Lifter::Gpu(ctx, acc) => acc.add_view(ctx, cam, map),
        }
    }

    /// The per-Gaussian averages and hit counts.
    pub fn finish(self) -> Result<Lifted, GpuError> {
        match self {
            Lifter::Cpu(acc) => Ok(acc.finish()),
            Lifter::Gpu(ctx, acc) => (*acc).finish(&ctx),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lift::{MapGrid, Resample};
    use crate::render::gpu::tests::{camera, random_scene, three_views};
    use ::gpu::testing::context_or_skip;

    /// One round of stacked channels gives each part what its own round gives: CCM lifts the layers of
    /// one map size together on the strength of it. Bit for bit on the CPU; on a GPU to float rounding
    /// (its kernels' layouts follow the channel count).
    #[test]
    fn a_round_of_stacked_channels_is_its_parts_rounds() {
        let scene = random_scene(300, 2, 5);
        let cams = three_views();
        let grid = |channels| MapGrid {
            height: 9,
            width: 10,
            channels,
            up: Resample::Bilinear,
            down: Resample::Bilinear,
        };
        // Two parts of 3 and 4 channels per cell; the stacked map is each cell's 3 then its 4.
        let part = |v: usize, channels: usize, salt: usize| -> Vec<f32> {
            (0..grid(channels).len())
                .map(|i| ((i * 7 + v * 5 + salt) % 17) as f32 / 16.0)
                .collect()
        };
        let stacked = |v: usize| -> Vec<f32> {
            let (a, b) = (part(v, 3, 1), part(v, 4, 2));
            a.chunks(3)
                .zip(b.chunks(4))
                .flat_map(|(x, y)| x.iter().chain(y).copied())
                .collect()
        };
        let round =
            |session: &mut LiftSession<'_>, channels, map_of: &dyn Fn(usize) -> Vec<f32>| {
                let mut back = vec![Vec::new(); cams.len()];
                session
                    .lift_and_render_back::<GpuError>(
                        &grid(channels),
                        &mut |v| Ok(map_of(v)),
                        &mut |v, m| {
                            back[v] = m;
                            Ok(())
                        },
                    )
                    .unwrap();
                back
            };
        let mut devices = vec![SplatDevice::Cpu];
        devices.extend(context_or_skip().map(SplatDevice::Gpu));
        for device in devices {
            let mut session = device.lift_session(&scene, &cams);
            let whole = round(&mut session, 7, &stacked);
            let a = round(&mut session, 3, &|v| part(v, 3, 1));
            let b = round(&mut session, 4, &|v| part(v, 4, 2));
            // Passes over slices of the channels (the devices' memory bounds): the same again.
            let mut in_passes = device.lift_session(&scene, &cams).with_pass_channels(2);
            let in_passes_of_two = round(&mut in_passes, 7, &stacked);
            // The maps given in device buffers (CCM's maps on a GPU): lifted where they are, the
            // passes' slices cut on the device, the same values back.
            if let SplatDevice::Gpu(ctx) = &device {
                let upload = |map: Vec<f32>| {
                    let len = map.len();
                    F32Buffer::new(::gpu::prims::upload_f32(&ctx.client, &map), len).unwrap()
                };
                for (session, host) in [(&mut session, &whole), (&mut in_passes, &in_passes_of_two)]
                {
                    let mut back = vec![Vec::new(); cams.len()];
                    session
                        .lift_values_and_render_back::<GpuError>(
                            &grid(7),
                            &mut |v| Ok(F32Values::Device(upload(stacked(v)))),
                            &mut |v, m| {
                                assert!(m.is_on_device(), "rendered back on the device");
                                back[v] = device.values_on_host(m)?;
                                Ok(())
                            },
                        )
                        .unwrap();
                    // Equal to float rounding: the sums over the Gaussians are atomic adds, in
                    // no fixed order.
                    let worst = back
                        .iter()
                        .flatten()
                        .zip(host.iter().flatten())
                        .map(|(x, y)| (x - y).abs())
                        .fold(0.0f32, f32::max);
                    assert!(worst < 1e-5, "device maps off by {worst}");
                }
            }
            for v in 0..cams.len() {
                let split: Vec<f32> = a[v]
                    .chunks(3)
                    .zip(b[v].chunks(4))
                    .flat_map(|(x, y)| x.iter().chain(y).copied())
                    .collect();
                assert!(split.iter().any(|&x| x > 0.05), "view {v} sees the maps");
                if device.is_cpu() {
                    assert_eq!(whole[v], split, "view {v}");
                    assert_eq!(in_passes_of_two[v], split, "view {v}, passes of 2 channels");
                } else {
                    for (got, what) in [(&whole[v], "stacked"), (&in_passes_of_two[v], "in passes")]
                    {
                        let worst = got
                            .iter()
                            .zip(&split)
                            .map(|(x, y)| (x - y).abs())
                            .fold(0.0f32, f32::max);
                        assert!(worst < 1e-5, "view {v}, {what}: off by {worst}");
                    }
                }
            }
        }
    }

    /// The same frame, loss and gradients from either backend (the GPU one only where a device exists).
    #[test]
    fn both_backends_agree_on_render_and_gradients() {
        let scene = random_scene(40, 1, 3);
        let cam = camera(48, 32);
        let settings = RenderSettings::default();
        let loss = |rgb: &[f32]| (rgb.iter().sum::<f32>(), vec![1.0; rgb.len()]);
        let cpu = SplatDevice::Cpu;
        let frame = cpu.render(&scene, &cam, &settings, None).unwrap();
        let (radii, value, grads) = cpu.render_with_loss(&scene, &cam, &settings, loss).unwrap();
        assert_eq!(radii, frame.radii);
        assert!((value - frame.rgb.iter().sum::<f32>()).abs() < 1e-3);
        assert!(grads.means.iter().any(|g| g.abs() > 0.0));
        let Some(ctx) = context_or_skip() else {
            return;
        };
        let gpu = SplatDevice::Gpu(ctx);
        let gpu_frame = gpu.render(&scene, &cam, &settings, None).unwrap();
        let err = frame
            .rgb
            .iter()
            .zip(&gpu_frame.rgb)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        assert!(err < 1e-4, "CPU and GPU renders differ by {err}");
        let (gpu_radii, gpu_value, _) =
            gpu.render_with_loss(&scene, &cam, &settings, loss).unwrap();
        assert_eq!(gpu_radii, radii);
        assert!((gpu_value - value).abs() < 1e-2 * value.abs().max(1.0));
    }
}
