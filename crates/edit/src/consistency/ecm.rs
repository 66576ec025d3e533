//! ECM, the editing consistency module (docs/algorithm.md §1.3).
//!
//! At its steps (by default 4, 9 and 14), right after the UNet pass, the target and layout predictions of all
//! views are decoded, two copies of the scene (VcEdit's "mini-GS") are fitted to them, rendered from every
//! view, encoded, and replace the predictions. The copies start from the editing state (optimiser moments
//! and current rates included) and run a few epochs over the views with the rates halved every few epochs,
//! without densification or anchors.

use candle_core::Tensor;
use rand::seq::SliceRandom;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use splat::train::optim::Group;
use splat::train::TrainState;
use splat::train::{PairTrainer, StepKind};
use splat::SplatDevice;
use splat::{Camera, GaussianScene, Image};

use super::{MultiView, MultiViewError};
use crate::compute::candle_err;
use crate::fit::{check_targets, EditTrainer, ImageLoss, Targets};
use crate::ledger::StageWork;
use crate::sampler::{image_to_tensor, NoiseSource, ViewState};

/// Everything ECM is configured with: when it runs and how its fits go.
#[derive(Clone, Debug, Serialize)]
pub struct EcmSettings {
    /// Sampler steps (0-based) after whose UNet pass ECM runs.
    pub steps: Vec<usize>,
    /// Which Gaussians the fits may move.
    pub scope: EcmScope,
    /// Which attributes the fits may change.
    pub params: EcmParams,
    /// Epochs over the views, and the epochs after which the rates halve.
    pub epochs: usize,
    pub halve_every: usize,
    /// Fewest Adam steps per fit. The reference's 6 epochs assume its 96 views (576 steps); with fewer
    /// views the same epochs are too few steps for the copy to take on the predicted colours at these
    /// rates (16 views: 96 steps move a colour by at most ~0.2), and ECM then pulls every prediction
    /// back to the source. So epochs grow to reach this many steps, with the halvings stretched alike.
    pub min_steps: usize,
}

impl EcmSettings {
    /// The reference's ECM for a `steps`-step schedule: after steps where (i+1) % 5 == 0 (rescaled for
    /// fewer than 5 steps, [`super::module_steps`]), 6 epochs with the rates halved every 2, stretched to
    /// at least 576 steps; our safer defaults for what the fits change (editable Gaussians only,
    /// appearance only).
    pub fn reference(steps: usize) -> Self {
        Self {
            steps: super::module_steps(steps, super::ECM_PERIOD),
            scope: EcmScope::Masked,
            params: EcmParams::Appearance,
            epochs: 6,
            halve_every: 2,
            min_steps: 6 * 96,
        }
    }

    /// The fits' (epochs, epochs between rate halvings) for `views` views: the configured epochs, or more
    /// to reach [`Self::min_steps`], the halvings scaled by the same factor.
    pub fn schedule(&self, views: usize) -> (usize, usize) {
        let base = self.epochs.max(1);
        let epochs = base.max(self.min_steps.div_ceil(views.max(1)));
        let halve_every = (self.halve_every.max(1) * epochs).div_ceil(base).max(1);
        (epochs, halve_every)
    }
}

/// Which Gaussians ECM's fits may move.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum EcmScope {
    /// Only the editable (masked) Gaussians: the paper's intent, and the safer reading (default).
    #[value(help = "ECM fits move only the editable Gaussians")]
    Masked,
    /// Every Gaussian: what the reference most likely does (its gradient hooks are lost in the deep copy).
    #[value(help = "ECM fits move every Gaussian (what the reference code most likely does)")]
    All,
}

