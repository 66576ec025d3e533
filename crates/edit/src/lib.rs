//! Editing: the InfEdit sampler, attention control, the VcEdit consistency modules and the editing loop.

pub mod align;
pub mod blend;
pub mod clip_score;
pub mod consistency;
pub mod control;
pub mod gif;
pub mod infedit;
pub mod lpips;
pub mod masks;
pub mod metrics;
pub mod model;
pub mod multiview;
pub mod noise;
pub mod outputs;
pub mod pipeline;
pub mod report;
pub mod train;
pub mod viz;
