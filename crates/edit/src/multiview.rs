//! VcEdit's multi-view sampler: InfEdit over all views at once, with the consistency modules.
//!
//! - One initial noise and one per-step noise shared by every view and branch.
//! - **CCM** (cross-attention consistency, default steps 6 and 13): a recording pass per view captures the
//!   conditional cross-attention maps of the small layers (after InfEdit's refinement); for each layer the
//!   maps of the real tokens (3 branches × heads × L channels) are upsampled to the render resolution,
//!   lifted onto the Gaussians over all views, rendered back, downsampled, clamped to [0, 1] and substituted
//!   in that step's real pass (padding tokens keep the recorded values; no renormalisation over tokens).
//! - **ECM** (editing consistency, default steps 4, 9, 14): the target and layout predictions of all views are
//!   decoded, two fresh copies of the scene are fitted to them, rendered, encoded, and replace the
//!   predictions.
//! - **Blend-map consistency** (every step): the three local-blend maps of every view are lifted and rendered
//!   back before the local blend, which then uses the dynamic threshold for `me` (VcEdit's variant).
//!
//! Follows algorithm.md §1 (the reference's `EditConsistPipeline.__call__`).

use std::collections::HashMap;
use std::time::{Duration, Instant};

use candle_core::{DType, Tensor};
use splat::render::{render, RenderSettings};
use splat::{Camera, GaussianScene, Image};

use crate::blend::blend_maps;
use crate::consistency::{make_consistent, Resample};
use crate::infedit::{EditPlan, ViewState};
use crate::model::EditModel;
use crate::noise::NoiseSource;
use crate::viz;

/// Which consistency modules run, and when (step indices, 0-based).
#[derive(Clone, Debug, serde::Serialize)]
pub struct ConsistencySettings {
    pub ccm_steps: Vec<usize>,
    pub ecm_steps: Vec<usize>,
    pub blend_consistency: bool,
}

impl ConsistencySettings {
    /// The reference schedule: CCM when (i+1) % 7 == 0, ECM when (i+1) % 5 == 0, blend maps every step.
    pub fn reference(steps: usize) -> Self {
        Self {
            ccm_steps: (0..steps).filter(|i| (i + 1) % 7 == 0).collect(),
            ecm_steps: (0..steps).filter(|i| (i + 1) % 5 == 0).collect(),
            blend_consistency: true,
        }
    }

