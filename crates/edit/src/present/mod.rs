//! Showing a run to people: the HTML report (`report`), the turntable GIF (`gif`) and attention and mask
//! images (`viz`).

pub mod gif;
pub mod report;
pub mod viz;
