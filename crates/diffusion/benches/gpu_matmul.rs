//! GPU matrix products at the shapes of SD 1.5's first level at 512² (4096 tokens × 320 channels): the
//! projections (k = n = 320) and the feed-forward (n = 1280), as a plain product and as a linear layer
//! (weight [n, k], read transposed), in f32 and with f16 weights.
//!
//! `cargo bench -p vcedit-diffusion --bench gpu_matmul [-- --runs 3 --device gpu --precisions f32,f16]`
//! Prints one `RESULT {json}` line per measurement. On Mesa lavapipe (a CPU rasteriser) the numbers only
//! hint at how a kernel change moves real-GPU speed.

use std::time::Instant;

use candle_core::{Device, Tensor};
use diffusion::device::{ops, GpuDevice, GpuTensor, Precision};

fn arg_value(args: &[String], name: &str) -> Option<String> {
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1).cloned())
}

/// Best wall time of `runs` calls of `f` (after one warm-up call that also compiles the kernel).
fn best_of(runs: usize, mut f: impl FnMut() -> GpuTensor) -> f64 {
    f().to_cpu().expect("warm-up read-back");
    (0..runs)
        .map(|_| {
            let start = Instant::now();
            f().to_cpu().expect("read-back");
            start.elapsed().as_secs_f64()
        })
        .fold(f64::INFINITY, f64::min)
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let runs: usize = arg_value(&args, "--runs")
        .map(|r| r.parse().expect("--runs takes a number"))
        .unwrap_or(3);
    let choice: gpu::DeviceChoice = arg_value(&args, "--device")
        .unwrap_or_else(|| "gpu".into())
        .parse()
        .expect("--device gpu|auto");
    let Some(context) = gpu::open(choice).expect("a GPU opens") else {
        eprintln!("gpu_matmul bench: no GPU (device {choice:?}); nothing to measure");
        return;
    };
    let precisions: Vec<Precision> = arg_value(&args, "--precisions")
        .unwrap_or_else(|| "f32,f16".into())
        .split(',')
        .map(|p| p.parse().expect("--precisions takes f32 and/or f16"))
        .collect();
    for precision in precisions {
        let device = GpuDevice::with_precision(context.clone(), precision);
        eprintln!("gpu_matmul bench on {}, {precision} weights", device.name());
        for (m, k, n) in [(4096, 320, 320), (4096, 320, 1280)] {
            let a = Tensor::randn(0f32, 1.0, (m, k), &Device::Cpu).unwrap();
            let b = Tensor::randn(0f32, 1.0, (k, n), &Device::Cpu).unwrap();
            let w = Tensor::randn(0f32, 1.0, (n, k), &Device::Cpu).unwrap();
            let ga = GpuTensor::upload(&device, &a).unwrap();
            let gb = GpuTensor::upload(&device, &b).unwrap();
            let gw = device.cached(&w).unwrap();
            let gflop = 2.0 * (m * k * n) as f64 / 1e9;
            let mut timed = vec![(
                "linear",
                best_of(runs, || ops::linear(&ga, &gw, None).unwrap()),
            )];
            if precision == Precision::F32 {
                // Activation × activation products do not depend on the weight precision.
                timed.push(("matmul", best_of(runs, || ops::matmul(&ga, &gb).unwrap())));
            }
            for (what, secs) in timed {
                eprintln!(
                    "  {what} {m}x{k}x{n}: {:.1} ms, {:.2} GFLOP/s",
                    secs * 1e3,
                    gflop / secs
                );
                println!(
                    "RESULT {{\"what\":\"{what}\",\"precision\":\"{precision}\",\"m\":{m},\"k\":{k},\"n\":{n},\"seconds\":{secs:.4},\"gflops\":{:.2},\"device\":\"{}\"}}",
                    gflop / secs,
                    device.name()
                );
            }
        }
    }
}
