//! Training the demo model: a small Stable-Diffusion-architecture model learnt from the procedural world by
//! vcedit's own code (candle autograd on the CPU), saved in diffusers layout so every command loads it like
//! any SD checkpoint (`EditModel::load`, `vcedit model check`, `vcedit edit-image`, ...).
//!
//! # What gets built ([`TrainConfig::demo`])
//!
//! | part | architecture | why |
//! | --- | --- | --- |
//! | tokenizer | CLIP BPE learnt on the caption words ([`crate::bpe`]) | one token per word: one cross-attention map per word |
//! | codec | `AutoencoderKL`, channels 16/32/64, 1 resnet per block, 4 latent channels | 128² images → 32×32×4 latents (4×, SD's is 8×): at 8× one latent pixel spanned the vase's stripes and the mushroom's stem (docs/demo-model.md); the narrow high-resolution stages keep training affordable |
//! | text encoder | `CLIPTextModel`, hidden 64, 2 layers, 4 heads, 77 positions | the demo grammar needs little capacity; 77 positions because the edit pipeline pads to SD's length |
//! | UNet | `UNet2DConditionModel`, channels 16/32/64/128, cross-attention at 16×16 and 8×8 (+ mid block), 4 heads | ~3M parameters: trainable in about two hours here; a narrow first level at 32² without attention; two cross-attention resolutions for the local blend and CCM |
//! | scheduler | `LCMScheduler` config over scaled-linear betas 0.00335 → 0.0107, 1000 steps (SD's 0.00085 → 0.012 shifted for 32² latents; `unet.beta_start`/`beta_end` in a `--config` change them) | the editor's 15-step LCM schedule runs on it; DDIM reads the same betas |
//!
//! The UNet is an ordinary ε-prediction model (no LCM distillation): InfEdit only needs ε and the x₀ it
//! implies at each of its steps.
//!
//! # Stages (all resumable)
//!
//! 1. **Tokenizer** written to `OUT/tokenizer` (deterministic, instant).
//! 2. **Render** `samples` world views once into memory (8-bit RGB; ~17 ms per 128² view).
//! 3. **Codec** ([`codec`]): AdamW on random 64² crops, L1 + edge + tiny KL loss; the EMA weights are exported
//!    to `OUT/vae` with `scaling_factor` = 1/std of the posterior samples (SD's recipe).
//! 4. **Encode** every sample with the codec (posterior mean and std cached in the checkpoint folder).
//! 5. **Denoiser** ([`denoiser`]): text encoder + UNet jointly, ε-prediction, min-SNR-5 weighting,
//!    stratified timesteps, 10 % empty captions; the EMA weights go to `OUT/unet` and `OUT/text_encoder`.
//!
//! Randomness is a pure function of (seed, stage, step) (see [`step_rng`]), so a run resumed from a checkpoint
//! draws exactly the batches it would have drawn. Checkpoints (`OUT/checkpoints/`: weights, AdamW moments,
//! EMA weights, `state.json` with the step) are written every `checkpoint_minutes` and at the end of each
//! stage; rerunning the same command continues from them. Parallel reductions make runs agree to float
//! rounding, not bit for bit.
//!
//! Training speed came from the diffusion crate's kernels: fused conv/norm/softmax/GEGLU with backward passes
//! (candle's composite ops were 10-40× slower on these shapes).

pub mod codec;
pub mod config;
pub mod data;
pub mod denoiser;
pub mod optim;

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use diffusion::tokenizer::ClipTokenizer;
use diffusion::vae::AutoencoderKL;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

pub use config::{CodecConfig, TextConfig, TrainConfig, UnetConfig};
use data::RenderedSet;
use denoiser::LatentSet;
use optim::{learning_rate, AdamSettings, AdamW, Ema};

