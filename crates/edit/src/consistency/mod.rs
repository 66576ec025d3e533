//! VcEdit's multi-view sampler: InfEdit over all views at once, with the paper's three consistency modules.
//!
//! One initial noise and one per-step noise are shared by every view and branch. Each step runs, in order:
//! - **CCM**, cross-attention consistency (`ccm.rs`, docs/algorithm.md §1.1; default steps 6 and 13): the
//!   views' cross-attention maps are lifted onto the Gaussians, rendered back and used in the step's pass;
//! - the UNet pass and InfEdit's update of every view (docs/algorithm.md §1.2);
//! - **ECM**, editing consistency (`ecm.rs`, §1.3; default steps 4, 9, 14): two copies of the scene are
//!   fitted to the views' predictions and their renders replace them;
//! - **blend-map consistency** (`blend.rs`, §1.4; every step after the first): the local-blend maps are
//!   lifted and rendered back before the local blend.
//!
//! CCM and blend-map consistency rest on one operation, lifting per-view maps onto the Gaussians and
//! rendering them back (`lift.rs`). Follows docs/algorithm.md §1 (the reference's
//! `EditConsistPipeline.__call__`).

mod blend;
mod ccm;
mod ecm;
mod lift;

pub use ecm::{EcmFitter, EcmParams, EcmScope, EcmSettings, SceneFitter};
pub use lift::make_consistent;
pub use splat::lift::{MapGrid, Resample};

use std::time::{Duration, Instant};

use candle_core::Tensor;
use gpu::traffic::DeviceTraffic;
use serde::{Deserialize, Serialize};
use splat::{Camera, GaussianScene, Image};

use crate::ledger::{StageWork, WorkLedger};
use crate::sampler::{image_to_tensor, EditModel, EditPlan, NoiseSource, ViewState};

/// Which consistency modules run, and when (sampler step indices, 0-based).
#[derive(Clone, Debug, Serialize)]
pub struct ConsistencySettings {
    /// Steps at which CCM runs.
    pub ccm_steps: Vec<usize>,
    /// ECM: its steps and its fits.
    pub ecm: EcmSettings,
    /// Whether the blend maps are made consistent (every step).
    pub blend_consistency: bool,
}

/// The reference's CCM period: its code runs CCM after steps where (i+1) % 7 == 0.
pub const CCM_PERIOD: usize = 7;
/// The reference's ECM period: (i+1) % 5 == 0.
pub const ECM_PERIOD: usize = 5;
/// The schedule length the reference runs (its places for the modules are scaled from it).
const REFERENCE_STEPS: usize = 15;

/// The steps a module with the reference's `period` runs at in a `steps`-step schedule: every
/// `period`-th step, as the reference places them. A schedule shorter than the period, where that rule
/// places none and the module would silently not run, gets it at the reference's places in its own 15
/// steps scaled to the schedule (step ⌈k·period·steps/15⌉ − 1): CCM at the 7th and 14th fifteenths,
/// ECM at the 5th, 10th and 15th, rounded up, so the last step keeps its module.
pub fn module_steps(steps: usize, period: usize) -> Vec<usize> {
    let periodic: Vec<usize> = (0..steps).filter(|i| (i + 1) % period == 0).collect();
    if !periodic.is_empty() || steps == 0 {
        return periodic;
    }
    let mut scaled: Vec<usize> = (1..=REFERENCE_STEPS / period)
        .map(|k| (k * period * steps).div_ceil(REFERENCE_STEPS) - 1)
        .collect();
    scaled.dedup();
    scaled
}

impl ConsistencySettings {
    /// The reference schedule ([`module_steps`]): CCM when (i+1) % 7 == 0, ECM when (i+1) % 5 == 0
    /// (rescaled for schedules shorter than those periods), blend maps every step.
    pub fn reference(steps: usize) -> Self {
        Self {
            ccm_steps: module_steps(steps, CCM_PERIOD),
            ecm: EcmSettings::reference(steps),
            blend_consistency: true,
        }
    }

