//! Measuring an edit: multi-view consistency and preservation (`metrics`, no weights needed), LPIPS (also the
//! fits' perceptual loss) and CLIP directional similarity (`clip_score`).

pub mod clip_score;
pub mod lpips;
pub mod metrics;
