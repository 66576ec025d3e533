//! Helpers shared by the integration tests.

// Each test binary uses a subset.
#![allow(dead_code)]

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use candle_core::{Device, Tensor};
use diffusion::device::Precision;

/// A folder in the original `taesd.py` layout (`taesd_encoder.safetensors` + `taesd_decoder.safetensors`)
/// holding the tiny random bf16 weights. They are committed as one file with `encoder.`/`decoder.` key
/// prefixes: files named like the real TAESD weights belong to ../shared/assets, not to this repository.
pub fn tiny_original_layout(dir: &Path) -> PathBuf {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../fixtures/vae/taesd-tiny-original-weights.safetensors");
    let all = candle_core::safetensors::load(&path, &Device::Cpu)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    for part in ["encoder", "decoder"] {
        let prefix = format!("{part}.");
        let tensors: HashMap<String, Tensor> = all
            .iter()
            .filter_map(|(k, v)| k.strip_prefix(&prefix).map(|k| (k.to_string(), v.clone())))
            .collect();
        assert!(!tensors.is_empty(), "no {part} weights");
        candle_core::safetensors::save(&tensors, dir.join(format!("taesd_{part}.safetensors")))
            .unwrap();
    }
    dir.to_path_buf()
}

// Each test binary uses a subset.
#[allow(unused_imports)]
pub use testkit::diff::{
    tensor_max_abs_diff as max_abs_diff, tensor_relative_error as relative_error,
    tensor_relative_l2 as relative_l2,
};

/// Runs `f` with bf16 products, or returns `None` after one printed line on a CPU without them.
pub fn in_bf16<R>(f: impl FnOnce() -> R) -> Option<R> {
    use diffusion::device::{with_cpu_precision, CpuPrecision};
    match with_cpu_precision(CpuPrecision::Bf16, f) {
        Ok(r) => Some(r),
        Err(e) => {
            eprintln!("skipped: {e}");
            None
        }
    }
}

/// The test GPU (lavapipe in CI) with f32 weights, or `None` after one printed line when there is no
/// Vulkan device.
pub fn gpu_or_skip() -> Option<diffusion::device::GpuDevice> {
    gpu::testing::context_or_skip()
        .map(|ctx| diffusion::device::GpuDevice::with_precision(ctx, Precision::F32))
}

/// The test GPU twice, each with the relative error its output may have against the CPU: f32 weights
/// (1e-4, the CPU's numbers up to summation order) and f16 weights with f32 arithmetic (1e-2). Empty
/// after one printed line when there is no Vulkan device.
pub fn gpus_or_skip() -> Vec<(diffusion::device::GpuDevice, f32)> {
    let Some(ctx) = gpu::testing::context_or_skip() else {
        return Vec::new();
    };
    [(Precision::F32, 1e-4), (Precision::F16, 1e-2)]
        .into_iter()
        .map(|(p, tolerance)| {
            let device = diffusion::device::GpuDevice::with_precision(ctx.clone(), p);
            (device, tolerance)
        })
        .collect()
}
