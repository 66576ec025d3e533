//! One UNet forward: the SD 1.5 config with random weights (no files needed), or a model folder's UNet
//! (`--model DIR`, so that another program can run the same weights: tools/gpu-check runs diffusers on
//! them), plus the peak memory of loading SD 1.5 weights stored in f16.
//!
//! `vcedit bench unet [--batches 1,6] [--runs 2] [--size 64] [--model DIR] [--device cpu|gpu|auto]
//! [--precision f16|f32|bf16] [--hooks none,device,host] [--small] [--skip-load] [--check]`
//!
//! `--device gpu` runs the forward on the GPU (`gpu` takes a software adapter such as lavapipe too);
//! `--small` shrinks the random model's channels to [64, 128, 256, 256] (same blocks, heads and context),
//! a UNet lavapipe runs in seconds. `--hooks` lists the attention hooks to time, each on every batch:
//! `none`; `device`, an InfEdit-shaped hook (batch swaps of the self-attention Q/K/V, the cross-attention
//! probabilities read and rebuilt) whose tensors stay where the UNet runs, as the editing controller's
//! do; `host`, the same hook reading every tensor back and uploading it again (what a host-side hook
//! costs; the A/B for a GPU).
//! One `RESULT` line per batch and hook (the first call, which compiles the GPU kernels and uploads the
//! weights, apart from the warm runs; tools/bench_unet_torch.py --compare parses them).
//! Thread count: RAYON_NUM_THREADS (candle's matmul and our kernels use the rayon pool).
//!
//! `--check` on a GPU also runs the first batch once on the CPU and reports the GPU output's relative
//! error against it (`rel_err`): the end-to-end cost of the GPU path's rounding (f16 operands on tensor
//! cores, f16 weights), measured on the card itself. On the CPU with bf16 products it runs the first
//! batch in bf16 and in f32 and reports `rel_err` and `rel_l2` (relative L2) of bf16 against f32.
//! `--precision` on the CPU: `bf16` products (the default where the CPU has AVX512-BF16; the model then
//! keeps only its weights' bf16 pairs, except under `--check`) or `f32` (the default elsewhere).
//!
//! `--load-rss FILE` (internal): loads an SD 1.5 UNet from FILE and prints the process's peak RSS.

use std::collections::HashMap;
use std::path::Path;
use std::sync::Mutex;
use std::time::Instant;

use candle_core::{DType, Device, Shape, Tensor};
use candle_nn::var_builder::SimpleBackend;
use candle_nn::VarBuilder;
use diffusion::device::DeviceTensor;
use diffusion::loader::{Component, ModelDir};
use diffusion::unet::{
    AttentionHook, AttnCall, AttnKind, MapEdit, Qkv, UNet2DConditionModel, UNetConfig,
};

use crate::{
    arg_list, arg_parsed, arg_value, cpu_seconds, has_flag, network_device, networks_on,
    peak_rss_mb, report, status_mb, BenchError, Result, Timed,
};

type CandleResult<T> = candle_core::Result<T>;

/// `unet/config.json` of runwayml/stable-diffusion-v1-5 (diffusers 0.6 era, as published).
const SD15_UNET_CONFIG: &str = r#"{
  "_class_name": "UNet2DConditionModel",
  "_diffusers_version": "0.6.0",
  "act_fn": "silu",
  "attention_head_dim": 8,
  "block_out_channels": [320, 640, 1280, 1280],
  "center_input_sample": false,
  "cross_attention_dim": 768,
  "down_block_types": ["CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "DownBlock2D"],
  "downsample_padding": 1,
  "flip_sin_to_cos": true,
  "freq_shift": 0,
  "in_channels": 4,
  "layers_per_block": 2,
  "mid_block_scale_factor": 1,
  "norm_eps": 1e-05,
  "norm_num_groups": 32,
  "out_channels": 4,
  "sample_size": 64,
  "up_block_types": ["UpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D"]
}"#;

fn config() -> UNetConfig {
    UNetConfig::from_json(SD15_UNET_CONFIG).expect("embedded SD 1.5 config parses")
}

/// The SD 1.5 architecture with a fifth of its channels (for software GPUs).
fn small_config() -> UNetConfig {
    let mut c = config();
    c.block_out_channels = vec![64, 128, 256, 256];
    c
}

