//! The measurement behind the README's stack decision (GPU > Stack): burn 0.22 (CPU backends `flex` and
//! `ndarray`, GPU backend `wgpu`, with fusion and autotune) against vcedit's own stack (candle tensors +
//! fused CPU kernels; CubeCL kernels through wgpu) on the same UNet, weights and inputs.
//!
//! ```text
//! cd tools/stack-bench
//! XDG_RUNTIME_DIR=/tmp cargo run --release -- conformance
//! XDG_RUNTIME_DIR=/tmp cargo run --release -- speed --config small --size 32 --batch 6 --runs 3
//! XDG_RUNTIME_DIR=/tmp cargo run --release -- speed --config sd15 --size 64 --batch 1 --backends ours-cpu,flex
//! ```
//!
//! `conformance` runs the tiny LCM UNet fixture (diffusers' own output is the reference); `speed` builds
//! random weights for an SD 1.5-shaped config (`small`: channels 64–256) and times one forward per run,
//! input upload and output read-back included on every backend, printing each backend's relative
//! difference from our CPU result. Backends: ours-cpu, ours-gpu, flex, ndarray, burn-wgpu.

mod burn_unet;

use std::collections::HashMap;
use std::path::PathBuf;
use std::time::Instant;

use burn::tensor::{Device, DeviceKind, Tensor, TensorData};
use burn_unet::{BurnUNet, HostWeights};
use candle_core::{DType, Device as Cpu, Tensor as CTensor};
use candle_nn::{VarBuilder, VarMap};
use diffusion::device::{GpuDevice, Precision};
use diffusion::unet::{UNet2DConditionModel, UNetConfig};

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn arg(args: &[String], name: &str) -> Option<String> {
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1).cloned())
}

/// One UNet call's inputs on the host.
struct Inputs {
    sample: CTensor,
    timesteps: Vec<f32>,
    context: CTensor,
    timestep_cond: Option<CTensor>,
}

fn host(t: &CTensor) -> (Vec<f32>, Vec<usize>) {
    (
        t.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
        t.dims().to_vec(),
    )
}

fn burn_tensor<const D: usize>(t: &CTensor, device: &Device) -> Tensor<D> {
    let (values, shape) = host(t);
    Tensor::from_data(TensorData::new(values, shape), device)
}

/// ‖a − b‖ / ‖b‖.
fn relative(a: &[f32], b: &[f32]) -> f64 {
    assert_eq!(a.len(), b.len());
    let (mut diff, mut norm) = (0f64, 0f64);
    for (x, y) in a.iter().zip(b) {
        diff += (*x as f64 - *y as f64).powi(2);
        norm += (*y as f64).powi(2);
    }
    (diff / norm.max(1e-30)).sqrt()
}

enum Backend {
    Ours(Option<GpuDevice>),
    Burn(Device),
}

fn open(name: &str) -> Backend {
    match name {
        "ours-cpu" => Backend::Ours(None),
        "ours-gpu" => {
            let context = gpu::open("gpu".parse().unwrap())
                .expect("a GPU opens")
                .expect("a GPU is there");
            Backend::Ours(Some(GpuDevice::with_precision(context, Precision::F32)))
        }
        "flex" => Backend::Burn(Device::flex()),
        #[allow(deprecated)]
        "ndarray" => Backend::Burn(Device::ndarray()),
        "burn-wgpu" => Backend::Burn(Device::wgpu(DeviceKind::DefaultDevice)),
        other => panic!("unknown backend {other}"),
    }
}

/// A loaded network on one backend.
enum Net {
    Ours(UNet2DConditionModel, Option<GpuDevice>),
    Burn(BurnUNet),
}

impl Net {
    fn load(backend: Backend, ours: &UNetConfig, weights: &HashMap<String, CTensor>) -> Net {
        match backend {
            Backend::Ours(device) => {
                let vb = VarBuilder::from_tensors(weights.clone(), DType::F32, &Cpu::Cpu);
                Net::Ours(UNet2DConditionModel::load(ours, vb).unwrap(), device)
            }
            Backend::Burn(device) => {
                let config = burn_unet::Config::from_ours(ours);
                let host: HostWeights = weights.iter().map(|(k, v)| (k.clone(), host(v))).collect();
                Net::Burn(BurnUNet::load(&config, &host, &device))
            }
        }
    }