#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    #[error("{}: {source}", .path.display())]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{}: {msg}", .path.display())]
    File { path: PathBuf, msg: String },
    #[error("invalid training config: {0}")]
    Config(String),
    #[error(
        "{}: the checkpoints there come from a different training config; pass --restart to discard \
         them or use another output folder",
        .0.display()
    )]
    Incompatible(PathBuf),
    #[error(transparent)]
    Tokenizer(#[from] diffusion::tokenizer::TokenizerError),
    #[error(transparent)]
    Bpe(#[from] crate::bpe::BpeError),
    #[error("{0}")]
    Candle(#[from] candle_core::Error),
    #[error("training diverged at {stage} step {step}: loss {loss}")]
    Diverged {
        stage: &'static str,
        step: u64,
        loss: f64,
    },
}

/// What the trainer reports while it works.
#[derive(Clone, Debug)]
pub enum Event {
    /// A stage with `total` units of work begins, `done` of them already finished (when resuming).
    Stage {
        name: &'static str,
        total: u64,
        done: u64,
    },
    /// Work units finished so far in the current stage, with the running loss when there is one.
    Progress { done: u64, loss: Option<f64> },
    /// A one-line message (checkpoint written, numbers measured, ...).
    Note(String),
}

/// Progress of a run, persisted as `checkpoints/state.json`.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct TrainState {
    pub config: TrainConfig,
    pub codec_step: u64,
    /// Set once the codec was exported; the codec step it was exported at.
    pub codec_exported_at: Option<u64>,
    pub scaling_factor: Option<f64>,
    /// Codec step the cached latents were encoded with.
    pub latents_from_codec_step: Option<u64>,
    pub unet_step: u64,
    pub unet_exported_at: Option<u64>,
    /// Mean losses over windows of steps: (stage, last step of the window, loss).
    pub loss_history: Vec<(String, u64, f64)>,
    /// Wall-clock seconds spent per stage (summed over resumed runs).
    pub seconds: HashMap<String, f64>,
    /// The model folder this run started from (`--init`): its codec was taken as it is and its UNet and
    /// text encoder were trained further.
    #[serde(default)]
    pub init_from: Option<PathBuf>,
}

/// A summary of a finished run.
#[derive(Clone, Debug)]
pub struct TrainSummary {
    pub state: TrainState,
    pub weight_bytes: u64,
}

const CODEC_TAG: u64 = 0xc0dec;
const UNET_TAG: u64 = 0x0e7;
const HISTORY_WINDOW: u64 = 100;

/// The random generator of step `step` of stage `tag` (see the module docs).
pub fn step_rng(seed: u64, tag: u64, step: u64) -> ChaCha8Rng {
    let mix = |mut z: u64| {
        z = z.wrapping_add(0x9e37_79b9_7f4a_7c15);
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    };
    ChaCha8Rng::seed_from_u64(mix(seed ^ mix(tag ^ mix(step))))
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> TrainError + '_ {
    move |source| TrainError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// Saves named tensors as safetensors atomically (temporary file, then rename).
fn save_tensors(tensors: &HashMap<String, Tensor>, path: &Path) -> Result<(), TrainError> {
    let tmp = path.with_extension("safetensors.tmp");
    candle_core::safetensors::save(tensors, &tmp)?;
    std::fs::rename(&tmp, path).map_err(io_err(path))
}

fn load_tensors(path: &Path) -> Result<HashMap<String, Tensor>, TrainError> {
    candle_core::safetensors::load(path, &Device::Cpu).map_err(|e| TrainError::File {
        path: path.to_path_buf(),
        msg: e.to_string(),
    })
}

fn write_json(path: &Path, value: &impl Serialize) -> Result<(), TrainError> {
    let mut text = serde_json::to_string_pretty(value).expect("serialisable");
    text.push('\n');
    files::atomic_write(path, text.as_bytes()).map_err(io_err(path))
}

/// A trainable model's weights, optimiser and EMA, checkpointed together.
struct Trainable {
    varmap: candle_nn::VarMap,
    optimizer: AdamW,
    ema: Ema,
}

impl Trainable {
    fn new(varmap: candle_nn::VarMap, ema_decay: f64) -> Result<Self, TrainError> {
        let optimizer = AdamW::new(&varmap, AdamSettings::default())?;
        let ema = Ema::new(&varmap, ema_decay)?;
        Ok(Self {
            varmap,
            optimizer,
            ema,
        })
    }

    fn save(&self, path: &Path) -> Result<(), TrainError> {
        let mut all: HashMap<String, Tensor> = optim::named_vars(&self.varmap)
            .into_iter()
            .map(|(k, v)| (format!("param.{k}"), v.as_tensor().clone()))
            .collect();
        all.extend(self.optimizer.state());
        all.extend(self.ema.state());
        save_tensors(&all, path)
    }

    fn load(&mut self, path: &Path, steps: u64) -> Result<(), TrainError> {
        let all = load_tensors(path)?;
        let bad = |msg: String| TrainError::File {
            path: path.to_path_buf(),
            msg,
        };
        for (name, var) in optim::named_vars(&self.varmap) {
            let t = all
                .get(&format!("param.{name}"))
                .ok_or_else(|| bad(format!("missing parameter {name}")))?;
            var.set(t).map_err(|e| bad(format!("{name}: {e}")))?;
        }
        self.optimizer
            .load_state(&all, steps)
            .map_err(|e| bad(e.to_string()))?;
        self.ema.load_state(&all).map_err(|e| bad(e.to_string()))
    }

    /// One optimiser step on `loss`; returns the gradient norm.
    fn step(&mut self, loss: &Tensor, lr: f64) -> Result<f64, TrainError> {
        let grads = loss.backward()?;
        let norm = self.optimizer.step(&grads, lr)?;
        self.ema.update(self.optimizer.steps)?;
        Ok(norm)
    }
}

/// The paths of a run.
struct Layout {
    out: PathBuf,
    checkpoints: PathBuf,
}

impl Layout {
    fn new(out: &Path) -> Self {
        Self {
            out: out.to_path_buf(),
            checkpoints: out.join("checkpoints"),
        }
    }
    fn state(&self) -> PathBuf {
        self.checkpoints.join("state.json")
    }
    fn codec(&self) -> PathBuf {
        self.checkpoints.join("codec.safetensors")
    }
    fn denoiser(&self) -> PathBuf {
        self.checkpoints.join("denoiser.safetensors")
    }
    fn latents(&self) -> PathBuf {
        self.checkpoints.join("latents.safetensors")
    }
}

/// Options of [`train`] besides the config.
#[derive(Clone, Debug, Default)]
pub struct TrainOptions {
    /// Discard existing checkpoints instead of continuing them.
    pub restart: bool,
    /// The command line that started the run (written into the model's README).
    pub command: Option<String>,
    /// Start from this exported model (diffusers layout, same architecture) instead of from scratch:
    /// its autoencoder is kept as it is (so the latent space stays the one its UNet learnt) and its
    /// UNet and text encoder are trained further for `unet.steps` steps on freshly rendered samples.
    /// Ignored when `OUT/checkpoints` already holds a run, which then continues.
    pub init: Option<PathBuf>,
}

/// Trains (or continues training) the demo model into `out`. See the module docs.
pub fn train(
    out: &Path,
    config: &TrainConfig,
    options: &TrainOptions,
    events: &mut dyn FnMut(Event),
) -> Result<TrainSummary, TrainError> {
    config.validate().map_err(TrainError::Config)?;
    let paths = Layout::new(out);
    if options.restart && paths.checkpoints.exists() {
        std::fs::remove_dir_all(&paths.checkpoints).map_err(io_err(&paths.checkpoints))?;
    }
    std::fs::create_dir_all(&paths.checkpoints).map_err(io_err(&paths.checkpoints))?;
    // Checkpoints are large and local: keep them out of version control wherever OUT lives.
    let ignore = paths.checkpoints.join(".gitignore");
    files::atomic_write(&ignore, b"*\n").map_err(io_err(&ignore))?;

    let mut state = match std::fs::read_to_string(paths.state()) {
        Ok(text) => {
            let saved: TrainState = serde_json::from_str(&text).map_err(|e| TrainError::File {
                path: paths.state(),
                msg: e.to_string(),
            })?;
            if !saved.config.compatible_with(config) {
                return Err(TrainError::Incompatible(paths.checkpoints.clone()));
            }
            events(Event::Note(format!(
                "resuming from {} (codec step {}, unet step {})",
                paths.checkpoints.display(),
                saved.codec_step,
                saved.unet_step
            )));
            TrainState {
                config: config.clone(),
                ..saved
            }
        }
        Err(_) => TrainState {
            config: config.clone(),
            codec_step: 0,
            codec_exported_at: None,
            scaling_factor: None,
            latents_from_codec_step: None,
            unet_step: 0,
            unet_exported_at: None,
            loss_history: Vec::new(),
            seconds: HashMap::new(),
            init_from: None,
        },
    };
    if let (Some(init), 0, 0) = (&options.init, state.codec_step, state.unet_step) {
        adopt_codec(init, out, config, &mut state, events)?;
        save_state(&paths, &state)?;
    }

    let bpe = crate::bpe::demo_bpe();
    let tokenizer_dir = out.join("tokenizer");
    bpe.write_tokenizer(&tokenizer_dir, config.text.max_positions)?;
    let tokenizer =
        ClipTokenizer::from_dir(&tokenizer_dir)?.with_max_length(config.text.max_positions);

    let mut rendered: Option<RenderedSet> = None;
    let render = |events: &mut dyn FnMut(Event)| -> RenderedSet {
        events(Event::Stage {
            name: "render",
            total: config.samples as u64,
            done: 0,
        });
        RenderedSet::render(
            &config.dataset(),
            config.seed,
            config.samples,
            &mut |done| {
                events(Event::Progress {
                    done: done as u64,
                    loss: None,
                })
            },
        )
    };

    let codec_current = state.codec_exported_at == Some(config.codec.steps)
        && out.join("vae/config.json").is_file();
    if !codec_current {
        let data = rendered.get_or_insert_with(|| render(events));
        train_codec(&paths, config, &mut state, data, events)?;
    }

    let latents_current =
        state.latents_from_codec_step == Some(config.codec.steps) && paths.latents().is_file();
    let latents = if latents_current {
        load_latents(&paths, &state, &tokenizer)?
    } else {
        let data = rendered.get_or_insert_with(|| render(events));
        encode_latents(&paths, config, &mut state, data, &tokenizer, events)?
    };
    drop(rendered);

    if state.unet_exported_at != Some(config.unet.steps) || !out.join("unet/config.json").is_file()
    {
        train_denoiser(
            &paths,
            config,
            &mut state,
            &latents,
            bpe.vocab_size(),
            events,
        )?;
        write_json(
            &out.join("scheduler/scheduler_config.json"),
            &config.scheduler_config_json(),
        )?;
        write_json(
            &out.join("model_index.json"),
            &TrainConfig::model_index_json(),
        )?;
    }
    let weight_bytes = weight_bytes(out);
    write_readme(out, &state, options.command.as_deref(), weight_bytes)?;
    Ok(TrainSummary {
        state,
        weight_bytes,
    })
}

fn save_state(paths: &Layout, state: &TrainState) -> Result<(), TrainError> {
    write_json(&paths.state(), state)
}

/// Keeps a running loss and the stage's share of the history.
struct LossWindow {
    sum: f64,
    count: u64,
}

impl LossWindow {
    fn push(&mut self, state: &mut TrainState, stage: &str, step: u64, loss: f64) {
        self.sum += loss;
        self.count += 1;
        if step.is_multiple_of(HISTORY_WINDOW) {
            state
                .loss_history
                .push((stage.to_string(), step, self.sum / self.count as f64));
            self.sum = 0.0;
            self.count = 0;
        }
    }
}

fn train_codec(
    paths: &Layout,
    config: &TrainConfig,
    state: &mut TrainState,
    data: &RenderedSet,
    events: &mut dyn FnMut(Event),
) -> Result<(), TrainError> {
    let c = &config.codec;
    let trainer = codec::CodecTrainer::new(config)?;
    let mut trainable = Trainable::new(trainer.varmap.clone(), c.ema_decay)?;
    if state.codec_step > 0 {
        trainable.load(&paths.codec(), state.codec_step)?;
    }
    let stage = Stage {
        name: "codec",
        tag: CODEC_TAG,
        steps: c.steps,
        warmup: c.warmup,
        lr: c.lr,
        checkpoint: paths.codec(),
        state_file: paths.state(),
    };
    run_stage(
        &stage,
        config,
        state,
        |s| &mut s.codec_step,
        &mut trainable,
        &mut |rng| {
            let (loss, parts) = trainer.loss(config, data, rng)?;
            Ok((loss, parts.total, parts.l1))
        },
        events,
    )?;

    // Export the EMA weights with the measured scaling factor.
    let weights = trainable.ema.weights();
    let vb = VarBuilder::from_tensors(weights.clone(), DType::F32, &Device::Cpu);
    let model = AutoencoderKL::new(&codec::vae_config(config, 1.0), vb)?;
    let mut rng = step_rng(config.seed, CODEC_TAG, u64::MAX);
    let scaling = codec::measure_scaling_factor(&model, data, 1024, &mut rng)?;
    events(Event::Note(format!("codec scaling_factor {scaling:.5}")));
    let dir = paths.out.join("vae");
    std::fs::create_dir_all(&dir).map_err(io_err(&dir))?;
    save_tensors(&weights, &dir.join("diffusion_pytorch_model.safetensors"))?;
    write_json(&dir.join("config.json"), &config.vae_config_json(scaling))?;
    state.scaling_factor = Some(scaling);
    state.codec_exported_at = Some(state.codec_step);
    save_state(paths, state)
}

/// One training stage's fixed numbers.
struct Stage {
    name: &'static str,
    /// Separates the stages' random streams.
    tag: u64,
    steps: u64,
    warmup: u64,
    lr: f64,
    /// The stage's weights + optimiser checkpoint, and the run's state file.
    checkpoint: PathBuf,
    state_file: PathBuf,
}

/// One training step's loss: (loss to minimise, its value, the value to log).
type StepLoss<'a> = dyn FnMut(&mut ChaCha8Rng) -> Result<(Tensor, f64, f64), TrainError> + 'a;

/// The loop both stages share: seeded per-step batches, warm-up + cosine rate, divergence check, loss
/// history and progress, periodic checkpoints, and a final save. `counter` picks the stage's step in the
/// state; `loss` returns (loss to minimise, its value, the value to log).
fn run_stage(
    stage: &Stage,
    config: &TrainConfig,
    state: &mut TrainState,
    counter: fn(&mut TrainState) -> &mut u64,
    trainable: &mut Trainable,
    loss: &mut StepLoss,
    events: &mut dyn FnMut(Event),
) -> Result<(), TrainError> {
    events(Event::Stage {
        name: stage.name,
        total: stage.steps,
        done: (*counter(state)).min(stage.steps),
    });
    let started = Instant::now();
    let mut last_checkpoint = Instant::now();
    let mut window = LossWindow { sum: 0.0, count: 0 };
    let mut running: Option<f64> = None;
    while *counter(state) < stage.steps {
        let step = *counter(state);
        let mut rng = step_rng(config.seed, stage.tag, step);
        let (value, total, logged) = loss(&mut rng)?;
        if !total.is_finite() {
            return Err(TrainError::Diverged {
                stage: stage.name,
                step,
                loss: total,
            });
        }
        let lr = learning_rate(step, stage.steps, stage.warmup, stage.lr, 0.1);
        trainable.step(&value, lr)?;
        *counter(state) += 1;
        let done = *counter(state);
        window.push(state, stage.name, done, logged);
        let r = running.map_or(logged, |r| 0.98 * r + 0.02 * logged);
        running = Some(r);
        events(Event::Progress {
            done,
            loss: Some(r),
        });
        if last_checkpoint.elapsed().as_secs_f64() > 60.0 * config.checkpoint_minutes {
            add_seconds(state, stage.name, &mut last_checkpoint, started);
            trainable.save(&stage.checkpoint)?;
            write_json(&stage.state_file, state)?;
            events(Event::Note(format!(
                "checkpoint at {} step {done}",
                stage.name
            )));
        }
    }
    add_seconds(state, stage.name, &mut last_checkpoint, started);
    trainable.save(&stage.checkpoint)
}

fn add_seconds(state: &mut TrainState, stage: &str, since: &mut Instant, _started: Instant) {
    *state.seconds.entry(stage.to_string()).or_default() += since.elapsed().as_secs_f64();
    *since = Instant::now();
}

/// Token ids of every caption and of the empty prompt.
fn caption_ids(
    captions: &[String],
    tokenizer: &ClipTokenizer,
) -> Result<(Tensor, Tensor), TrainError> {
    let dev = Device::Cpu;
    let mut flat = Vec::new();
    for c in captions {
        let enc = tokenizer.encode_strict(c)?;
        flat.extend(enc.ids);
    }
    let len = tokenizer.max_length();
    let ids = Tensor::from_vec(flat, (captions.len(), len), &dev)?;
    let empty = Tensor::new(tokenizer.encode("").ids, &dev)?;
    Ok((ids, empty))
}

fn encode_latents(
    paths: &Layout,
    config: &TrainConfig,
    state: &mut TrainState,
    data: &RenderedSet,
    tokenizer: &ClipTokenizer,
    events: &mut dyn FnMut(Event),
) -> Result<LatentSet, TrainError> {
    let vae = AutoencoderKL::load(&paths.out.join("vae")).map_err(|e| TrainError::File {
        path: paths.out.join("vae"),
        msg: e.to_string(),
    })?;
    events(Event::Stage {
        name: "encode",
        total: data.len() as u64,
        done: 0,
    });
    let (mean, std) = codec::encode_all(&vae, data, &mut |done| {
        events(Event::Progress {
            done: done as u64,
            loss: None,
        })
    })?;
    let captions = serde_json::to_string(&data.captions).expect("json");
    let caption_path = paths.checkpoints.join("captions.json");
    files::atomic_write(&caption_path, captions.as_bytes()).map_err(io_err(&caption_path))?;
    let tensors = HashMap::from([
        ("mean".to_string(), mean.clone()),
        ("std".to_string(), std.clone()),
    ]);
    save_tensors(&tensors, &paths.latents())?;
    state.latents_from_codec_step = Some(config.codec.steps);
    save_state(paths, state)?;
    let (ids, empty_ids) = caption_ids(&data.captions, tokenizer)?;
    Ok(LatentSet {
        mean,
        std,
        ids,
        empty_ids,
        scaling_factor: state.scaling_factor.unwrap_or(1.0),
    })
}

fn load_latents(
    paths: &Layout,
    state: &TrainState,
    tokenizer: &ClipTokenizer,
) -> Result<LatentSet, TrainError> {
    let mut tensors = load_tensors(&paths.latents())?;
    let caption_path = paths.checkpoints.join("captions.json");
    let text = std::fs::read_to_string(&caption_path).map_err(io_err(&caption_path))?;
    let captions: Vec<String> = serde_json::from_str(&text).map_err(|e| TrainError::File {
        path: caption_path.clone(),
        msg: e.to_string(),
    })?;
    let missing = |what: &str| TrainError::File {
        path: paths.latents(),
        msg: format!("missing tensor {what}"),
    };
    let mean = tensors.remove("mean").ok_or_else(|| missing("mean"))?;
    let std = tensors.remove("std").ok_or_else(|| missing("std"))?;
    if mean.dim(0)? != captions.len() {
        return Err(TrainError::File {
            path: caption_path,
            msg: format!("{} captions for {} latents", captions.len(), mean.dim(0)?),
        });
    }
    let (ids, empty_ids) = caption_ids(&captions, tokenizer)?;
    Ok(LatentSet {
        mean,
        std,
        ids,
        empty_ids,
        scaling_factor: state.scaling_factor.unwrap_or(1.0),
    })
}

fn train_denoiser(
    paths: &Layout,
    config: &TrainConfig,
    state: &mut TrainState,
    latents: &LatentSet,
    vocab_size: usize,
    events: &mut dyn FnMut(Event),
) -> Result<(), TrainError> {
    let u = &config.unet;
    let trainer = denoiser::DenoiserTrainer::new(config, vocab_size)?;
    if let (Some(init), 0) = (&state.init_from, state.unet_step) {
        // Before the optimiser and EMA are made, so the EMA starts from these weights too.
        let added = load_denoiser_weights(init, config, &trainer.varmap)?;
        let grown = if added > 0 {
            format!(" ({added} tensors of added attention start as identity)")
        } else {
            String::new()
        };
        events(Event::Note(format!(
            "UNet and text encoder start from {}{grown}",
            init.display()
        )));
    }
    let mut trainable = Trainable::new(trainer.varmap.clone(), u.ema_decay)?;
    if state.unet_step > 0 {
        trainable.load(&paths.denoiser(), state.unet_step)?;
    }
    let stage = Stage {
        name: "unet",
        tag: UNET_TAG,
        steps: u.steps,
        warmup: u.warmup,
        lr: u.lr,
        checkpoint: paths.denoiser(),
        state_file: paths.state(),
    };
    run_stage(
        &stage,
        config,
        state,
        |s| &mut s.unet_step,
        &mut trainable,
        &mut |rng| {
            let (loss, parts) = trainer.loss(config, latents, rng)?;
            Ok((loss, parts.total, parts.mse))
        },
        events,
    )?;

    // Export the EMA weights: the UNet as diffusers names it, the text encoder with transformers 4's
    // `text_model.` prefix (what SD checkpoints on the hub carry; both loaders accept it).
    let mut unet = HashMap::new();
    let mut text = HashMap::new();
    for (name, t) in trainable.ema.weights() {
        if let Some(rest) = name.strip_prefix("unet.") {
            unet.insert(rest.to_string(), t);
        } else if let Some(rest) = name.strip_prefix("text_encoder.") {
            text.insert(format!("text_model.{rest}"), t);
        }
    }
    let unet_dir = paths.out.join("unet");
    let text_dir = paths.out.join("text_encoder");
    for dir in [&unet_dir, &text_dir] {
        std::fs::create_dir_all(dir).map_err(io_err(dir))?;
    }
    save_tensors(&unet, &unet_dir.join("diffusion_pytorch_model.safetensors"))?;
    write_json(&unet_dir.join("config.json"), &config.unet_config_json())?;
    save_tensors(&text, &text_dir.join("model.safetensors"))?;
    write_json(
        &text_dir.join("config.json"),
        &config.text_config_json(vocab_size),
    )?;
    state.unet_exported_at = Some(state.unet_step);
    save_state(paths, state)
}

/// `--init`: takes the autoencoder of the model in `init` as this run's, exported at the configured codec
/// step so the codec stage is skipped (the UNet to be trained further learnt that codec's latents).
fn adopt_codec(
    init: &Path,
    out: &Path,
    config: &TrainConfig,
    state: &mut TrainState,
    events: &mut dyn FnMut(Event),
) -> Result<(), TrainError> {
    let src = init.join("vae");
    let config_path = src.join("config.json");
    let text = std::fs::read_to_string(&config_path).map_err(io_err(&config_path))?;
    let bad = |msg: String| TrainError::File {
        path: config_path.clone(),
        msg,
    };
    let json: serde_json::Value = serde_json::from_str(&text).map_err(|e| bad(e.to_string()))?;
    let scaling = json
        .get("scaling_factor")
        .and_then(serde_json::Value::as_f64)
        .filter(|s| s.is_finite() && *s > 0.0)
        .ok_or_else(|| bad("no positive scaling_factor".into()))?;
    // The codec must be the one this config would have trained: same architecture, same weights' shapes.
    let weights_path = src.join("diffusion_pytorch_model.safetensors");
    let weights = load_tensors(&weights_path)?;
    let expected = codec::CodecTrainer::new(config)?;
    check_weights(
        &weights_path,
        &weights,
        &optim::named_vars(&expected.varmap),
        "",
        |_| false,
    )?;
    let dst = out.join("vae");
    if dst != src {
        std::fs::create_dir_all(&dst).map_err(io_err(&dst))?;
        save_tensors(&weights, &dst.join("diffusion_pytorch_model.safetensors"))?;
        write_json(&dst.join("config.json"), &config.vae_config_json(scaling))?;
    }
    events(Event::Note(format!(
        "codec taken from {} (scaling_factor {scaling:.5})",
        src.display()
    )));
    state.codec_step = config.codec.steps;
    state.codec_exported_at = Some(config.codec.steps);
    state.scaling_factor = Some(scaling);
    state.init_from = Some(init.to_path_buf());
    Ok(())
}

/// Checks that `weights` (read from `path`) hold exactly the variables of `vars` whose names start with
/// `prefix`, each under its name without the prefix and with its shape, except those `may_lack` accepts
/// as absent. Returns the absent ones (with the prefix).
fn check_weights(
    path: &Path,
    weights: &HashMap<String, Tensor>,
    vars: &[(String, candle_core::Var)],
    prefix: &str,
    may_lack: impl Fn(&str) -> bool,
) -> Result<Vec<String>, TrainError> {
    let bad = |msg: String| TrainError::File {
        path: path.to_path_buf(),
        msg: format!("{msg} (not the architecture this training config builds)"),
    };
    let mut count = 0;
    let mut absent = Vec::new();
    for (name, var) in vars {
        let Some(key) = name.strip_prefix(prefix) else {
            continue;
        };
        let Some(t) = weights.get(key) else {
            if may_lack(key) {
                absent.push(name.clone());
                continue;
            }
            return Err(bad(format!("missing tensor {key}")));
        };
        count += 1;
        if t.dims() != var.as_tensor().dims() {
            return Err(bad(format!(
                "{key} has shape {:?}, expected {:?}",
                t.dims(),
                var.as_tensor().dims()
            )));
        }
    }
    if weights.len() != count {
        return Err(bad(format!("{} tensors, expected {count}", weights.len())));
    }
    Ok(absent)
}

/// The UNet attention module (`…attentions.N.`) that `key` belongs to, when `init` has no tensor of that
/// module at all: an attention the training config adds to a block that had none.
fn added_attention<'a>(key: &'a str, init: &HashMap<String, Tensor>) -> Option<&'a str> {
    const MARK: &str = ".attentions.";
    let start = key.find(MARK)? + MARK.len();
    let module = &key[..start + key[start..].find('.')? + 1];
    (!init.keys().any(|k| k.starts_with(module))).then_some(module)
}

