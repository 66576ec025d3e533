//! Two appearance fits of copies of one state in one launch sequence (ECM's target and layout fits on a
//! GPU). Both copies start from the same scene and keep its geometry, so a view's kept projection and
//! tile lists are the same for both: one [`GpuFrozenGeometry`] serves the pair. Their parameters and
//! moments sit in one scene of 2n Gaussians (the first fit's `0..n`, the second's `n..2n`), so a paired
//! step — each fit's own view, its own target — is one launch per kernel: the colours of both halves,
//! the raster forward of two images, the loss of both, the raster and projection backward, Adam over
//! 2n. Each fit's result is that of its own [`DeviceTrainer`](super::DeviceTrainer) steps, up to the
//! order in which the backward's atomics add.

use super::optim::GpuAdam;
use super::{l1_dssim_images, L1DssimWeights};
use crate::cameras::Camera;
use crate::render::gpu::{
    project_and_bin, render_backward_device, render_kept_pair, Binned, GpuFrozenGeometry,
    GpuOutputGrads, GpuScene,
};
use crate::render::RenderSettings;
use crate::scene::GaussianScene;
use crate::train::optim::Adam;
use crate::train::TrainState;
use ::gpu::cubecl::server::Handle;
use ::gpu::gpu_call;
use ::gpu::prims::upload_u32;
use ::gpu::{GpuContext, GpuError};

/// Both fits' parameters, moments and trainable mask on the device, and the kept views they share.
pub struct DevicePair {
    /// 2n Gaussians: the first fit's, then the second's.
    scene: GpuScene,
    adam: GpuAdam,
    /// One u32 flag per Gaussian of the 2n (the state's mask, twice).
    trainable: Option<Handle>,
    kept: GpuFrozenGeometry,
}

/// `values` twice, one copy after the other.
fn twice(values: &[f32]) -> Vec<f32> {
    [values, values].concat()
}

impl DevicePair {
    /// Two copies of `state` (its scene, moments and trainable mask; no anchors) on the device.
    pub fn upload(ctx: &GpuContext, state: &TrainState) -> Self {
        let s = &state.scene;
        let scene = GaussianScene {
            sh_degree: s.sh_degree,
            means: twice(&s.means),
            log_scales: twice(&s.log_scales),
            quats: twice(&s.quats),
            opacity_logits: twice(&s.opacity_logits),
            sh: twice(&s.sh),
        };
        let mut adam = state.adam.clone();
        for moments in [
            &mut adam.means,
            &mut adam.log_scales,
            &mut adam.quats,
            &mut adam.opacity,
            &mut adam.sh,
        ] {
            moments.m = twice(&moments.m);
            moments.v = twice(&moments.v);
        }
        let trainable = state.trainable.as_ref().map(|mask| {
            let flags: Vec<u32> = mask.iter().chain(mask).map(|&t| u32::from(t)).collect();
            upload_u32(&ctx.client, &flags)
        });
        Self {
            scene: GpuScene::upload(ctx, &scene),
            adam: GpuAdam::from_host(ctx, &adam),
            trainable,
            kept: GpuFrozenGeometry::default(),
        }
    }

    /// The first fit's half as a scene of n Gaussians: the kept views are made from it (the second
    /// half's geometry is the same).
    fn first_half(&self) -> GpuScene {
        let s = &self.scene;
        GpuScene {
            len: s.len / 2,
            sh_degree: s.sh_degree,
            means: s.means.clone(),
            log_scales: s.log_scales.clone(),
            quats: s.quats.clone(),
            opacity_logits: s.opacity_logits.clone(),
            sh: s.sh.clone(),
        }
    }

    /// View `v` from `camera`: the kept one, or one made for this step where the budget refuses it.
    fn view(&mut self, ctx: &GpuContext, camera: &Camera, v: usize) -> Result<Binned, GpuError> {
        let half = self.first_half();
        match self.kept.view(ctx, &half, camera, v)? {
            Some(bins) => Ok(bins.clone()),
            None => gpu_call(|| project_and_bin(ctx, &half, camera, true)),
        }
    }

    /// One step of each fit: the first on view `views[0]` seen from `cameras[0]` against `targets[0]`
    /// (H*W*3 on the device), the second on its own; both views of one size. `adam` gives the rates
    /// (its geometry rates must be 0: the geometry is kept) and counts the step, for both fits, as
    /// [`super::DeviceTrainer::step_weighted`] with `weights` and no further term does for one.
    #[allow(clippy::too_many_arguments)]
    pub fn step(
        &mut self,
        ctx: &GpuContext,
        adam: &mut Adam,
        cameras: [&Camera; 2],
        views: [usize; 2],
        targets: [&Handle; 2],
        settings: &RenderSettings,
        weights: L1DssimWeights,
    ) -> Result<(), GpuError> {
        assert!(
            adam.geometry_fixed(),
            "a pair of fits keeps the geometry: its rates must be 0"
        );
        let a = self.view(ctx, cameras[0], views[0])?;
        let b = self.view(ctx, cameras[1], views[1])?;
        let frame = render_kept_pair(ctx, &self.scene, [&a, &b], settings)?;
        let (w, h) = (cameras[0].width as usize, cameras[0].height as usize);
        let loss = l1_dssim_images(ctx, &frame.rgb, &targets, w, h, 3, weights)?;
        let out_grads = GpuOutputGrads::rgb_only(&loss.grad);
        let grads = render_backward_device(ctx, &self.scene, settings, None, &frame, &out_grads)?;
        self.adam
            .step_masked(ctx, adam, &self.scene, &grads, self.trainable.as_ref())
    }

    /// The two fitted scenes.
    pub fn download(&self, ctx: &GpuContext) -> Result<[GaussianScene; 2], GpuError> {
        let both = self.scene.download(ctx)?;
        let n = self.scene.len / 2;
        let k = crate::scene::sh_coeffs(both.sh_degree);
        let half = |second: bool| {
            let part = |values: &[f32], per: usize| {
                let (first, rest) = values.split_at(per * n);
                if second { rest } else { first }.to_vec()
            };
            GaussianScene {
                sh_degree: both.sh_degree,
                means: part(&both.means, 3),
                log_scales: part(&both.log_scales, 3),
                quats: part(&both.quats, 4),
                opacity_logits: part(&both.opacity_logits, 1),
                sh: part(&both.sh, 3 * k),
            }
        };
        Ok([half(false), half(true)])
    }

    /// Device bytes the shared kept views hold.
    #[cfg(test)]
    pub(crate) fn kept_bytes(&self) -> usize {
        self.kept.bytes()
    }
}
