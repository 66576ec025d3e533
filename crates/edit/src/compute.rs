//! Where an edit's work runs: the CPU, or one GPU shared by the splatting engine and the networks (one
//! `--device` means one adapter). [`Compute`] only pairs the two engines' device seams —
//! [`diffusion::device::Device`] and [`splat::SplatDevice`] — which decide everything else; the CPU path
//! of each stays the reference its GPU path is tested against.

use diffusion::device::{Device, GpuDevice, Precision};
use gpu::{GpuContext, GpuError};
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

    /// "CPU" and its products' precision, or the adapter and the weights' precision, for logs and run.json.
    pub fn describe(&self) -> String {
        self.networks.describe()
    }
}

/// A GPU error where a candle error is expected (the networks' and the sampler's error type).
pub fn candle_err(e: GpuError) -> candle_core::Error {
    candle_core::Error::Msg(e.to_string())
}
