//! What the GPU tests share: the test device, random inputs, and the comparison against the CPU
//! (the ops agree with their CPU twins to a relative error of [`TOLERANCE`]: max abs difference over the
//! reference's max abs value; lavapipe runs ~0.3 GFLOP/s, so shapes are tiny).

use std::sync::OnceLock;

pub use candle_core::{Device, Tensor};

use super::matmul::with_own_matmul;
pub use super::{GpuDevice, GpuTensor, Precision};
pub use crate::kernels::op_args::Addend;
pub use testkit::diff::tensor_relative_error as relative_error;

/// The test GPU (lavapipe in CI) shared by the tests of this binary, or `None` after the one line
/// `gpu::testing::context_or_skip` prints when there is no Vulkan device.
pub fn device_or_skip() -> Option<GpuDevice> {
    static DEVICE: OnceLock<GpuDevice> = OnceLock::new();
    if let Some(device) = DEVICE.get() {
        return Some(device.clone());
    }
    let device = GpuDevice::with_precision(gpu::testing::context_or_skip()?, Precision::F32);
    Some(DEVICE.get_or_init(|| device).clone())
}

/// The relative error the f32 ops must keep to against the CPU.
pub const TOLERANCE: f32 = 1e-4;

/// Standard normal f32 values of `shape`, on the CPU.
pub fn randn(shape: &[usize]) -> Tensor {
    Tensor::randn(0f32, 1.0, shape, &Device::Cpu).unwrap()
}

/// `t` uploaded to `device`.
pub fn up(device: &GpuDevice, t: &Tensor) -> GpuTensor {
    GpuTensor::upload(device, t).unwrap()
}

/// Asserts `gpu` matches `cpu` in shape and to the relative tolerance.
pub fn check(what: &str, gpu: &GpuTensor, cpu: &Tensor) {
    check_within(what, gpu, cpu, TOLERANCE);
}

/// Asserts `gpu` matches `cpu` in shape and to `tolerance` (max abs difference over max abs value);
/// returns the relative error.
pub fn check_within(what: &str, gpu: &GpuTensor, cpu: &Tensor, tolerance: f32) -> f32 {
    let rel = relative_error(&gpu.to_cpu().unwrap(), cpu);
    assert!(rel <= tolerance, "{what}: relative error {rel:.3e}");
    rel
}

/// `t` rounded to f16 and back (what an f16 weight or operand holds).
pub fn rounded_f16(t: &Tensor) -> Tensor {
    t.to_dtype(candle_core::DType::F16)
        .unwrap()
        .to_dtype(candle_core::DType::F32)
        .unwrap()
}

/// Runs a product test on both engines: CubeCL's matrix-product library (the default) and our own
/// register-blocked kernel (`VCEDIT_GPU_MATMUL=own`, and the fallback where the library declines).
pub fn on_both_engines(test: impl Fn()) {
    test();
    with_own_matmul(test);
}
