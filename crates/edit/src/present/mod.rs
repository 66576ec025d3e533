//! Showing a run to people: the HTML report (`report`), the interactive 3D before/after viewer it embeds
//! (`viewer`, also `vcedit view`), the turntable GIF (`gif`) and attention and mask images (`viz`).

pub mod gif;
pub mod report;
pub mod viewer;
pub mod viz;