/// Hands out deterministic pseudo-random weights (uniform, variance 1/fan_in; norm weights near 1) by name,
/// as plain tensors so the inference path runs, and remembers them when `made` is given (for saving in
/// f16; otherwise the model holds the only copy, as a loaded model does).
struct RandomWeights {
    made: Option<Mutex<HashMap<String, Tensor>>>,
}

impl SimpleBackend for RandomWeights {
    fn get(
        &self,
        shape: Shape,
        name: &str,
        _: candle_nn::Init,
        dtype: DType,
        dev: &Device,
    ) -> CandleResult<Tensor> {
        let n = shape.elem_count();
        let fan_in: usize = shape.dims().iter().skip(1).product::<usize>().max(1);
        let is_norm_weight = name.ends_with("weight") && shape.rank() == 1;
        let bound = if is_norm_weight {
            0.1
        } else {
            (3.0 / fan_in as f32).sqrt()
        };
        let offset = if is_norm_weight { 1.0 } else { 0.0 };
        // xorshift64*, seeded from the name so every tensor differs.
        let mut state = name.bytes().fold(0x9E37_79B9_7F4A_7C15u64, |h, b| {
            (h ^ b as u64).wrapping_mul(0x100_0000_01B3)
        });
        let data: Vec<f32> = (0..n)
            .map(|_| {
                state ^= state >> 12;
                state ^= state << 25;
                state ^= state >> 27;
                let unit =
                    (state.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 40) as f32 / (1u64 << 24) as f32;
                offset + bound * (2.0 * unit - 1.0)
            })
            .collect();
        let t = Tensor::from_vec(data, shape, dev)?.to_dtype(dtype)?;
        if let Some(made) = &self.made {
            made.lock().unwrap().insert(name.to_string(), t.clone());
        }
        Ok(t)
    }

    fn get_unchecked(&self, name: &str, _: DType, _: &Device) -> CandleResult<Tensor> {
        candle_core::bail!("random weights: {name} requested without a shape")
    }

    fn contains_tensor(&self, _name: &str) -> bool {
        false
    }
}

/// The controller's work without its bookkeeping: in batches of six (InfEdit's `[S,T,M]` × CFG) the
/// self-attention Q/K/V of each half come from its first items, and the conditional half's
/// cross-attention probabilities are split per branch and concatenated back.
struct InfEditShaped {
    /// Read every tensor back and upload it again (a host-side hook).
    via_host: bool,
}

impl InfEditShaped {
    fn route(&self, t: DeviceTensor) -> CandleResult<DeviceTensor> {
        if self.via_host {
            t.same_device(&t.to_cpu()?)
        } else {
            Ok(t)
        }
    }
}

impl AttentionHook for InfEditShaped {
    fn qkv(&mut self, call: &AttnCall, qkv: Qkv) -> CandleResult<Qkv> {
        if call.kind != AttnKind::SelfAttn || !call.batch.is_multiple_of(6) {
            return Ok(qkv);
        }
        let idx: Vec<u32> = (0..call.batch as u32)
            .map(|b| b - b % 3 + u32::from(b % 3 == 1))
            .collect();
        qkv.try_map(|t| self.route(t)?.index_select(&idx, 0))
    }

    /// Like InfEdit's controller while it refines: the maps of the blend-sized (16²) and smaller layers
    /// are read, the larger layers' refinement goes to the values.
    fn wants_probs(&self, call: &AttnCall) -> bool {
        call.kind == AttnKind::CrossAttn && call.height * call.width <= 16 * 16
    }

    fn map_edits(&self, call: &AttnCall) -> Vec<MapEdit> {
        if call.kind != AttnKind::CrossAttn || !call.batch.is_multiple_of(6) {
            return Vec::new();
        }
        // Each view's conditional target row takes the conditional source's maps, token for token.
        (0..call.batch / 6)
            .map(|view| MapEdit {
                row: 6 * view + 4,
                source: 6 * view + 3,
                keep: vec![0.2; call.keys],
                take: (0..call.keys).map(|j| (j, 0.8)).collect(),
            })
            .collect()
    }

