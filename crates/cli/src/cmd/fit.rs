//! `vcedit fit --data DIR --out scene.ply`: train a 3DGS scene from posed images.

use anyhow::{bail, Context, Result};
use splat::cameras::{load_cameras, CameraSet};
use splat::train::scene_fit::{fit_on, load_dataset, DatasetOptions, FitConfig, LOSS_READ_EVERY};
use std::path::{Path, PathBuf};
use std::time::Instant;

use crate::args::memory::MemoryCheckArg;
use crate::args::output::{scene_output, ForceArg};
use crate::args::parse::{positive, whole};
use crate::args::{BackgroundArg, DeviceArg, SizeArg};
use crate::progress::Reporter;

#[derive(clap::Args, Debug)]
#[command(
    about = "Train a 3DGS scene from posed images",
    after_help = "Views come from a COLMAP model (DIR, DIR/sparse/0) or a transforms*.json (nerfstudio/Blender). \
RGBA images are composited on --background (NeRF-synthetic scenes use white). Gaussians start from COLMAP's points3D when present, else from \
random points in the region the cameras look at. Every --holdout-every-th view (0, k, 2k, ...) is held out and \
the PSNR on those views is reported.

Examples:
  vcedit fit --data lego/ --out lego.ply --background white
  vcedit fit --data garden/ --out garden.ply --size 512x336 --steps 15000
  vcedit fit --data garden/ --out garden.ply -r 4"
)]
pub struct Args {
    /// Folder (or file) with the posed images: COLMAP model or transforms*.json.
    #[arg(long, value_name = "DIR")]
    pub data: PathBuf,
    /// Output scene, written atomically; its name chooses the format (*.ply is the INRIA layout; also
    /// *.compressed.ply, *.splat, *.spz, *.sog, DIR/meta.json).
    #[arg(long, value_name = "FILE")]
    pub out: PathBuf,
    #[command(flatten)]
    pub force: ForceArg,
    /// Optimisation steps (one view per step; the INRIA trainer's --iterations). The default fits
    /// NeRF-synthetic scenes at 200x200 to ~31-32 dB in under 10 minutes on 2 cores.
    #[arg(
        long,
        default_value_t = 5000,
        value_parser = positive::<u64>,
        allow_negative_numbers = true
    )]
    pub steps: u64,
    /// The old name of --steps, kept for scripts: in `edit` and `demo` --iterations counts
    /// render → edit → fit rounds, so here it is deprecated and says so.
    #[arg(
        long,
        hide = true,
        value_name = "N",
        conflicts_with = "steps",
        value_parser = positive::<u64>,
        allow_negative_numbers = true
    )]
    pub iterations: Option<u64>,
    #[command(flatten)]
    pub size: SizeArg,
    /// Downscale as the INRIA trainer's -r does: 1, 2, 4 or 8 divide the views' size; any other N
    /// makes them N pixels wide (same aspect ratio). Instead of --size.
    #[arg(
        short = 'r',
        long,
        value_name = "N",
        conflicts_with = "size",
        value_parser = positive::<u32>,
        allow_negative_numbers = true
    )]
    pub resolution: Option<u32>,
    /// Hold out views 0, k, 2k, ... for evaluation; 0 trains on every view.
    #[arg(
        long,
        value_name = "K",
        default_value_t = 5,
        value_parser = whole::<usize>,
        allow_negative_numbers = true
    )]
    pub holdout_every: usize,
    #[command(flatten)]
    pub background: BackgroundArg,
    #[command(flatten)]
    pub device: DeviceArg,
    /// Seed of every random choice (initial points, view order, splits).
    #[arg(long, default_value_t = 0, value_parser = whole::<u64>, allow_negative_numbers = true)]
    pub seed: u64,
    /// Highest SH degree (raised by one every 1000 steps).
    #[arg(
        long,
        default_value_t = 3,
        value_parser = clap::value_parser!(u32).range(0..=3),
        allow_negative_numbers = true
    )]
    pub sh_degree: u32,
    /// Random initial points when the data has no point cloud (or an empty one).
    #[arg(long, default_value_t = 20_000, value_parser = positive::<usize>, allow_negative_numbers = true)]
    pub init_points: usize,
    /// Stop densifying after this step (default: half of --steps, at most 15000).
    #[arg(long, value_name = "STEP", value_parser = whole::<u64>, allow_negative_numbers = true)]
    pub densify_until: Option<u64>,
    /// Evaluate the held-out PSNR every N steps (0 = only at the end).
    #[arg(
        long,
        value_name = "N",
        default_value_t = 1000,
        value_parser = whole::<u64>,
        allow_negative_numbers = true
    )]
    pub eval_every: u64,
    #[command(flatten)]
    pub memory: MemoryCheckArg,
}

