//! `vcedit edit`: view-consistent editing of a 3DGS scene (VcEdit).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Context};
use edit::consistency::{ConsistencySettings, EcmParams, EcmScope};
use edit::fit::{ImageLoss, TrainSettings};
use edit::run::{run_edit, write_outputs, Box3, EditJob, GuidanceMode, MaskSource, RunInputs};
use edit::sampler::EditModel;
use indicatif::{ProgressBar, ProgressStyle};

use super::edit_opts::{ModelArgs, PromptArgs, SamplerArgs};

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
pub enum GuidanceArg {
    /// All views edited jointly with the consistency modules (VcEdit).
    Joint,
    /// Every view edited on its own (the inconsistent guidance of per-view editors; a baseline).
    PerView,
}

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
pub enum EcmParamsArg {
    /// ECM fits change colours and opacities only (geometry stays; no floaters from few views).
    Appearance,
    /// ECM fits change every attribute, as the reference does.
    All,
}

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
pub enum EcmScopeArg {
    /// ECM fits move only the editable Gaussians.
    Masked,
    /// ECM fits move every Gaussian (what the reference code most likely does).
    All,
}

/// Edit a 3D Gaussian Splatting scene from a source prompt to a target prompt, consistently across views.
#[derive(clap::Args, Debug)]
#[command(after_help = "Examples:
  vcedit edit --scene man/point_cloud.ply --cameras man/sparse/0 --model ./LCM_Dreamshaper_v7 \\
      --source \"a man\" --target \"a clown\" --mask-word man --out clown/
  vcedit edit --scene trained/ --model ./sd15 --taesd ./taesd --source \"a bear\" --target \"a brown bear\" \\
      --max-views 24 --size 256 --iterations 1 --out bear/
  vcedit edit ... --guidance per-view --out baseline/     # the per-view baseline, same settings
  vcedit edit ... --out clown/ --resume                   # continue after an interruption

