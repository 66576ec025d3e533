//! The VcEdit editing loop (docs/algorithm.md §0), with its checkpoints and outputs.
//!
//! Iteration k: render the V selected views of the current scene, edit them jointly with the multi-view
//! sampler (iteration 0: source → target; later iterations: target → target, re-editing the current
//! renders), then fit the scene to those guidance images for `fit_steps` single-view steps. Every iteration
//! ends with an atomic checkpoint, so `--resume` continues after an interruption and gives the same result
//! as an uninterrupted run: all randomness of iteration k is derived from (seed, k), never from a stream that
//! an interruption would cut.
//!
//! - `job`: what a run is given ([`EditJob`]) and gives back ([`EditResult`]);
//! - `edit_loop`: [`run_edit`], the loop itself, and [`edit_scene`], the loop and the outputs (what the
//!   commands run);
//! - `masks`: the editable region;
//! - `checkpoint`: the state saved after every iteration;
//! - `outputs`: the files written per iteration and at the end ([`write_outputs`]);
//! - `shape`: whether a fit keeps the editable region's geometry ([`KeepShape`]);
//! - `work`: the work and memory a run needs ([`work_plan`]);
//! - `estimate`: how long it will take, from unit costs timed here ([`calibrate`], [`Estimate`]).

mod checkpoint;
mod edit_loop;
mod estimate;
mod job;
mod masks;
mod outputs;
mod shape;
mod work;

pub use edit_loop::{edit_scene, run_edit, scene_extent};
pub use estimate::{calibrate, Calibration, Estimate, PlannedCounts};
pub use job::{
    DeltaDecode, EditJob, EditResult, GuidanceMode, IterationTimes, MaskSource, Progress, Quiet,
    RunError,
};
pub use masks::{mask_from_box, Box3, MaskError};
pub use outputs::{write_outputs, RunInputs, Written};
pub use shape::{footprint_change, KeepShape, ShapeDecision, KEPT_SHAPE_RATE};
pub use work::{image_edit_memory, work_plan, WorkPlan};
