//! `vcedit model check`: validate a model folder and summarise it.
//!
//! Checks, in order, collecting every problem of a stage into one error:
//! 1. presence: all components, configs, tokenizer files and weights (see [`ModelDir::open`]);
//! 2. headers: each safetensors header is read (no tensor data) and checked against the file size and
//!    against the configs (embedding and convolution shapes, channel counts shared between components);
//! 3. loading (unless headers-only): the text encoder, UNet and VAE are built from the weights, which
//!    reports any missing tensor or shape mismatch the headers did not reveal.

use std::collections::BTreeMap;
use std::fmt;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use candle_core::{DType, Device};
use serde_json::Value;

use crate::clip::{ClipTextConfig, ClipTextModel};
use crate::loader::{read_json, Component, LoadError, ModelDir, Problem};
use crate::scheduler::{LcmVariant, Scheduler, SchedulerError};
use crate::taesd::{AutoencoderTiny, TaesdConfig};
use crate::tokenizer::{ClipTokenizer, TokenizerSource};
use crate::unet::{UNet2DConditionModel, UNetConfig};
use crate::vae::{AutoencoderKL, AutoencoderKLConfig};
use crate::weights::{read_safetensors_header, TensorInfo};

/// What [`check_model`] should do beyond reading headers.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CheckDepth {
    /// Files, configs and safetensors headers only.
    HeadersOnly,
    /// Also build every model from its weights (f32, memory-mapped).
    Load,
}

/// One weight-bearing component.
#[derive(Debug, Clone)]
pub struct WeightsReport {
    pub component: Component,
    /// `_class_name` of its config (or transformers' `architectures[0]`).
    pub class: String,
    /// Weight files relative to the model root.
    pub files: Vec<String>,
    pub variant: Option<String>,
    pub sharded: bool,
    pub tensors: usize,
    pub parameters: usize,
    /// Parameters per on-disk dtype ("F16" → count).
    pub dtypes: BTreeMap<String, usize>,
    pub bytes_on_disk: u64,
    /// Time to build the model from its weights, when loaded.
    pub load_time: Option<Duration>,
    /// A one-line architecture summary from the config.
    pub details: String,
}

#[derive(Debug, Clone)]
pub struct TokenizerReport {
    pub source: TokenizerSource,
    pub vocab_size: usize,
    pub max_length: usize,
    pub pad_token: String,
    /// The config's `model_max_length` when it differs from the text encoder's positions.
    pub config_max_length_ignored: Option<f64>,
}

#[derive(Debug, Clone)]
pub struct SchedulerReport {
    pub class: String,
    pub details: String,
}

/// The image sizes a model takes: what `--size` must be a multiple of, and why.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SizeNeeds {
    /// Image pixels per latent pixel (the codec's downscale).
    pub codec: usize,
    /// UNet downsamplings (each halves the latents; the up path needs even sizes at each).
    pub downsamplings: u32,
    /// The UNet's `sample_size` in image pixels (what it was trained at), where the config says.
    pub native: Option<usize>,
}

impl SizeNeeds {
    /// What every image side must be a multiple of.
    pub fn multiple(&self) -> usize {
        self.codec << self.downsamplings
    }
}

/// Everything `model check` prints.
#[derive(Debug, Clone)]
pub struct ModelReport {
    pub root: PathBuf,
    pub pipeline_class: Option<String>,
    pub weights: Vec<WeightsReport>,
    pub tokenizer: TokenizerReport,
    pub scheduler: SchedulerReport,
    pub sizes: SizeNeeds,
    pub loaded: bool,
}

impl ModelReport {
    pub fn total_parameters(&self) -> usize {
        self.weights.iter().map(|w| w.parameters).sum()
    }
}

/// The config's class, else the one `model_index.json` declares for the component.
fn class_of(config: &Value, declared: Option<&str>) -> String {
    config
        .get("_class_name")
        .and_then(Value::as_str)
        .or_else(|| {
            config
                .get("architectures")
                .and_then(|a| a.get(0))
                .and_then(Value::as_str)
        })
        .or(declared)
        .unwrap_or("?")
        .to_string()
}