Outputs in --out: edited.ply, iter_K/guidance/*.png, attention/*.png, mask/*.png, before/ and after/ renders,
turntable.gif, run.json and report.html (open it in a browser).")]
pub struct Args {
    /// Input scene: a 3DGS .ply or an INRIA trainer output folder.
    #[arg(long, value_name = "PLY|DIR")]
    pub scene: PathBuf,
    /// Cameras: COLMAP model, transforms.json or INRIA cameras.json (default: the scene folder's
    /// cameras.json, else --orbit cameras).
    #[arg(long, value_name = "FILE|DIR")]
    pub cameras: Option<PathBuf>,
    /// Generate this many orbit cameras around the scene when it has none.
    #[arg(long, default_value_t = 32, value_name = "N")]
    pub orbit: usize,
    #[command(flatten)]
    pub model: ModelArgs,
    #[command(flatten)]
    pub prompts: PromptArgs,
    /// Output folder.
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    #[command(flatten)]
    pub sampler: SamplerArgs,
    /// At most this many views (a seeded sample of the cameras).
    #[arg(long, default_value_t = 96)]
    pub max_views: usize,
    /// Render → edit → fit iterations.
    #[arg(long, default_value_t = 2)]
    pub iterations: usize,
    /// Fitting steps per iteration (one view per step).
    #[arg(long, default_value_t = 400)]
    pub fit_steps: usize,
    /// How guidance images are made.
    #[arg(long, value_enum, default_value = "joint")]
    pub guidance: GuidanceArg,
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
    #[arg(long, value_delimiter = ',', value_name = "I,J,..")]
    pub ccm_steps: Option<Vec<usize>>,
    /// ECM step indices (default: steps where (i+1) % 5 == 0).
    #[arg(long, value_delimiter = ',', value_name = "I,J,..")]
    pub ecm_steps: Option<Vec<usize>>,
    /// Which Gaussians ECM's fits may move.
    #[arg(long, value_enum, default_value = "masked")]
    pub ecm_scope: EcmScopeArg,
    /// Which attributes ECM's fits may change.
    #[arg(long, value_enum, default_value = "appearance")]
    pub ecm_params: EcmParamsArg,
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
    /// A Gaussian is editable when its lifted mask value exceeds this.
    #[arg(long, default_value_t = 0.5)]
    pub mask_threshold: f32,
    /// LPIPS-VGG weights (vgg16.safetensors + lpips_vgg.safetensors; tools/convert_lpips_weights.py).
    /// Without them the fits use L1 + D-SSIM.
    #[arg(long, value_name = "DIR")]
    pub lpips: Option<PathBuf>,
    /// Background colour of every render, R,G,B in [0, 1] (the reference renders over black).
    #[arg(long, default_value = "0,0,0", value_parser = parse_rgb, allow_hyphen_values = true)]
    pub background: [f32; 3],
    /// Continue an interrupted run in --out.
    #[arg(long)]
    pub resume: bool,
    /// Start even if the memory estimate exceeds the available memory.
    #[arg(long)]
    pub ignore_memory_check: bool,
    /// Stop right after this iteration's checkpoint, as a kill would (tests of --resume).
    #[arg(long, hide = true, value_name = "K")]
    pub stop_after_iteration: Option<usize>,
}

/// Progress bars, one per stage, for the editing pipeline.
pub struct Bars {
    bar: Option<ProgressBar>,
    /// Plain progress lines instead of bars when stderr is not a terminal (logs, CI, `nohup`): indicatif
    /// hides its bars there and would swallow the log lines printed through them.
    plain: Option<PlainProgress>,
}

/// Line-per-update progress for non-terminal stderr, throttled to one line per stage every 30 s.
struct PlainProgress {
    start: Instant,
    stage: String,
    total: u64,
    done: u64,
    last_line: Instant,
}

impl PlainProgress {
    fn line(&mut self) {
        let t = self.start.elapsed().as_secs();
        eprintln!(
            "[{}:{:02}:{:02}] {}: {}/{}",
            t / 3600,
            t / 60 % 60,
            t % 60,
            self.stage,
            self.done,
            self.total
        );
        self.last_line = Instant::now();
    }
}

impl Bars {
    pub fn new() -> Self {
        use std::io::IsTerminal;
        let plain = (!std::io::stderr().is_terminal()).then(|| PlainProgress {
            start: Instant::now(),
            stage: String::new(),
            total: 0,
            done: 0,
            last_line: Instant::now(),
        });
        Self { bar: None, plain }
    }

    /// Clears the last bar.
    pub fn finish(&mut self) {
        if let Some(b) = self.bar.take() {
            b.finish_and_clear();
        }
    }
}

impl edit::run::Progress for Bars {
    fn stage(&mut self, name: &str, total: u64) {
        if let Some(p) = &mut self.plain {
            p.stage = name.to_string();
            p.total = total;
            p.done = 0;
            p.line();
            return;
        }
        if let Some(b) = self.bar.take() {
            b.finish_and_clear();
        }
        let bar = ProgressBar::new(total);
        bar.set_style(
            ProgressStyle::with_template("{prefix:40} [{bar:30}] {pos}/{len} {elapsed}, ETA {eta}")
                .expect("valid template")
                .progress_chars("=> "),
        );
        bar.set_prefix(name.to_string());
        self.bar = Some(bar);
    }

    fn advance(&mut self, n: u64) {
        if let Some(p) = &mut self.plain {
            p.done += n;
            if p.last_line.elapsed().as_secs() >= 30 {
                p.line();
            }
            return;
        }
        if let Some(b) = &self.bar {
            b.inc(n);
        }
    }

    fn log(&mut self, line: &str) {
        match &self.bar {
            Some(b) => b.println(line),
            None => eprintln!("{line}"),
        }
    }
}

/// Parses "R,G,B" with components in [0, 1], or the names black / white.
pub fn parse_rgb(s: &str) -> Result<[f32; 3], String> {
    match s {
        "black" => return Ok([0.0; 3]),
        "white" => return Ok([1.0; 3]),
        _ => {}
    }
    let v: Vec<f32> = s
        .split(',')
        .map(|x| {
            x.trim()
                .parse::<f32>()
                .map_err(|_| format!("'{x}' is not a number"))
        })
        .collect::<Result<_, _>>()?;
    match v.as_slice() {
        [r, g, b] if v.iter().all(|c| (0.0..=1.0).contains(c)) => Ok([*r, *g, *b]),
        _ => Err(format!(
            "expected R,G,B with components in [0, 1] (or black/white), got '{s}'"
        )),
    }
}

pub fn run(args: Args) -> anyhow::Result<()> {
    diffusion::runtime::tune_allocator_for_inference();
    let t0 = Instant::now();
    let infedit = args.sampler.settings()?;
    let (w, h) = args.sampler.size()?;
    if args.iterations == 0 {
        bail!("--iterations must be at least 1");
    }
    if args.max_views == 0 {
        bail!("--max-views must be at least 1");
    }
    if !(0.0..1.0).contains(&args.mask_threshold) {
        bail!("--mask-threshold {} must be in [0, 1)", args.mask_threshold);
    }

    // Inputs.
    let (scene, scene_cams) = splat::open_scene(&args.scene)?;
    let camera_set = match &args.cameras {
        Some(p) => Some(splat::cameras::load_cameras(p)?),
        None => scene_cams,
    };
    let mut cameras: Vec<splat::Camera> = match camera_set {
        Some(set) => set.cameras,
        None => {
            let (lo, hi) =
                splat::cameras::robust_bounds(&scene, 0.01).context("the scene is empty")?;
            eprintln!(
                "no cameras given: using {} orbit cameras around the scene",
                args.orbit
            );
            splat::cameras::orbit_cameras(lo, hi, args.orbit, w, h)
        }
    };
    if cameras.is_empty() {
        bail!("no cameras to edit from");
    }
    cameras = cameras
        .iter()
        .map(|c| splat::cameras::to_working_resolution(c, w, h))
        .collect();

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
            bail!("{name}: step {bad} is past the last step ({})", steps - 1);
        }
    }
    if args.no_ccm {
        consistency.ccm_steps.clear();
    }
    if args.no_ecm {
        consistency.ecm.steps.clear();
    }
    consistency.ecm.scope = match args.ecm_scope {
        EcmScopeArg::Masked => EcmScope::Masked,
        EcmScopeArg::All => EcmScope::All,
    };
    consistency.ecm.params = match args.ecm_params {
        EcmParamsArg::Appearance => EcmParams::Appearance,
        EcmParamsArg::All => EcmParams::All,
    };
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
        guidance: match args.guidance {
            GuidanceArg::Joint => GuidanceMode::Joint,
            GuidanceArg::PerView => GuidanceMode::PerView,
        },
        iterations: args.iterations,
        fit_steps: args.fit_steps,
        max_views: args.max_views,
        seed: args.sampler.seed,
        mask,
        mask_threshold: args.mask_threshold,
        train: TrainSettings::new((args.iterations * args.fit_steps) as u64),
        size: (w, h),
        background: args.background,
        stop_after_iteration: args.stop_after_iteration,
    };

    let model = EditModel::load(&args.model.model, args.model.taesd.as_deref())
        .with_context(|| format!("loading model {}", args.model.model.display()))?;
    let mut notes = Vec::new();
    let loss = match &args.lpips {
        Some(dir) => ImageLoss::lpips(edit::eval::lpips::Lpips::load(dir)?),
        None => {
            let note =
                "no --lpips weights: fitting with 10·L1 + 2.5·D-SSIM instead of 10·L1 + 10·LPIPS"
                    .to_string();
            eprintln!("note: {note}");
            notes.push(note);
            ImageLoss::dssim()
        }
    };

    let plan = edit::run::work_plan(&job, &model, &scene, cameras.len());
    eprintln!("{}", plan.describe());
    let available = edit::run::available_memory();
    if let Some(avail) = available {
        if plan.memory_bytes > avail && !args.ignore_memory_check {
            bail!(
                "this run needs about {:.1} GB but {:.1} GB are available; reduce --max-views or --size, \
                 or pass --ignore-memory-check",
                plan.memory_bytes as f64 / 1e9,
                avail as f64 / 1e9
            );
        }
    }

    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let mut bars = Bars::new();
    let result = run_edit(
        &job,
        &model,
        &loss,
        &scene,
        &cameras,
        &args.out,
        args.resume,
        &mut bars,
    )?;
    let inputs = RunInputs {
        scene: &args.scene.display().to_string(),
        cameras: &args
            .cameras
            .as_ref()
            .map_or("(scene cameras / orbit)".to_string(), |p| {
                p.display().to_string()
            }),
        model: &args.model.model.display().to_string(),
        loss: loss.describe(),
        notes,
    };
    let written = write_outputs(
        &args.out, &job, &inputs, &scene, &cameras, &result, &mut bars,
    )?;
    bars.finish();
    println!("edited scene: {}", written.scene.display());
    println!("report: {}", written.report.display());
    println!("done in {:.1} min", t0.elapsed().as_secs_f64() / 60.0);
    Ok(())
}
