//! Stable Diffusion 1.x components on candle (CPU) with attention hooks, conformant with diffusers.
//!
//! Network code (`clip`, `layers`, `unet`, `vae`, `taesd`) computes through the private `kernels` module,
//! one function per op; weight files are opened by `weights` (safetensors headers, memory-mapped tensors).

pub mod clip;
mod kernels;
/// Where a network runs: the [`Device`](device::Device) seam (CPU or GPU) and its tensors.
pub mod device {
    pub use crate::kernels::bf16::{
        clear_weight_cache as clear_cpu_weight_cache, weight_cache_bytes,
    };
    pub use crate::kernels::gpu::{ops, GpuDevice, GpuTensor, Precision, UnknownPrecision};
    pub use crate::kernels::{
        bf16_products_available, cpu_precision, set_cpu_precision, with_cpu_precision,
        Bf16Unavailable, CpuPrecision, CpuPrecisionError,
    };
    pub use crate::kernels::{Device, DeviceTensor, Storage, Unary};
}
mod layers;
pub mod loader;
pub mod lpips;
pub mod model_check;
pub mod runtime;
pub mod scheduler;
pub mod taesd;
pub mod tokenizer;
pub mod unet;
pub mod vae;
mod weights;
