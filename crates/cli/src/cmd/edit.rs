//! `vcedit edit`: view-consistent editing of a 3DGS scene (VcEdit).

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context};
use edit::consistency::{ConsistencySettings, EcmParams, EcmScope};
use edit::fit::{ImageLoss, TrainSettings};
use edit::run::{
    edit_scene, Box3, DeltaDecode, EditJob, GuidanceMode, KeepShape, MaskSource, RunInputs,
};
use edit::sampler::EditModel;

use crate::args::editing::{ModelArgs, PromptArgs, SamplerArgs};
use crate::args::memory::MemoryCheckArg;
use crate::args::output::{fingerprint, finished_run, open_with_settings, say_finished, ForceArg};
use crate::args::parse::{finite, positive, whole};
use crate::args::{BackgroundArg, CameraArgs, ComputeArgs, DEFAULT_ORBIT_VIEWS};
use crate::progress::Reporter;

/// What a finished run leaves in --out (run.json is written last).
const FINAL_FILES: [&str; 3] = ["edited.ply", "report.html", "run.json"];

/// Edit a 3D Gaussian Splatting scene from a source prompt to a target prompt, consistently across views.
#[derive(clap::Args, Debug)]
#[command(
    mut_arg("max_views", |a| a.default_value("96")),
    after_help = "Cameras come from --cameras, else --orbit, else the scene folder (INRIA output with cameras.json), else an \
orbit of 32 views around the scene; --max-views keeps an evenly spaced subset. Renders are over --background (the \
reference renders over black).

Examples:
  vcedit edit --scene man/point_cloud.ply --cameras man/sparse/0 \\
      --model ./LCM_Dreamshaper_v7 --source \"a man\" --target \"a clown\" \\
      --mask-word man --out clown/
  vcedit edit --scene trained/ --model ./sd15 --taesd ./taesd \\
      --source \"a bear\" --target \"a brown bear\" \\
      --max-views 24 --size 256 --iterations 1 --out bear/
  vcedit edit ... --guidance per-view --out baseline/   # the per-view baseline
  vcedit edit ... --out clown/ --resume                 # continue after a stop

