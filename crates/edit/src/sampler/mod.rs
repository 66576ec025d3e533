//! The single-view editor: InfEdit (inversion-free editing with an LCM, docs/algorithm.md §2) and what it is
//! built from. VcEdit's multi-view sampler (`consistency`) drives the same per-view state step by step.
//!
//! - `infedit`: the edit plan (text conditioning, alignment, timesteps), the per-view state and the DDCM step;
//! - `batch`: which UNet samples (branch × guidance half) a pass computes;
//! - `control`: InfEdit's unified attention control, one attention hook per view;
//! - `align`: token alignment between the source and target prompts;
//! - `local_blend`: the local blend, where the edit may change the latents;
//! - `model`: the diffusion model an edit runs on, and images ↔ tensors;
//! - `noise`: where the random numbers come from.

mod align;
mod batch;
mod control;
mod infedit;
mod local_blend;
mod model;
mod noise;

pub use align::{align_prompts, global_align, AlignError, AlignInputs, TokenAlignment};
pub use batch::{BatchLayout, Branch, Sample, SampleSettings};
pub use control::{ControlSettings, EditController, RecordedMaps, DEFAULT_STORE_MAX_TOKENS};
pub use infedit::{
    edit_image, EditError, EditOutcome, EditPlan, EditPrompts, InfEditSettings, ViewState,
};
pub use local_blend::BlendThresholds;
pub use model::{image_to_tensor, tensor_to_images, EditModel, ModelError};
pub use noise::{NoiseSource, RecordedNoise, SeededNoise};

pub(crate) use local_blend::{blend_maps, mean_over_layers_and_heads};