    /// Per-view guidance: every view edited independently (the inconsistent guidance of peer methods).
    pub fn none() -> Self {
        Self {
            ccm_steps: Vec::new(),
            ecm_steps: Vec::new(),
            blend_consistency: false,
        }
    }
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

/// Time spent per stage.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct StageTimes {
    pub encode: f64,
    pub ccm: f64,
    pub unet: f64,
    pub ecm: f64,
    pub blend: f64,
    pub decode: f64,
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

/// Result of a multi-view edit.
pub struct MultiViewOutcome {
    /// Edited images (the guidance), one per view, RGB in [0, 1].
    pub images: Vec<Image>,
    /// Final per-view states (attention stores for per-word maps, last predictions).
    pub views: Vec<ViewState>,
    /// The last step's blend maps per view `[3, H, W]` (after consistency when enabled).
    pub blend_maps: Vec<Tensor>,
    pub times: StageTimes,
}

#[derive(Debug, thiserror::Error)]
pub enum MultiViewError {
    #[error("{0}")]
    Candle(#[from] candle_core::Error),
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
    /// Needed when `consistency.ecm_steps` is not empty.
    pub fitter: Option<&'a dyn SceneFitter>,
    /// Seed for the ECM fits' view order.
    pub seed: u64,
    /// Background of ECM's renders.
    pub background: [f32; 3],
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
        if !self.consistency.ecm_steps.is_empty() && self.fitter.is_none() {
            return Err(MultiViewError::Input("ECM needs a scene fitter".into()));
        }
        let mut times = StageTimes::default();
        let timed =
            |stage: Stage, t: Instant, times: &mut StageTimes| times.add(stage, t.elapsed());

        let t = Instant::now();
        let mut views = Vec::with_capacity(images.len());
        let shape = plan.latent_shape();
        let mut x0s = Vec::with_capacity(images.len());
        for img in images {
            x0s.push(model.encode(&viz::image_to_tensor(img)?, noise)?);
        }
        // One initial noise for every view (the reference repeats view 0's).
        let init = noise.sample(&shape)?;
        for x0 in x0s {
            views.push(plan.initial_state(x0, &init)?);
        }
        timed(Stage::Encode, t, &mut times);

        let mut last_maps = Vec::new();
        for i in 0..plan.timesteps.len() {
            let n = noise.sample(&shape)?;
            if self.consistency.ccm_steps.contains(&i) {
                let t = Instant::now();
                self.cross_attention_consistency(&mut views, i)?;
                progress(i, Stage::Ccm);
                timed(Stage::Ccm, t, &mut times);
            }
            let t = Instant::now();
            for view in views.iter_mut() {
                let eps = plan.predict(model, view, i)?;
                view.controller.end_step();
                plan.update(view, i, &eps, &n)?;
            }
            progress(i, Stage::Unet);
            timed(Stage::Unet, t, &mut times);
            if self.consistency.ecm_steps.contains(&i) {
                let t = Instant::now();
                self.editing_consistency(&mut views, i, noise)?;
                progress(i, Stage::Ecm);
                timed(Stage::Ecm, t, &mut times);
            }
            if i > 0 {
                let t = Instant::now();
                last_maps = self.blend(&mut views, i)?;
                progress(i, Stage::Blend);
                timed(Stage::Blend, t, &mut times);
            }
        }
        let t = Instant::now();
        let mut out = Vec::with_capacity(views.len());
        for view in &views {
            let pred = view
                .pred_t
                .as_ref()
                .ok_or_else(|| MultiViewError::Input("no step ran".into()))?;
            out.push(model.decode_images(pred)?.remove(0));
        }
        timed(Stage::Decode, t, &mut times);
        Ok(MultiViewOutcome {
            images: out,
            views,
            blend_maps: last_maps,
            times,
        })
    }

    /// CCM at step `i`: record, lift, render back, substitute.
    fn cross_attention_consistency(
        &self,
        views: &mut [ViewState],
        i: usize,
    ) -> Result<(), MultiViewError> {
        let plan = self.plan;
        let mut recorded = Vec::with_capacity(views.len());
        for view in views.iter_mut() {
            view.controller.start_recording();
            plan.predict(self.model, view, i)?;
            recorded.push(view.controller.finish_recording());
        }
        let layers = recorded[0].len();
        if recorded.iter().any(|r| r.len() != layers) {
            return Err(MultiViewError::Input(
                "views recorded different attention layers".into(),
            ));
        }
        let real = plan.alignment.target_len.max(plan.source_len);
        let mut consistent: Vec<HashMap<String, Tensor>> = vec![HashMap::new(); views.len()];
        for k in 0..layers {
            let (sh, sw) = recorded[0][k].size;
            let dims = recorded[0][k].maps.dims4()?; // [3, heads, N, tokens]
            let (branches, heads, nq, tokens) = dims;
            let l = real.min(tokens);
            let channels = branches * heads * l;
            // Per view: [N, 3*heads*L] interleaved, channel = (branch*heads + head)*L + token.
            let as_map = |maps: &Tensor| -> candle_core::Result<Vec<f32>> {
                maps.to_dtype(DType::F32)?
                    .narrow(3, 0, l)?
                    .reshape((branches * heads, nq, l))?
                    .permute((1, 0, 2))?
                    .flatten_all()?
                    .to_vec1()
            };
            let rec = &recorded;
            let mut backs: Vec<Option<Vec<f32>>> = vec![None; views.len()];
            make_consistent(
                self.scene,
                self.cameras,
                (sh, sw),
                channels,
                Resample::Bilinear,
                Resample::Bilinear,
                &mut |v| as_map(&rec[v][k].maps),
                &mut |v, back| {
                    backs[v] = Some(back);
                    Ok(())
                },
            )?;
            for (v, back) in backs.into_iter().enumerate() {
                let back = back.expect("every view rendered");
                let maps = &recorded[v][k].maps;
                let lifted =
                    Tensor::from_vec(back, (nq, branches * heads, l), &candle_core::Device::Cpu)?
                        .permute((1, 0, 2))?
                        .reshape((branches, heads, nq, l))?;
                let merged = if l < tokens {
                    Tensor::cat(
                        &[
                            &lifted,
                            &maps.to_dtype(DType::F32)?.narrow(3, l, tokens - l)?,
                        ],
                        3,
                    )?
                } else {
                    lifted
                };
                consistent[v].insert(recorded[v][k].layer.clone(), merged.clamp(0f32, 1f32)?);
            }
        }
        for (view, maps) in views.iter_mut().zip(consistent) {
            view.controller.set_consistent_maps(maps);
        }
        Ok(())
    }

