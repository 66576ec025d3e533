//! What vcedit's tests share, in one place (a dev-dependency only; nothing here ships in the binary):
//!
//! - [`diff`]: how far two results are apart (largest absolute difference, relative L2), for slices and
//!   for candle tensors.
//! - [`paths`]: the repository's committed fixtures and the machine's shared third-party assets.
//! - [`scenes`]: small generated Gaussian scenes (a ball, a textured sphere) for end-to-end tests.
//! - [`output`]: reading a finished `vcedit` process's output in a test.
//! - [`fuzz`]: the file readers' mutation fuzzer, with its counting allocator.
//!
//! The GPU test device stays in `gpu::testing`: the gpu crate's own unit tests need it, and a crate's
//! unit tests cannot take their own types from a crate built on top of it.

pub mod diff;
pub mod fuzz;
pub mod output;
pub mod paths;
pub mod scenes;
