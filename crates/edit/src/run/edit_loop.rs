//! The editing loop itself: render → edit all views jointly → fit, once per iteration.

use std::path::Path;
use std::time::Instant;

use gpu::traffic::DeviceTraffic;
use splat::render::Frame;
use splat::render::{ExtraChannels, RenderSettings};
use splat::{Camera, GaussianScene, Image};

use crate::consistency::{ConsistencySettings, EcmFitter, MultiView, MultiViewOutcome, Stage};
use crate::eval::metrics::{multiview_consistency, ConsistencySummary, ViewGeometry, WarpSettings};
use crate::fit::{EditTrainer, ImageLoss};
use crate::sampler::{EditModel, EditPlan, SeededNoise};

use super::checkpoint::{fingerprint, Checkpoint, TrainerSetup};
use super::estimate::about;
use super::job::{
    EditJob, EditResult, GuidanceMode, IterationTimes, MaskSource, Progress, RunError, SeedPurpose,
};
use super::masks::{self, Box3};
use super::outputs;
use super::shape::{footprint_change, KeepShape, ShapeDecision};

/// A whole edit into `out`: [`run_edit`], then [`outputs::write_outputs`] — the one sequence `vcedit edit`
/// and the demo run. Returns the result (the demo scores it) and the written paths.
pub fn edit_scene(
    job: &EditJob,
    model: &EditModel,
    loss: &ImageLoss,
    scene: &GaussianScene,
    cameras: &[Camera],
    out: &Path,
    resume: bool,
    inputs: &outputs::RunInputs<'_>,
    progress: &mut dyn Progress,
) -> Result<(EditResult, outputs::Written), RunError> {
    let result = run_edit(job, model, loss, scene, cameras, out, resume, progress)?;
    let written = outputs::write_outputs(out, job, inputs, scene, cameras, &result, progress)?;
    Ok((result, written))
}

/// Runs an edit. `scene` and `cameras` (already at the working resolution) are the inputs; outputs go to
/// `out` (guidance images per iteration; the caller writes the final outputs). With `resume`, a
/// checkpoint in `out` is continued.
pub fn run_edit(
    job: &EditJob,
    model: &EditModel,
    loss: &ImageLoss,
    scene: &GaussianScene,
    cameras: &[Camera],
    out: &Path,
    resume: bool,
    progress: &mut dyn Progress,
) -> Result<EditResult, RunError> {
    if cameras.is_empty() {
        return Err(RunError::Input("no cameras".into()));
    }
    if scene.is_empty() {
        return Err(RunError::Input("the scene has no Gaussians".into()));
    }
    let run = Run {
        job,
        model,
        loss,
        out,
    };
    let compute = &model.compute;
    let (mut trainer, mut state, resumed_from) = run.start(scene, cameras, resume, progress)?;
    trainer.device = compute.splat().clone();
    let cams: Vec<Camera> = state.views.iter().map(|&i| cameras[i].clone()).collect();
    let before = compute
        .splat()
        .render_images(scene, &cams, job.background)?;
    let mut guidance = outputs::read_guidance(out, state.iterations_done, cams.len())?;

    for k in state.iterations_done..job.iterations {
        let mut times = IterationTimes::default();

        // Render the current scene from the edited views.
        let t = Instant::now();
        progress.stage(&run.stage(k, "rendering"), cams.len() as u64);
        let settings = RenderSettings {
            background: job.background,
        };
        let renders = compute
            .splat()
            .render_views(trainer.scene(), &cams, &settings, None)?;
        let sources: Vec<Image> = renders.iter().map(|r| r.rgb_image()).collect();
        progress.advance(cams.len() as u64);
        times.render = t.elapsed().as_secs_f64();

        // Edit all views jointly into guidance images.
        let (plan, edited) = run.edit_views(&trainer, &cams, &sources, k, progress)?;
        times.sampler = edited.times;
        times.work = edited.work;
        state
            .guidance_consistency
            .push(guidance_consistency(&edited.images, &cams, &renders));
        outputs::write_iteration(out, k, &sources, &edited.images)?;
        if k == 0 {
            if let Some(first) = edited.views.first() {
                state.attention = outputs::write_word_maps(out, &plan, first, job.size)?;
            }
        }

        // Fit the scene to the guidance, its geometry kept where the guidance keeps the footprint.
        let t = Instant::now();
        let traffic = DeviceTraffic::now();
        let shape = run.shape_decision(&trainer, &cams, &sources, &edited.images)?;
        if job.keep_shape != KeepShape::Never {
            progress.log(&shape.describe());
        }
        progress.stage(&run.stage(k, "fitting"), job.fit_steps as u64);
        trainer.set_geometry_rate(shape.geometry_rate);
        let fitted = trainer.fit(
            &cams,
            &edited.images,
            job.fit_steps,
            loss,
            job.seed_for(k, SeedPurpose::Fit),
            &mut |n| progress.advance(n),
        );
        // ECM's fits copy the trainer's state: they keep the reference's rates.
        trainer.set_geometry_rate(1.0);
        fitted?;
        state.shape.push(shape);
        times.fit = t.elapsed().as_secs_f64();
        times.work.fit.fit_steps += job.fit_steps;
        times
            .work
            .fit
            .add_traffic(DeviceTraffic::now().since(traffic));
        guidance.push(edited.images);

        state.iterations_done = k + 1;
        let took = times.total();
        state.times.push(times);
        state.save(out, &trainer)?;
        // The overall ETA: iterations cost alike (the first also compiles GPU kernels, so it overshoots).
        let left = job.iterations - (k + 1);
        let eta = if left > 0 {
            format!(
                "; about {} left for {left} more iteration{}",
                about(took * left as f64),
                if left == 1 { "" } else { "s" }
            )
        } else {
            String::new()
        };
        progress.log(&format!(
            "iteration {} done ({}/): {} Gaussians in {}{eta}",
            k + 1,
            outputs::iteration_dir_name(k),
            trainer.scene().len(),
            about(took),
        ));
        if job.stop_after_iteration == Some(k + 1) {
            return Err(RunError::Stopped { iteration: k + 1 });
        }
    }

    Ok(EditResult {
        scene: trainer.state.scene,
        views: state.views,
        mask: state.mask,
        before,
        guidance,
        times: state.times,
        word_maps: state
            .attention
            .iter()
            .map(|(w, f)| (w.clone(), out.join("attention").join(f)))
            .collect(),
        guidance_consistency: state.guidance_consistency,
        shape: state.shape,
        resumed_from,
    })
}