fn usize_key(config: &Value, key: &str) -> Option<usize> {
    config.get(key).and_then(Value::as_u64).map(|v| v as usize)
}

fn list_key(config: &Value, key: &str) -> Vec<usize> {
    config
        .get(key)
        .and_then(Value::as_array)
        .map(|a| {
            a.iter()
                .filter_map(|v| v.as_u64().map(|v| v as usize))
                .collect()
        })
        .unwrap_or_default()
}

/// `cross_attention_dim` may be a number or a per-block list; all entries must agree for SD 1.x.
fn cross_attention_dims(config: &Value) -> Vec<usize> {
    match config.get("cross_attention_dim") {
        Some(Value::Number(n)) => n.as_u64().map(|v| vec![v as usize]).unwrap_or_default(),
        Some(Value::Array(a)) => a
            .iter()
            .filter_map(|v| v.as_u64().map(|v| v as usize))
            .collect(),
        _ => vec![1280], // diffusers' default
    }
}

/// Human-readable byte count (GiB/MiB/KiB, two decimals).
pub fn format_bytes(bytes: u64) -> String {
    let b = bytes as f64;
    if b >= (1u64 << 30) as f64 {
        format!("{:.2} GiB", b / (1u64 << 30) as f64)
    } else if b >= (1u64 << 20) as f64 {
        format!("{:.2} MiB", b / (1u64 << 20) as f64)
    } else if b >= 1024.0 {
        format!("{:.1} KiB", b / 1024.0)
    } else {
        format!("{bytes} B")
    }
}

/// Parameter count with a unit (k, M, B).
pub fn format_count(n: usize) -> String {
    let f = n as f64;
    if f >= 1e9 {
        format!("{:.2}B", f / 1e9)
    } else if f >= 1e6 {
        format!("{:.1}M", f / 1e6)
    } else if f >= 1e3 {
        format!("{:.1}k", f / 1e3)
    } else {
        n.to_string()
    }
}

struct Headers {
    by_name: BTreeMap<String, TensorInfo>,
    report: WeightsReport,
    config: Value,
}

/// A component that failed to load: the file its error names when that is under `root` (so the file is
/// named once, as `vae/config.json: reason`), else the component's folder.
fn load_problem(root: &Path, folder: &str, reason: String) -> Problem {
    if let Some((head, rest)) = reason.split_once(": ") {
        let named = Path::new(head);
        if named.starts_with(root) && named != root {
            return Problem::Invalid {
                file: rel(root, named),
                reason: rest.to_string(),
            };
        }
    }
    Problem::Invalid {
        file: folder.into(),
        reason,
    }
}

fn rel(root: &Path, path: &Path) -> String {
    path.strip_prefix(root)
        .unwrap_or(path)
        .display()
        .to_string()
}

fn read_headers(dir: &ModelDir, component: Component) -> Result<Headers, LoadError> {
    let config: Value = read_json(&dir.config_path(component))?;
    let weights = dir.weight_files(component)?;
    let mut by_name = BTreeMap::new();
    let mut dtypes = BTreeMap::new();
    let mut bytes_on_disk = 0;
    for file in &weights.files {
        bytes_on_disk += std::fs::metadata(file).map(|m| m.len()).unwrap_or(0);
        for info in read_safetensors_header(file)? {
            *dtypes.entry(info.dtype.clone()).or_insert(0) += info.num_elements();
            by_name.insert(info.name.clone(), info);
        }
    }
    let report = WeightsReport {
        component,
        class: class_of(&config, dir.declared_class(component).map(|(_, c)| c)),
        files: weights.files.iter().map(|f| rel(dir.root(), f)).collect(),
        variant: weights.variant.clone(),
        sharded: weights.sharded,
        tensors: by_name.len(),
        parameters: by_name.values().map(TensorInfo::num_elements).sum(),
        dtypes,
        bytes_on_disk,
        load_time: None,
        details: String::new(),
    };
    Ok(Headers {
        by_name,
        report,
        config,
    })
}

