//! VAE / TAESD timing with random weights (SD 1.x configs), f32 on the CPU or on a GPU.
//!
//! `cargo bench -p vcedit-diffusion --bench vae [-- SIZE] [--batch N] [--device cpu|gpu|auto]
//! [--precision f16|f32]` (SIZE = image side in pixels, default 256; batch default 1; `gpu` takes a
//! software adapter such as lavapipe too).
//! `python tools/bench_vae.py SIZE` times diffusers on the same shapes for comparison. Threads: RAYON_NUM_THREADS.

use std::collections::HashMap;
use std::time::Instant;

use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use diffusion::device::{GpuDevice, Precision};
use diffusion::taesd::{AutoencoderTiny, TaesdConfig};
use diffusion::vae::{AutoencoderKL, AutoencoderKLConfig};

/// Random plain tensors for every parameter (no `Var`s, so the fused inference kernels run).
fn random_weights<T>(build: impl Fn(VarBuilder) -> candle_core::Result<T>) -> VarBuilder<'static> {
    let varmap = VarMap::new();
    build(VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu)).unwrap();
    let tensors: HashMap<String, Tensor> = varmap
        .data()
        .lock()
        .unwrap()
        .iter()
        .map(|(k, v)| (k.clone(), (v.as_tensor().detach() * 0.05).unwrap()))
        .collect();
    VarBuilder::from_tensors(tensors, DType::F32, &Device::Cpu)
}

fn time<T>(label: &str, runs: usize, mut f: impl FnMut() -> T) {
    // The first call also compiles the GPU kernels it meets (a per-process cost), so it is shown apart.
    let start = Instant::now();
    f();
    let first = start.elapsed().as_secs_f64();
    let start = Instant::now();
    for _ in 0..runs {
        std::hint::black_box(f());
    }
    println!(
        "{label}: {:.3} s (first call {first:.3} s)",
        start.elapsed().as_secs_f64() / runs as f64
    );
}

fn arg_value(args: &[String], name: &str) -> Option<String> {
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1).cloned())
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    // The size is the first bare number (not the value of a flag).
    let size: usize = args
        .iter()
        .enumerate()
        .find(|&(i, _)| i == 0 || !args[i - 1].starts_with("--"))
        .and_then(|(_, a)| a.parse().ok())
        .unwrap_or(256);
    let batch: usize = arg_value(&args, "--batch").map_or(1, |b| b.parse().expect("--batch N"));
    let precision: Precision = arg_value(&args, "--precision")
        .unwrap_or_else(|| "f16".into())
        .parse()
        .expect("--precision f16|f32");
    let gpu = match arg_value(&args, "--device").as_deref() {
        None | Some("cpu") => None,
        Some(choice) => {
            let choice: gpu::DeviceChoice = choice.parse().expect("--device cpu|gpu|auto");
            GpuDevice::open(choice)
                .expect("a GPU opens")
                .map(|d| GpuDevice::with_precision(d.context().clone(), precision))
        }
    };
    let gpu = gpu.as_ref();
    let dev = Device::Cpu;
    let image = Tensor::rand(-1f32, 1.0, (batch, 3, size, size), &dev).unwrap();
    let latents = Tensor::randn(0f32, 1.0, (batch, 4, size / 8, size / 8), &dev).unwrap();
    println!(
        "image {size}x{size}, latents {}x{}, batch {batch}, {}",
        size / 8,
        size / 8,
        gpu.map_or_else(
            || format!("CPU, {} threads", rayon::current_num_threads()),
            |g| format!("{} ({} weights)", g.name(), g.precision())
        )
    );

    let cfg = AutoencoderKLConfig::sd15();
    let vae = AutoencoderKL::new(&cfg, random_weights(|vb| AutoencoderKL::new(&cfg, vb))).unwrap();
    time("AutoencoderKL encode (moments)", 2, || {
        vae.encode_on(&image, gpu).unwrap()
    });
    time("AutoencoderKL decode", 2, || {
        vae.decode_on(&latents, gpu).unwrap()
    });

    let cfg = TaesdConfig::default();
    let tiny =
        AutoencoderTiny::new(&cfg, random_weights(|vb| AutoencoderTiny::new(&cfg, vb))).unwrap();
    time("TAESD encode", 3, || tiny.encode_on(&image, gpu).unwrap());
    time("TAESD decode", 3, || tiny.decode_on(&latents, gpu).unwrap());
}
