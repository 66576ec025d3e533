//! CLIP's two towers, built from one transformer encoder layer: the text encoder (the UNet's
//! cross-attention context, and CLIP scores' text side) and the vision encoder (CLIP scores' image side).

mod encoder;
mod text;
mod vision;

pub use encoder::ClipActivation;
pub use text::{ids_tensor, ClipError, ClipTextConfig, ClipTextModel};
pub use vision::{ClipVisionConfig, ClipVisionModel};