/// `--init`: sets the UNet and text encoder variables (prefixes `unet.` / `text_encoder.`) from the
/// exported model in `init`, the inverse of [`train_denoiser`]'s export. The config may grow the init
/// model's UNet by attention on blocks that had none (e.g. text at a finer level): those modules keep
/// their fresh initialisation but for `proj_out`, set to zero, so that each new transformer adds nothing
/// to its residual and the grown UNet starts out computing exactly what the init model does (ControlNet's
/// zero convolutions); it then learns to use the new attention instead of starting over. Returns the
/// number of added variables.
fn load_denoiser_weights(
    init: &Path,
    config: &TrainConfig,
    varmap: &candle_nn::VarMap,
) -> Result<usize, TrainError> {
    check_attention_kinds(init, config)?;
    let vars = optim::named_vars(varmap);
    let unet_path = init.join("unet/diffusion_pytorch_model.safetensors");
    let unet = load_tensors(&unet_path)?;
    let added = check_weights(&unet_path, &unet, &vars, "unet.", |key| {
        added_attention(key, &unet).is_some()
    })?;
    let text_path = init.join("text_encoder/model.safetensors");
    // Both the transformers-4 layout (`text_model.` prefix, what the export writes) and the bare one.
    let text: HashMap<String, Tensor> = load_tensors(&text_path)?
        .into_iter()
        .map(|(k, t)| (k.strip_prefix("text_model.").unwrap_or(&k).to_string(), t))
        .collect();
    check_weights(&text_path, &text, &vars, "text_encoder.", |_| false)?;
    for (name, var) in &vars {
        if added.contains(name) {
            let module = added_attention(&name["unet.".len()..], &unet).unwrap_or_default();
            if name["unet.".len() + module.len()..].starts_with("proj_out.") {
                var.set(&var.as_tensor().zeros_like()?)?;
            }
            continue;
        }
        let t = match name.strip_prefix("unet.") {
            Some(key) => &unet[key],
            None => &text[name.strip_prefix("text_encoder.").unwrap_or(name)],
        };
        var.set(t)?;
    }
    Ok(added.len())
}

