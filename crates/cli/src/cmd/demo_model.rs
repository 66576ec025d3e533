//! `vcedit demo-model`: train the self-made demo model (`train`) and draw samples from a model (`sample`).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Context};
use demo::sample::{generate, SampleSettings};
use demo::train::{train, Event, TrainConfig, TrainOptions};
use edit::sampler::EditModel;

use crate::args::output::{output_file, require_extension};
use crate::args::parse::{finite, positive, whole};
use crate::progress::Reporter;

/// Train the demo model or sample from a model.
#[derive(clap::Args, Debug)]
pub struct Args {
    #[command(subcommand)]
    pub command: DemoModelCommand,
}

#[derive(clap::Subcommand, Debug)]
pub enum DemoModelCommand {
    /// Train the small SD-architecture demo model on the procedural world (resumable).
    Train(TrainArgs),
    /// Generate images from prompts with a model (DDIM + classifier-free guidance) into a grid PNG.
    Sample(SampleArgs),
}

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
pub enum Preset {
    /// The committed demo model: 128² images, ~3M-parameter UNet (about 1.5 hours on 2 cores).
    Demo,
    /// A minute-scale model for tests (32² images, tiny networks).
    Tiny,
}

#[derive(clap::Args, Debug)]
#[command(after_help = "Examples:
  vcedit demo-model train --out models/demo
  vcedit demo-model train --out /tmp/tiny --preset tiny --unet-steps 50
  vcedit demo-model train --out /tmp/t --init models/demo --unet-steps 900
  vcedit demo-model train --out /tmp/f --config fine.json

Rerunning the same command continues from OUT/checkpoints; --restart discards them.")]
pub struct TrainArgs {
    /// Output folder (diffusers layout; checkpoints go to OUT/checkpoints).
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    #[arg(long, value_enum, default_value = "demo", conflicts_with = "config")]
    pub preset: Preset,
    /// A whole training config as JSON instead of a preset: the fields of the "config" object in a
    /// run's OUT/checkpoints/state.json (architecture, steps, rates). The options below override it.
    #[arg(long, value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// Random seed (world samples, initialisation, batches).
    #[arg(long, value_parser = whole::<u64>, allow_negative_numbers = true)]
    pub seed: Option<u64>,
    /// Number of world samples to render and train on.
    #[arg(long, value_parser = positive::<usize>, allow_negative_numbers = true)]
    pub samples: Option<usize>,
    /// Codec training steps.
    #[arg(long, value_parser = whole::<u64>, allow_negative_numbers = true)]
    pub codec_steps: Option<u64>,
    /// UNet + text encoder training steps.
    #[arg(long, value_parser = whole::<u64>, allow_negative_numbers = true)]
    pub unet_steps: Option<u64>,
    /// Minutes between checkpoints.
    #[arg(long, value_parser = finite::<f64>, allow_negative_numbers = true)]
    pub checkpoint_minutes: Option<f64>,
    /// Discard existing checkpoints and start over.
    #[arg(long)]
    pub restart: bool,
    /// Train further from an exported model of the same architecture (e.g. models/demo): its
    /// autoencoder is kept, its UNet and text encoder are trained for --unet-steps more steps on
    /// newly rendered samples (use another --seed for other samples). The config may add attention
    /// to UNet blocks that had none (unet.cross_attention, unet.only_cross_attention): it starts
    /// out adding nothing and is learnt from there. Only read when OUT has no checkpoints yet.
    #[arg(long, value_name = "DIR")]
    pub init: Option<PathBuf>,
    /// Peak learning rate of the UNet and text encoder (default: the preset's).
    #[arg(long, value_parser = finite::<f64>, allow_negative_numbers = true)]
    pub unet_lr: Option<f64>,
}

#[derive(clap::Args, Debug)]
#[command(after_help = "Examples:
  vcedit demo-model sample --model models/demo \\
      --prompt \"a red sphere\" --prompt \"a blue striped cube\" \\
      --per-prompt 4 --out grid.png")]
