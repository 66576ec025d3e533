//! A time estimate before a run: the run's unit costs timed on this machine (one UNet call of the run's
//! view batch, one render, one CCM lifting round), scaled by the counts of its [`WorkPlan`].
//!
//! The UNet is never timed at the run's size: a call of 8 views at 512² can take many minutes on a CPU,
//! longer than a user waits for an estimate. It is timed on one view at the run's latents halved until
//! small (8² for SD 1.5 at 512²), then at each doubling while the next probe is expected to fit
//! [`UNET_PROBE_BUDGET_SECS`], and the largest probe is scaled up by the ratio of multiply-adds
//! (`UNetConfig::multiply_adds`, which counts self-attention's square growth).
//!
//! Rough by design: the codec's encodes and decodes are not counted (on SD 1.5 a few percent of a CPU
//! run), a fit step is taken as three renders (forward, backward, Adam), and every lifting pass as CCM's
//! widest (the blend's are narrower); a small probe does less work per second than a large call, so
//! the scaled UNet cost leans high. What it is for is telling "minutes" from "days" before a user waits.

use std::time::Instant;

use candle_core::{DType, Device, Tensor};
use splat::lift::{MapGrid, Resample};
use splat::render::RenderSettings;
use splat::{Camera, GaussianScene};

use crate::sampler::EditModel;

use super::job::{EditJob, RunError};

/// Plans with fewer UNet calls than this are not calibrated: the calibration would cost a noticeable
/// share of the run, and a short run shows its pace soon enough.
pub const CALIBRATE_FROM_UNET_CALLS: usize = 50;

/// Channels of the calibrating lifting round: SD 1.5's CCM maps, 3 branches × 8 heads × 6 prompt tokens.
const LIFT_CHANNELS: usize = 144;

/// Seconds the UNet probes may take together (the first, smallest one always runs): a larger probe
/// runs only while the time spent plus its expected time stays within this.
pub const UNET_PROBE_BUDGET_SECS: f64 = 30.0;

/// The smallest latent side probed (where a size allows it): below it a call is mostly overhead.
const MIN_PROBE_SIDE: usize = 8;

/// The UNet call that was timed and scaled up.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct UnetProbe {
    /// Latent width and height of the timed call (one view: 6 branches).
    pub latent: (usize, usize),
    pub seconds: f64,
    /// Multiply-adds of the run's call over the timed one's.
    pub scale: f64,
}

/// Seconds of one unit of each kind of work, measured on this machine and device.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct Calibration {
    /// One UNet call of the plan's view batch (6 branches per view), no hook: `probe` scaled up.
    pub unet_call: f64,
    pub probe: UnetProbe,
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

/// The counts of a run's plan that its estimate scales the unit costs by (`WorkPlan::counts`).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PlannedCounts {
    /// View passes through the UNet (recording passes included) and views per call.
    pub unet_calls: usize,
    pub view_batch: usize,
    /// UNet samples the run computes (0: not counted; then six a view pass).
    pub unet_samples: usize,
    pub renders: usize,
    pub fit_steps: usize,
    /// Lifting passes, in units of one view's round of a CCM-wide map.
    pub lifts: usize,
}