/// Checks that a tensor exists with the expected shape (a `None` entry accepts any size there).
fn expect_shape(
    problems: &mut Vec<Problem>,
    headers: &Headers,
    name: &str,
    expected: &[Option<usize>],
    why: &str,
) {
    let file = headers.report.component.folder().to_string();
    match headers.by_name.get(name) {
        None => problems.push(Problem::Invalid {
            file: format!("{file}/ weights"),
            reason: format!("tensor {name} is missing"),
        }),
        Some(info) => {
            let fits = info.shape.len() == expected.len()
                && info
                    .shape
                    .iter()
                    .zip(expected)
                    .all(|(s, e)| e.is_none_or(|e| e == *s));
            if !fits {
                let shown: Vec<String> = expected
                    .iter()
                    .map(|e| e.map_or("_".to_string(), |v| v.to_string()))
                    .collect();
                problems.push(Problem::Invalid {
                    file: format!("{file}/ weights"),
                    reason: format!(
                        "{name} has shape {:?}, expected [{}] ({why})",
                        info.shape,
                        shown.join(", ")
                    ),
                });
            }
        }
    }
}

/// Validates and summarises a model folder; see the module docs for the stages.
pub fn check_model(path: &Path, depth: CheckDepth) -> Result<ModelReport, LoadError> {
    let dir = ModelDir::open(path)?;
    let root = dir.root().to_path_buf();
    let inconsistent = |problems: Vec<Problem>| LoadError::Inconsistent {
        root: root.clone(),
        problems,
    };

    let mut text = read_headers(&dir, Component::TextEncoder)?;
    let mut unet = read_headers(&dir, Component::Unet)?;
    let mut vae = read_headers(&dir, Component::Vae)?;
    let te_config: ClipTextConfig =
        serde_json::from_value(text.config.clone()).map_err(|e| LoadError::BadFile {
            path: dir.config_path(Component::TextEncoder),
            message: format!("not a CLIP text config: {e}"),
        })?;
    let tokenizer = ClipTokenizer::from_dir(dir.component_dir(Component::Tokenizer))
        .map_err(|e| match load_problem(&root, "tokenizer", e.to_string()) {
            // The tokenizer's errors name their file; keep that, once.
            Problem::Invalid { file, reason } if file != "tokenizer" => LoadError::BadFile {
                path: root.join(file),
                message: reason,
            },
            _ => LoadError::BadFile {
                path: dir.component_dir(Component::Tokenizer),
                message: e.to_string(),
            },
        })?
        .with_max_length(te_config.max_position_embeddings);
    let scheduler_path = dir.config_path(Component::Scheduler);
    // The scheduler's errors name their file already; it is said once.
    let scheduler = Scheduler::from_config_file(&scheduler_path, LcmVariant::Diffusers022)
        .map_err(|e| match e {
            SchedulerError::Config { path, message } => LoadError::BadFile { path, message },
            SchedulerError::Io { path, source } => LoadError::Io { path, source },
            other => LoadError::BadFile {
                path: scheduler_path.clone(),
                message: other.to_string(),
            },
        })?;

    // Stage 2: shapes against configs and across components.
    let mut problems = Vec::new();
    let te_prefix = if text
        .by_name
        .contains_key("text_model.embeddings.token_embedding.weight")
    {
        "text_model."
    } else {
        ""
    };
    let hidden = te_config.hidden_size;
    expect_shape(
        &mut problems,
        &text,
        &format!("{te_prefix}embeddings.token_embedding.weight"),
        &[Some(te_config.vocab_size), Some(hidden)],
        "vocab_size × hidden_size",
    );
    expect_shape(
        &mut problems,
        &text,
        &format!("{te_prefix}embeddings.position_embedding.weight"),
        &[Some(te_config.max_position_embeddings), Some(hidden)],
        "max_position_embeddings × hidden_size",
    );
    if tokenizer.vocab_size() > te_config.vocab_size {
        problems.push(Problem::Invalid {
            file: "tokenizer/".into(),
            reason: format!(
                "{} tokens, but the text encoder embeds only {}",
                tokenizer.vocab_size(),
                te_config.vocab_size
            ),
        });
    }
    let unet_in = usize_key(&unet.config, "in_channels").unwrap_or(4);
    let unet_out = usize_key(&unet.config, "out_channels").unwrap_or(4);
    let unet_channels = list_key(&unet.config, "block_out_channels");
    let first = unet_channels.first().copied();
    expect_shape(
        &mut problems,
        &unet,
        "conv_in.weight",
        &[first, Some(unet_in), None, None],
        "block_out_channels[0] × in_channels",
    );
    expect_shape(
        &mut problems,
        &unet,
        "conv_out.weight",
        &[Some(unet_out), first, None, None],
        "out_channels × block_out_channels[0]",
    );
    let cond_dim = usize_key(&unet.config, "time_cond_proj_dim");
    let has_cond = unet.by_name.contains_key("time_embedding.cond_proj.weight");
    if cond_dim.is_some() != has_cond {
        problems.push(Problem::Invalid {
            file: "unet/ weights".into(),
            reason: format!(
                "time_cond_proj_dim is {cond_dim:?} but time_embedding.cond_proj.weight is {}",
                if has_cond { "present" } else { "absent" }
            ),
        });
    }
    for dim in cross_attention_dims(&unet.config) {
        if dim != hidden {
            problems.push(Problem::Invalid {
                file: "unet/config.json".into(),
                reason: format!(
                    "cross_attention_dim {dim} does not match the text encoder's hidden_size {hidden}"
                ),
            });
            break;
        }
    }
    let vae_class = vae.report.class.clone();
    let latent = usize_key(&vae.config, "latent_channels").unwrap_or(4);
    if unet_out != latent {
        problems.push(Problem::Invalid {
            file: "unet/config.json".into(),
            reason: format!(
                "out_channels {unet_out} differs from the VAE's latent_channels {latent}"
            ),
        });
    }
    if unet_in != latent && unet_in != 2 * latent {
        problems.push(Problem::Invalid {
            file: "unet/config.json".into(),
            reason: format!(
                "in_channels {unet_in} is neither latent_channels {latent} nor twice that (InstructPix2Pix)"
            ),
        });
    }
    if vae_class != "AutoencoderTiny" {
        let vae_channels = list_key(&vae.config, "block_out_channels");
        let vae_in = usize_key(&vae.config, "in_channels").unwrap_or(3);
        expect_shape(
            &mut problems,
            &vae,
            "encoder.conv_in.weight",
            &[vae_channels.first().copied(), Some(vae_in), None, None],
            "block_out_channels[0] × in_channels",
        );
        expect_shape(
            &mut problems,
            &vae,
            "decoder.conv_in.weight",
            &[vae_channels.last().copied(), Some(latent), None, None],
            "block_out_channels[-1] × latent_channels",
        );
    }
    if !problems.is_empty() {
        return Err(inconsistent(problems));
    }

    // Stage 3: build the models.
    let loaded = depth == CheckDepth::Load;
    if loaded {
        let device = Device::Cpu;
        let mut problems = Vec::new();
        let start = Instant::now();
        if let Err(e) = ClipTextModel::load(&dir, DType::F32, &device) {
            problems.push(load_problem(&root, "text_encoder/", e.to_string()));
        }
        text.report.load_time = Some(start.elapsed());

        let start = Instant::now();
        let unet_result = (|| -> Result<(), String> {
            let cfg_text = std::fs::read_to_string(dir.config_path(Component::Unet))
                .map_err(|e| e.to_string())?;
            let cfg = UNetConfig::from_json(&cfg_text).map_err(|e| e.to_string())?;
            let vb = dir
                .var_builder(Component::Unet, DType::F32, &device)
                .map_err(|e| e.to_string())?;
            UNet2DConditionModel::load(&cfg, vb).map_err(|e| e.to_string())?;
            Ok(())
        })();
        if let Err(reason) = unet_result {
            problems.push(load_problem(&root, "unet/", reason));
        }
        unet.report.load_time = Some(start.elapsed());

        let start = Instant::now();
        let vae_result = (|| -> Result<(), String> {
            let config_path = dir.config_path(Component::Vae);
            let vb = dir
                .var_builder(Component::Vae, DType::F32, &device)
                .map_err(|e| e.to_string())?;
            if vae_class == "AutoencoderTiny" {
                let cfg = TaesdConfig::from_file(&config_path).map_err(|e| e.to_string())?;
                AutoencoderTiny::new(&cfg, vb).map_err(|e| e.to_string())?;
            } else {
                let cfg =
                    AutoencoderKLConfig::from_file(&config_path).map_err(|e| e.to_string())?;
                AutoencoderKL::new(&cfg, vb).map_err(|e| e.to_string())?;
            }
            Ok(())
        })();
        if let Err(reason) = vae_result {
            problems.push(load_problem(&root, "vae/", reason));
        }
        vae.report.load_time = Some(start.elapsed());
        // Every weight finite: a NaN loads and runs without error, and decodes black images.
        for component in [Component::TextEncoder, Component::Unet, Component::Vae] {
            for file in dir.weight_files(component)?.files {
                if let Some((tensor, index)) = crate::weights::first_non_finite(&file)? {
                    problems.push(Problem::Invalid {
                        file: rel(&root, &file),
                        reason: format!(
                            "tensor {tensor} holds a NaN or an infinity (the first at element {index}, \
                             counting from 0); the weights \
                             are damaged or were converted wrongly"
                        ),
                    });
                }
            }
        }
        if !problems.is_empty() {
            return Err(inconsistent(problems));
        }
    }

    text.report.details = format!(
        "{} layers, hidden {}, {} heads, {:?}, {} positions, vocab {}{}",
        te_config.num_hidden_layers,
        hidden,
        te_config.num_attention_heads,
        te_config.hidden_act,
        te_config.max_position_embeddings,
        te_config.vocab_size,
        if te_prefix.is_empty() {
            ""
        } else {
            ", keys under text_model."
        }
    );
    unet.report.details = format!(
        "in {unet_in} / out {unet_out} channels, blocks {:?}, cross-attention {}{}{}",
        unet_channels,
        hidden,
        cond_dim.map_or(String::new(), |d| format!(", LCM time condition {d}")),
        usize_key(&unet.config, "sample_size")
            .map_or(String::new(), |s| format!(", sample size {s}")),
    );
    vae.report.details = format!(
        "{vae_class}, latent channels {latent}, scaling factor {}",
        vae.config
            .get("scaling_factor")
            .and_then(Value::as_f64)
            .map_or("?".to_string(), |v| v.to_string())
    );

    let tokenizer_config: Value = {
        let p = dir.config_path(Component::Tokenizer);
        if p.is_file() {
            read_json(&p)?
        } else {
            Value::Null
        }
    };
    let config_max = tokenizer_config
        .get("model_max_length")
        .and_then(Value::as_f64)
        .filter(|&m| m != te_config.max_position_embeddings as f64);
    let tokenizer_report = TokenizerReport {
        source: tokenizer.source(),
        vocab_size: tokenizer.vocab_size(),
        max_length: tokenizer.max_length(),
        pad_token: tokenizer
            .id_to_token(tokenizer.pad_id())
            .unwrap_or("?")
            .to_string(),
        config_max_length_ignored: config_max,
    };
    let scheduler_report = scheduler_summary(&scheduler);
    // diffusers' defaults where a config leaves the blocks out: KL (64,), Tiny four stages, UNet four.
    let codec_blocks = match list_key(&vae.config, "block_out_channels").len() {
        0 if vae_class == "AutoencoderTiny" => {
            match list_key(&vae.config, "encoder_block_out_channels").len() {
                0 => 4,
                n => n,
            }
        }
        0 => 1,
        n => n,
    };
    let codec = 1usize << (codec_blocks - 1);
    let unet_blocks = if unet_channels.is_empty() {
        4
    } else {
        unet_channels.len()
    };
    let sizes = SizeNeeds {
        codec,
        downsamplings: (unet_blocks - 1) as u32,
        native: usize_key(&unet.config, "sample_size").map(|s| s * codec),
    };
    Ok(ModelReport {
        root,
        pipeline_class: dir.pipeline_class().map(str::to_owned),
        weights: vec![text.report, unet.report, vae.report],
        tokenizer: tokenizer_report,
        scheduler: scheduler_report,
        sizes,
        loaded,
    })
}

