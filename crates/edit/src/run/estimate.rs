//! A time estimate before a run: the run's unit costs timed on this machine (one UNet call of the run's
//! view batch, one render, one CCM lifting round), scaled by the counts of its [`WorkPlan`].
//!
//! Rough by design: the codec's encodes and decodes are not counted (on SD 1.5 a few percent of a CPU
//! run), a fit step is taken as three renders (forward, backward, Adam), and every lifting pass as CCM's
//! widest (the blend's are narrower). What it is for is telling "minutes" from "days" before a user waits.

use std::time::Instant;

use candle_core::{DType, Device, Tensor};
use splat::lift::{MapGrid, Resample};
use splat::render::RenderSettings;
use splat::{Camera, GaussianScene};

use crate::sampler::EditModel;

use super::job::{EditJob, RunError};
use super::work::WorkPlan;

/// Plans with fewer UNet calls than this are not calibrated: the calibration would cost a noticeable
/// share of the run, and a short run shows its pace soon enough.
pub const CALIBRATE_FROM_UNET_CALLS: usize = 50;

/// Channels of the calibrating lifting round: SD 1.5's CCM maps, 3 branches × 8 heads × 6 prompt tokens.
const LIFT_CHANNELS: usize = 144;

/// Seconds of one unit of each kind of work, measured on this machine and device.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct Calibration {
    /// One UNet call of the plan's view batch (6 branches per view), no hook.
    pub unet_call: f64,
    /// One RGB render at the run's size.
    pub render: f64,
    /// One view's lifting round (lift onto the scene and render back) of a CCM-wide map.
    pub lift: f64,
}

/// A run's estimated duration and its parts, in seconds.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct Estimate {
    pub total: f64,
    pub unet: f64,
    /// Renders, fit steps and lifting passes.
    pub splatting: f64,
    pub calibration: Calibration,
}

impl Estimate {
    /// From the plan's counts and the unit costs.
    pub fn new(plan: &WorkPlan, calibration: Calibration) -> Self {
        let calls = plan.unet_calls.div_ceil(plan.view_batch.max(1));
        let unet = calls as f64 * calibration.unet_call;
        let splatting = (plan.renders + 3 * plan.fit_steps) as f64 * calibration.render
            + plan.lifts as f64 * calibration.lift;
        Estimate {
            total: unet + splatting,
            unet,
            splatting,
            calibration,
        }
    }

    /// One line for the work plan, within 74 columns (80 with the plan's indent) for durations runs have.
    pub fn describe(&self) -> String {
        format!(
            "time ≈ {} (UNet {}, splatting {}; a UNet call {} here)",
            about(self.total),
            about(self.unet),
            about(self.splatting),
            unit_cost(self.calibration.unet_call)
        )
    }
}

/// Whether `plan` is long enough to be worth calibrating.
pub fn worth_calibrating(plan: &WorkPlan) -> bool {
    plan.unet_calls >= CALIBRATE_FROM_UNET_CALLS
}

/// Times the unit costs of `job` on `model`'s device with `scene` seen from `camera` (at the run's size).
/// On a GPU each unit runs twice and the second is timed: the first compiles the kernels (which the run
/// then finds compiled).
pub fn calibrate(
    job: &EditJob,
    model: &EditModel,
    scene: &GaussianScene,
    camera: &Camera,
    view_batch: usize,
) -> Result<Calibration, RunError> {
    let warm_up = !model.compute.splat().is_cpu();
    let timed = |f: &mut dyn FnMut() -> Result<(), RunError>| -> Result<f64, RunError> {
        if warm_up {
            f()?;
        }
        let start = Instant::now();
        f()?;
        Ok(start.elapsed().as_secs_f64())
    };

    let f = model.downscale();
    let (w, h) = (job.size.0 as usize / f, job.size.1 as usize / f);
    let batch = 6 * view_batch.max(1);
    let sample = Tensor::randn(
        0f32,
        1.0,
        (batch, model.latent_channels(), h, w),
        &Device::Cpu,
    )?;
    let empty = model.tokenizer.encode("");
    let ids = diffusion::clip::ids_tensor(&[empty], &Device::Cpu)?;
    let context = model.encode_text(&ids)?;
    let context = context.repeat((batch, 1, 1))?.to_dtype(DType::F32)?;
    let timesteps = Tensor::new(&[499u32], &Device::Cpu)?;
    let unet_call = timed(&mut || {
        model.predict(&sample, &timesteps, &context, None)?;
        Ok(())
    })?;

    let splat = model.compute.splat();
    let settings = RenderSettings {
        background: job.background,
    };
    let render = timed(&mut || {
        splat.render(scene, camera, &settings, None)?;
        Ok(())
    })?;

    let grid = MapGrid {
        height: 16,
        width: 16,
        channels: LIFT_CHANNELS,
        up: Resample::Bilinear,
        down: Resample::Bilinear,
    };
    let map = vec![0.5f32; grid.len()];
    let cameras = std::slice::from_ref(camera);
    let lift = timed(&mut || {
        splat.lift_and_render_back::<RunError>(
            scene,
            cameras,
            &grid,
            &mut |_| Ok(map.clone()),
            &mut |_, _| Ok(()),
        )
    })?;
    Ok(Calibration {
        unet_call,
        render,
        lift,
    })
}