/// Which attributes ECM's fits may change.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum EcmParams {
    /// Colours (all SH coefficients) and opacities; positions, scales and rotations stay (default). ECM is
    /// there to reconcile the views' appearance. With the reference's 96 views the geometry is pinned by
    /// many cameras, but with the 16-24 views a CPU run affords, 576 Adam steps on positions and scales
    /// fit the views' disagreements with geometry: the demo's striped vase grew floaters above it, which
    /// the guidance then taught the main fit (preservation 24 dB; 43 dB with geometry fixed, guidance
    /// cross-view error 0.038 → 0.048 on the object, oracle colour fidelity lost → 1.0).
    #[value(
        help = "ECM fits change colours and opacities only (geometry stays; no floaters from few views)"
    )]
    Appearance,
    /// All six attribute groups, as the reference does.
    #[value(help = "ECM fits change every attribute, as the reference does")]
    All,
}

/// Fits a copy of a scene to one image per camera (ECM's "mini-GS").
pub trait SceneFitter {
    /// Returns the fitted copy, or a description of what went wrong.
    fn fit(
        &self,
        scene: &GaussianScene,
        cameras: &[Camera],
        images: &[Image],
        seed: u64,
    ) -> Result<GaussianScene, String>;

    /// Two fits of copies of `scene`, to `images[0]` with `seed` and to `images[1]` with `seed + 1`: the
    /// same as two calls of [`SceneFitter::fit`], which fitters may run side by side.
    fn fit_pair(
        &self,
        scene: &GaussianScene,
        cameras: &[Camera],
        images: [&[Image]; 2],
        seed: u64,
    ) -> Result<[GaussianScene; 2], String> {
        fit_in_turn(self, scene, cameras, images, seed)
    }
}

/// [`SceneFitter::fit_pair`] one fit after the other.
fn fit_in_turn<F: SceneFitter + ?Sized>(
    fitter: &F,
    scene: &GaussianScene,
    cameras: &[Camera],
    images: [&[Image]; 2],
    seed: u64,
) -> Result<[GaussianScene; 2], String> {
    Ok([
        fitter.fit(scene, cameras, images[0], seed)?,
        fitter.fit(scene, cameras, images[1], seed + 1)?,
    ])
}

/// ECM's mini-GS fitter: fresh copies of the editing state fitted to each set of predictions.
pub struct EcmFitter<'a> {
    base: &'a TrainState,
    loss: &'a ImageLoss,
    settings: &'a EcmSettings,
    background: [f32; 3],
    device: &'a SplatDevice,
}

impl<'a> EcmFitter<'a> {
    pub fn new(trainer: &'a EditTrainer, loss: &'a ImageLoss, settings: &'a EcmSettings) -> Self {
        Self {
            base: &trainer.state,
            loss,
            settings,
            background: trainer.background,
            device: &trainer.device,
        }
    }
}

