//! Keeping the shape where the edit does not change it (issue "edits that keep the shape").
//!
//! The editing fit trains every attribute with GaussianEditor's rates, and Adam moves each parameter by
//! about its rate per step whatever the size of its gradient: in a colour edit the positions, sizes and
//! orientations of the editable Gaussians drift too. At the edit's resolution the drift hides (the demo's
//! red → blue sphere: silhouette IoU 0.985 at 128²), closer up it frays the outline (0.958 at 512²).
//! Refitting that run's guidance with the geometry rates × 0.1 gave 0.997 / 0.994 with the same colour
//! fidelity; × 0 gave 0.997 / 0.999; fitting at twice the guidance's resolution made it worse (0.957 /
//! 0.923); no densification 0.988 / 0.968 (docs/demo-model.md).
//!
//! So geometry follows the guidance: before each iteration's fit, the pixels the guidance changes
//! *outside* the editable region's rendered footprint are counted. An edit that changes nothing there (a
//! new colour, pattern or material) keeps the geometry rates at [`KEPT_SHAPE_RATE`]; one that reaches
//! beyond the footprint (a hat, ears, a mane) fits with the reference's full rates. Shrinking is left to
//! the opacities, whose rate is never reduced. A deliberate deviation from the reference, which fits every
//! edit with full rates (`--keep-shape never`).

use serde::{Deserialize, Serialize};
use splat::Image;

/// Factor on the position, scale and rotation rates of a fit whose guidance keeps the shape.
pub const KEPT_SHAPE_RATE: f32 = 0.1;

/// The share of the editable footprint's area that the guidance may change outside it (pixels more than
/// [`MARGIN_PX`] away) while the edit still counts as keeping the shape.
pub const FOOTPRINT_TOLERANCE: f64 = 0.01;

/// A pixel counts as changed when a channel moved by more than this (the oracle's outside-change rule).
const CHANGED: f32 = 0.1;

/// Pixels this close to the footprint count as on it (the outline's own anti-aliasing and blur).
pub const MARGIN_PX: usize = 2;

/// Coverage above which a pixel is part of the footprint, and above which it is near it.
const ON: f32 = 0.5;
const NEAR: f32 = 0.02;

/// Whether an editing fit keeps the geometry of the editable region ([`KEPT_SHAPE_RATE`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum KeepShape {
    /// When the guidance changes nothing outside the editable region (the default).
    #[default]
    #[value(help = "When the guidance changes nothing outside the editable region (the default)")]
    Auto,
    /// Never: every fit trains the geometry at full rate (the reference).
    #[value(help = "Never: geometry trained at full rate, as the reference (outlines may fray)")]
    Never,
    /// Always: appearance edits (colour, pattern, material) on any mask.
    #[value(help = "Always: for colour, pattern or material edits")]
    Always,
}

/// What one iteration's fit did with the geometry rates, and why.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ShapeDecision {
    /// Pixels the guidance changed outside the editable footprint, per footprint pixel (measured under
    /// `auto` with a mask).
    pub footprint_change: Option<f64>,
    /// The factor the position, scale and rotation rates were fitted with.
    pub geometry_rate: f32,
}

impl ShapeDecision {
    /// The decision under `keep`, given the guidance's change outside the footprint (`None`: not
    /// measured, e.g. no mask, where the footprint is the whole image and tells nothing).
    pub fn new(keep: KeepShape, footprint_change: Option<f64>) -> Self {
        let kept = match keep {
            KeepShape::Never => false,
            KeepShape::Always => true,
            KeepShape::Auto => footprint_change.is_some_and(|c| c <= FOOTPRINT_TOLERANCE),
        };
        Self {
            footprint_change,
            geometry_rate: if kept { KEPT_SHAPE_RATE } else { 1.0 },
        }
    }

    pub fn kept(&self) -> bool {
        self.geometry_rate < 1.0
    }

    /// One log line (within 80 columns).
    pub fn describe(&self) -> String {
        let change = self
            .footprint_change
            .map(|c| format!(" ({:.1} % of its area changed outside it)", 100.0 * c))
            .unwrap_or_default();
        if self.kept() {
            format!(
                "shape kept{change}: geometry fitted at {}× rate",
                self.geometry_rate
            )
        } else {
            format!("shape free{change}: geometry fitted at full rate")
        }
    }
}