impl Estimate {
    /// From the plan's counts and the unit costs. The calibration times a call of `view_batch` views with
    /// six samples each; a run computes only the samples that are read (`BatchLayout`: 5, 4 or 3 a view
    /// with default settings), so where the plan counts its samples the UNet's time follows them.
    pub fn new(plan: &PlannedCounts, calibration: Calibration) -> Self {
        let calls = plan.unet_calls.div_ceil(plan.view_batch.max(1));
        let samples = plan.unet_samples;
        let unet = if samples > 0 {
            samples as f64 / (6 * plan.view_batch.max(1)) as f64 * calibration.unet_call
        } else {
            calls as f64 * calibration.unet_call
        };
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

/// Whether a plan of `unet_calls` view passes is long enough to be worth calibrating.
pub fn worth_calibrating(unet_calls: usize) -> bool {
    unet_calls >= CALIBRATE_FROM_UNET_CALLS
}

/// Times the unit costs of `job` on `model`'s device with `scene` seen from `camera` (at the run's size);
/// `note` receives a line per step (what is being timed, and what it took). On a GPU each unit runs
/// twice and the second is timed: the first compiles the kernels (which the run then finds compiled).
pub fn calibrate(
    job: &EditJob,
    model: &EditModel,
    scene: &GaussianScene,
    camera: &Camera,
    view_batch: usize,
    note: &mut dyn FnMut(&str),
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
    let full = (job.size.0 as usize / f, job.size.1 as usize / f);
    let config = model.unet.config();
    let levels = config.block_out_channels.len().saturating_sub(1) as u32;
    let work = |(w, h): (usize, usize), views: usize| {
        config
            .multiply_adds(6 * views, h, w, 77)
            .map(|m| m as f64)
            .map_err(|e| RunError::Input(e.to_string()))
    };
    let full_work = work(full, view_batch.max(1))?;
    let empty = model.tokenizer.encode("");
    let ids = diffusion::clip::ids_tensor(&[empty], &Device::Cpu)?;
    let context = model
        .encode_text(&ids)?
        .repeat((6, 1, 1))?
        .to_dtype(DType::F32)?;
    let timesteps = Tensor::new(&[499u32], &Device::Cpu)?;
    let sizes = probe_sizes(full, 2usize.pow(levels));
    let (sw, sh) = sizes[0];
    // Within 80 columns with the plan's indent for the sizes runs have.
    note(&format!(
        "UNet, one view, from {sw}×{sh} latents up (≤ {UNET_PROBE_BUDGET_SECS:.0} s), scaled to {}×{} × {}:",
        full.0,
        full.1,
        crate::present::count(view_batch.max(1), "view", "views"),
    ));
    let probe = probe_unet(
        &sizes,
        &|size| work(size, 1).unwrap_or(f64::NAN),
        UNET_PROBE_BUDGET_SECS,
        &mut |(w, h)| {
            let sample =
                Tensor::randn(0f32, 1.0, (6, model.latent_channels(), h, w), &Device::Cpu)?;
            timed(&mut || {
                model.predict(&sample, &timesteps, &context, None)?;
                Ok(())
            })
        },
        note,
    )?;
    let scale = full_work / work(probe.0, 1)?;
    let probe = UnetProbe {
        latent: probe.0,
        seconds: probe.1,
        scale,
    };
    let unet_call = probe.seconds * scale;

    note("timing one render and one lifting round…");
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
        probe,
        render,
        lift,
    })
}

/// Latent sizes to probe, smallest first: `full` halved while both sides stay multiples of `multiple`
/// (the UNet's downsamplings need them) and at least [`MIN_PROBE_SIDE`], then doubled back up to `full`.
fn probe_sizes(full: (usize, usize), multiple: usize) -> Vec<(usize, usize)> {
    let mut sizes = vec![full];
    let halvable =
        |side: usize| side.is_multiple_of(2) && (side / 2).is_multiple_of(multiple.max(1));
    while let Some(&(w, h)) = sizes.last() {
        if !(halvable(w) && halvable(h) && w.min(h) / 2 >= MIN_PROBE_SIDE) {
            break;
        }
        sizes.push((w / 2, h / 2));
    }
    sizes.reverse();
    sizes
}

