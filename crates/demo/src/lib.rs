//! The self-made demo: a procedural world of Gaussian objects, the small SD-architecture model trained on it, and `vcedit demo`.

pub mod world;