/// Pixels that `guidance` changes against `sources` (the renders it was made from) outside the editable
/// footprint, per footprint pixel, over all views. `coverage[v]` is view v's rendered coverage of the
/// editable Gaussians (0–1 per pixel, the images' size). `None` when the footprint is empty in every view.
pub fn footprint_change(
    coverage: &[Vec<f32>],
    sources: &[Image],
    guidance: &[Image],
) -> Option<f64> {
    let (mut changed, mut footprint) = (0usize, 0usize);
    for ((cov, src), gd) in coverage.iter().zip(sources).zip(guidance) {
        let (w, h) = (src.width as usize, src.height as usize);
        if cov.len() != w * h || (gd.width, gd.height) != (src.width, src.height) {
            continue;
        }
        footprint += cov.iter().filter(|&&c| c >= ON).count();
        let near = dilate(cov, w, h);
        let (cs, cg) = (src.channels as usize, gd.channels as usize);
        for p in (0..w * h).filter(|&p| !near[p]) {
            let moved = (0..3).any(|k| {
                (gd.data[cg * p + k].clamp(0.0, 1.0) - src.data[cs * p + k].clamp(0.0, 1.0)).abs()
                    > CHANGED
            });
            changed += moved as usize;
        }
    }
    (footprint > 0).then(|| changed as f64 / footprint as f64)
}

/// Pixels within [`MARGIN_PX`] of one the footprint touches (coverage above [`NEAR`]): a max filter,
/// rows then columns.
fn dilate(coverage: &[f32], w: usize, h: usize) -> Vec<bool> {
    let touched: Vec<bool> = coverage.iter().map(|&c| c > NEAR).collect();
    let mut rows = vec![false; w * h];
    for y in 0..h {
        for x in 0..w {
            let (x0, x1) = (x.saturating_sub(MARGIN_PX), (x + MARGIN_PX).min(w - 1));
            rows[y * w + x] = (x0..=x1).any(|xx| touched[y * w + xx]);
        }
    }
    let mut out = vec![false; w * h];
    for y in 0..h {
        let (y0, y1) = (y.saturating_sub(MARGIN_PX), (y + MARGIN_PX).min(h - 1));
        for x in 0..w {
            out[y * w + x] = (y0..=y1).any(|yy| rows[yy * w + x]);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 20×20 grey image, and a footprint covering the square [8, 12)².
    fn scene() -> (Image, Vec<f32>) {
        let image = Image::from_data(20, 20, 3, vec![0.5; 20 * 20 * 3]);
        let coverage = (0..400)
            .map(|p| {
                let (x, y) = (p % 20, p / 20);
                ((8..12).contains(&x) && (8..12).contains(&y)) as u8 as f32
            })
            .collect();
        (image, coverage)
    }

    fn paint(image: &mut Image, xs: std::ops::Range<usize>, ys: std::ops::Range<usize>, v: f32) {
        for y in ys {
            for x in xs.clone() {
                image.data[3 * (y * 20 + x)] = v;
            }
        }
    }

    #[test]
    fn a_change_on_the_footprint_keeps_the_shape() {
        let (source, coverage) = scene();
        let mut guidance = source.clone();
        // The footprint recoloured, and its rim's blur 2 px around it: nothing outside counts.
        paint(&mut guidance, 6..14, 6..14, 1.0);
        let change = footprint_change(&[coverage], &[source], &[guidance]);
        assert_eq!(change, Some(0.0));
        let d = ShapeDecision::new(KeepShape::Auto, change);
        assert!(d.kept());
        assert_eq!(d.geometry_rate, KEPT_SHAPE_RATE);
        assert!(d.describe().len() <= 80, "{}", d.describe());
    }

    #[test]
    fn a_change_beyond_the_footprint_frees_the_shape() {
        let (source, coverage) = scene();
        let mut guidance = source.clone();
        // A growth three pixels wide, 3 px beyond the footprint's right edge: 12 pixels, per 16 of the
        // footprint.
        paint(&mut guidance, 14..17, 8..12, 1.0);
        let change = footprint_change(
            std::slice::from_ref(&coverage),
            std::slice::from_ref(&source),
            &[guidance],
        )
        .unwrap();
        assert!((change - 12.0 / 16.0).abs() < 1e-9, "{change}");
        let d = ShapeDecision::new(KeepShape::Auto, Some(change));
        assert!(!d.kept());
        assert_eq!(d.geometry_rate, 1.0);
        assert!(d.describe().len() <= 80, "{}", d.describe());
        // Small changes up to the tolerance still keep it; a change below the threshold is no change.
        let mut faint = source.clone();
        paint(&mut faint, 0..20, 0..20, 0.55);
        assert_eq!(
            footprint_change(&[coverage], &[source], &[faint]),
            Some(0.0)
        );
        assert!(ShapeDecision::new(KeepShape::Auto, Some(FOOTPRINT_TOLERANCE)).kept());
    }

    #[test]
    fn never_always_and_no_footprint() {
        assert!(!ShapeDecision::new(KeepShape::Never, Some(0.0)).kept());
        assert!(ShapeDecision::new(KeepShape::Always, Some(0.5)).kept());
        assert!(ShapeDecision::new(KeepShape::Always, None).kept());
        // No mask (the footprint is everything) or nothing editable in view: the reference's rates.
        assert!(!ShapeDecision::new(KeepShape::Auto, None).kept());
        let (source, _) = scene();
        assert_eq!(
            footprint_change(
                &[vec![0.0; 400]],
                std::slice::from_ref(&source),
                std::slice::from_ref(&source)
            ),
            None
        );
    }
}