    /// One line saying when each module runs in a `steps`-step schedule, and where a module is off or
    /// placed by rescaling (not by the reference's period): the plan a user reads before the run.
    pub fn describe(&self, steps: usize) -> String {
        let list = |name: &str, at: &[usize], period: usize| {
            if at.is_empty() {
                return format!("{name} off");
            }
            let rescaled = if steps < period && at == module_steps(steps, period) {
                format!(" (fewer steps than the reference's period {period}: its places rescaled)")
            } else {
                String::new()
            };
            let at: Vec<String> = at.iter().map(usize::to_string).collect();
            format!("{name} at {}{rescaled}", at.join(", "))
        };
        let blend = if !self.blend_consistency {
            "blend maps off"
        } else if steps > 1 {
            "blend maps every step after the first"
        } else {
            "blend maps never (one step)"
        };
        format!(
            "modules (steps 0-{}): {}; {}; {blend}",
            steps.saturating_sub(1),
            list("CCM", &self.ccm_steps, CCM_PERIOD),
            list("ECM", &self.ecm.steps, ECM_PERIOD)
        )
    }

    /// Per-view guidance: every view edited independently (the inconsistent guidance of peer methods).
    pub fn none() -> Self {
        Self {
            ccm_steps: Vec::new(),
            ecm: EcmSettings::reference(0),
            blend_consistency: false,
        }
    }
}

/// What the sampler is doing, for progress display.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stage {
    Encode,
    Ccm,
    Unet,
    Ecm,
    Blend,
    Decode,
}

/// Wall-clock seconds spent per stage.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct StageTimes {
    pub encode: f64,
    pub ccm: f64,
    pub unet: f64,
    pub ecm: f64,
    pub blend: f64,
    pub decode: f64,
    /// Of `ccm`: the layers' lifting rounds, from the recorded maps to the consistent ones (the rest is
    /// the recording UNet passes). Where the time goes inside CCM; not a stage of its own.
    #[serde(default)]
    pub ccm_lifting: f64,
    /// Of `ecm`: the two fits (the rest decodes the predictions, renders the fitted copies and encodes
    /// the renders). Scales with the fits' steps, not with the views.
    #[serde(default)]
    pub ecm_fits: f64,
}

impl StageTimes {
    fn add(&mut self, stage: Stage, d: Duration) {
        let s = d.as_secs_f64();
        match stage {
            Stage::Encode => self.encode += s,
            Stage::Ccm => self.ccm += s,
            Stage::Unet => self.unet += s,
            Stage::Ecm => self.ecm += s,
            Stage::Blend => self.blend += s,
            Stage::Decode => self.decode += s,
        }
    }
}

/// Where a stage started: the clock, and the device's counts ([`DeviceTraffic`]).
#[derive(Clone, Copy)]
struct StageStart {
    time: Instant,
    traffic: DeviceTraffic,
}

impl StageStart {
    fn now() -> Self {
        Self {
            time: Instant::now(),
            traffic: DeviceTraffic::now(),
        }
    }
}

/// The ledger's entry of `stage`.
fn stage_work(work: &mut WorkLedger, stage: Stage) -> &mut StageWork {
    match stage {
        Stage::Encode => &mut work.encode,
        Stage::Ccm => &mut work.ccm,
        Stage::Unet => &mut work.unet,
        Stage::Ecm => &mut work.ecm,
        Stage::Blend => &mut work.blend,
        Stage::Decode => &mut work.decode,
    }
}

/// Result of a multi-view edit.
pub struct MultiViewOutcome {
    /// Edited images (the guidance), one per view, RGB in [0, 1].
    pub images: Vec<Image>,
    /// Final per-view states (attention stores for per-word maps, last predictions).
    pub views: Vec<ViewState>,
    /// The last step's blend maps per view `[3, H, W]` (after consistency when enabled).
    pub blend_maps: Vec<Tensor>,
    pub times: StageTimes,
    /// The work each stage did.
    pub work: WorkLedger,
}