    /// One forward, inputs uploaded and the prediction read back to the host.
    fn forward(&self, inputs: &Inputs) -> Vec<f32> {
        match self {
            Net::Ours(model, device) => {
                let t = CTensor::new(inputs.timesteps.as_slice(), &Cpu::Cpu).unwrap();
                let out = model
                    .forward_on(
                        &inputs.sample,
                        &t,
                        &inputs.context,
                        inputs.timestep_cond.as_ref(),
                        None,
                        &device
                            .clone()
                            .map_or(diffusion::device::Device::Cpu, diffusion::device::Device::Gpu),
                    )
                    .unwrap();
                host(&out).0
            }
            Net::Burn(model) => {
                let device = model.device();
                let out = model.forward(
                    burn_tensor(&inputs.sample, device),
                    &inputs.timesteps,
                    burn_tensor(&inputs.context, device),
                    inputs
                        .timestep_cond
                        .as_ref()
                        .map(|c| burn_tensor(c, device)),
                );
                out.into_data().try_to_vec::<f32>().unwrap()
            }
        }
    }
}

fn all_backends() -> String {
    "ours-cpu,flex,ndarray,ours-gpu,burn-wgpu".into()
}

fn backends(args: &[String]) -> Vec<String> {
    arg(args, "--backends")
        .unwrap_or_else(all_backends)
        .split(',')
        .map(String::from)
        .collect()
}

/// The tiny LCM UNet and diffusers' prediction for it (fixtures/unet/tiny-lcm.safetensors).
fn conformance(args: &[String]) {
    let dir = repo().join("fixtures/models/tiny-lcm/unet");
    let json = std::fs::read_to_string(dir.join("config.json")).unwrap();
    let ours = UNetConfig::from_json(&json).unwrap();
    let weights =
        candle_core::safetensors::load(dir.join("diffusion_pytorch_model.safetensors"), &Cpu::Cpu)
            .unwrap();
    let weights: HashMap<String, CTensor> = weights
        .into_iter()
        .map(|(k, v)| (k, v.to_dtype(DType::F32).unwrap()))
        .collect();
    let fx = candle_core::safetensors::load(
        repo().join("fixtures/unet/tiny-lcm.safetensors"),
        &Cpu::Cpu,
    )
    .unwrap();
    let batch = fx["sample"].dims()[0];
    let timesteps: Vec<f32> = fx["timesteps"]
        .to_dtype(DType::F32)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1()
        .unwrap();
    let timesteps = if timesteps.len() == 1 {
        vec![timesteps[0]; batch]
    } else {
        timesteps
    };
    let inputs = Inputs {
        sample: fx["sample"].clone(),
        timesteps,
        context: fx["encoder_hidden_states"].clone(),
        timestep_cond: fx.get("timestep_cond").cloned(),
    };
    let reference = host(&fx["noise_pred"]).0;
    println!("conformance: tiny LCM UNet, batch {batch}, relative error against diffusers");
    for name in backends(args) {
        let net = Net::load(open(&name), &ours, &weights);
        let out = net.forward(&inputs);
        println!("  {name:>10}: {:.2e}", relative(&out, &reference));
    }
}

/// Random weights for `config`: the names and shapes our loader asks for, uniform in ±√(3/fan-in)
/// (norm weights 1 ± 0.1, biases ± 0.1).
fn random_weights(config: &UNetConfig) -> HashMap<String, CTensor> {
    let varmap = VarMap::new();
    let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Cpu::Cpu);
    UNet2DConditionModel::load(config, vb).unwrap();
    let vars = varmap.data().lock().unwrap();
    vars.iter()
        .map(|(name, var)| {
            let dims = var.dims().to_vec();
            let (lo, hi) = if dims.len() == 1 {
                if name.ends_with("weight") {
                    (0.9, 1.1)
                } else {
                    (-0.1, 0.1)
                }
            } else {
                let fan_in: usize = dims[1..].iter().product();
                let bound = (3.0 / fan_in as f64).sqrt();
                (-bound, bound)
            };
            let t = CTensor::rand(lo as f32, hi as f32, dims, &Cpu::Cpu).unwrap();
            (name.clone(), t)
        })
        .collect()
}

