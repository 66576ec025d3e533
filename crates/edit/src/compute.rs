//! Where an edit's work runs: the CPU, or one GPU shared by the splatting engine and the networks (one
//! `--device` means one adapter). Every render, lift and fit of the editing code goes through [`Compute`],
//! so the CPU path stays the reference the GPU path is tested against.

use diffusion::device::{GpuDevice, Precision};
use splat::gpu::{GpuContext, GpuError, GpuLiftAccumulator, GpuScene, HostFrame};
use splat::lift::{LiftAccumulator, Lifted};
use splat::render::{render, ExtraChannels, RenderOutput, RenderSettings};
use splat::{Camera, GaussianScene, Image};

/// The device of a run: `None` is the CPU.
#[derive(Clone, Debug, Default)]
pub struct Compute {
    gpu: Option<GpuDevice>,
}

impl Compute {
    /// Everything on the CPU.
    pub fn cpu() -> Self {
        Self { gpu: None }
    }

    /// Everything on the GPU `context` opens (`None`: the CPU), the networks' matrix weights held in
    /// `precision` there.
    pub fn on(context: Option<GpuContext>, precision: Precision) -> Self {
        Self {
            gpu: context.map(|c| GpuDevice::with_precision(c, precision)),
        }
    }

    /// The networks' side of the device (`None`: the CPU).
    pub fn networks(&self) -> Option<&GpuDevice> {
        self.gpu.as_ref()
    }

    /// The splatting engine's side of the device (`None`: the CPU).
    pub fn splat(&self) -> Option<&GpuContext> {
        self.gpu.as_ref().map(GpuDevice::context)
    }

    /// "CPU" or the adapter and the weights' precision, for logs and run.json.
    pub fn describe(&self) -> String {
        match &self.gpu {
            Some(gpu) => format!("{}, {} weights", gpu.context().describe(), gpu.precision()),
            None => "CPU".into(),
        }
    }

    /// Renders `scene` from every camera (the scene is uploaded once on a GPU). `extra`: N*C values
    /// composited as extra channels.
    pub fn render_views(
        &self,
        scene: &GaussianScene,
        cameras: &[Camera],
        settings: &RenderSettings,
        extra: Option<ExtraChannels<'_>>,
    ) -> Result<Vec<HostFrame>, GpuError> {
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
        sink: &mut dyn FnMut(usize, HostFrame) -> Result<(), E>,
    ) -> Result<(), E> {
        let Some(ctx) = self.splat() else {
            for (v, c) in cameras.iter().enumerate() {
                sink(v, host_frame(render(scene, c, settings, extra)))?;
            }
            return Ok(());
        };
        let dev = GpuScene::upload(ctx, scene);
        let extra_dev =
            extra.map(|e| (::gpu::prims::upload_f32(&ctx.client, e.values), e.channels));
        for (v, cam) in cameras.iter().enumerate() {
            let frame = splat::gpu::render_device(
                ctx,
                &dev,
                cam,
                settings,
                extra_dev.as_ref().map(|(h, c)| (h, *c)),
            )?;
            sink(v, splat::gpu::download(ctx, &frame, scene.len())?)?;
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
            .map(HostFrame::rgb_image)
            .collect())
    }

    /// A lifting of per-view maps onto the Gaussians of `scene`, one view at a time.
    pub fn lifter<'s>(&self, scene: &'s GaussianScene, channels: usize) -> Lifter<'s> {
        match self.splat() {
            Some(ctx) => Lifter::Gpu(
                ctx.clone(),
                Box::new(GpuLiftAccumulator::new(ctx, scene, channels)),
            ),
            None => Lifter::Cpu(LiftAccumulator::new(scene, channels)),
        }
    }
}

/// A lifting under way on the CPU or the GPU (see [`Compute::lifter`]).
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

/// A CPU render in the type GPU renders are read back as (the saved backward state dropped).
pub fn host_frame(out: RenderOutput) -> HostFrame {
    HostFrame {
        width: out.width,
        height: out.height,
        rgb: out.rgb,
        alpha: out.alpha,
        depth: out.depth,
        extra: out.extra,
        channels: out.channels,
        radii: out.radii,
    }
}

/// A GPU error where a candle error is expected (the networks' and the sampler's error type).
pub fn candle_err(e: GpuError) -> candle_core::Error {
    candle_core::Error::Msg(e.to_string())
}