/// What every part of a run reads: the job, the model, the fits' loss and the output folder.
struct Run<'a> {
    job: &'a EditJob,
    model: &'a EditModel,
    loss: &'a ImageLoss,
    out: &'a Path,
}

impl Run<'_> {
    /// The progress label of a stage of iteration `k`.
    fn stage(&self, k: usize, what: &str) -> String {
        // Counted from 1 for people, the folder from 0: both named, so neither surprises.
        format!(
            "iteration {}/{} ({}/): {what}",
            k + 1,
            self.job.iterations,
            outputs::iteration_dir_name(k)
        )
    }

    /// The trainer and run state to start iterating from: the checkpoint in `out` when resuming (with the
    /// iteration it was written after), else a fresh start on the selected views with the editable mask.
    fn start(
        &self,
        scene: &GaussianScene,
        cameras: &[Camera],
        resume: bool,
        progress: &mut dyn Progress,
    ) -> Result<(EditTrainer, Checkpoint, Option<usize>), RunError> {
        let job = self.job;
        let fp = fingerprint(job, scene, cameras);
        let views = select_views(cameras.len(), job.max_views);
        let cams: Vec<Camera> = views.iter().map(|&i| cameras[i].clone()).collect();
        let setup = TrainerSetup {
            train: &job.train,
            extent: scene_extent(&cams),
            background: job.background,
        };
        if resume && Checkpoint::exists(self.out) {
            let (state, trainer) = Checkpoint::load(self.out, &fp, &setup)?;
            let k = state.iterations_done;
            progress.log(&format!(
                "resuming after iteration {k} of {}",
                job.iterations
            ));
            return Ok((trainer, state, Some(k)));
        }
        if resume {
            progress.log("no checkpoint to resume from; starting from the beginning");
        }
        let mask = editable_mask(job, self.model, scene, &cams, progress)?;
        let trainer = EditTrainer::new(
            scene,
            mask.clone(),
            setup.train.clone(),
            setup.extent,
            setup.background,
        );
        Ok((trainer, Checkpoint::start(views, fp, mask), None))
    }

    /// Iteration `k`'s joint edit of the views' current renders `sources`: VcEdit's multi-view sampler (or
    /// per-view InfEdit, as the job says). Iteration 0 edits source → target; later iterations target →
    /// target, re-editing the scene that already shows the target. Returns the plan it ran with and the
    /// result.
    fn edit_views(
        &self,
        trainer: &EditTrainer,
        cams: &[Camera],
        sources: &[Image],
        k: usize,
        progress: &mut dyn Progress,
    ) -> Result<(EditPlan, MultiViewOutcome), RunError> {
        let job = self.job;
        let mut prompts = job.prompts.clone();
        if k > 0 {
            prompts.source = prompts.target.clone();
        }
        let (w, h) = job.size;
        let mut plan = EditPlan::new(self.model, &prompts, &job.infedit, (w as usize, h as usize))?;
        let consistency = match job.guidance {
            GuidanceMode::Joint => {
                plan.thresholds.dynamic_me = true;
                job.consistency.clone()
            }
            GuidanceMode::PerView => ConsistencySettings::none(),
        };
        let fitter = EcmFitter::new(trainer, self.loss, &consistency.ecm);
        let sampler = MultiView {
            model: self.model,
            plan: &plan,
            scene: trainer.scene(),
            cameras: cams,
            consistency: &consistency,
            fitter: Some(&fitter),
            seed: job.seed_for(k, SeedPurpose::Ecm),
            background: job.background,
            view_batch: super::work::view_batch(job, self.model, trainer.scene(), cams.len()),
            delta_decode: job.delta_decode.applies(k),
        };
        // One unit per UNet step, per CCM and ECM call (ECM's fits take as long as several steps) and for
        // the decode, so the bar reaches its end only when the guidance is ready.
        let steps = plan.timesteps.len();
        let calls = |at: &[usize]| at.iter().filter(|&&i| i < steps).count();
        let units = steps + calls(&consistency.ccm_steps) + calls(&consistency.ecm.steps) + 1;
        // The bar's units named, so "6/21" reads as progress through the steps and calls.
        let what = format!(
            "editing {} views ({steps} steps, {} CCM, {} ECM, decode)",
            cams.len(),
            calls(&consistency.ccm_steps),
            calls(&consistency.ecm.steps)
        );
        progress.stage(&self.stage(k, &what), units as u64);
        let mut noise = SeededNoise::new(job.seed_for(k, SeedPurpose::Noise));
        let edited = sampler.run(sources, &mut noise, &mut |_, stage| {
            if matches!(stage, Stage::Unet | Stage::Ccm | Stage::Ecm) {
                progress.advance(1);
            }
        })?;
        progress.advance(1);
        Ok((plan, edited))
    }

    /// Whether an iteration's fit keeps the editable region's geometry: under `auto` with a mask, from the
    /// pixels the guidance changed outside the mask's rendered footprint (`shape` module).
    fn shape_decision(
        &self,
        trainer: &EditTrainer,
        cams: &[Camera],
        sources: &[Image],
        guidance: &[Image],
    ) -> Result<ShapeDecision, RunError> {
        let keep = self.job.keep_shape;
        let mask = trainer.state.trainable.as_deref();
        let change = match (keep, mask) {
            (KeepShape::Auto, Some(mask)) => {
                let values: Vec<f32> = mask.iter().map(|&m| m as u8 as f32).collect();
                let extra = ExtraChannels {
                    values: &values,
                    channels: 1,
                };
                let coverage: Vec<Vec<f32>> = self
                    .model
                    .compute
                    .splat()
                    .render_views(
                        trainer.scene(),
                        cams,
                        &RenderSettings::default(),
                        Some(extra),
                    )?
                    .into_iter()
                    .map(|f| f.extra)
                    .collect();
                footprint_change(&coverage, sources, guidance)
            }
            _ => None,
        };
        Ok(ShapeDecision::new(keep, change))
    }
}