impl EcmFitter<'_> {
    /// A fit's starting state: a deep copy of the editing state with `scene` (same optimiser moments
    /// and current rates: the reference's deep-copied optimizer), no densification, no anchor loss,
    /// and with [`EcmParams::Appearance`] the geometry rates 0.
    fn start_state(&self, scene: &GaussianScene) -> Result<TrainState, String> {
        if scene.len() != self.base.len() {
            return Err("ECM scene differs from the editing state".into());
        }
        let mut state = self.base.clone();
        state.scene.clone_from(scene);
        state.anchor = None;
        if self.settings.scope == EcmScope::All {
            state.trainable = None;
        }
        if self.settings.params == EcmParams::Appearance {
            for g in [Group::Means, Group::LogScales, Group::Quats] {
                state.adam.group_lr_scale[g.index()] = 0.0;
            }
        }
        Ok(state)
    }

    /// Runs a fit's schedule: per epoch the rates (StepLR(step_size = 2 epochs, γ = 0.5), stretched
    /// with the epochs) and a view order drawn from each of `rngs` (one per fit), then `step` with each
    /// fit's view at each position of the orders.
    fn run_schedule<const FITS: usize>(
        &self,
        state: &mut TrainState,
        views: usize,
        rngs: &mut [ChaCha8Rng; FITS],
        mut step: impl FnMut(&mut TrainState, [usize; FITS]) -> Result<(), String>,
    ) -> Result<(), String> {
        let base_scale = state.adam.lr_scale;
        let (epochs, halve_every) = self.settings.schedule(views);
        for epoch in 0..epochs {
            state.adam.lr_scale = base_scale * 0.5f32.powi((epoch / halve_every) as i32);
            let orders = rngs.each_mut().map(|rng| {
                let mut order: Vec<usize> = (0..views).collect();
                order.shuffle(rng);
                order
            });
            for k in 0..views {
                step(state, orders.each_ref().map(|order| order[k]))?;
            }
        }
        Ok(())
    }

    /// Both fits stepped together on a GPU ([`PairTrainer`]: one launch sequence per step for the two,
    /// the views' kept projections shared), each with its own seed's view orders: the same fits as in
    /// turn, up to the order of the backward's atomic sums. `None` where they cannot: on the CPU, with
    /// [`EcmParams::All`] (every step projects and bins each fit's geometry anew; those fits stay in
    /// turn), with LPIPS on the GPU (a device term per image), or views of different sizes.
    fn fit_together(
        &self,
        scene: &GaussianScene,
        cameras: &[Camera],
        images: [&[Image]; 2],
        seed: u64,
    ) -> Result<Option<[GaussianScene; 2]>, String> {
        if self.device.is_cpu() || self.settings.params != EcmParams::Appearance {
            return Ok(None);
        }
        for set in images {
            check_targets(cameras, set).map_err(|e| e.to_string())?;
        }
        let mut state = self.start_state(scene)?;
        let loss = Targets::new(self.loss, images[0]);
        let targets = images.map(|set| set.iter().map(|t| t.data.as_slice()));
        let Some(mut pair) = PairTrainer::new(
            self.device,
            &loss,
            targets,
            cameras,
            self.background,
            &state,
        ) else {
            return Ok(None);
        };
        let mut rngs = [seed, seed + 1].map(ChaCha8Rng::seed_from_u64);
        self.run_schedule(&mut state, cameras.len(), &mut rngs, |state, [a, b]| {
            pair.step(&mut state.adam, [&cameras[a], &cameras[b]], [a, b])
                .map_err(|e| e.to_string())
        })?;
        pair.finish().map(Some).map_err(|e| e.to_string())
    }
}

impl SceneFitter for EcmFitter<'_> {
    fn fit(
        &self,
        scene: &GaussianScene,
        cameras: &[Camera],
        images: &[Image],
        seed: u64,
    ) -> Result<GaussianScene, String> {
        check_targets(cameras, images).map_err(|e| e.to_string())?;
        let mut state = self.start_state(scene)?;
        let mut targets = Targets::new(self.loss, images);
        let mut trainer = targets.trainer(self.device, self.background);
        if self.settings.params == EcmParams::Appearance {
            // Each view's projection is then the same at every step: kept, and no geometry gradients
            // (the copy's geometry moments are thrown away with it).
            trainer.freeze_geometry();
        }
        // No densification: every step is an ordinary one (resident with the D-SSIM loss on a device).
        let kind = StepKind::Ordinary {
            track_stats: false,
            read_loss: false,
        };
        let mut rngs = [ChaCha8Rng::seed_from_u64(seed)];
        self.run_schedule(&mut state, cameras.len(), &mut rngs, |state, [v]| {
            trainer
                .step(state, &cameras[v], v, &mut targets, kind)
                .map(drop)
                .map_err(|e| e.to_string())
        })?;
        trainer.sync(&mut state).map_err(|e| e.to_string())?;
        Ok(state.scene)
    }

    /// On the CPU the target and layout fits run side by side: a step's parallel loops are short at
    /// editing sizes, so one fit alone leaves cores idle between them (two fits take ~17 % less wall
    /// time on 2 cores, docs/performance.md). The results are the same: no result of a fit depends on the threads' timing. On
    /// a GPU the appearance fits step together, one launch sequence for both ([`Self::fit_together`]);
    /// fits that cannot run one after the other (side by side they would only queue on the one device
    /// and double its memory).
    fn fit_pair(
        &self,
        scene: &GaussianScene,
        cameras: &[Camera],
        images: [&[Image]; 2],
        seed: u64,
    ) -> Result<[GaussianScene; 2], String> {
        if !self.device.is_cpu() {
            return match self.fit_together(scene, cameras, images, seed)? {
                Some(pair) => Ok(pair),
                None => fit_in_turn(self, scene, cameras, images, seed),
            };
        }
        let (a, b) = rayon::join(
            || self.fit(scene, cameras, images[0], seed),
            || self.fit(scene, cameras, images[1], seed + 1),
        );
        Ok([a?, b?])
    }
}

