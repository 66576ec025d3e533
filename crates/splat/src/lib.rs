//! Gaussian splatting engine: scenes, cameras, a differentiable renderer (CPU reference and GPU), lifting
//! of 2D maps onto Gaussians, and the trainer that fits scenes to images.
//!
//! Layout, by concern:
//! - types: [`scene`] ([`GaussianScene`]), [`cameras`] ([`Camera`] and the camera readers), [`image`];
//! - input/output: [`formats`] (every scene reader and writer; [`read_scene`] and [`open_scene`] the
//!   entries);
//! - rendering: [`render`] (CPU: projection → tile binning → rasterisation, each with its backward; and
//!   `render::gpu`, the CubeCL twins); [`lift`] (on the CPU and in `lift::gpu`), both joined behind
//!   [`SplatDevice`], the device seam;
//! - training, above them: [`train`] (the trainer, optimiser, densification, anchors, losses,
//!   checkpoints, the scene fit; the device-resident steps in `train::gpu`).
//!
//! Conventions used everywhere in this crate (and by every crate above it):
//! - Cameras are OpenCV cameras: x right, y down, z forward; `world_to_camera` maps world points into that
//!   frame. Pixel (i, j) (column i, row j) covers [i, i+1) x [j, j+1); its centre is (i + 0.5, j + 0.5).
//! - Images are row-major, channel-interleaved `f32` in [0, 1] unless said otherwise.
//! - Scene parameters are stored as the INRIA trainer stores them: log-scales, logit-opacities,
//!   unnormalised quaternions (w, x, y, z), and SH coefficients.

pub mod cameras;
mod device;
pub mod formats;
pub mod image;
mod layout;
pub mod lift;
pub mod render;
pub mod scene;
pub mod train;

/// The GPU the device seam runs on (opened with the `gpu` crate) and its error.
pub use ::gpu::{GpuContext, GpuError};
pub use cameras::Camera;
pub use device::{cpu_lift_round_bytes, LiftSession, Lifter, SplatDevice};
/// The INRIA PLY reader and writer, at their historical path.
pub use formats::ply;
pub use formats::{
    open_scene, read_scene, write_scene, FormatError, OpenError, OutputFormat, WriteReport,
};
pub use image::Image;
pub use scene::GaussianScene;

/// The GPU stages behind [`SplatDevice`] (projection + binning + rasterisation, its backward, the resident
/// trainer, the device loss), for the benches that time them one by one: not a stable interface, and
/// only built with the `stages` feature.
#[cfg(feature = "stages")]
#[doc(hidden)]
pub mod stages {
    pub use crate::render::gpu::{render_backward_device, render_device, GpuOutputGrads, GpuScene};
    pub use crate::train::gpu::{l1_dssim_weighted, DeviceTrainer};
}
