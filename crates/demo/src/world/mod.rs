//! A procedural world for the demo: objects built directly from Gaussians (no fitting), with colours and
//! surface patterns, captions in a small fixed grammar, a dataset of (render, caption) pairs from random
//! orbit views, and an oracle that measures edit fidelity without CLIP.
//!
//! - [`shape`]: [`ShapeKind`] (the object words of the captions) and [`Shape`] (their dimensions).
//! - [`spec`]: [`SceneSpec`] (what a scene contains, serde), random or caption-driven generation.
//! - [`caption`](mod@caption): the caption grammar and [`VOCABULARY`], [`caption()`](caption::caption) and
//!   [`parse_caption`].
//! - [`build`]: spec to Gaussians ([`build_scene`]) with per-Gaussian labels (object, part, colour slot).
//! - [`dataset`]: random orbit views, rendered samples, deterministic parallel streams, sample grids.
//! - [`oracle`]: per-pixel label images and edit fidelity / preservation scores.
//!
//! World conventions: z is up, the floor is z = 0, objects are about one unit across.

pub mod build;
pub mod caption;
pub mod dataset;
pub(crate) mod geometry;
pub mod oracle;
pub mod palette;
pub mod pattern;
pub mod shape;
pub mod spec;

pub use build::{build_scene, BuildSettings, BuiltScene, GaussianLabels, Slot};
pub use caption::{caption, parse_caption, Appearance, CaptionError, VOCABULARY};
pub use dataset::{DatasetConfig, OrbitView, Sample, ViewSampling};
pub use geometry::Part;
pub use oracle::{EditScore, LabelImage, Oracle, OracleSettings};
pub use palette::{ColorName, ColorSpec};
pub use pattern::{Orientation, Pattern, PatternKind};
pub use shape::{Shape, ShapeKind};
pub use spec::{GeneratorSettings, ObjectSpec, SceneSpec};

use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
pub enum WorldError {
    #[error(transparent)]
    Caption(#[from] CaptionError),
    /// Two specs that should share their geometry do not (or an edit asks for a different object).
    #[error("{0}")]
    Incompatible(String),
    /// Images handed to the oracle do not fit its cameras.
    #[error("{0}")]
    Input(String),
    #[error("{}: cannot write: {msg}", path.display())]
    Write { path: PathBuf, msg: String },
}