    /// ECM at step `i`: fit the scene to the decoded predictions, render, encode, substitute.
    fn editing_consistency(
        &self,
        views: &mut [ViewState],
        i: usize,
        noise: &mut dyn NoiseSource,
    ) -> Result<(), MultiViewError> {
        let fitter = self.fitter.expect("checked in run");
        let model = self.model;
        let decode = |pred: &Tensor| -> candle_core::Result<Image> {
            Ok(model.decode_images(pred)?.remove(0))
        };
        let mut targets = Vec::with_capacity(views.len());
        let mut layouts = Vec::with_capacity(views.len());
        for view in views.iter() {
            targets.push(decode(view.pred_t.as_ref().expect("updated"))?);
            layouts.push(decode(view.pred_m.as_ref().expect("updated"))?);
        }
        let seed = self.seed.wrapping_mul(1_000_003).wrapping_add(i as u64 * 2);
        let fit_t = fitter
            .fit(self.scene, self.cameras, &targets, seed)
            .map_err(MultiViewError::Fit)?;
        let fit_m = fitter
            .fit(self.scene, self.cameras, &layouts, seed + 1)
            .map_err(MultiViewError::Fit)?;
        let settings = RenderSettings {
            background: self.background,
        };
        for (v, view) in views.iter_mut().enumerate() {
            let cam = &self.cameras[v];
            let mut encode = |scene: &GaussianScene| -> candle_core::Result<Tensor> {
                let out = render(scene, cam, &settings, None);
                let img = Image::from_data(cam.width, cam.height, 3, out.rgb);
                let t = viz::image_to_tensor(&img)?.clamp(-1f32, 1f32)?;
                model.encode(&t, noise)
            };
            let pred_t = encode(&fit_t)?;
            let pred_m = encode(&fit_m)?;
            self.plan.rebase(view, i, pred_t, pred_m)?;
        }
        Ok(())
    }

    /// Blend maps of every view, made consistent when enabled, then the local blend. Returns the maps.
    fn blend(&self, views: &mut [ViewState], i: usize) -> Result<Vec<Tensor>, MultiViewError> {
        let plan = self.plan;
        let (lh, lw) = plan.latent_size;
        let mut maps = Vec::with_capacity(views.len());
        for view in views.iter() {
            maps.push(blend_maps(
                view.controller.blend_store(),
                plan.blend_size,
                &plan.alignment,
                plan.latent_size,
                1e-6,
            )?);
        }
        if self.consistency.blend_consistency {
            let hwc = |m: &Tensor| -> candle_core::Result<Vec<f32>> {
                m.permute((1, 2, 0))?.flatten_all()?.to_vec1()
            };
            let src = maps.clone();
            make_consistent(
                self.scene,
                self.cameras,
                (lh, lw),
                3,
                Resample::Nearest,
                Resample::Nearest,
                &mut |v| hwc(&src[v]),
                &mut |v, back| {
                    maps[v] = Tensor::from_vec(back, (lh, lw, 3), &candle_core::Device::Cpu)?
                        .permute((2, 0, 1))?
                        .contiguous()?;
                    Ok(())
                },
            )?;
        }
        for (view, m) in views.iter_mut().zip(&maps) {
            plan.blend_with_maps(view, i, m)?;
        }
        Ok(maps)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reference_schedule() {
        let c = ConsistencySettings::reference(15);
        assert_eq!(c.ccm_steps, vec![6, 13]);
        assert_eq!(c.ecm_steps, vec![4, 9, 14]);
        assert!(c.blend_consistency);
    }
}