/// Runs `run` (seconds of one call) on `sizes` in turn, smallest first, while the time spent plus the
/// next probe's expected time (the last one's scaled by `work`) stays within `budget`; returns the
/// largest size timed and its seconds.
fn probe_unet(
    sizes: &[(usize, usize)],
    work: &dyn Fn((usize, usize)) -> f64,
    budget: f64,
    run: &mut dyn FnMut((usize, usize)) -> Result<f64, RunError>,
    note: &mut dyn FnMut(&str),
) -> Result<((usize, usize), f64), RunError> {
    let mut spent = 0.0;
    let mut last: Option<((usize, usize), f64)> = None;
    for &size in sizes {
        if let Some((prev, secs)) = last {
            let expected = secs * work(size) / work(prev);
            if expected.is_nan() || spent + expected > budget {
                note(&format!(
                    "  a probe at {}×{} would take about {}: scaling up the {}×{} one",
                    size.0,
                    size.1,
                    unit_cost(expected),
                    prev.0,
                    prev.1
                ));
                break;
            }
        }
        let secs = run(size)?;
        spent += secs;
        note(&format!(
            "  UNet at {}×{}: {}",
            size.0,
            size.1,
            unit_cost(secs)
        ));
        last = Some((size, secs));
    }
    Ok(last.expect("probe_sizes returns at least the full size"))
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

    fn plan(unet_calls: usize, view_batch: usize) -> PlannedCounts {
        PlannedCounts {
            unet_calls,
            view_batch,
            unet_samples: 0,
            renders: 100,
            fit_steps: 500,
            lifts: 20,
        }
    }

    #[test]
    fn the_estimate_scales_the_unit_costs_by_the_counts() {
        let c = Calibration {
            unet_call: 2.0,
            probe: UnetProbe {
                latent: (8, 8),
                seconds: 0.1,
                scale: 20.0,
            },
            render: 0.1,
            lift: 0.5,
        };
        let e = Estimate::new(&plan(272, 1), c);
        assert_eq!(e.unet, 544.0);
        assert!((e.splatting - ((100.0 + 1500.0) * 0.1 + 10.0)).abs() < 1e-9);
        assert_eq!(e.total, e.unet + e.splatting);
        // A view batch of 8: a call does 8 views' work (272 / 8 = 34 calls).
        assert_eq!(Estimate::new(&plan(272, 8), c).unet, 68.0);
        // Where the plan counts its samples (4 of the 6 a call was timed with, for each of the 272 view
        // passes), the UNet's time follows them.
        let mut counted = plan(272, 1);
        counted.unet_samples = 272 * 4;
        assert!((Estimate::new(&counted, c).unet - 544.0 * 4.0 / 6.0).abs() < 1e-9);
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
    fn probes_start_small_and_stay_multiples_of_the_downsamplings() {
        // SD 1.5 at 512²: 64² latents, multiples of 8.
        assert_eq!(
            probe_sizes((64, 64), 8),
            [(8, 8), (16, 16), (32, 32), (64, 64)]
        );
        // Non-square, and a size whose half is no longer a multiple.
        assert_eq!(probe_sizes((96, 64), 8), [(24, 16), (48, 32), (96, 64)]);
        assert_eq!(probe_sizes((40, 40), 8), [(40, 40)]);
        // Never below the smallest side.
        assert_eq!(probe_sizes((16, 16), 1), [(8, 8), (16, 16)]);
    }

    #[test]
    fn the_unet_probe_stays_within_its_budget_and_never_runs_a_call_too_slow_to_wait_for() {
        // A machine where a call costs its multiply-adds: quadratic in the pixels, 1 s at 8².
        let work = |(w, h): (usize, usize)| {
            let p = (w * h) as f64;
            p + p * p / 64.0
        };
        let secs = |size| work(size) / work((8, 8));
        let sizes = probe_sizes((64, 64), 8);
        let mut ran = Vec::new();
        let mut lines = Vec::new();
        let (size, seconds) = probe_unet(
            &sizes,
            &work,
            UNET_PROBE_BUDGET_SECS,
            &mut |size| {
                ran.push(size);
                Ok(secs(size))
            },
            &mut |line| lines.push(line.to_string()),
        )
        .unwrap();
        // 8² (1 s) and 16² (~10 s) fit the budget; 32² (~130 s) would not, nor the full 64².
        assert_eq!(ran, [(8, 8), (16, 16)]);
        assert_eq!(size, (16, 16));
        let spent: f64 = ran.iter().map(|&s| secs(s)).sum();
        assert!(spent <= UNET_PROBE_BUDGET_SECS);
        // Scaled by the work, the probe gives the full call's time.
        let full = seconds * work((64, 64)) / work(size);
        assert!((full - secs((64, 64))).abs() < 1e-6 * full);
        // Every probe and the one skipped are said.
        assert_eq!(lines.len(), 3, "{lines:?}");
        assert!(lines[2].contains("32×32") && lines[2].contains("scaling up the 16×16"));
        // A fast machine times the run's own size.
        let mut ran = Vec::new();
        probe_unet(
            &sizes,
            &work,
            UNET_PROBE_BUDGET_SECS,
            &mut |size| {
                ran.push(size);
                Ok(secs(size) / 1000.0)
            },
            &mut |_| {},
        )
        .unwrap();
        assert_eq!(ran.last(), Some(&(64, 64)));
    }

    #[test]
    fn short_plans_are_not_calibrated() {
        assert!(!worth_calibrating(CALIBRATE_FROM_UNET_CALLS - 1));
        assert!(worth_calibrating(CALIBRATE_FROM_UNET_CALLS));
    }

    #[test]
    fn durations_read_as_people_say_them() {
        assert_eq!(about(42.0), "42 s");
        assert_eq!(about(600.0), "10 min");
        assert_eq!(about(3.0 * 3600.0), "3.0 h");
        assert_eq!(about(2.5 * 86400.0), "2.5 days");
    }
}