fn speed(args: &[String]) {
    let which = arg(args, "--config").unwrap_or_else(|| "small".into());
    let size: usize = arg(args, "--size").map_or(32, |s| s.parse().unwrap());
    let batch: usize = arg(args, "--batch").map_or(6, |s| s.parse().unwrap());
    let runs: usize = arg(args, "--runs").map_or(3, |s| s.parse().unwrap());
    let mut ours = UNetConfig::sd15();
    match which.as_str() {
        "small" => ours.block_out_channels = vec![64, 128, 256, 256],
        "sd15" => {}
        other => panic!("--config small|sd15, not {other}"),
    }
    let weights = random_weights(&ours);
    let inputs = Inputs {
        sample: CTensor::randn(0f32, 1.0, (batch, 4, size, size), &Cpu::Cpu).unwrap(),
        timesteps: vec![500.0; batch],
        context: CTensor::randn(0f32, 1.0, (batch, 77, 768), &Cpu::Cpu).unwrap(),
        timestep_cond: None,
    };
    println!(
        "speed: {which} UNet, {size}x{size} latents, batch {batch}, {runs} timed runs after a warm-up, {} threads",
        std::thread::available_parallelism().map_or(0, |n| n.get())
    );
    let mut reference: Option<(String, Vec<f32>)> = None;
    for name in backends(args) {
        let start = Instant::now();
        let net = Net::load(open(&name), &ours, &weights);
        let load = start.elapsed().as_secs_f64();
        let start = Instant::now();
        let first = net.forward(&inputs);
        let warm = start.elapsed().as_secs_f64();
        let mut times: Vec<f64> = (0..runs)
            .map(|_| {
                let start = Instant::now();
                let out = net.forward(&inputs);
                assert_eq!(out.len(), first.len());
                start.elapsed().as_secs_f64()
            })
            .collect();
        times.sort_by(|a, b| a.partial_cmp(b).unwrap());
        let against = match &reference {
            Some((r, values)) => format!("{:.1e} from {r}", relative(&first, values)),
            None => "reference".into(),
        };
        println!(
            "  {name:>10}: median {:.3} s, min {:.3} s (load {load:.1} s, warm-up {warm:.1} s); output {against}",
            times[times.len() / 2],
            times[0],
        );
        if reference.is_none() {
            reference = Some((name.clone(), first));
        }
        drop(net);
    }
}

/// One matrix product at SD 1.5's first-level feed-forward shape (4096 × 320 × 1280) on our GPU kernel
/// and on burn-wgpu: best of `--runs`, upload excluded, read-back included.
fn matmul(args: &[String]) {
    let runs: usize = arg(args, "--runs").map_or(3, |s| s.parse().unwrap());
    let (m, k, n) = (4096, 320, 1280);
    let a = CTensor::randn(0f32, 1.0, (m, k), &Cpu::Cpu).unwrap();
    let b = CTensor::randn(0f32, 1.0, (k, n), &Cpu::Cpu).unwrap();
    let want = host(&a.matmul(&b).unwrap()).0;
    let gflop = 2.0 * (m * k * n) as f64 / 1e9;
    let best = |f: &mut dyn FnMut() -> Vec<f32>| {
        let got = f();
        let secs = (0..runs)
            .map(|_| {
                let start = Instant::now();
                f();
                start.elapsed().as_secs_f64()
            })
            .fold(f64::INFINITY, f64::min);
        (secs, relative(&got, &want))
    };
    let Backend::Ours(Some(device)) = open("ours-gpu") else {
        unreachable!()
    };
    let (ga, gb) = (
        diffusion::device::GpuTensor::upload(&device, &a).unwrap(),
        diffusion::device::GpuTensor::upload(&device, &b).unwrap(),
    );
    let (secs, err) = best(&mut || {
        host(
            &diffusion::device::ops::matmul(&ga, &gb)
                .unwrap()
                .to_cpu()
                .unwrap(),
        )
        .0
    });
    println!(
        "  ours-gpu  matmul {m}x{k}x{n}: {:.1} ms, {:.2} GFLOP/s (error {err:.1e})",
        secs * 1e3,
        gflop / secs
    );
    let device = Device::wgpu(DeviceKind::DefaultDevice);
    let (ba, bb): (Tensor<2>, Tensor<2>) = (burn_tensor(&a, &device), burn_tensor(&b, &device));
    let (secs, err) = best(&mut || {
        ba.clone()
            .matmul(bb.clone())
            .into_data()
            .try_to_vec::<f32>()
            .unwrap()
    });
    println!(
        "  burn-wgpu matmul {m}x{k}x{n}: {:.1} ms, {:.2} GFLOP/s (error {err:.1e})",
        secs * 1e3,
        gflop / secs
    );
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    match args.first().map(String::as_str) {
        Some("conformance") => conformance(&args),
        Some("speed") => speed(&args),
        Some("matmul") => matmul(&args),
        _ => {
            eprintln!("usage: stack-bench conformance|speed [--backends {}] [--config small|sd15] [--size N] [--batch B] [--runs R]", all_backends());
            std::process::exit(2);
        }
    }
}