    fn probs(&mut self, call: &AttnCall, probs: DeviceTensor) -> CandleResult<DeviceTensor> {
        let probs = self.route(probs)?;
        let parts = (0..call.batch)
            .map(|b| probs.narrow(0, b, 1))
            .collect::<CandleResult<Vec<_>>>()?;
        DeviceTensor::cat(&parts.iter().collect::<Vec<_>>(), 0)
    }
}

/// Builds the SD 1.5 UNet with random weights; also returns the weights by name.
/// The UNet of `config` with [`RandomWeights`], and its weights by name when `keep_weights`.
fn random_model(
    config: &UNetConfig,
    keep_weights: bool,
) -> Result<(UNet2DConditionModel, HashMap<String, Tensor>)> {
    let backend = std::sync::Arc::new(RandomWeights {
        made: keep_weights.then(|| Mutex::new(HashMap::new())),
    });
    let vb = VarBuilder::from_backend(
        Box::new(SharedBackend(backend.clone())),
        DType::F32,
        Device::Cpu,
    );
    let model = UNet2DConditionModel::load(config, vb)?;
    let weights = backend
        .made
        .as_ref()
        .map(|made| std::mem::take(&mut *made.lock().expect("weights lock")))
        .unwrap_or_default();
    Ok((model, weights))
}

struct SharedBackend(std::sync::Arc<RandomWeights>);

impl SimpleBackend for SharedBackend {
    fn get(
        &self,
        s: Shape,
        name: &str,
        h: candle_nn::Init,
        dtype: DType,
        dev: &Device,
    ) -> CandleResult<Tensor> {
        self.0.get(s, name, h, dtype, dev)
    }
    fn get_unchecked(&self, name: &str, dtype: DType, dev: &Device) -> CandleResult<Tensor> {
        self.0.get_unchecked(name, dtype, dev)
    }
    fn contains_tensor(&self, name: &str) -> bool {
        self.0.contains_tensor(name)
    }
}

/// Which attention hook a measurement runs with.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum HookChoice {
    None,
    Device,
    Host,
}

impl std::str::FromStr for HookChoice {
    type Err = BenchError;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "none" => Ok(Self::None),
            "device" => Ok(Self::Device),
            "host" => Ok(Self::Host),
            other => Err(BenchError::new(format!(
                "--hooks: none, device or host, not '{other}'"
            ))),
        }
    }
}

impl HookChoice {
    fn name(self) -> &'static str {
        match self {
            Self::None => "none",
            Self::Device => "device",
            Self::Host => "host",
        }
    }

    fn hook(self) -> Option<InfEditShaped> {
        match self {
            Self::None => None,
            Self::Device => Some(InfEditShaped { via_host: false }),
            Self::Host => Some(InfEditShaped { via_host: true }),
        }
    }
}

/// Loads the UNet of the model folder `dir` (its config and safetensors weights).
fn folder_model(dir: &Path) -> Result<UNet2DConditionModel> {
    let model = ModelDir::open_components(dir, &[Component::Unet])?;
    let weights = model.weight_files(Component::Unet)?;
    Ok(UNet2DConditionModel::from_files(
        &model.config_path(Component::Unet),
        &weights.files,
    )?)
}

