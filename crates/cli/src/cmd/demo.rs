//! `vcedit demo`: edit a procedural scene with the bundled demo model, no downloads.

use std::path::{Path, PathBuf};

use anyhow::Context;

use edit::run::{DeltaDecode, KeepShape};

use demo::run::{
    demo_job, demo_scene, load_model, reference_rows, reference_table, run_variant, summary, table,
    variant_dir, DemoOptions, Variant, PAIRS, SOURCE_SCENE,
};

use crate::args::memory::MemoryCheckArg;
use crate::args::output::{fingerprint, finished_run, say_finished, ForceArg, OutputDir};
use crate::args::parse::{positive, whole};
use crate::args::ComputeArgs;
use crate::progress::Reporter;

/// Run the whole pipeline on a built-in procedural scene with the self-made demo model.
#[derive(clap::Args, Debug)]
#[command(after_help = "Examples:
  vcedit demo              # a red sphere becomes a blue one, in ./vcedit-demo/
  vcedit demo --pair 1     # another built-in edit (see --list)
  vcedit demo --compare    # per-view guidance, no CCM, no ECM, full VcEdit
  vcedit demo --resume     # go on after an interruption (same settings)")]
pub struct Args {
    /// Output folder. A folder holding another run's outputs is refused (see --force).
    #[arg(long, default_value = "vcedit-demo")]
    pub out: PathBuf,
    #[command(flatten)]
    pub force: ForceArg,
    #[command(flatten)]
    pub compute: ComputeArgs,
    /// Which built-in edit to run (0-based; see --list).
    #[arg(long, default_value_t = 0, value_parser = whole::<usize>, allow_negative_numbers = true)]
    pub pair: usize,
    /// List the built-in edits and exit.
    #[arg(long)]
    pub list: bool,
    /// Run per-view guidance, VcEdit without CCM, without ECM and full VcEdit; the table goes to
    /// compare.md and compare.json in --out.
    #[arg(long)]
    pub compare: bool,
    /// Demo model folder (default: the model built into this binary, written once to ~/.cache/vcedit).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Number of views (at least 2).
    #[arg(long, default_value_t = 16, value_parser = positive::<usize>, allow_negative_numbers = true)]
    pub views: usize,
    /// Render → edit → fit iterations.
    #[arg(long, default_value_t = 2, value_parser = positive::<usize>, allow_negative_numbers = true)]
    pub iterations: usize,
    /// Fitting steps per iteration.
    #[arg(long, default_value_t = 300, value_parser = whole::<usize>, allow_negative_numbers = true)]
    pub fit_steps: usize,
    /// LCM steps.
    #[arg(long, default_value_t = 15, value_parser = positive::<usize>, allow_negative_numbers = true)]
    pub steps: usize,
    /// Random seed.
    #[arg(long, default_value_t = 0, value_parser = whole::<u64>, allow_negative_numbers = true)]
    pub seed: u64,
    /// Continue an interrupted demo in --out (same settings): each variant goes on from its last
    /// checkpoint.
    #[arg(long, conflicts_with = "force")]
    pub resume: bool,
    /// Which iterations hand on the source plus the decoded change (as `vcedit edit`).
    #[arg(long, value_enum, default_value = "always")]
    pub delta_decode: DeltaDecode,
    /// When the fits keep the object's geometry (as `vcedit edit`).
    #[arg(long, value_enum, default_value = "auto")]
    pub keep_shape: KeepShape,
    /// UNet level whose cross-attention maps drive the local blend and CCM (as `vcedit edit`);
    /// default: the built-in model's level 1 (its 16×16 maps). For other demo models, e.g. one grown
    /// with `demo-model train --config tools/demo-model/text32.json`.
    #[arg(long, value_name = "LEVEL", value_parser = whole::<usize>, allow_negative_numbers = true)]
    pub blend_level: Option<usize>,
    /// Fewest Adam steps of each ECM fit (as `vcedit edit`; default 576, the reference's 6 epochs ×
    /// 96 views). With few views ECM's fits are most of the time: a lower value is a quicker, rougher
    /// run, e.g. a smoke test of a device.
    #[arg(long, value_name = "N", value_parser = whole::<usize>, allow_negative_numbers = true)]
    pub ecm_min_steps: Option<usize>,
    #[command(flatten)]
    pub memory: MemoryCheckArg,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    if args.list {
        for (i, (s, t, _)) in PAIRS.iter().enumerate() {
            crate::out!("{i}: \"{s}\" → \"{t}\"");
        }
        return Ok(());
    }
    if args.views < 2 {
        crate::usage!("--views {}: the demo needs at least 2 views", args.views);
    }
    if args.pair >= PAIRS.len() {
        crate::usage!(
            "--pair {} does not exist (0..{}; see --list)",
            args.pair,
            PAIRS.len() - 1
        );
    }
    let model_dir = match &args.model {
        Some(dir) => dir.clone(),
        None => crate::embedded::demo_model()?,
    };
    let mut opts = DemoOptions::new(model_dir.clone(), args.out.clone());
    opts.pair = args.pair;
    opts.views = args.views;
    opts.iterations = args.iterations;
    opts.fit_steps = args.fit_steps;
    opts.steps = args.steps;
    opts.seed = args.seed;
    opts.resume = args.resume;
    opts.delta_decode = args.delta_decode;
    opts.keep_shape = args.keep_shape;
    opts.blend_level = args.blend_level;
    opts.ecm_min_steps = args.ecm_min_steps;
    let settings_key = fingerprint(&(
        &model_dir,
        args.pair,
        args.compare,
        opts.views,
        args.iterations,
        args.fit_steps,
        args.steps,
        args.seed,
        args.delta_decode,
        args.keep_shape,
        args.blend_level,
        args.ecm_min_steps,
    ));
    // The model folder is an input: nothing inside it is ever written.
    let inputs = [model_dir.as_path()];
    // The same demo finished in --out: nothing to do.
    let finals: &[&str] = if args.compare {
        &["compare.md", "compare.json"]
    } else {
        &["edited.ply", "report.html", "run.json"]
    };
    if !args.force.force
        && !args.resume
        && finished_run(&args.out, "demo", &settings_key, None, finals, &inputs)?
    {
        say_finished(&args.out);
        if args.compare {
            crate::out!("table: {}", args.out.join("compare.md").display());
        } else {
            say_where(&args.out)?;
        }
        return Ok(());
    }
    let scene = demo_scene(&opts)?;
    // The demo's networks are tiny (a 128² latent UNet of a few MB); its time goes to lifting, renders
    // and ECM's fits, which ran faster on WGSL (docs/gpu-results.md: on an H100 its SPIR-V run took 71 s
    // for the first of two iterations, the H200's WGSL run 57.9 s for both).
    let model = load_model(&model_dir)?;
    let job = demo_job(&opts, &scene, Variant::Full);
    // The level the demo will use (its own, or --blend-level): a --model without cross-attention there
    // is refused here, before any folder is made.
    edit::sampler::EditPlan::check_blend_level(&model, job.infedit.blend_level)
        .context("--blend-level")?;
    let model = model.on(args.compute.open_for(gpu::Workload::Splatting)?);
    eprintln!(
        "demo: \"{}\" → \"{}\", {} Gaussians, {} views at {}², model {}",
        scene.prompts.source,
        scene.prompts.target,
        scene.built.scene.len(),
        opts.views,
        opts.size,
        model_dir.display()
    );
    // The same work plan `vcedit edit` prints (memory, and on a GPU the view batch), for the full variant.
    let plan = edit::run::work_plan(&job, &model, &scene.built.scene, scene.cameras.len());
    eprintln!("{}", plan.describe());
    eprintln!("      {}", job.describe_modules());
    args.memory.check(plan.memory_bytes, "--views")?;
    args.memory
        .check_gpu(plan.gpu_memory_bytes, plan.gpu_free_bytes, "--views")?;
    let out_dir = OutputDir::open(&args.out, "demo", &settings_key, args.force.force, &inputs)?;
    crate::interrupt::resumable_run_in(&args.out);
    let mut progress = Reporter::new().on_gpu(!model.compute.splat().is_cpu());
    if args.compare {
        let mut scores = Vec::new();
        for v in Variant::ALL {
            eprintln!("-- {}", v.name());
            scores.push(run_variant(
                &opts,
                &model,
                &scene,
                v,
                &variant_dir(&args.out, v),
                &mut progress,
            )?);
        }
        progress.finish();
        let references = reference_rows(&opts, &model, &scene)?;
        let md = format!("{}\n{}", table(&scores), reference_table(&references));
        for s in &scores {
            crate::out!("{}", summary(s));
        }
        files::atomic_write(&args.out.join("compare.md"), md.as_bytes())?;
        crate::out!("table: {}", args.out.join("compare.md").display());
        files::atomic_write(
            &args.out.join("compare.json"),
            &serde_json::to_vec_pretty(&serde_json::json!({
                "runs": scores,
                "references": references,
            }))?,
        )?;
        crate::out!("reports: {}", args.out.join("*/report.html").display());
        out_dir.finish();
    } else {
        let s = run_variant(
            &opts,
            &model,
            &scene,
            Variant::Full,
            &args.out,
            &mut progress,
        )?;
        progress.finish();
        super::edit::warn_if_unchanged(s.changed_fraction, "the renders inside the editable mask");
        crate::stdout::write(&summary(&s))?;
        say_where(&args.out)?;
        out_dir.finish();
    }
    Ok(())
}

/// Where a demo's results are, and how to look at the scenes (the command relative to the current
/// folder where it can be, so that it fits a line).
fn say_where(out: &Path) -> anyhow::Result<()> {
    crate::out!("edited scene: {}", out.join("edited.ply").display());
    crate::out!("report: {}", out.join("report.html").display());
    let cwd = std::env::current_dir().unwrap_or_default();
    let short = out.strip_prefix(&cwd).unwrap_or(out);
    crate::out!(
        "compare in 3D: vcedit view {} {}",
        short.join(SOURCE_SCENE).display(),
        short.join("edited.ply").display()
    );
    Ok(())
}