pub struct SampleArgs {
    /// Model folder (diffusers layout).
    #[arg(long, value_name = "DIR")]
    pub model: PathBuf,
    /// A prompt (repeat for several); one grid row per prompt.
    #[arg(long = "prompt", required = true)]
    pub prompts: Vec<String>,
    /// Images per prompt (the grid's columns).
    #[arg(long, default_value_t = 4, value_parser = positive::<usize>, allow_negative_numbers = true)]
    pub per_prompt: usize,
    /// DDIM steps.
    #[arg(long, default_value_t = 30, value_parser = positive::<usize>, allow_negative_numbers = true)]
    pub steps: usize,
    /// Classifier-free guidance scale.
    #[arg(long, default_value_t = 4.0, value_parser = finite::<f64>, allow_negative_numbers = true)]
    pub guidance: f64,
    /// DDIM eta (0 = deterministic).
    #[arg(long, default_value_t = 0.0, value_parser = finite::<f64>, allow_negative_numbers = true)]
    pub eta: f64,
    /// Random seed.
    #[arg(long, default_value_t = 0, value_parser = whole::<u64>, allow_negative_numbers = true)]
    pub seed: u64,
    /// Output PNG (the prompts go to the same path with extension .txt).
    #[arg(long, value_name = "FILE")]
    pub out: PathBuf,
    #[command(flatten)]
    pub force: crate::args::output::ForceArg,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    match args.command {
        DemoModelCommand::Train(a) => run_train(a),
        DemoModelCommand::Sample(a) => run_sample(a),
    }
}

/// A training config from a JSON file; a file that does not parse or whose numbers do not fit together is
/// named with the problem.
fn read_config(path: &std::path::Path) -> anyhow::Result<TrainConfig> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("--config {}: cannot read it", path.display()))?;
    let config: TrainConfig = serde_json::from_str(&text)
        .map_err(|e| anyhow::anyhow!("--config {}: not a training config: {e}", path.display()))?;
    config
        .validate()
        .map_err(|e| anyhow::anyhow!("--config {}: {e}", path.display()))?;
    Ok(config)
}

fn run_train(args: TrainArgs) -> anyhow::Result<()> {
    if let Some(m) = args.checkpoint_minutes {
        if m <= 0.0 {
            bail!("--checkpoint-minutes {m} must be positive");
        }
    }
    let mut config = match &args.config {
        Some(path) => read_config(path)?,
        None => match args.preset {
            Preset::Demo => TrainConfig::demo(),
            Preset::Tiny => TrainConfig::tiny(),
        },
    };
    if let Some(v) = args.seed {
        config.seed = v;
    }
    if let Some(v) = args.samples {
        config.samples = v;
    }
    if let Some(v) = args.codec_steps {
        config.codec.steps = v;
    }
    if let Some(v) = args.unet_steps {
        config.unet.steps = v;
    }
    if let Some(v) = args.checkpoint_minutes {
        config.checkpoint_minutes = v;
    }
    if let Some(v) = args.unet_lr {
        if v <= 0.0 {
            bail!("--unet-lr {v} must be positive");
        }
        config.unet.lr = v;
    }
    // Temporary files of a killed training run (the folder is resumable, so its own files stay).
    files::clean_stale_temps(&args.out)?;
    files::clean_stale_temps(&args.out.join("checkpoints"))?;
    if let Some(init) = &args.init {
        if !init.join("unet/config.json").is_file() {
            bail!(
                "--init {}: not an exported model (no unet/config.json)",
                init.display()
            );
        }
    }
    // The exact command, for the model's README (without --restart, so rerunning it resumes).
    let command = std::iter::once("vcedit".to_string())
        .chain(std::env::args().skip(1).filter(|a| a != "--restart"))
        .map(|a| {
            if a.contains(' ') {
                format!("\"{a}\"")
            } else {
                a
            }
        })
        .collect::<Vec<_>>()
        .join(" ");
    crate::out!("{command}");
    // Threading: candle's own CPU thread pool spin-waits at a barrier after every op; on a busy 2-core
    // machine that made training steps 2-3x slower, so candle runs its elementwise ops on the calling
    // thread while rayon (the fused kernels, GEMMs) uses every core. Both read these variables when
    // their pools start, i.e. later than this point; a user's own settings win.
    for (key, value) in [
        ("CANDLE_NUM_THREADS", "1".to_string()),
        ("RAYON_NUM_THREADS", cores()),
    ] {
        if std::env::var_os(key).is_none() {
            std::env::set_var(key, value);
        }
    }
    // Training allocates and frees activations every step; keep them in the heap.

    let mut progress = Reporter::new();
    let started = Instant::now();
    let options = TrainOptions {
        restart: args.restart,
        command: Some(command),
        init: args.init.clone(),
    };
    let summary = train(&args.out, &config, &options, &mut |event| match event {
        Event::Stage { name, total, done } => progress.resume_stage(name, total, done),
        Event::Progress { done, loss } => {
            if let Some(l) = loss {
                progress.set_message(format!("loss {l:.4}"));
            }
            progress.set_position(done);
        }
        Event::Note(text) => progress.log(&text),
    })
    .with_context(|| format!("training into {}", args.out.display()))?;
    progress.finish();
    let s = &summary.state;
    crate::out!(
        "done in {:.1} min: codec {} steps, unet {} steps, scaling_factor {:.5}, weights {:.1} MB -> {}",
        started.elapsed().as_secs_f64() / 60.0,
        s.codec_step,
        s.unet_step,
        s.scaling_factor.unwrap_or(f64::NAN),
        summary.weight_bytes as f64 / 1e6,
        args.out.display()
    );
    Ok(())
}

