//! UNet forward benchmark with the SD 1.5 config and random weights (no files needed), plus the peak
//! memory of loading SD 1.5 weights stored in f16.
//!
//! `cargo bench -p vcedit-diffusion --bench unet [-- --batches 1,6 --runs 2 --size 64]`
//! `-- --device gpu` runs the forward on the GPU (VCEDIT_DEVICE rules: lavapipe needs
//! VCEDIT_ALLOW_SOFTWARE_GPU=1 or an explicit `gpu`); `-- --small` shrinks the channels to
//! [64, 128, 256, 256] (same blocks, heads and context), a UNet lavapipe runs in seconds.
//! `-- --hook device|host` runs every call through an InfEdit-shaped attention hook (batch swaps of the
//! self-attention Q/K/V, the cross-attention probabilities read and rebuilt): `device` keeps the hook's
//! tensors where the UNet runs (as the editing controller does), `host` reads them back and uploads them
//! again (what a host-side hook costs; the A/B for a GPU).
//! Prints one `RESULT {json}` line per measurement (tools/bench_unet_torch.py --compare parses them).
//! Thread count: RAYON_NUM_THREADS (candle's matmul and our kernels use the rayon pool).
//!
//! `-- --load-rss FILE` (internal): loads an SD 1.5 UNet from FILE and prints the process's peak RSS.

use std::collections::HashMap;
use std::time::Instant;

use std::sync::Mutex;

use candle_core::{DType, Device, Result, Shape, Tensor};
use candle_nn::var_builder::SimpleBackend;
use candle_nn::VarBuilder;
use diffusion::device::DeviceTensor;
use diffusion::unet::{
    AttentionHook, AttnCall, AttnKind, MapEdit, UNet2DConditionModel, UNetConfig,
};

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
/// as plain tensors so the inference path runs, and remembers them (for saving in f16).
struct RandomWeights {
    made: Mutex<HashMap<String, Tensor>>,
}

impl SimpleBackend for RandomWeights {
    fn get(
        &self,
        shape: Shape,
        name: &str,
        _: candle_nn::Init,
        dtype: DType,
        dev: &Device,
    ) -> Result<Tensor> {
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
        self.made
            .lock()
            .unwrap()
            .insert(name.to_string(), t.clone());
        Ok(t)
    }

    fn get_unchecked(&self, name: &str, _: DType, _: &Device) -> Result<Tensor> {
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
    fn route(&self, t: DeviceTensor) -> Result<DeviceTensor> {
        if self.via_host {
            t.same_device(&t.to_cpu()?)
        } else {
            Ok(t)
        }
    }
}

impl AttentionHook for InfEditShaped {
    fn qkv(
        &mut self,
        call: &AttnCall,
        q: DeviceTensor,
        k: DeviceTensor,
        v: DeviceTensor,
    ) -> Result<(DeviceTensor, DeviceTensor, DeviceTensor)> {
        if call.kind != AttnKind::SelfAttn || !call.batch.is_multiple_of(6) {
            return Ok((q, k, v));
        }
        let (q, k, v) = (self.route(q)?, self.route(k)?, self.route(v)?);
        let idx: Vec<u32> = (0..call.batch as u32)
            .map(|b| b - b % 3 + u32::from(b % 3 == 1))
            .collect();
        Ok((
            q.index_select(&idx, 0)?,
            k.index_select(&idx, 0)?,
            v.index_select(&idx, 0)?,
        ))
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

    fn probs(&mut self, call: &AttnCall, probs: DeviceTensor) -> Result<DeviceTensor> {
        let probs = self.route(probs)?;
        let parts = (0..call.batch)
            .map(|b| probs.narrow(0, b, 1))
            .collect::<Result<Vec<_>>>()?;
        DeviceTensor::cat(&parts.iter().collect::<Vec<_>>(), 0)
    }
}

/// Builds the SD 1.5 UNet with random weights; also returns the weights by name.
fn random_model(config: &UNetConfig) -> (UNet2DConditionModel, HashMap<String, Tensor>) {
    let backend = std::sync::Arc::new(RandomWeights {
        made: Mutex::new(HashMap::new()),
    });
    let vb = VarBuilder::from_backend(
        Box::new(SharedBackend(backend.clone())),
        DType::F32,
        Device::Cpu,
    );
    let model = UNet2DConditionModel::load(config, vb).expect("SD 1.5 UNet builds");
    let weights = std::mem::take(&mut *backend.made.lock().unwrap());
    (model, weights)
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
    ) -> Result<Tensor> {
        self.0.get(s, name, h, dtype, dev)
    }
    fn get_unchecked(&self, name: &str, dtype: DType, dev: &Device) -> Result<Tensor> {
        self.0.get_unchecked(name, dtype, dev)
    }
    fn contains_tensor(&self, name: &str) -> bool {
        self.0.contains_tensor(name)
    }
}

/// A `/proc/self/status` memory field in MB (`VmHWM` = peak RSS, `RssAnon` = heap, `RssFile` = mapped files).
fn status_mb(field: &str) -> f64 {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    status
        .lines()
        .find_map(|l| l.strip_prefix(field).and_then(|v| v.strip_prefix(':')))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<f64>().ok())
        .map(|kb| kb / 1024.0)
        .unwrap_or(f64::NAN)
}

