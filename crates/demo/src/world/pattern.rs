//! Surface patterns, evaluated per Gaussian from its surface coordinates.
//!
//! Every patterned surface in the world is parametrised the same way, so one pattern reads the same on a
//! sphere, a vase or a box:
//! - `turn` in [0, 1): the position around the object's vertical axis (azimuth for surfaces of revolution,
//!   perimeter position for box sides), so patterns wrap around seamlessly;
//! - `v`: the position along the surface in world units (arc length along the profile of a surface of
//!   revolution, height on box sides continuing inwards on the top and bottom faces), so stripes, checks
//!   and dots keep their size in the world.
//!
//! Around the axis the pattern has an even number `k` of cells chosen so a cell is about one `period` wide
//! at the object's reference circumference: then checks alternate across the seam and diagonal stripes
//! close into helices.

use serde::{Deserialize, Serialize};

/// The pattern families of the caption vocabulary.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PatternKind {
    Solid,
    Stripes,
    Checker,
    Dots,
    Gradient,
}

impl PatternKind {
    pub const ALL: [PatternKind; 5] = [
        PatternKind::Solid,
        PatternKind::Stripes,
        PatternKind::Checker,
        PatternKind::Dots,
        PatternKind::Gradient,
    ];

    /// The caption adjective; `None` for solid (a solid object is just "a red sphere").
    pub fn word(self) -> Option<&'static str> {
        match self {
            PatternKind::Solid => None,
            PatternKind::Stripes => Some("striped"),
            PatternKind::Checker => Some("checkered"),
            PatternKind::Dots => Some("dotted"),
            PatternKind::Gradient => Some("gradient"),
        }
    }

    pub fn from_word(word: &str) -> Option<PatternKind> {
        PatternKind::ALL
            .into_iter()
            .find(|p| p.word() == Some(word))
    }

    /// Whether the pattern shows the second colour.
    pub fn uses_second_color(self) -> bool {
        self != PatternKind::Solid
    }
}

/// Which way a pattern runs on the upright object.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Orientation {
    /// Stripes are rings around the object; checks are aligned; dots are in aligned rows; gradients run
    /// along the surface from bottom to top.
    Horizontal,
    /// Stripes run from bottom to top; dots are staggered; gradients run around the object.
    Vertical,
    /// Stripes wind as helices; checks become diamonds; dots are staggered; gradients run both ways.
    Diagonal,
}

impl Orientation {
    pub const ALL: [Orientation; 3] = [
        Orientation::Horizontal,
        Orientation::Vertical,
        Orientation::Diagonal,
    ];
}

/// One instance of a pattern: the family plus the parameters that vary between instances.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Pattern {
    pub kind: PatternKind,
    pub orientation: Orientation,
    /// Size of one period along the surface, world units (a stripe pair, two checks, the dot spacing). For
    /// gradients: the length of the transition as a fraction of the object's extent along the surface.
    pub period: f32,
    /// Shift in fractions of a period: [around the axis, along the surface]. For gradients the second
    /// component moves the transition's centre along the object.
    pub phase: [f32; 2],
    /// Diagonal stripes wind to the right (+1) or to the left (-1).
    pub handedness: i8,
    /// Dot radius as a fraction of the period.
    pub dot_radius: f32,
}

impl Pattern {
    /// A solid pattern (only the first colour shows).
    pub fn solid() -> Self {
        Self {
            kind: PatternKind::Solid,
            orientation: Orientation::Horizontal,
            period: 1.0,
            phase: [0.0; 2],
            handedness: 1,
            dot_radius: 0.3,
        }
    }
}

/// Where a point lies on a patterned surface (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfacePoint {
    pub turn: f32,
    pub v: f32,
}

/// Per-object constants a pattern needs besides the point.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PatternFrame {
    /// Circumference of the object at its widest, world units.
    pub circumference: f32,
    /// Range of `v` over the object's patterned surface.
    pub v_range: [f32; 2],
}

impl Pattern {
    /// Weight of the second colour at `p`, in [0, 1]: 0 or 1 for everything but gradients.
    pub fn mix(&self, p: SurfacePoint, frame: &PatternFrame) -> f32 {
        let period = self.period.max(1e-4);
        let k = cells_around(frame.circumference, period) as f32;
        // Cell coordinates: `a` around (k cells per turn), `b` along the surface.
        let a = p.turn * k + self.phase[0];
        let b = p.v / period + self.phase[1];
        let bit = |on: bool| if on { 1.0 } else { 0.0 };
        match self.kind {
            PatternKind::Solid => 0.0,
            PatternKind::Stripes => {
                let s = match self.orientation {
                    Orientation::Horizontal => b,
                    Orientation::Vertical => a,
                    Orientation::Diagonal => b + self.handedness.signum() as f32 * a,
                };
                bit(s.rem_euclid(1.0) >= 0.5)
            }
            PatternKind::Checker => {
                let (s, t) = match self.orientation {
                    Orientation::Diagonal => (b + a, b - a),
                    _ => (a, b),
                };
                bit((s.floor() as i64 + t.floor() as i64).rem_euclid(2) == 1)
            }
            PatternKind::Dots => {
                let row = b.floor();
                // Staggered rows shift every other row by half a cell; k is even so this wraps.
                let shift = if self.orientation == Orientation::Horizontal {
                    0.0
                } else {
                    0.5 * (row as i64).rem_euclid(2) as f32
                };
                let da = (a - shift).rem_euclid(1.0) - 0.5;
                let db = b - row - 0.5;
                bit(da * da + db * db <= self.dot_radius * self.dot_radius)
            }
            PatternKind::Gradient => {
                let [lo, hi] = frame.v_range;
                let centre = lo + (hi - lo) * (0.3 + 0.4 * self.phase[1].rem_euclid(1.0));
                let along = ((p.v - centre) / (period * (hi - lo)).max(1e-4) + 0.5).clamp(0.0, 1.0);
                // Around the axis: a triangle wave so the colour is continuous across the seam.
                let x = (p.turn + self.phase[0]).rem_euclid(1.0);
                let around = 1.0 - (2.0 * x - 1.0).abs();
                match self.orientation {
                    Orientation::Horizontal => along,
                    Orientation::Vertical => around,
                    Orientation::Diagonal => 0.5 * (along + around),
                }
            }
        }
    }
}