pub fn main(args: &[String], reexec: &[String]) -> Result<()> {
    if let Some(path) = arg_value(args, "--load-rss") {
        let before = peak_rss_mb();
        let start = Instant::now();
        let files = [std::path::PathBuf::from(&path)];
        let vb = diffusion::loader::var_builder_from_files(&files, DType::F32, &Device::Cpu)?;
        let model = UNet2DConditionModel::load(&config(), vb)?;
        let elapsed = start.elapsed();
        report(serde_json::json!({
            "bench": "unet", "impl": "candle", "what": "load_f16", "seconds": crate::secs(elapsed),
            "peak_rss_mb": peak_rss_mb().round(), "anon_mb": status_mb("RssAnon").round(),
            "file_mb": status_mb("RssFile").round(), "rss_before_mb": before.round(),
        }));
        eprintln!(
            "  loaded SD 1.5 (f16 file) in {:.2} s",
            elapsed.as_secs_f64()
        );
        drop(model);
        return Ok(());
    }
    let batches: Vec<usize> = arg_list(args, "--batches", "1,6")?;
    let runs: usize = arg_parsed(args, "--runs", 2)?;
    let size: usize = arg_parsed(args, "--size", 64)?;
    let small = has_flag(args, "--small");
    let hooks: Vec<HookChoice> = match (arg_value(args, "--hooks"), arg_value(args, "--hook")) {
        (None, Some(one)) => vec![one.parse()?],
        _ => arg_list(args, "--hooks", "none")?,
    };
    let model_dir = arg_value(args, "--model");
    let device = network_device(args, "cpu")?;
    let on_device = diffusion::device::Device::from(device.clone());
    let threads = candle_core::utils::get_num_threads();
    let cpu_precision = diffusion::device::cpu_precision();
    let on = networks_on(device.as_ref());
    let start = Instant::now();
    // Under bf16 products a model keeps only its weights' bf16 pairs, except for --check, which
    // compares against f32 products over the f32 weights (so those are kept, and packed beside them).
    let check_bf16 = device.is_none()
        && has_flag(args, "--check")
        && cpu_precision == diffusion::device::CpuPrecision::Bf16;
    let load = || -> Result<(UNet2DConditionModel, bool, String)> {
        Ok(match &model_dir {
            Some(dir) => (folder_model(Path::new(dir))?, false, dir.clone()),
            None => {
                let config = if small { small_config() } else { config() };
                let (model, _) = random_model(&config, false)?;
                let which = if small { "small SD 1.5" } else { "SD 1.5" };
                (model, true, format!("{which} config, random weights"))
            }
        })
    };
    let (model, random, which) = if check_bf16 {
        diffusion::device::with_cpu_precision(diffusion::device::CpuPrecision::F32, load)
            .map_err(BenchError::new)??
    } else {
        load()?
    };
    let config = model.config().clone();
    eprintln!(
        "unet bench: {which}, {size}x{size} latents, {on}, {runs} timed runs; loaded in {:.1} s",
        start.elapsed().as_secs_f64()
    );
    // The context width every block takes (SD 1.x: one value; a per-block list must agree to be run here).
    let context_dim = config
        .resolve()
        .map_err(|e| BenchError::new(e.join("; ")))?
        .cross_attention_dim
        .first()
        .copied()
        .unwrap_or(768);
    for &batch in &batches {
        let sample = Tensor::randn(
            0f32,
            1.0,
            (batch, config.in_channels, size, size),
            &Device::Cpu,
        )?;
        let context = Tensor::randn(0f32, 1.0, (batch, 77, context_dim), &Device::Cpu)?;
        let t = Tensor::new(&[500f32], &Device::Cpu)?;
        for &choice in &hooks {
            let mut hook = choice.hook();
            let cpu_start = cpu_seconds();
            let timed = Timed::measure(runs, || {
                let out = model.forward_on(
                    &sample,
                    &t,
                    &context,
                    None,
                    hook.as_mut().map(|h| h as &mut dyn AttentionHook),
                    &on_device,
                )?;
                if out.dims() != [batch, config.out_channels, size, size] {
                    return Err(BenchError::new(format!("unet output {:?}", out.dims())));
                }
                Ok(out)
            })?;
            let cpu = (cpu_seconds() - cpu_start) / (runs + 1) as f64;
            eprintln!(
                "  batch {batch}, hook {}: best {:.3} s, median {:.3} s, first call {:.3} s",
                choice.name(),
                timed.best().as_secs_f64(),
                timed.median().as_secs_f64(),
                timed.first.as_secs_f64()
            );
            let mut rel_l2 = None;
            let rel_err = match &device {
                Some(_)
                    if has_flag(args, "--check") && batch == batches[0] && choice == hooks[0] =>
                {
                    let run = |on| model.forward_on(&sample, &t, &context, None, None, on);
                    let rel = crate::relative_error(
                        &run(&on_device)?,
                        &run(&diffusion::device::Device::Cpu)?,
                    )?;
                    eprintln!("  batch {batch}: GPU against CPU, relative error {rel:.2e}");
                    Some(rel)
                }
                None if has_flag(args, "--check")
                    && cpu_precision == diffusion::device::CpuPrecision::Bf16
                    && batch == batches[0]
                    && choice == hooks[0] =>
                {
                    // bf16 products against f32 ones, same weights and inputs.
                    let run = |precision| {
                        diffusion::device::with_cpu_precision(precision, || {
                            model.forward_on(&sample, &t, &context, None, None, &on_device)
                        })
                        .map_err(BenchError::new)?
                        .map_err(BenchError::from)
                    };
                    let (low, full) = (
                        run(diffusion::device::CpuPrecision::Bf16)?,
                        run(diffusion::device::CpuPrecision::F32)?,
                    );
                    let (rel, l2) = (
                        crate::relative_error(&low, &full)?,
                        crate::relative_l2(&low, &full)?,
                    );
                    eprintln!(
                        "  batch {batch}: bf16 against f32, relative L2 {l2:.2e}, largest difference {rel:.2e} of the largest value"
                    );
                    rel_l2 = Some(l2);
                    Some(rel)
                }
                _ => None,
            };
            let mut fields = serde_json::json!({
                "bench": "unet",
                "impl": if device.is_some() { "vcedit-gpu" } else { "candle" },
                "what": "forward",
                "model": which,
                "hook": choice.name(),
                "batch": batch,
                "size": size,
                "threads": threads,
                "device": on,
                "cpu_seconds_per_call": (cpu * 100.0).round() / 100.0,
                "peak_rss_mb": peak_rss_mb().round(),
                // The warm time under the name tools/bench_unet_torch.py --compare reads.
                "seconds": crate::secs(timed.best()),
            });
            if let Some(rel) = rel_err {
                fields["rel_err"] = rel.into();
            }
            if let Some(l2) = rel_l2 {
                fields["rel_l2"] = l2.into();
            }
            if device.is_none() {
                fields["precision"] = cpu_precision.name().into();
            }
            if let Some(device) = &device {
                let estimate = config
                    .activation_estimate(batch, size, size, 77, false)
                    .map_err(BenchError::new)?;
                let (reserved, _) = device.memory_reserved_and_in_use();
                let map = fields.as_object_mut().expect("object");
                map.insert("compiler".into(), device.context().compiler.clone().into());
                map.insert(
                    "matmul_path".into(),
                    diffusion::device::ops::matmul_path(device)
                        .to_string()
                        .into(),
                );
                map.insert("conv_path".into(), conv_paths().into());
                map.insert(
                    "weights_mb".into(),
                    (device.weight_bytes() as f64 / 1e6).round().into(),
                );
                map.insert(
                    "activations_estimate_mb".into(),
                    (estimate.total() as f64 / 1e6).round().into(),
                );
                map.insert(
                    "pools_reserved_mb".into(),
                    (reserved as f64 / 1e6).round().into(),
                );
            }
            report(timed.json(fields));
        }
    }
    drop(model);

    if !random || small || device.is_some() || has_flag(args, "--skip-load") {
        return Ok(());
    }
    // Peak memory of loading SD 1.5 stored in f16, measured in a fresh process.
    let path = std::env::temp_dir().join("vcedit-bench-sd15-unet-f16.safetensors");
    if !path.exists() {
        // The same weights again (they are made from their names), this time kept to be saved.
        let (_, weights) = random_model(&config, true)?;
        let half = weights
            .iter()
            .map(|(k, v)| Ok((k.clone(), v.to_dtype(DType::F16)?)))
            .collect::<CandleResult<HashMap<String, Tensor>>>()?;
        candle_core::safetensors::save(&half, &path)?;
    }
    let status = std::process::Command::new(std::env::current_exe()?)
        .args(reexec)
        .arg("--load-rss")
        .arg(&path)
        .status()?;
    if !status.success() {
        return Err(BenchError::new("the load-memory measurement failed"));
    }
    Ok(())
}

/// How the run's convolutions were routed: the forced path, or "tuned: D of N direct" over the problems
/// the tuner settled (pointwise convolutions are products and never tuned).
fn conv_paths() -> String {
    use diffusion::device::ops::{forced_conv_path, tuned_conv_paths, ConvPath};
    if let Some(path) = forced_conv_path() {
        return path.to_string();
    }
    let tuned = tuned_conv_paths();
    let direct = tuned.iter().filter(|(_, p)| *p == ConvPath::Direct).count();
    format!("tuned: {direct} of {} direct", tuned.len())
}
