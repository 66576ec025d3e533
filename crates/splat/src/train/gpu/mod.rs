//! A fit step with everything on the device: render, L1 + D-SSIM, backward, the HGS anchor gradient,
//! Adam (with the trainable mask) and the densification statistics. The host [`TrainState`] is the
//! reference copy: structural changes (densification, opacity resets, SH degree changes) run there after
//! [`DeviceTrainer::download_into`], and the trainer is rebuilt from it afterwards.

mod anchor;
mod densify;
mod loss;
mod optim;
mod pair;
#[cfg(test)]
mod tests;

pub use anchor::GpuAnchor;
pub use densify::GpuDensifyStats;
#[cfg(test)]
pub use loss::l1_dssim;
pub use loss::{l1_dssim_images, l1_dssim_weighted, GpuLoss, L1DssimWeights};
pub use optim::GpuAdam;
pub use pair::DevicePair;

use crate::cameras::Camera;
use crate::render::gpu::{
    render_backward_device, render_device, render_kept, GpuFrozenGeometry, GpuOutputGrads, GpuScene,
};
use crate::render::RenderSettings;
use crate::train::optim::Adam;
use crate::train::TrainState;
use ::gpu::cubecl::server::Handle;
use ::gpu::prims::upload_u32;
use ::gpu::{F32Buffer, GpuContext, GpuError};

/// Scene parameters, Adam moments, densification statistics and, when the state has them, the
/// trainable mask and the anchors, on the device.
pub struct DeviceTrainer {
    scene: GpuScene,
    adam: GpuAdam,
    stats: GpuDensifyStats,
    /// One u32 flag per Gaussian (`TrainState::trainable`).
    trainable: Option<Handle>,
    anchor: Option<GpuAnchor>,
    /// Set by [`DeviceTrainer::freeze_geometry`]: the views' kept projections and tile lists.
    frozen: Option<GpuFrozenGeometry>,
}

impl DeviceTrainer {
    /// Uploads the host state: parameters, moments, statistics, and the trainable mask and anchors when
    /// it has them (the mask and anchors only change with the structure, when the trainer is rebuilt).
    pub fn upload(ctx: &GpuContext, state: &TrainState) -> Self {
        let trainable = state.trainable.as_ref().map(|mask| {
            let flags: Vec<u32> = mask.iter().map(|&t| u32::from(t)).collect();
            upload_u32(&ctx.client, &flags)
        });
        let anchor = state
            .anchor
            .as_ref()
            .map(|a| GpuAnchor::upload(ctx, a, state.trainable.as_deref()));
        Self {
            scene: GpuScene::upload(ctx, &state.scene),
            adam: GpuAdam::from_host(ctx, &state.adam),
            stats: GpuDensifyStats::from_host(ctx, &state.stats),
            trainable,
            anchor,
            frozen: None,
        }
    }

    /// From now on the caller keeps the geometry fixed and needs no gradients for it (ECM's appearance
    /// fits): steps whose means, scales and rotations rates are all 0 and that track no densification
    /// statistics render each view from its kept projection and tile lists (`gpu::frozen`) and skip
    /// the geometry's backward (its gradients are 0; Adam then only decays those moments). A step with
    /// a geometry rate above 0 runs the full pass and forgets the kept views.
    pub fn freeze_geometry(&mut self) {
        self.frozen.get_or_insert_with(GpuFrozenGeometry::default);
    }

    /// Device bytes the kept views hold (0 unless [`Self::freeze_geometry`] was called).
    #[cfg(test)]
    pub(crate) fn frozen_bytes(&self) -> usize {
        self.frozen.as_ref().map_or(0, GpuFrozenGeometry::bytes)
    }

    /// Writes the device state back into `state` (the mask and anchors never change on the device).
    pub fn download_into(&self, ctx: &GpuContext, state: &mut TrainState) -> Result<(), GpuError> {
        state.scene = self.scene.download(ctx)?;
        self.adam.download_into(ctx, &mut state.adam)?;
        state.stats = self.stats.download(ctx)?;
        Ok(())
    }

    /// One step on `target` (H*W*3 on the device) seen from `camera` (view 0) with the loss
    /// `(1 − ssim_weight)·L1 + ssim_weight·D-SSIM`; `adam` gives the rates and counts the step. Returns
    /// the loss value. (The benches' entry; the trainer steps with [`Self::step_weighted`].)
    #[cfg(feature = "stages")]
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
        self.step_weighted(
            ctx,
            adam,
            camera,
            0,
            target,
            settings,
            L1DssimWeights::blend(ssim_weight),
            track_stats,
            |_, grad| Ok::<_, GpuError>(grad),
        )?
        .value(ctx)
    }

    /// [`DeviceTrainer::step`] with the loss `weights.l1·L1 + weights.dssim·D-SSIM` (the editing fit's
    /// 10 : 2.5), on view `v` (the key of its kept projection after [`Self::freeze_geometry`]). The anchor gradient, when there are anchors, is added before Adam, as the editing fit
    /// does on the host. Returns the image loss (anchor term excluded) still on the device: reading its
    /// value copies two image-sized maps back, which a caller that does not need it skips.
    ///
    /// `term` adds a loss term the device evaluates elsewhere (a perceptual network on the same GPU): it
    /// gets the render (H*W*3) and the L1 + D-SSIM gradient w.r.t. it and returns the total gradient
    /// (the identity `|_, grad| Ok(grad)` adds nothing).
    pub fn step_weighted<E: From<GpuError>>(
        &mut self,
        ctx: &GpuContext,
        adam: &mut Adam,
        camera: &Camera,
        v: usize,
        target: &Handle,
        settings: &RenderSettings,
        weights: L1DssimWeights,
        track_stats: bool,
        term: impl FnOnce(&F32Buffer, F32Buffer) -> Result<F32Buffer, E>,
    ) -> Result<GpuLoss, E> {
        let geometry_fixed = adam.geometry_fixed();
        let kept = match self.frozen.as_mut() {
            Some(frozen) if !geometry_fixed => {
                frozen.clear();
                None
            }
            Some(frozen) if !track_stats => frozen.view(ctx, &self.scene, camera, v)?,
            _ => None,
        };
        let frame = match kept {
            Some(bins) => render_kept(ctx, &self.scene, bins, settings)?,
            None => render_device(ctx, &self.scene, camera, settings, None)?,
        };
        let (w, h) = (camera.width as usize, camera.height as usize);
        let loss = l1_dssim_weighted(ctx, &frame.rgb, target, w, h, 3, weights)?;
        let values = w * h * 3;
        let rgb = F32Buffer::new(frame.rgb.clone(), values).map_err(GpuError::BufferTooSmall)?;
        let grad = F32Buffer::new(loss.grad.clone(), values).map_err(GpuError::BufferTooSmall)?;
        let rgb_grad = term(&rgb, grad)?.into_handle();
        let grads = render_backward_device(
            ctx,
            &self.scene,
            settings,
            None,
            &frame,
            &GpuOutputGrads::rgb_only(&rgb_grad),
        )?;
        if let Some(anchor) = &self.anchor {
            anchor.add_grad(ctx, &self.scene, &grads)?;
        }
        self.adam
            .step_masked(ctx, adam, &self.scene, &grads, self.trainable.as_ref())?;
        if track_stats {
            self.stats.add(ctx, &frame, &grads, 1)?;
        }
        Ok(loss)
    }
}