#[derive(Debug, thiserror::Error)]
pub enum MultiViewError {
    #[error("{0}")]
    Candle(#[from] candle_core::Error),
    #[error(transparent)]
    Gpu(#[from] gpu::GpuError),
    #[error("ECM fit failed: {0}")]
    Fit(String),
    #[error("{0}")]
    Input(String),
}

/// The inputs of a multi-view edit.
pub struct MultiView<'a> {
    pub model: &'a EditModel,
    pub plan: &'a EditPlan,
    pub scene: &'a GaussianScene,
    /// Cameras at the working resolution (the plan's image size).
    pub cameras: &'a [Camera],
    pub consistency: &'a ConsistencySettings,
    /// Needed when `consistency.ecm.steps` is not empty.
    pub fitter: Option<&'a dyn SceneFitter>,
    /// Seed for the ECM fits' view order.
    pub seed: u64,
    /// Background of ECM's renders.
    pub background: [f32; 3],
    /// Views per UNet call (see [`crate::sampler::EditPlan::predict_views`]); 1 = one view at a time.
    pub view_batch: usize,
    /// Return each source image plus what the edit changed in decoded space (decode(x̂0_T) −
    /// decode(x0)) instead of decode(x̂0_T) alone; see [`crate::run::DeltaDecode`].
    pub delta_decode: bool,
}

impl MultiView<'_> {
    /// Edits all views. `images[v]` is the source render of `cameras[v]` (RGB, working resolution).
    /// `progress(stage, done, total)` reports work units within the current step.
    pub fn run(
        &self,
        images: &[Image],
        noise: &mut dyn NoiseSource,
        progress: &mut dyn FnMut(usize, Stage),
    ) -> Result<MultiViewOutcome, MultiViewError> {
        let plan = self.plan;
        let model = self.model;
        if images.len() != self.cameras.len() || images.is_empty() {
            return Err(MultiViewError::Input(format!(
                "{} images for {} cameras",
                images.len(),
                self.cameras.len()
            )));
        }
        if !self.consistency.ecm.steps.is_empty() && self.fitter.is_none() {
            return Err(MultiViewError::Input("ECM needs a scene fitter".into()));
        }
        let mut times = StageTimes::default();
        let mut work = WorkLedger::default();
        let batches = images.len().div_ceil(self.view_batch.max(1));
        // A stage's wall time, and on a GPU its launches and reads, from its start to now.
        let timed = |stage: Stage, t: StageStart, times: &mut StageTimes, work: &mut WorkLedger| {
            times.add(stage, t.time.elapsed());
            stage_work(work, stage).add_traffic(DeviceTraffic::now().since(t.traffic));
        };

        let t = StageStart::now();
        let mut views = Vec::with_capacity(images.len());
        let shape = plan.latent_shape();
        let sources = images;
        let images = images
            .iter()
            .map(image_to_tensor)
            .collect::<candle_core::Result<Vec<_>>>()?;
        let x0s = model.encode_each(&images, self.view_batch, noise)?;
        work.encode.vae_encodes += images.len();
        // One initial noise for every view (the reference repeats view 0's).
        let init = noise.sample(&shape)?;
        for x0 in x0s {
            views.push(plan.initial_state(x0, &init)?);
        }
        timed(Stage::Encode, t, &mut times, &mut work);

        let mut last_maps = Vec::new();
        // CCM's layers and the blend maps' steps lift over the same scene and cameras.
        let mut lift = model.compute.splat().lift_session(self.scene, self.cameras);
        for i in 0..plan.timesteps.len() {
            let n = noise.sample(&shape)?;
            if self.consistency.ccm_steps.contains(&i) {
                let t = StageStart::now();
                times.ccm_lifting +=
                    self.cross_attention_consistency(&mut views, i, &mut lift, &mut work.ccm)?;
                progress(i, Stage::Ccm);
                timed(Stage::Ccm, t, &mut times, &mut work);
            }
            let t = StageStart::now();
            work.unet.unet_calls += batches;
            for batch in views.chunks_mut(self.view_batch.max(1)) {
                let mut batch: Vec<&mut ViewState> = batch.iter_mut().collect();
                work.unet.unet_samples += batch.len() * batch[0].controller.layout().len();
                let eps = plan.predict_views(model, &mut batch, i)?;
                for (view, eps) in batch.into_iter().zip(eps) {
                    view.controller.end_step();
                    plan.update(view, i, &eps, &n)?;
                }
            }
            progress(i, Stage::Unet);
            timed(Stage::Unet, t, &mut times, &mut work);
            if self.consistency.ecm.steps.contains(&i) {
                let t = StageStart::now();
                times.ecm_fits += self.editing_consistency(&mut views, i, noise, &mut work.ecm)?;
                progress(i, Stage::Ecm);
                timed(Stage::Ecm, t, &mut times, &mut work);
            }
            if i > 0 {
                let t = StageStart::now();
                last_maps = self.local_blend(&mut views, i, &mut lift, &mut work.blend)?;
                progress(i, Stage::Blend);
                timed(Stage::Blend, t, &mut times, &mut work);
            }
        }
        let t = StageStart::now();
        let preds = views
            .iter()
            .map(|view| view.pred_t.as_ref())
            .collect::<Option<Vec<_>>>()
            .ok_or_else(|| MultiViewError::Input("no step ran".into()))?;
        let mut out = model.decode_each(&preds, self.view_batch)?;
        work.decode.vae_decodes += preds.len();
        if self.delta_decode {
            let x0s: Vec<&Tensor> = views.iter().map(|v| &v.x0).collect();
            let decoded_sources = model.decode_each(&x0s, self.view_batch)?;
            work.decode.vae_decodes += x0s.len();
            for ((edited, decoded_source), source) in
                out.iter_mut().zip(&decoded_sources).zip(sources)
            {
                add_decoded_change(edited, decoded_source, source);
            }
        }
        timed(Stage::Decode, t, &mut times, &mut work);
        Ok(MultiViewOutcome {
            images: out,
            views,
            blend_maps: last_maps,
            times,
            work,
        })
    }
}

