//! Stable Diffusion 1.x components on candle (CPU) with attention hooks, conformant with diffusers.

pub mod clip;
pub mod conv;
pub mod layers;
pub mod loader;
pub mod model_check;
pub mod scheduler;
pub mod taesd;
pub mod tokenizer;
pub mod train_ops;
pub mod unet;
pub mod vae;