fn scheduler_summary(scheduler: &Scheduler) -> SchedulerReport {
    let details = match scheduler {
        Scheduler::Lcm(s) => {
            let c = s.config();
            let mut reference = s.clone();
            let steps = 15.min(c.original_inference_steps);
            let schedule = reference
                .set_timesteps(steps, None, 1.0)
                .map(|t| format!("{t:?}"))
                .unwrap_or_else(|e| e.to_string());
            format!(
                "{:?} betas {}..{}, {} train steps, {:?}, original_inference_steps {}; \
                 {steps} steps (diffusers 0.22) = {schedule}",
                c.beta_schedule,
                c.beta_start,
                c.beta_end,
                c.num_train_timesteps,
                c.prediction_type,
                c.original_inference_steps
            )
        }
        Scheduler::Ddim(s) => {
            let c = s.config();
            format!(
                "{:?} betas {}..{}, {} train steps, {:?}, {:?} spacing, steps_offset {}, set_alpha_to_one {}",
                c.beta_schedule,
                c.beta_start,
                c.beta_end,
                c.num_train_timesteps,
                c.prediction_type,
                c.timestep_spacing,
                c.steps_offset,
                c.set_alpha_to_one
            )
        }
    };
    SchedulerReport {
        class: scheduler.class_name().to_string(),
        details,
    }
}