/// Number of pattern cells around an object: even, at least 2, each about one period wide.
pub fn cells_around(circumference: f32, period: f32) -> u32 {
    let half = (0.5 * circumference / period.max(1e-4)).round();
    2 * (half.clamp(1.0, 512.0) as u32)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pattern(kind: PatternKind, orientation: Orientation) -> Pattern {
        Pattern {
            kind,
            orientation,
            period: 0.25,
            phase: [0.1, 0.3],
            handedness: 1,
            dot_radius: 0.3,
        }
    }

    const FRAME: PatternFrame = PatternFrame {
        circumference: 3.0,
        v_range: [0.0, 1.5],
    };

    fn grid() -> impl Iterator<Item = SurfacePoint> {
        (0..200).flat_map(|i| {
            (0..60).map(move |j| SurfacePoint {
                turn: i as f32 / 200.0,
                v: j as f32 * 1.5 / 60.0,
            })
        })
    }

    #[test]
    fn two_tone_patterns_cover_both_colours_in_expected_proportions() {
        for o in Orientation::ALL {
            for (kind, lo, hi) in [
                (PatternKind::Stripes, 0.4, 0.6),
                (PatternKind::Checker, 0.4, 0.6),
                // Dot area / cell area = pi r^2 = 0.28.
                (PatternKind::Dots, 0.2, 0.36),
            ] {
                let p = pattern(kind, o);
                let pts: Vec<f32> = grid().map(|s| p.mix(s, &FRAME)).collect();
                assert!(pts.iter().all(|&m| m == 0.0 || m == 1.0));
                let frac = pts.iter().sum::<f32>() / pts.len() as f32;
                assert!(frac > lo && frac < hi, "{kind:?} {o:?}: {frac}");
            }
            let solid = pattern(PatternKind::Solid, o);
            assert!(grid().all(|s| solid.mix(s, &FRAME) == 0.0));
        }
    }

    #[test]
    fn patterns_wrap_seamlessly_around_the_axis() {
        for kind in [
            PatternKind::Stripes,
            PatternKind::Checker,
            PatternKind::Dots,
            PatternKind::Gradient,
        ] {
            for o in Orientation::ALL {
                let p = pattern(kind, o);
                // A point right on a stripe edge may fall either way; allow one such point.
                let mismatches = (0..50)
                    .filter(|j| {
                        let v = *j as f32 * 0.031 + 0.004;
                        let before = p.mix(
                            SurfacePoint {
                                turn: 1.0 - 1e-5,
                                v,
                            },
                            &FRAME,
                        );
                        let after = p.mix(SurfacePoint { turn: 1e-5, v }, &FRAME);
                        (before - after).abs() > 0.01
                    })
                    .count();
                assert!(mismatches <= 1, "{kind:?} {o:?}: {mismatches}");
            }
        }
    }

    #[test]
    fn phase_moves_the_pattern_and_gradient_spans_both_colours() {
        let a = pattern(PatternKind::Stripes, Orientation::Horizontal);
        let mut b = a;
        b.phase[1] += 0.5;
        let differ = grid()
            .filter(|&s| a.mix(s, &FRAME) != b.mix(s, &FRAME))
            .count();
        // Half a period of shift swaps every stripe.
        assert!(differ as f32 > 0.95 * grid().count() as f32);

        let g = Pattern {
            period: 0.6,
            ..pattern(PatternKind::Gradient, Orientation::Horizontal)
        };
        let bottom = g.mix(SurfacePoint { turn: 0.0, v: 0.0 }, &FRAME);
        let top = g.mix(SurfacePoint { turn: 0.0, v: 1.5 }, &FRAME);
        assert!(bottom < 0.1 && top > 0.9, "{bottom} {top}");
        let vertical = pattern(PatternKind::Gradient, Orientation::Vertical);
        let m: Vec<f32> = (0..100)
            .map(|i| {
                vertical.mix(
                    SurfacePoint {
                        turn: i as f32 / 100.0,
                        v: 0.5,
                    },
                    &FRAME,
                )
            })
            .collect();
        assert!(m.iter().cloned().fold(1.0, f32::min) < 0.05);
        assert!(m.iter().cloned().fold(0.0, f32::max) > 0.95);
    }

    #[test]
    fn cells_around_is_even_and_tracks_the_period() {
        assert_eq!(cells_around(3.0, 0.25), 12);
        assert_eq!(cells_around(0.1, 1.0), 2);
        for c in [0.3_f32, 1.0, 2.7, 6.2] {
            assert_eq!(cells_around(c, 0.2) % 2, 0);
        }
        for w in ["striped", "checkered", "dotted", "gradient"] {
            assert_eq!(PatternKind::from_word(w).and_then(|k| k.word()), Some(w));
        }
        assert_eq!(PatternKind::from_word("solid"), None);
    }
}
