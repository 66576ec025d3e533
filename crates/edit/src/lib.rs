//! Editing: VcEdit's text-driven, view-consistent editing of a 3D Gaussian Splatting scene, by stage.
//!
//! - [`sampler`]: InfEdit, the single-view editor (attention control, token alignment, local blend, the
//!   model and its noise);
//! - [`consistency`]: VcEdit's multi-view sampler and the paper's modules, one file each: CCM
//!   (`consistency/ccm.rs`), ECM (`consistency/ecm.rs`) and blend-map consistency (`consistency/blend.rs`),
//!   on the shared lift-and-render-back (`consistency/lift.rs`);
//! - [`compute`]: the device a run uses (CPU, or one GPU for splatting and networks);
//! - [`fit`]: fitting Gaussians to edited images (the loop's fit; ECM's fits start from it);
//! - [`run`]: the editing loop (render → joint edit → fit), masks, checkpoints and outputs;
//! - [`eval`]: metrics, LPIPS and CLIP scores;
//! - [`present`]: the HTML report, the turntable GIF and attention images.

pub mod compute;
pub mod consistency;
pub mod eval;
pub mod fit;
pub mod ledger;
pub mod present;
pub mod run;
pub mod sampler;
