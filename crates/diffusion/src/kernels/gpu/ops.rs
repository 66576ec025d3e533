//! Host side of the GPU kernels: one function per op on [`GpuTensor`](super::GpuTensor)s, the same
//! semantics (shapes, broadcasting, layouts) as the CPU op it mirrors. Launches are asynchronous; errors
//! surface when a result is read back.
//!
//! Each op lives with its kernels in its family's file (`elementwise`, `layout`, `matmul`, `conv`,
//! `norm`, `attention`, `vgg`); this module gathers the public ones of every family, so a new op is
//! reachable here without a line of its own.

pub use super::attention::*;
pub use super::conv::*;
pub use super::elementwise::*;
pub use super::launch::TRANSIENT_CAP_BYTES;
pub use super::layout::*;
pub use super::matmul::*;
pub use super::norm::*;
pub use super::vgg::*;