/// Peak memory of a fit, roughly: the decoded training images, a full-resolution decode per thread while
/// loading, the renderer's per-pixel buffers (forward, backward, SSIM) and the Gaussians with their
/// gradients and moments, allowing densification to grow them tenfold.
fn fit_memory(set: &CameraSet, size: Option<(u32, u32)>, init_points: usize) -> u64 {
    let pixels = |w: u32, h: u32| w as u64 * h as u64;
    let working: Vec<u64> = set
        .cameras
        .iter()
        .map(|c| size.map_or(pixels(c.width, c.height), |(w, h)| pixels(w, h)))
        .collect();
    let images: u64 = working.iter().map(|p| p * 3 * 4).sum();
    let largest_source = set
        .cameras
        .iter()
        .map(|c| pixels(c.width, c.height))
        .max()
        .unwrap_or(0);
    let threads = rayon::current_num_threads() as u64;
    let decode = largest_source * 4 * 4 * threads;
    let render = working.iter().copied().max().unwrap_or(0) * 4 * 48;
    let points = set
        .points
        .as_ref()
        .map_or(0, |p| p.positions.len())
        .max(init_points) as u64;
    // 59 floats per Gaussian at SH degree 3; parameters, gradients, two moments and spare copies.
    let gaussians = 10 * points * 59 * 4 * 6;
    images + decode + render + gaussians + 300_000_000
}

/// The working size `-r N` gives, as the INRIA trainer computes it: the views' size divided by N for N in
/// 1, 2, 4, 8 (rounded), else N pixels wide at the views' aspect ratio (truncated). The views must share
/// one size, since vcedit fits at one working size.
fn inria_resolution(set: &CameraSet, r: u32) -> Result<(u32, u32)> {
    let Some(first) = set.cameras.first() else {
        bail!("-r/--resolution: the data has no views");
    };
    let (w, h) = (first.width, first.height);
    if let Some(other) = set.cameras.iter().find(|c| (c.width, c.height) != (w, h)) {
        bail!(
            "-r/--resolution needs views of one size, the data has {w}x{h} and {}x{}: give --size WxH instead",
            other.width,
            other.height
        );
    }
    let (w, h) = if matches!(r, 1 | 2 | 4 | 8) {
        let div = |v: u32| (f64::from(v) / f64::from(r)).round() as u32;
        (div(w), div(h))
    } else {
        (r, (f64::from(h) * f64::from(r) / f64::from(w)) as u32)
    };
    if w == 0 || h == 0 || w > 16384 || h > 16384 {
        bail!(
            "-r/--resolution {r} gives {w}x{h} views from {}x{}: each side must be 1 to 16384",
            first.width,
            first.height
        );
    }
    Ok((w, h))
}

/// The fit's progress message: the smoothed loss, the last held-out PSNR with the step it was measured
/// at (evaluations are sparse, so an undated value reads as current), the Gaussian count.
fn progress_message(loss: Option<f32>, psnr: Option<(u64, f64)>, gaussians: usize) -> String {
    let loss = loss.map_or(String::new(), |v| format!("loss {v:.4}"));
    let psnr = psnr.map_or(String::new(), |(step, v)| {
        format!(" held-out PSNR {v:.2} at step {step}")
    });
    format!("{loss}{psnr} N {gaussians}")
}

