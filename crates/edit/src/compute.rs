//! Where an edit's work runs: the CPU, or one GPU shared by the splatting engine and the networks (one
//! `--device` means one adapter). [`Compute`] only pairs the two engines' device seams —
//! [`diffusion::device::Device`] and [`splat::SplatDevice`] — which decide everything else; the CPU path
//! of each stays the reference its GPU path is tested against.

use diffusion::device::{Device, GpuDevice, Precision};
use gpu::{GpuContext, GpuError, GpuLimits};
use splat::SplatDevice;

/// The devices of a run: both engines on the CPU, or both on one GPU.
#[derive(Clone, Debug, Default)]
pub struct Compute {
    networks: Device,
    splat: SplatDevice,
}

impl Compute {
    /// Everything on the CPU.
    pub fn cpu() -> Self {
        Self::default()
    }

    /// Everything on the GPU `context` opens (`None`: the CPU), the networks' matrix weights held in
    /// `precision` there.
    pub fn on(context: Option<GpuContext>, precision: Precision) -> Self {
        match context {
            Some(ctx) => Self {
                networks: Device::Gpu(GpuDevice::with_precision(ctx.clone(), precision)),
                splat: SplatDevice::Gpu(ctx),
            },
            None => Self::cpu(),
        }
    }

    /// Where the networks run.
    pub fn networks(&self) -> &Device {
        &self.networks
    }

    /// Where the splatting engine runs.
    pub fn splat(&self) -> &SplatDevice {
        &self.splat
    }

    /// Whether the work runs on a GPU (both engines do, or neither).
    pub fn is_gpu(&self) -> bool {
        self.networks.is_gpu()
    }

    /// The GPU's limits (largest buffer, stated and free memory); `None` on the CPU.
    pub fn gpu_limits(&self) -> Option<&GpuLimits> {
        self.networks.gpu().map(|gpu| &gpu.context().limits)
    }

    /// The GPU's free memory when it was opened, where its vendor's interface reports it; `None` on the
    /// CPU and where unknown.
    pub fn gpu_free_bytes(&self) -> Option<u64> {
        self.gpu_limits()
            .and_then(|limits| limits.free_bytes_at_open)
    }

    /// Device memory `parameters` network weights take in the GPU's weight precision; `None` on the CPU
    /// (weights stay on the host there).
    pub fn gpu_weight_bytes(&self, parameters: u64) -> Option<u64> {
        self.networks
            .gpu()
            .map(|gpu| parameters * gpu.precision().weight_bytes_per_element() as u64)
    }

    /// "CPU" and its products' precision, or the adapter and the weights' precision, for logs and run.json.
    pub fn describe(&self) -> String {
        self.networks.describe()
    }
}

/// A GPU error where a candle error is expected (the networks' and the sampler's error type).
pub fn candle_err(e: GpuError) -> candle_core::Error {
    candle_core::Error::Msg(e.to_string())
}
