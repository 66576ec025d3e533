//! A fit step with everything on the device: render, L1 + D-SSIM, backward, Adam and the densification
//! statistics. The host [`TrainState`] is the reference copy: structural changes (densification,
//! opacity resets, SH degree changes) run there after [`DeviceTrainer::download_into`], and the trainer
//! is rebuilt from it afterwards.

use super::{
    l1_dssim, render_backward_device, render_device, GpuAdam, GpuContext, GpuDensifyStats,
    GpuError, GpuOutputGrads, GpuScene,
};
use crate::optim::Adam;
use crate::render::RenderSettings;
use crate::train::TrainState;
use crate::Camera;
use ::gpu::cubecl::server::Handle;

/// Scene parameters, Adam moments and densification statistics on the device.
pub struct DeviceTrainer {
    scene: GpuScene,
    adam: GpuAdam,
    stats: GpuDensifyStats,
}

impl DeviceTrainer {
    /// Uploads the host state (no trainable mask or anchor support: `fit` uses neither).
    pub fn upload(ctx: &GpuContext, state: &TrainState) -> Self {
        Self {
            scene: GpuScene::upload(ctx, &state.scene),
            adam: GpuAdam::from_host(ctx, &state.adam),
            stats: GpuDensifyStats::from_host(ctx, &state.stats),
        }
    }

    /// Writes the device state back into `state`.
    pub fn download_into(&self, ctx: &GpuContext, state: &mut TrainState) -> Result<(), GpuError> {
        state.scene = self.scene.download(ctx)?;
        self.adam.download_into(ctx, &mut state.adam)?;
        state.stats = self.stats.download(ctx)?;
        Ok(())
    }

    /// One step on `target` (H*W*3 on the device) seen from `camera`; `adam` gives the rates and counts
    /// the step. Returns the loss value.
    #[allow(clippy::too_many_arguments)]
    pub fn step(
        &mut self,
        ctx: &GpuContext,
        adam: &mut Adam,
        camera: &Camera,
        target: &Handle,
        settings: &RenderSettings,
        ssim_weight: f32,
        track_stats: bool,
    ) -> Result<f32, GpuError> {
        let frame = render_device(ctx, &self.scene, camera, settings, None)?;
        let (w, h) = (camera.width as usize, camera.height as usize);
        let loss = l1_dssim(ctx, &frame.rgb, target, w, h, 3, ssim_weight)?;
        let grads = render_backward_device(
            ctx,
            &self.scene,
            settings,
            None,
            &frame,
            &GpuOutputGrads {
                rgb: &loss.grad,
                alpha: None,
                depth: None,
                extra: None,
            },
        )?;
        self.adam.step(ctx, adam, &self.scene, &grads)?;
        if track_stats {
            self.stats.add(ctx, &frame, &grads, 1)?;
        }
        loss.value(ctx)
    }
}