/// An attention the init model has must attend to what it learnt to: its self-attention layer read as a
/// text one (`only_cross_attention` switched on a block that had attention) holds weights of the right
/// shape whenever the block's width is the text's, so the shapes alone would not catch it.
fn check_attention_kinds(init: &Path, config: &TrainConfig) -> Result<(), TrainError> {
    let path = init.join("unet/config.json");
    let text = std::fs::read_to_string(&path).map_err(io_err(&path))?;
    let bad = |msg: String| TrainError::File {
        path: path.clone(),
        msg,
    };
    let resolved = diffusion::unet::UNetConfig::from_json(&text)
        .map_err(|e| bad(e.to_string()))?
        .resolve()
        .map_err(|e| bad(e.join("; ")))?;
    let wanted = &config.unet;
    for (i, kind) in resolved.down.iter().enumerate() {
        let has = *kind == diffusion::unet::BlockKind::CrossAttn;
        let only_init = resolved
            .only_cross_attention
            .get(i)
            .copied()
            .unwrap_or(false);
        let only_wanted = wanted.only_cross_attention.get(i).copied().unwrap_or(false);
        if has && wanted.cross_attention.get(i) == Some(&true) && only_init != only_wanted {
            return Err(bad(format!(
                "down block {i}'s attention has only_cross_attention {only_init}, the training config \
                 asks {only_wanted}: a block's attention cannot change what it attends to"
            )));
        }
    }
    Ok(())
}

