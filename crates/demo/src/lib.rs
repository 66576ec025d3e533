//! The self-made demo: a procedural world of Gaussian objects, the small SD-architecture model trained on it, and `vcedit demo`.

pub mod bpe;
pub mod run;
pub mod sample;
pub mod train;
pub mod world;
