//! VAE / TAESD timing with random weights (SD 1.x configs), f32 on the CPU.
//!
//! `cargo bench -p vcedit-diffusion --bench vae [-- SIZE]` (SIZE = image side in pixels, default 256).
//! `python tools/bench_vae.py SIZE` times diffusers on the same shapes for comparison. Threads: RAYON_NUM_THREADS.

use std::collections::HashMap;
use std::time::Instant;

use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
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
    f(); // warm-up
    let start = Instant::now();
    for _ in 0..runs {
        std::hint::black_box(f());
    }
    println!(
        "{label}: {:.3} s",
        start.elapsed().as_secs_f64() / runs as f64
    );
}

fn main() {
    let size: usize = std::env::args()
        .skip(1)
        .find_map(|a| a.parse().ok())
        .unwrap_or(256);
    let dev = Device::Cpu;
    let image = Tensor::rand(-1f32, 1.0, (1, 3, size, size), &dev).unwrap();
    let latents = Tensor::randn(0f32, 1.0, (1, 4, size / 8, size / 8), &dev).unwrap();
    println!(
        "image {size}x{size}, latents {}x{}, threads {}",
        size / 8,
        size / 8,
        rayon::current_num_threads()
    );

    let cfg = AutoencoderKLConfig::sd15();
    let vae = AutoencoderKL::new(&cfg, random_weights(|vb| AutoencoderKL::new(&cfg, vb))).unwrap();
    time("AutoencoderKL encode_mean", 2, || {
        vae.encode_mean(&image).unwrap()
    });
    time("AutoencoderKL decode", 2, || vae.decode(&latents).unwrap());

    let cfg = TaesdConfig::default();
    let tiny =
        AutoencoderTiny::new(&cfg, random_weights(|vb| AutoencoderTiny::new(&cfg, vb))).unwrap();
    time("TAESD encode", 3, || tiny.encode(&image).unwrap());
    time("TAESD decode", 3, || tiny.decode(&latents).unwrap());
}