/// Total size of the exported weight files.
fn weight_bytes(out: &Path) -> u64 {
    [
        "unet/diffusion_pytorch_model.safetensors",
        "vae/diffusion_pytorch_model.safetensors",
        "text_encoder/model.safetensors",
    ]
    .iter()
    .filter_map(|p| std::fs::metadata(out.join(p)).ok())
    .map(|m| m.len())
    .sum()
}

/// Writes `OUT/README.md`: what the folder is, the command that made it and the run's numbers.
fn write_readme(
    out: &Path,
    state: &TrainState,
    command: Option<&str>,
    weight_bytes: u64,
) -> Result<(), TrainError> {
    let c = &state.config;
    let mean_of = |stage: &str, first: bool| -> Option<(u64, f64)> {
        let mut it = state.loss_history.iter().filter(|(s, _, _)| s == stage);
        let pick = if first { it.next() } else { it.next_back() };
        pick.map(|(_, step, loss)| (*step, *loss))
    };
    let loss_line = |stage: &str, what: &str| -> String {
        match (mean_of(stage, true), mean_of(stage, false)) {
            (Some((s0, l0)), Some((s1, l1))) => {
                format!("{what}: {l0:.4} (steps ≤ {s0}) → {l1:.4} (steps ≤ {s1})")
            }
            _ => format!("{what}: not recorded"),
        }
    };
    let secs = |stage: &str| state.seconds.get(stage).copied().unwrap_or(0.0);
    let text = format!(
        "# vcedit demo model\n\n\
         A small Stable-Diffusion-architecture model (diffusers layout) trained by vcedit itself on its\n\
         procedural world (`crates/demo/src/world`). It loads like any SD checkpoint:\n\
         `vcedit model check {dir}`, `vcedit edit-image --model {dir} ...`.\n\n\
         Produced by:\n\n```\n{cmd}\n```\n\n\
         Rerunning that command continues from `checkpoints/` (not committed) or, when complete, only\n\
         rewrites the tokenizer and this README.\n\n\
         | part | architecture |\n| --- | --- |\n\
         | tokenizer | CLIP BPE, {vocab} tokens, one per caption word |\n\
         | text encoder | CLIPTextModel, hidden {th}, {tl} layers, {thd} heads, {tp} positions |\n\
         | UNet | UNet2DConditionModel, channels {uc:?}, cross-attention {ua:?}{only}, {uh} heads, ε-prediction |\n\
         | VAE | AutoencoderKL, channels {vc:?}, {lat} latent channels, scaling_factor {sf:.5} |\n\
         | scheduler | LCMScheduler config, scaled-linear betas {bs} → {be}, 1000 steps |\n\n\
         Training: seed {seed}, {n} rendered {size}×{size} samples; {codec_part};\n\
         UNet + text encoder {us} steps × {ub} ({umin:.1} min){init_part}.\n\
         Exported weights are EMA averages, {mb:.1} MB in all (f32 safetensors).\n\n\
         - {codec_loss}\n- {unet_loss}\n",
        dir = out.display(),
        cmd = command.unwrap_or("vcedit demo-model train (command not recorded)"),
        vocab = crate::bpe::demo_bpe().vocab_size(),
        th = c.text.hidden_size,
        tl = c.text.layers,
        thd = c.text.heads,
        tp = c.text.max_positions,
        uc = c.unet.block_out_channels,
        ua = c.unet.cross_attention,
        only = if c.unet.only_cross_attention.contains(&true) {
            format!(" (text only, no self-attention: {:?})", c.unet.only_cross_attention)
        } else {
            String::new()
        },
        uh = c.unet.heads,
        vc = c.codec.block_out_channels,
        lat = c.codec.latent_channels,
        sf = state.scaling_factor.unwrap_or(f64::NAN),
        bs = c.unet.beta_start,
        be = c.unet.beta_end,
        seed = c.seed,
        n = c.samples,
        size = c.image_size,
        codec_part = match &state.init_from {
            Some(init) => format!("codec taken from {}", init.display()),
            None => format!(
                "codec {} steps × {} crops of {}² ({:.1} min)",
                state.codec_step,
                c.codec.batch,
                c.codec.crop,
                secs("codec") / 60.0
            ),
        },
        init_part = match &state.init_from {
            Some(init) => format!(", starting from the UNet and text encoder of {}", init.display()),
            None => String::new(),
        },
        us = state.unet_step,
        ub = c.unet.batch,
        umin = secs("unet") / 60.0,
        mb = weight_bytes as f64 / 1e6,
        codec_loss = if state.init_from.is_some() {
            "codec: not trained in this run (taken as it was)".to_string()
        } else {
            loss_line("codec", "codec L1 reconstruction error (images in [-1, 1])")
        },
        unet_loss = loss_line("unet", "UNet noise-prediction MSE"),
    );
    let path = out.join("README.md");
    files::atomic_write(&path, text.as_bytes()).map_err(io_err(&path))
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;
    use testkit::diff::tensor_max_abs_diff as max_abs_diff;

    /// Writes `trainer`'s weights (built from `config`) as an exported model folder would hold them.
    fn export(trainer: &denoiser::DenoiserTrainer, config: &TrainConfig, dir: &Path) {
        let mut unet = HashMap::new();
        let mut text = HashMap::new();
        for (name, var) in optim::named_vars(&trainer.varmap) {
            let t = var.as_tensor().clone();
            match name.strip_prefix("unet.") {
                Some(key) => unet.insert(key.to_string(), t),
                None => text.insert(format!("text_model.{}", &name["text_encoder.".len()..]), t),
            };
        }
        for (sub, file, tensors) in [
            ("unet", "diffusion_pytorch_model.safetensors", &unet),
            ("text_encoder", "model.safetensors", &text),
        ] {
            std::fs::create_dir_all(dir.join(sub)).unwrap();
            save_tensors(tensors, &dir.join(sub).join(file)).unwrap();
        }
        write_json(&dir.join("unet/config.json"), &config.unet_config_json()).unwrap();
    }

    fn predict(trainer: &denoiser::DenoiserTrainer) -> Tensor {
        let dev = Device::Cpu;
        let ids = Tensor::from_vec(
            (0..2 * 77).map(|i| (i * 7 % 50) as u32).collect(),
            (2, 77),
            &dev,
        )
        .unwrap();
        let context = trainer.text_encoder.forward(&ids).unwrap();
        let noisy = (Tensor::arange(0f32, 128.0, &dev).unwrap() * 0.7)
            .unwrap()
            .sin()
            .unwrap()
            .reshape((2, 4, 4, 4))
            .unwrap();
        let t = Tensor::new(&[100f32, 700.0], &dev).unwrap();
        trainer
            .unet
            .forward(&noisy, &t, &context, None, None)
            .unwrap()
    }

    #[test]
    fn init_grows_attention_that_starts_as_identity() {
        let dir = tempfile::tempdir().unwrap();
        let mut small = TrainConfig::tiny();
        small.unet.cross_attention = vec![false, true];
        let init = denoiser::DenoiserTrainer::new(&small, 50).unwrap();
        export(&init, &small, dir.path());

        // Text at the top level too, attending to nothing but the text there.
        let mut grown = small.clone();
        grown.unet.cross_attention = vec![true, true];
        grown.unet.only_cross_attention = vec![true, false];
        grown.validate().unwrap();
        let trainer = denoiser::DenoiserTrainer::new(&grown, 50).unwrap();
        let added = load_denoiser_weights(dir.path(), &grown, &trainer.varmap).unwrap();
        assert!(added > 0);
        let before = predict(&init);
        let after = predict(&trainer);
        let diff = max_abs_diff(&before, &after);
        assert!(diff < 1e-5, "{diff}");

        // The new modules are on the path: a non-zero proj_out changes the prediction.
        let vars = optim::named_vars(&trainer.varmap);
        let (_, proj) = vars
            .iter()
            .find(|(n, _)| n == "unet.down_blocks.0.attentions.0.proj_out.weight")
            .unwrap();
        assert_eq!(
            proj.as_tensor()
                .abs()
                .unwrap()
                .sum_all()
                .unwrap()
                .to_scalar::<f32>()
                .unwrap(),
            0.0
        );
        proj.set(&proj.as_tensor().ones_like().unwrap()).unwrap();
        let changed = predict(&trainer);
        let diff = max_abs_diff(&before, &changed);
        assert!(diff > 1e-3, "{diff}");

        // An attention the init has cannot switch to the text, though its shapes match here (both the
        // block and the text are 16 wide); the error names the init's config.
        let mut other = grown.clone();
        other.unet.only_cross_attention = vec![true, true];
        let trainer = denoiser::DenoiserTrainer::new(&other, 50).unwrap();
        let err = load_denoiser_weights(dir.path(), &other, &trainer.varmap)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("unet/config.json") && err.contains("down block 1"),
            "{err}"
        );

        // Any other difference from the init's architecture is still refused, naming the weights.
        let mut fewer = small.clone();
        fewer.unet.layers_per_block = 2;
        let trainer = denoiser::DenoiserTrainer::new(&fewer, 50).unwrap();
        let err = load_denoiser_weights(dir.path(), &fewer, &trainer.varmap)
            .unwrap_err()
            .to_string();
        assert!(err.contains("diffusion_pytorch_model.safetensors"), "{err}");
    }
}