impl fmt::Display for ModelReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(f, "model        {}", self.root.display())?;
        if let Some(p) = &self.pipeline_class {
            writeln!(f, "pipeline     {p}")?;
        }
        for w in &self.weights {
            let dtypes: Vec<String> = w.dtypes.keys().map(|d| d.to_lowercase()).collect();
            let mut storage = dtypes.join("+");
            if let Some(v) = &w.variant {
                storage.push_str(&format!(", {v} variant"));
            }
            if w.sharded {
                storage.push_str(&format!(", {} shards", w.files.len()));
            }
            writeln!(
                f,
                "{:<12} {} - {} parameters in {} tensors, {} on disk ({storage}){}",
                w.component.folder(),
                w.class,
                format_count(w.parameters),
                w.tensors,
                format_bytes(w.bytes_on_disk),
                w.load_time.map_or(String::new(), |t| format!(
                    ", built in {:.2} s",
                    t.as_secs_f64()
                ))
            )?;
            writeln!(f, "{:<12} {}", "", w.details)?;
        }
        let t = &self.tokenizer;
        writeln!(
            f,
            "tokenizer    CLIP BPE from {} - {} tokens, {} positions, pad {:?}{}",
            t.source,
            t.vocab_size,
            t.max_length,
            t.pad_token,
            t.config_max_length_ignored
                .map_or(String::new(), |m| format!(
                    " (config's model_max_length {m:e} ignored)"
                ))
        )?;
        writeln!(
            f,
            "scheduler    {} - {}",
            self.scheduler.class, self.scheduler.details
        )?;
        let z = &self.sizes;
        writeln!(
            f,
            "sizes        --size: multiples of {} ({}× codec, {} UNet downsamplings){}",
            z.multiple(),
            z.codec,
            z.downsamplings,
            z.native
                .map_or(String::new(), |n| format!("; trained at {n}×{n}"))
        )?;
        let params = self.total_parameters() as u64;
        writeln!(
            f,
            "total        {} parameters; weights need {} in f32, {} in f16",
            format_count(params as usize),
            format_bytes(params * 4),
            format_bytes(params * 2)
        )?;
        write!(
            f,
            "status       {}",
            if self.loaded {
                "OK: all components load"
            } else {
                "OK: files, configs and weight headers are consistent (models not built)"
            }
        )
    }
}