/// Multi-view consistency of guidance images, warped with the geometry of the renders they were made from.
fn guidance_consistency(
    images: &[Image],
    cams: &[Camera],
    renders: &[Frame],
) -> Option<ConsistencySummary> {
    let geometry: Vec<ViewGeometry> = cams
        .iter()
        .zip(renders)
        .map(|(c, r)| ViewGeometry::from_render(c, r))
        .collect();
    multiview_consistency(
        &images.iter().collect::<Vec<_>>(),
        &geometry,
        &WarpSettings::default(),
    )
    .ok()
    .map(|r| r.summary)
}

/// The editable Gaussians the job's mask source selects (`None`: all of them).
fn editable_mask(
    job: &EditJob,
    model: &EditModel,
    scene: &GaussianScene,
    cams: &[Camera],
    progress: &mut dyn Progress,
) -> Result<Option<Vec<bool>>, RunError> {
    let mask = match &job.mask {
        MaskSource::None => return Ok(None),
        MaskSource::Box { min, max } => masks::mask_from_box(
            scene,
            &Box3 {
                min: *min,
                max: *max,
            },
        ),
        MaskSource::Given(mask) => {
            if mask.len() != scene.len() {
                return Err(RunError::Input(format!(
                    "the mask has {} flags for {} Gaussians",
                    mask.len(),
                    scene.len()
                )));
            }
            mask.clone()
        }
        MaskSource::Dir(dir) => {
            let maps = masks::load_mask_images(dir, cams)?;
            masks::threshold(
                &masks::lift_maps(&model.compute, scene, cams, &maps)?,
                job.mask_threshold,
            )
        }
        MaskSource::Word(word) => {
            progress.stage("mask: attention to the mask word", cams.len() as u64);
            let images = model
                .compute
                .splat()
                .render_images(scene, cams, job.background)?;
            let (w, h) = job.size;
            let plan = EditPlan::new(model, &job.prompts, &job.infedit, (w as usize, h as usize))?;
            let mut noise = SeededNoise::new(job.seed_for(0, SeedPurpose::Mask));
            // A mid-schedule timestep: noisy enough for the UNet to attend by meaning, not by pixels.
            let t = plan.timesteps[plan.timesteps.len() / 2];
            let maps = masks::word_attention_maps(
                model,
                &images,
                &job.prompts.source,
                word,
                t,
                plan.blend_size,
                &mut noise,
            )?;
            progress.advance(cams.len() as u64);
            masks::threshold(
                &masks::lift_maps(&model.compute, scene, cams, &maps)?,
                job.mask_threshold,
            )
        }
    };
    let n = mask.iter().filter(|&&m| m).count();
    progress.log(&format!("mask: {n} of {} Gaussians editable", mask.len()));
    if n == 0 {
        return Err(RunError::Input(
            "the mask selects no Gaussian; lower --mask-threshold or check the box / word / mask images".into(),
        ));
    }
    Ok(Some(mask))
}

