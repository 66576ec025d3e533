//! Gaussian splatting engine: scenes, cameras, a differentiable CPU renderer, lifting of 2D maps onto
//! Gaussians, and the optimiser that fits scenes to images.
//!
//! Conventions used everywhere in this crate (and by every crate above it):
//! - Cameras are OpenCV cameras: x right, y down, z forward; `world_to_camera` maps world points into that
//!   frame. Pixel (i, j) (column i, row j) covers [i, i+1) x [j, j+1); its centre is (i + 0.5, j + 0.5).
//! - Images are row-major, channel-interleaved `f32` in [0, 1] unless said otherwise.
//! - Scene parameters are stored as the INRIA trainer stores them: log-scales, logit-opacities,
//!   unnormalised quaternions (w, x, y, z), and SH coefficients.

pub mod anchor;
pub mod camera;
pub mod cameras;
pub mod checkpoint;
pub mod densify;
pub mod fit;
pub mod formats;
pub mod gpu;
pub mod image;
mod layout;
pub mod lift;
pub mod loss;
pub mod open;
pub mod optim;
pub mod render;
pub mod scene;
pub mod train;

pub use camera::Camera;
/// The INRIA PLY reader and writer, at their historical path.
pub use formats::ply;
pub use formats::{read_scene, write_scene, FormatError, OutputFormat, WriteReport};
pub use image::Image;
pub use open::{open_scene, OpenError};
pub use scene::GaussianScene;