/// A unit cost, to the precision a sub-second call needs.
fn unit_cost(secs: f64) -> String {
    if secs < 1.0 {
        format!("{:.0} ms", secs * 1e3)
    } else if secs < 90.0 {
        format!("{secs:.1} s")
    } else {
        about(secs)
    }
}

/// A duration as people say it: seconds, minutes, hours, days.
pub(crate) fn about(secs: f64) -> String {
    if secs < 90.0 {
        format!("{secs:.0} s")
    } else if secs < 5400.0 {
        format!("{:.0} min", secs / 60.0)
    } else if secs < 2.0 * 86400.0 {
        format!("{:.1} h", secs / 3600.0)
    } else {
        format!("{:.1} days", secs / 86400.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn plan(unet_calls: usize, view_batch: usize) -> WorkPlan {
        WorkPlan {
            views: 8,
            iterations: 2,
            unet_calls,
            renders: 100,
            fit_steps: 500,
            lifts: 20,
            ccm_layers: 11,
            memory_bytes: 0,
            gpu_memory_bytes: None,
            gpu_free_bytes: None,
            view_batch,
            estimate: None,
            work: Default::default(),
        }
    }

    #[test]
    fn the_estimate_scales_the_unit_costs_by_the_counts() {
        let c = Calibration {
            unet_call: 2.0,
            render: 0.1,
            lift: 0.5,
        };
        let e = Estimate::new(&plan(272, 1), c);
        assert_eq!(e.unet, 544.0);
        assert!((e.splatting - ((100.0 + 1500.0) * 0.1 + 10.0)).abs() < 1e-9);
        assert_eq!(e.total, e.unet + e.splatting);
        // A view batch of 8: a call does 8 views' work (272 / 8 = 34 calls).
        assert_eq!(Estimate::new(&plan(272, 8), c).unet, 68.0);
        assert_eq!(
            e.describe(),
            "time ≈ 12 min (UNet 9 min, splatting 3 min; a UNet call 2.0 s here)"
        );
        // The widest words: days, hours and a call of tens of seconds.
        let long = Estimate {
            total: 1.9 * 86400.0,
            unet: 1.8 * 86400.0,
            splatting: 2.5 * 3600.0,
            calibration: Calibration {
                unet_call: 41.3,
                ..c
            },
        };
        assert!(long.describe().chars().count() <= 74, "{}", long.describe());
        assert_eq!(unit_cost(0.089), "89 ms");
    }

    #[test]
    fn short_plans_are_not_calibrated() {
        assert!(!worth_calibrating(&plan(CALIBRATE_FROM_UNET_CALLS - 1, 1)));
        assert!(worth_calibrating(&plan(CALIBRATE_FROM_UNET_CALLS, 1)));
    }

    #[test]
    fn durations_read_as_people_say_them() {
        assert_eq!(about(42.0), "42 s");
        assert_eq!(about(600.0), "10 min");
        assert_eq!(about(3.0 * 3600.0), "3.0 h");
        assert_eq!(about(2.5 * 86400.0), "2.5 days");
    }
}