fn peak_rss_mb() -> f64 {
    status_mb("VmHWM")
}

/// User + system CPU seconds of this process (from /proc/self/stat, 100 Hz ticks), to judge runs on a
/// machine shared with other work: wall time inflates under contention, CPU time much less.
fn cpu_seconds() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    // Fields after the parenthesised command name; utime and stime are fields 14 and 15 overall.
    let rest = stat.rsplit_once(')').map(|(_, r)| r).unwrap_or("");
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let ticks = |i: usize| {
        fields
            .get(i)
            .and_then(|v| v.parse::<f64>().ok())
            .unwrap_or(f64::NAN)
    };
    (ticks(11) + ticks(12)) / 100.0
}

fn arg_value(args: &[String], name: &str) -> Option<String> {
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1).cloned())
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if let Some(path) = arg_value(&args, "--load-rss") {
        let before = peak_rss_mb();
        let start = Instant::now();
        let files = [std::path::PathBuf::from(&path)];
        let vb =
            diffusion::loader::var_builder_from_files(&files, DType::F32, &Device::Cpu).unwrap();
        let model = UNet2DConditionModel::load(&config(), vb).unwrap();
        let secs = start.elapsed().as_secs_f64();
        println!(
            "RESULT {{\"impl\":\"candle\",\"what\":\"load_f16\",\"seconds\":{secs:.3},\"peak_rss_mb\":{:.0},\"anon_mb\":{:.0},\"file_mb\":{:.0},\"rss_before_mb\":{before:.0}}}",
            peak_rss_mb(),
            status_mb("RssAnon"),
            status_mb("RssFile")
        );
        drop(model);
        return;
    }
    let batches: Vec<usize> = arg_value(&args, "--batches")
        .unwrap_or_else(|| "1,6".into())
        .split(',')
        .map(|b| b.parse().expect("--batches takes a comma-separated list"))
        .collect();
    let runs: usize = arg_value(&args, "--runs")
        .map(|r| r.parse().unwrap())
        .unwrap_or(2);
    let size: usize = arg_value(&args, "--size")
        .map(|r| r.parse().unwrap())
        .unwrap_or(64);
    let small = args.iter().any(|a| a == "--small");
    let mut hook = match arg_value(&args, "--hook").as_deref() {
        None | Some("none") => None,
        Some("device") => Some(InfEditShaped { via_host: false }),
        Some("host") => Some(InfEditShaped { via_host: true }),
        Some(other) => panic!("--hook none|device|host, not {other}"),
    };
    let device = match arg_value(&args, "--device").as_deref() {
        None | Some("cpu") => None,
        Some(choice) => {
            let choice: gpu::DeviceChoice = choice.parse().expect("--device cpu|gpu|auto");
            diffusion::device::GpuDevice::open(choice).expect("a GPU opens")
        }
    };
    // Recommended for any inference binary (see its doc comment).
    diffusion::runtime::tune_allocator_for_inference();
    let threads = candle_core::utils::get_num_threads();
    let on = device.as_ref().map_or_else(
        || format!("CPU, {threads} threads"),
        |d| d.name().to_string(),
    );
    let which = if small { "small SD 1.5" } else { "SD 1.5" };
    let hooked = match &hook {
        None => "no hook",
        Some(h) if h.via_host => "InfEdit-shaped hook via the host",
        Some(_) => "InfEdit-shaped hook on the device",
    };
    eprintln!(
        "unet bench: {which} config, {size}x{size} latents, {on}, {hooked}, {runs} timed runs"
    );

    let start = Instant::now();
    let config = if small { small_config() } else { config() };
    let (model, weights) = random_model(&config);
    eprintln!("  random weights: {:.1} s", start.elapsed().as_secs_f64());
    for &batch in &batches {
        let sample = Tensor::randn(0f32, 1.0, (batch, 4, size, size), &Device::Cpu).unwrap();
        let context = Tensor::randn(0f32, 1.0, (batch, 77, 768), &Device::Cpu).unwrap();
        let t = Tensor::new(&[500f32], &Device::Cpu).unwrap();
        let mut times = Vec::new();
        let mut cpu_times = Vec::new();
        for run in 0..=runs {
            let (start, cpu_start) = (Instant::now(), cpu_seconds());
            let out = model
                .forward_on(
                    &sample,
                    &t,
                    &context,
                    None,
                    hook.as_mut().map(|h| h as &mut dyn AttentionHook),
                    device.as_ref(),
                )
                .unwrap();
            let (secs, cpu) = (start.elapsed().as_secs_f64(), cpu_seconds() - cpu_start);
            assert_eq!(out.dims(), &[batch, 4, size, size]);
            let note = if run == 0 { " (warm-up)" } else { "" };
            eprintln!("  batch {batch} run {run}: {secs:.3} s wall, {cpu:.2} s cpu{note}");
            if run > 0 {
                times.push(secs);
                cpu_times.push(cpu);
            }
        }
        if let Some(device) = &device {
            let estimate = config
                .activation_estimate(batch, size, size, 77, false)
                .unwrap();
            let (reserved, _) = device.memory_reserved_and_in_use();
            eprintln!(
                "  GPU memory: weights {:.0} MB ({} weights), activations estimated {:.0} MB, pools reserve {:.0} MB",
                device.weight_bytes() as f64 / 1e6,
                device.precision(),
                estimate.total() as f64 / 1e6,
                reserved as f64 / 1e6
            );
        }
        cpu_times.sort_by(|a, b| a.partial_cmp(b).unwrap());
        times.sort_by(|a, b| a.partial_cmp(b).unwrap());
        println!(
            "RESULT {{\"impl\":\"{}\",\"what\":\"forward\",\"hook\":\"{}\",\"batch\":{batch},\"size\":{size},\"threads\":{threads},\"seconds\":{:.3},\"cpu_seconds\":{:.2},\"peak_rss_mb\":{:.0}}}",
            if device.is_some() { "vcedit-gpu" } else { "candle" },
            match &hook {
                None => "none",
                Some(h) if h.via_host => "host",
                Some(_) => "device",
            },
            times[0],
            cpu_times[0],
            peak_rss_mb()
        );
    }
    drop(model);

    if small || device.is_some() || args.iter().any(|a| a == "--skip-load") {
        drop(weights);
        return;
    }
    // Peak memory of loading SD 1.5 stored in f16, measured in a fresh process.
    let path = std::env::temp_dir().join("vcedit-bench-sd15-unet-f16.safetensors");
    if !path.exists() {
        let half: HashMap<String, Tensor> = weights
            .iter()
            .map(|(k, v)| (k.clone(), v.to_dtype(DType::F16).unwrap()))
            .collect();
        candle_core::safetensors::save(&half, &path).unwrap();
    }
    let status = std::process::Command::new(std::env::current_exe().unwrap())
        .arg("--load-rss")
        .arg(&path)
        .status()
        .unwrap();
    assert!(status.success());
}