impl MultiView<'_> {
    /// ECM at step `i`: fit the scene to the decoded predictions, render, encode, substitute. Returns
    /// the seconds of the two fits.
    pub(super) fn editing_consistency(
        &self,
        views: &mut [ViewState],
        i: usize,
        noise: &mut dyn NoiseSource,
        work: &mut StageWork,
    ) -> Result<f64, MultiViewError> {
        let fitter = self.fitter.expect("checked in run");
        let model = self.model;
        let batch = self.view_batch;
        let preds = |pick: fn(&ViewState) -> Option<&Tensor>| -> Vec<&Tensor> {
            views.iter().map(|v| pick(v).expect("updated")).collect()
        };
        let targets = model.decode_each(&preds(|v| v.pred_t.as_ref()), batch)?;
        let layouts = model.decode_each(&preds(|v| v.pred_m.as_ref()), batch)?;
        work.vae_decodes += 2 * views.len();
        let seed = self.seed.wrapping_mul(1_000_003).wrapping_add(i as u64 * 2);
        let fitting = std::time::Instant::now();
        let [fit_t, fit_m] = fitter
            .fit_pair(self.scene, self.cameras, [&targets, &layouts], seed)
            .map_err(MultiViewError::Fit)?;
        let fit_seconds = fitting.elapsed().as_secs_f64();
        let (epochs, _) = self.consistency.ecm.schedule(self.cameras.len());
        work.fit_steps += 2 * epochs * self.cameras.len();
        let compute = model.compute.splat();
        let render_t = compute
            .render_images(&fit_t, self.cameras, self.background)
            .map_err(candle_err)?;
        let render_m = compute
            .render_images(&fit_m, self.cameras, self.background)
            .map_err(candle_err)?;
        // Encoded in the order [t₀, m₀, t₁, m₁, …], the noise draws of one view at a time.
        let mut images = Vec::with_capacity(2 * views.len());
        for (img_t, img_m) in render_t.iter().zip(&render_m) {
            images.push(image_to_tensor(img_t)?.clamp(-1f32, 1f32)?);
            images.push(image_to_tensor(img_m)?.clamp(-1f32, 1f32)?);
        }
        // One view's pair at a time unless views are batched (a batch of two would change the CPU's bits).
        let encode_batch = if batch > 1 { 2 * batch } else { 1 };
        let latents = model.encode_each(&images, encode_batch, noise)?;
        work.vae_encodes += images.len();
        for (view, pair) in views.iter_mut().zip(latents.chunks_exact(2)) {
            self.plan
                .rebase(view, i, pair[0].clone(), pair[1].clone())?;
        }
        Ok(fit_seconds)
    }
}

#[cfg(test)]
mod tests {
    use super::EcmSettings;

    #[test]
    fn schedule_keeps_the_reference_at_96_views_and_stretches_below() {
        let s = EcmSettings::reference(15);
        assert_eq!(s.steps, vec![4, 9, 14]);
        // The reference: 6 epochs, rates halved every 2.
        assert_eq!(s.schedule(96), (6, 2));
        assert_eq!(s.schedule(200), (6, 2));
        // 16 views: 36 epochs (576 steps), halved every 12 — the same shape, stretched.
        assert_eq!(s.schedule(16), (36, 12));
        assert_eq!(s.schedule(0), (576, 192));
    }
}