pub fn run(mut args: Args) -> Result<()> {
    let started = Instant::now();
    if let Some(n) = args.iterations {
        eprintln!(
            "warning: fit --iterations is deprecated: it means --steps here (the INRIA trainer's name), \
             while in edit and demo --iterations counts render → edit → fit rounds; use --steps {n}"
        );
        args.steps = n;
    }
    // Everything is checked before the (long) fit: where it writes, what it reads, whether it fits.
    if splat::OutputFormat::for_path(&args.out).is_none() {
        bail!(
            "--out {}: unknown scene format: name it *.ply, *.compressed.ply, *.splat, *.spz, *.sog or meta.json",
            args.out.display()
        );
    }
    let set = load_cameras(&args.data).context("cannot load the training data")?;
    let mut inputs: Vec<PathBuf> = splat::cameras::camera_sources(&args.data);
    inputs.extend(set.image_paths.iter().flatten().cloned());
    let input_refs: Vec<&Path> = inputs.iter().map(PathBuf::as_path).collect();
    scene_output(&args.out, &input_refs, args.force.force)?;
    let size = match args.resolution {
        Some(r) => Some(inria_resolution(&set, r)?),
        None => args.size.size,
    };
    args.memory.check(
        fit_memory(&set, size, args.init_points),
        "--size or -r (or the number of views)",
    )?;
    let dataset = load_dataset(
        &args.data,
        &DatasetOptions {
            size,
            holdout_every: args.holdout_every,
            background: args.background.background,
        },
    )
    .context("cannot load the training data")?;
    let (w, h) = {
        let c = &dataset.train[0].camera;
        (c.width, c.height)
    };
    eprintln!(
        "{} training and {} held-out views at {w}x{h}{}",
        dataset.train.len(),
        dataset.test.len(),
        // Say what is really used: an empty point cloud falls back to random points.
        match &dataset.points {
            Some(p) if !p.positions.is_empty() =>
                format!(", {} initial points from the data", p.positions.len()),
            Some(_) => format!(
                "; the data's point cloud (points3D) is empty: starting from {} random points",
                args.init_points
            ),
            None => format!(", {} random initial points", args.init_points),
        }
    );
    let mut config = FitConfig {
        background: args.background.background,
        seed: args.seed,
        sh_degree: args.sh_degree,
        init_points: args.init_points,
        eval_every: args.eval_every,
        ..FitConfig::for_steps(args.steps)
    };
    if let Some(until) = args.densify_until {
        config.strategy.refine_stop = until;
    }
    let device = splat::SplatDevice::from(args.device.open_for(gpu::Workload::Splatting)?);
    let mut progress = Reporter::new().on_gpu(!device.is_cpu());
    progress.stage("fitting", args.steps);
    let mut smoothed = None::<f32>;
    let mut last_psnr = None::<(u64, f64)>;
    let result = fit_on(&dataset, &config, &device, &mut |p| {
        // Exponential moving average of the losses read (every step on the CPU, every
        // `LOSS_READ_EVERY`-th on a GPU), as the INRIA trainer shows.
        if let Some(loss) = p.loss {
            smoothed = Some(smoothed.map_or(loss, |s| 0.6 * loss + 0.4 * s));
        }
        if let Some(psnr) = p.test_psnr {
            last_psnr = Some((p.step, psnr));
            progress.log(&format!(
                "step {}: held-out PSNR {psnr:.2} dB, {} Gaussians, {:.0}s",
                p.step,
                p.gaussians,
                started.elapsed().as_secs_f64()
            ));
        }
        // Redrawn on the steps whose loss a GPU fit reads, so the line shows a fresh value.
        if p.step % LOSS_READ_EVERY == 0 || p.step == p.steps {
            progress.set_message(progress_message(smoothed, last_psnr, p.gaussians));
            progress.set_position(p.step);
        }
    })?;
    progress.finish();
    if result.scene.is_empty() {
        bail!(
            "the fit ended with no Gaussians (they were all pruned); nothing written to {}",
            args.out.display()
        );
    }
    // The error names the file already.
    let report = splat::write_scene(&args.out, &result.scene)?;
    if !report.is_lossless() {
        eprintln!("wrote {}: {report}", args.out.display());
    }
    let t = result.seconds;
    eprintln!(
        "time: render {:.0}s, loss {:.0}s, backward {:.0}s, optimiser {:.0}s, densify {:.0}s, eval {:.0}s; total {:.0}s{}",
        t.render,
        t.loss,
        t.backward,
        t.optimise,
        t.densify,
        t.eval,
        started.elapsed().as_secs_f64(),
        if t.device_reads > 0 {
            format!(
                "; {} device reads waited {:.1}s",
                t.device_reads, t.device_wait
            )
        } else {
            String::new()
        }
    );
    match result.test_psnr {
        Some(p) => crate::out!(
            "held-out PSNR {p:.2} dB over {} views (train {:.2} dB), {} Gaussians -> {}",
            dataset.test.len(),
            result.train_psnr,
            result.scene.len(),
            args.out.display()
        ),
        None => crate::out!(
            "train PSNR {:.2} dB, {} Gaussians -> {}",
            result.train_psnr,
            result.scene.len(),
            args.out.display()
        ),
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_progress_line_dates_its_psnr() {
        assert_eq!(
            progress_message(Some(0.01234), Some((200, 24.314)), 900),
            "loss 0.0123 held-out PSNR 24.31 at step 200 N 900"
        );
        assert_eq!(progress_message(None, None, 5), " N 5");
    }
}