Outputs in --out: edited.ply, iter_K/guidance/*.png, attention/*.png, mask/*.png, before/ and after/ renders,
turntable.gif, run.json and report.html (open it in a browser)."
)]
pub struct Args {
    /// Input scene: a scene file (PLY, compressed PLY, .splat, .spz, SOG) or an INRIA trainer output folder.
    #[arg(long, value_name = "PLY|DIR")]
    pub scene: PathBuf,
    #[command(flatten)]
    pub views: CameraArgs,
    #[command(flatten)]
    pub model: ModelArgs,
    #[command(flatten)]
    pub prompts: PromptArgs,
    /// Output folder. A folder holding another run's outputs is refused (see --force, --resume).
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    #[command(flatten)]
    pub force: ForceArg,
    #[command(flatten)]
    pub compute: ComputeArgs,
    #[command(flatten)]
    pub sampler: SamplerArgs,
    /// Render → edit → fit iterations.
    #[arg(long, default_value_t = 2, value_parser = positive::<usize>, allow_negative_numbers = true)]
    pub iterations: usize,
    /// Fitting steps per iteration (one view per step).
    #[arg(long, default_value_t = 400, value_parser = whole::<usize>, allow_negative_numbers = true)]
    pub fit_steps: usize,
    /// How guidance images are made.
    #[arg(long, value_enum, default_value = "joint")]
    pub guidance: GuidanceMode,
    /// Which iterations hand on the source plus the decoded change instead of the decoded image, so the
    /// autoencoder's blur does not pile up from one iteration to the next.
    #[arg(long, value_enum, default_value = "always")]
    pub delta_decode: DeltaDecode,
    /// When the fits keep the edited region's geometry (positions, sizes, orientations at a tenth of
    /// their rate), so a colour edit does not fray its outline.
    #[arg(long, value_enum, default_value = "auto")]
    pub keep_shape: KeepShape,
    /// Disable the cross-attention consistency module.
    #[arg(long)]
    pub no_ccm: bool,
    /// Disable the editing consistency module.
    #[arg(long)]
    pub no_ecm: bool,
    /// Disable blend-map consistency.
    #[arg(long)]
    pub no_blend_consistency: bool,
    /// CCM step indices (default: steps where (i+1) % 7 == 0).
    #[arg(
        long,
        value_delimiter = ',',
        value_name = "I,J,..",
        value_parser = whole::<usize>,
        allow_hyphen_values = true
    )]
    pub ccm_steps: Option<Vec<usize>>,
    /// ECM step indices (default: steps where (i+1) % 5 == 0).
    #[arg(
        long,
        value_delimiter = ',',
        value_name = "I,J,..",
        value_parser = whole::<usize>,
        allow_hyphen_values = true
    )]
    pub ecm_steps: Option<Vec<usize>>,
    /// Which Gaussians ECM's fits may move.
    #[arg(long, value_enum, default_value = "masked")]
    pub ecm_scope: EcmScope,
    /// Which attributes ECM's fits may change.
    #[arg(long, value_enum, default_value = "appearance")]
    pub ecm_params: EcmParams,
    /// Fewest Adam steps of each ECM fit: its epochs grow to reach them with few views (the reference's
    /// 6 epochs × 96 views).
    #[arg(long, default_value_t = 576, value_parser = whole::<usize>, allow_negative_numbers = true)]
    pub ecm_min_steps: usize,
    /// Views per UNet call (default: 1 on the CPU; on a GPU as many as fit about 6 GB of activations,
    /// at most 8). Batching views keeps a GPU busy; each view's result is the same.
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u16).range(1..=64))]
    pub view_batch: Option<u16>,
    /// Editable region: the source prompt's attention to this word.
    #[arg(long, value_name = "WORD", group = "maskgroup")]
    pub mask_word: Option<String>,
    /// Editable region: Gaussians inside xmin,ymin,zmin,xmax,ymax,zmax.
    #[arg(
        long,
        value_name = "BOX",
        group = "maskgroup",
        allow_hyphen_values = true
    )]
    pub mask_box: Option<Box3>,
    /// Editable region: per-view mask images (<camera name>.png, white = editable).
    #[arg(long, value_name = "DIR", group = "maskgroup")]
    pub mask_dir: Option<PathBuf>,
    /// A Gaussian is editable when its lifted mask value exceeds this (from 0 up to, not including, 1).
    #[arg(long, default_value_t = 0.5, value_parser = finite::<f32>, allow_negative_numbers = true)]
    pub mask_threshold: f32,
    /// LPIPS-VGG weights (vgg16.safetensors + lpips_vgg.safetensors; tools/convert_lpips_weights.py).
    /// Without them the fits use L1 + D-SSIM.
    #[arg(long, value_name = "DIR")]
    pub lpips: Option<PathBuf>,
    #[command(flatten)]
    pub background: BackgroundArg,
    /// Continue an interrupted run in --out (same settings); its files are kept.
    #[arg(long, conflicts_with = "force")]
    pub resume: bool,
    #[command(flatten)]
    pub memory: MemoryCheckArg,
    /// Skip the time estimate of a long run (UNet calls on one view at small sizes, scaled up, one render
    /// and one lifting round, timed before it starts: at most about half a minute; runs of 50 UNet
    /// passes or more, not resumed ones).
    #[arg(long)]
    pub no_estimate: bool,
    /// Stop right after this iteration's checkpoint, as a kill would (tests of --resume).
    #[arg(
        long,
        hide = true,
        value_name = "K",
        value_parser = whole::<usize>,
        allow_negative_numbers = true
    )]
    pub stop_after_iteration: Option<usize>,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let t0 = Instant::now();
    // Every argument is checked before any work; the output folder is opened last, so a refused run
    // leaves nothing behind.
    let infedit = args.sampler.settings()?;
    let (w, h) = args.sampler.size();
    if !(0.0..1.0).contains(&args.mask_threshold) {
        crate::usage!("--mask-threshold {} must be in [0, 1)", args.mask_threshold);
    }
    args.views.validate()?;
    for (option, dir) in [
        ("--mask-dir", &args.mask_dir),
        ("--lpips", &args.lpips),
        ("--taesd", &args.model.taesd),
    ] {
        if let Some(dir) = dir {
            if !dir.is_dir() {
                bail!("{option} {}: no such folder", dir.display());
            }
        }
    }

    // Inputs.
    let (scene, scene_cams) = splat::open_scene(&args.scene)?;
    if let Some(b) = &args.mask_box {
        if !edit::run::mask_from_box(&scene, b).contains(&true) {
            bail!(
                "--mask-box: the box holds none of the scene's {} Gaussians; check its corners",
                scene.len()
            );
        }
    }
    let (cameras, camera_source) =
        args.views
            .choose(&scene, scene_cams, Some((w, h)), DEFAULT_ORBIT_VIEWS)?;
    eprintln!("cameras: {} views from {camera_source}", cameras.len());

    let steps = infedit.steps;
    let mut consistency = ConsistencySettings::reference(steps);
    if let Some(s) = &args.ccm_steps {
        consistency.ccm_steps = s.clone();
    }
    if let Some(s) = &args.ecm_steps {
        consistency.ecm.steps = s.clone();
    }
    for (name, list) in [
        ("--ccm-steps", &consistency.ccm_steps),
        ("--ecm-steps", &consistency.ecm.steps),
    ] {
        if let Some(bad) = list.iter().find(|&&i| i >= steps) {
            crate::usage!("{name}: step {bad} is past the last step ({})", steps - 1);
        }
    }
    if args.no_ccm {
        consistency.ccm_steps.clear();
    }
    if args.no_ecm {
        consistency.ecm.steps.clear();
    }
    consistency.ecm.scope = args.ecm_scope;
    consistency.ecm.params = args.ecm_params;
    consistency.ecm.min_steps = args.ecm_min_steps;
    if args.no_blend_consistency {
        consistency.blend_consistency = false;
    }
    let mask = if let Some(word) = &args.mask_word {
        MaskSource::Word(word.clone())
    } else if let Some(b) = &args.mask_box {
        MaskSource::Box {
            min: b.min,
            max: b.max,
        }
    } else if let Some(d) = &args.mask_dir {
        MaskSource::Dir(d.clone())
    } else {
        MaskSource::None
    };
    let job = EditJob {
        prompts: args.prompts.prompts(),
        infedit,
        consistency,
        guidance: args.guidance,
        delta_decode: args.delta_decode,
        keep_shape: args.keep_shape,
        iterations: args.iterations,
        fit_steps: args.fit_steps,
        max_views: args.views.view_limit(cameras.len()),
        seed: args.sampler.seed,
        mask,
        mask_threshold: args.mask_threshold,
        train: TrainSettings::new((args.iterations * args.fit_steps) as u64),
        size: (w, h),
        background: args.background.background,
        stop_after_iteration: args.stop_after_iteration,
        view_batch: args.view_batch.map(usize::from),
    };

    // One run per folder: the settings that decide the result (a resumed run has the same), and the
    // inputs, which no write or --force may touch.
    let settings_key = fingerprint(&(
        serde_json::to_string(&job)?,
        &args.scene,
        &args.views.cameras,
        &args.model,
        &args.lpips,
    ));
    let mut inputs = splat::formats::scene_sources(&args.scene);
    inputs.extend(
        args.views
            .cameras
            .iter()
            .flat_map(|c| splat::cameras::camera_sources(c)),
    );
    inputs.push(args.model.model.clone());
    let input_refs: Vec<&Path> = inputs.iter().map(PathBuf::as_path).collect();
    let settings = settings_record(&job, &args)?;
    // The same run finished in --out: nothing to do (two days of work are not redone by accident).
    if !args.force.force
        && !args.resume
        && finished_run(
            &args.out,
            "edit",
            &settings_key,
            Some(&settings),
            &FINAL_FILES,
            &input_refs,
        )?
    {
        say_finished(&args.out);
        crate::out!("edited scene: {}", args.out.join("edited.ply").display());
        crate::out!("report: {}", args.out.join("report.html").display());
        return Ok(());
    }

    let model_dir = args.model.folder()?;
    let compute = args.compute.open()?;
    let model = EditModel::load(&model_dir, args.model.taesd.as_deref())
        .with_context(|| format!("loading model {}", model_dir.display()))?
        .on(compute.clone());
    args.sampler.check_model(&model)?;
    args.prompts
        .check_words(&model.tokenizer, args.mask_word.as_deref())?;
    let loss = match &args.lpips {
        // On the device the fit renders on: a fit step then reads the render back once and returns its
        // gradient, where a CPU network would cost seconds per step.
        Some(dir) => {
            ImageLoss::lpips(diffusion::lpips::Lpips::load(dir)?.on(compute.networks().clone()))
        }
        None => {
            // Said here; the report's "fit loss" line says it too (once).
            eprintln!(
                "note: no --lpips weights: fitting with 10·L1 + 2.5·D-SSIM instead of 10·L1 + 10·LPIPS"
            );
            ImageLoss::dssim()
        }
    };

    let mut plan = edit::run::work_plan(&job, &model, &scene, cameras.len());
    if let Some(bytes) = plan.gpu_memory_bytes.as_mut() {
        *bytes += loss.gpu_bytes(job.size, plan.views);
    }
    eprintln!("{}", plan.describe());
    eprintln!("      {}", job.describe_modules());
    eprintln!("      counts: {}", plan.work.describe());
    args.memory
        .check(plan.memory_bytes, "--max-views or --size")?;
    args.memory.check_gpu(
        plan.gpu_memory_bytes,
        plan.gpu_free_bytes,
        "--view-batch, --max-views or --size",
    )?;

    let out_dir = open_with_settings(
        &args.out,
        "edit",
        &settings_key,
        &settings,
        args.force.force,
        &input_refs,
    )?;
    if args.force.force {
        // Redone: until it finishes, the folder must not read as finished.
        let last = args.out.join(FINAL_FILES[2]);
        if files::check_not_inputs(&[last.as_path()], &input_refs).is_ok() {
            let _ = std::fs::remove_file(&last);
        }
    }
    crate::interrupt::resumable_run_in(&args.out);
    if !args.no_estimate && !args.resume && plan.worth_calibrating() {
        // After every check, so a refused run costs nothing; the GPU's kernels compiled here are the run's.
        eprintln!("      estimating the time (--no-estimate skips it):");
        let camera = &cameras[0];
        let calibration =
            edit::run::calibrate(&job, &model, &scene, camera, plan.view_batch, &mut |line| {
                eprintln!("      {line}")
            })
            .context("timing the run's unit costs (--no-estimate skips it)")?;
        let estimate = plan.set_estimate(calibration);
        eprintln!("      {}", estimate.describe());
    }
    let estimate = plan.estimate;
    let mut progress = Reporter::new().on_gpu(!compute.splat().is_cpu());
    let inputs = RunInputs {
        scene: &args.scene.display().to_string(),
        cameras: &camera_source.to_string(),
        model: &model_dir.display().to_string(),
        loss: loss.describe(),
        notes: Vec::new(),
        estimate,
    };
    let (_, written) = edit_scene(
        &job,
        &model,
        &loss,
        &scene,
        &cameras,
        &args.out,
        args.resume,
        &inputs,
        &mut progress,
    )?;
    progress.finish();
    out_dir.finish();
    let region = if written.metrics.preservation_outside_mask.is_some() {
        "the renders inside the editable mask"
    } else {
        "the renders"
    };
    warn_if_unchanged(written.metrics.changed_fraction, region);
    crate::out!("edited scene: {}", written.scene.display());
    crate::out!("report: {}", written.report.display());
    crate::out!("done in {:.1} min", t0.elapsed().as_secs_f64() / 60.0);
    Ok(())
}

/// What decides a run's result, as kept in its folder (`settings.json`): the job and the inputs' paths.
fn settings_record(job: &EditJob, args: &Args) -> anyhow::Result<serde_json::Value> {
    let mut settings = serde_json::to_value(job)?;
    if let Some(map) = settings.as_object_mut() {
        map.insert("scene".into(), args.scene.display().to_string().into());
        let path = |p: &Option<PathBuf>| p.as_ref().map(|p| p.display().to_string());
        map.insert("cameras".into(), path(&args.views.cameras).into());
        map.insert("model".into(), format!("{:?}", args.model).into());
        map.insert("lpips".into(), path(&args.lpips).into());
    }
    Ok(settings)
}

/// Below this fraction of changed pixels (`changed_fraction`) an edit is reported as having changed little.
/// With the first demo model at 128²: an edit with an empty blend region (`--thresh-e 1`) changed 1.4-3.4 %
/// of the pixels against the source's own codec round trip (the source branch drifts a little), a real one
/// 21 % of the image, 100 % of a 3D edit's mask. The current one's reconstruction drifts more (14 %; a real
/// edit 23 %), so `edit-image` names an empty blend region by the region itself.
const UNCHANGED_FRACTION: f64 = 0.05;

/// A warning line when an edit left `what` (the renders where it may act, an image) nearly as they were:
/// an edit that silently does nothing looks like success. `changed`: the changed fraction of the pixels.
pub(crate) fn warn_if_unchanged(changed: Option<f64>, what: &str) {
    if let Some(f) = changed.filter(|&f| f < UNCHANGED_FRACTION) {
        eprintln!(
            "warning: the edit changed little: {:.1} % of the pixels of {what} moved by more than {} \
             (0-1 scale). If the result looks like the source, edit harder: a lower --cross (fewer steps \
             of the source's attention), a lower --thresh-e (a larger blend region), a higher \
             --guidance-scale, or a target prompt further from the source.",
            100.0 * f,
            edit::eval::metrics::CHANGE_TOLERANCE
        );
    }
}
