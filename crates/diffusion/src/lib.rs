//! Stable Diffusion 1.x components on candle (CPU) with attention hooks, conformant with diffusers.

crates/diffusion/src/layers.rs

pub mod layers;
pub mod loader;
pub mod taesd;
pub mod tokenizer;
pub mod vae;