/// `edited` ← `source` + (`edited` − `decoded_source`), clamped to [0, 1]: the edit's change applied to
/// the source image itself, so what the autoencoder's round trip loses (its blur) is not handed on where
/// the edit changed nothing.
fn add_decoded_change(edited: &mut Image, decoded_source: &Image, source: &Image) {
    for ((e, d), s) in edited
        .data
        .iter_mut()
        .zip(&decoded_source.data)
        .zip(&source.data)
    {
        *e = (s + *e - d).clamp(0.0, 1.0);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_decoded_change_is_added_to_the_source() {
        let image = |v: &[f32]| Image::from_data(2, 1, 3, v.to_vec());
        let source = image(&[0.2, 0.4, 0.6, 0.9, 0.9, 0.9]);
        // Pixel 0: decoding blurred it (0.25 for 0.2) and the edit changed nothing; pixel 1: the edit
        // darkened the decoded source by 0.5.
        let decoded_source = image(&[0.25, 0.4, 0.55, 0.8, 0.8, 0.8]);
        let mut edited = image(&[0.25, 0.4, 0.55, 0.3, 0.3, 1.0]);
        add_decoded_change(&mut edited, &decoded_source, &source);
        let want = [0.2, 0.4, 0.6, 0.4, 0.4, 1.0];
        for (got, want) in edited.data.iter().zip(want) {
            assert!((got - want).abs() < 1e-6, "{:?}", edited.data);
        }
    }

    #[test]
    fn reference_schedule() {
        let c = ConsistencySettings::reference(15);
        assert_eq!(c.ccm_steps, vec![6, 13]);
        assert_eq!(c.ecm.steps, vec![4, 9, 14]);
        assert!(c.blend_consistency);
        // Longer schedules keep the reference's periods.
        let c = ConsistencySettings::reference(30);
        assert_eq!(c.ccm_steps, vec![6, 13, 20, 27]);
        assert_eq!(c.ecm.steps, vec![4, 9, 14, 19, 24, 29]);
        assert_eq!(
            ConsistencySettings::reference(15).describe(15),
            "modules (steps 0-14): CCM at 6, 13; ECM at 4, 9, 14; blend maps every step after the first"
        );
    }

    #[test]
    fn short_schedules_keep_both_modules() {
        // Fewer steps than a period: the reference's places rescaled, never an empty list.
        for steps in 1..15 {
            let c = ConsistencySettings::reference(steps);
            assert!(
                !c.ccm_steps.is_empty() && !c.ecm.steps.is_empty(),
                "{steps}"
            );
            assert!(c.ccm_steps.iter().chain(&c.ecm.steps).all(|&i| i < steps));
        }
        let c = ConsistencySettings::reference(4);
        assert_eq!(c.ccm_steps, vec![1, 3]);
        assert_eq!(c.ecm.steps, vec![1, 2, 3]);
        assert_eq!(ConsistencySettings::reference(2).ccm_steps, vec![0, 1]);
        assert_eq!(ConsistencySettings::reference(1).ecm.steps, vec![0]);
        // 6 steps: ECM by its period (step 4), CCM rescaled.
        let c = ConsistencySettings::reference(6);
        assert_eq!(c.ecm.steps, vec![4]);
        assert_eq!(c.ccm_steps, vec![2, 5]);
        let line = c.describe(6);
        assert!(line.contains("CCM at 2, 5 (fewer steps than the reference's period 7"));
        assert!(line.contains("ECM at 4;"), "{line}");
        // Switched off, said so.
        let mut off = ConsistencySettings::reference(4);
        off.ccm_steps.clear();
        assert!(off.describe(4).contains("CCM off"));
    }
}
