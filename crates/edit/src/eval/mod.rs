//! Measuring an edit: multi-view consistency and preservation (`metrics`, no weights needed) and CLIP
//! directional similarity (`clip_score`). LPIPS, the fits' perceptual loss, is a network of
//! `diffusion` (`diffusion::lpips`).

pub mod clip_score;
pub mod metrics;