/// Logical cores (rayon's default), as a string for the environment.
fn cores() -> String {
    std::thread::available_parallelism()
        .map_or(1, |n| n.get())
        .to_string()
}

fn run_sample(args: SampleArgs) -> anyhow::Result<()> {
    if args.eta < 0.0 {
        bail!("--eta {} must not be negative", args.eta);
    }
    // The grid and its prompts file, neither over a file of the model.
    require_extension(&args.out, "--out", &["png"], "the grid")?;
    let txt = args.out.with_extension("txt");
    let inputs = [args.model.as_path()];
    output_file(&args.out, &inputs, args.force.force)?;
    output_file(&txt, &inputs, args.force.force)?;
    let model = EditModel::load(&args.model, None)
        .with_context(|| format!("loading model {}", args.model.display()))?;
    let t0 = Instant::now();
    // Column k of every row shares its starting noise (seed + k), so rows differ only by prompt.
    let mut columns = Vec::with_capacity(args.per_prompt);
    for k in 0..args.per_prompt {
        let settings = SampleSettings {
            steps: args.steps,
            guidance: args.guidance,
            eta: args.eta,
            seed: args.seed.wrapping_add(1000 * k as u64),
            size: None,
        };
        // One batch per column; generate() offsets the seed by the prompt's index, undo that so every
        // row of a column starts from the same noise.
        let mut col = Vec::with_capacity(args.prompts.len());
        for p in &args.prompts {
            let mut images = generate(&model, std::slice::from_ref(p), &settings)
                .with_context(|| format!("sampling \"{p}\""))?;
            col.push(images.remove(0));
        }
        columns.push(col);
    }
    let mut tiles = Vec::with_capacity(args.prompts.len() * args.per_prompt);
    for row in 0..args.prompts.len() {
        for col in &columns {
            tiles.push(col[row].clone());
        }
    }
    let grid = demo::world::dataset::tile_grid(&tiles, args.per_prompt);
    grid.save_png(&args.out)?;
    let mut text = args.prompts.join("\n");
    text.push('\n');
    files::atomic_write(&txt, text.as_bytes())
        .with_context(|| format!("writing {}", txt.display()))?;
    crate::out!(
        "{} images in {:.1} s -> {}",
        tiles.len(),
        t0.elapsed().as_secs_f64(),
        args.out.display()
    );
    Ok(())
}