/// `min(n, max)` camera indices evenly spaced over the list (first and last included), in ascending
/// order: what `--max-views` means in every command. The reference draws a seeded random sample
/// (`random.sample`, seed 0), which Python's generator alone reproduces; even spacing covers an orbit or
/// a capture path without the gaps and clusters a random draw leaves, and picks the views `render` and
/// `metrics` pick for the same `--max-views`.
fn select_views(n: usize, max: usize) -> Vec<usize> {
    crate::present::report::subset_indices(n, max.max(1))
}

/// The INRIA trainer's scene extent: 1.1 × the largest distance of a camera centre from their mean.
pub fn scene_extent(cameras: &[Camera]) -> f32 {
    let n = cameras.len().max(1) as f64;
    let mut mean = [0.0f64; 3];
    for c in cameras {
        let p = c.center();
        for a in 0..3 {
            mean[a] += p[a] / n;
        }
    }
    let r = cameras
        .iter()
        .map(|c| {
            let p = c.center();
            ((p[0] - mean[0]).powi(2) + (p[1] - mean[1]).powi(2) + (p[2] - mean[2]).powi(2)).sqrt()
        })
        .fold(0.0f64, f64::max);
    (1.1 * r).max(1e-3) as f32
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn views_are_evenly_spaced_as_in_every_command() {
        assert_eq!(select_views(5, 96), vec![0, 1, 2, 3, 4]);
        assert_eq!(select_views(10, 4), vec![0, 3, 6, 9]);
        let a = select_views(200, 10);
        assert_eq!(a.len(), 10);
        assert!(a.windows(2).all(|w| w[0] < w[1]));
        assert_eq!((a[0], a[9]), (0, 199));
    }
}
