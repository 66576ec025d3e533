//! Surface sampling: surfaces of revolution (from a profile in the (r, z) half plane) and boxes, turned
//! into oriented surface elements that become flat Gaussians.
//!
//! Each element carries its position, outward normal, one unit tangent, its extent along the tangent and
//! along the other tangent (the spacing of the sampling there), the surface coordinates the patterns read
//! ([`crate::world::pattern`]) and the part it belongs to.

use super::pattern::SurfacePoint;
use glam::Vec3;
use rand::Rng;
use serde::{Deserialize, Serialize};
use std::f32::consts::TAU;

/// The named part of an object each Gaussian belongs to.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
#[repr(u8)]
pub enum Part {
    /// The main surface of a shape (sphere, cube, cylinder, ... the vase's outside, a snowman's snow).
    Body = 0,
    /// The vase's lip.
    Rim = 1,
    /// The inside of the vase.
    Inner = 2,
    /// A table top.
    Top = 3,
    Leg = 4,
    /// A mushroom's cap (top side).
    Cap = 5,
    /// A mushroom's gills (fixed colour).
    Underside = 6,
    /// A mushroom's stem (fixed colour).
    Stem = 7,
    /// A snowman's carrot nose (fixed colour).
    Nose = 8,
    /// A snowman's eyes (fixed colour).
    Eye = 9,
    Floor = 10,
}

impl Part {
    /// The colour of parts that do not follow the object's pattern.
    pub fn fixed_color(self) -> Option<[f32; 3]> {
        match self {
            Part::Underside => Some([0.80, 0.72, 0.60]),
            Part::Stem => Some([0.92, 0.88, 0.78]),
            Part::Nose => Some([0.95, 0.45, 0.08]),
            Part::Eye => Some([0.05, 0.05, 0.05]),
            _ => None,
        }
    }
}

/// One oriented surface element.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Element {
    pub pos: [f32; 3],
    pub normal: [f32; 3],
    pub tangent: [f32; 3],
    /// Extent (sampling spacing) along `tangent` and along `normal x tangent`.
    pub extent: [f32; 2],
    pub surface: SurfacePoint,
    pub part: Part,
}

/// How the `v` surface coordinate is measured on a surface of revolution.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum VMeasure {
    /// Arc length along the profile, continuing across its pieces.
    ArcLength,
    /// Height z (for stacks of separate pieces, such as a snowman, that should share horizontal bands).
    Height,
}

/// A profile in the (r, z) half plane: a chain of polyline pieces; each piece is sampled in its own rows so
/// corners (a cylinder's rims) keep sharp normals. The outward side is to the right of the direction of
/// travel: (dr, dz) has outward normal (dz, -dr).
#[derive(Clone, Debug, Default)]
pub(crate) struct Profile {
    /// Polyline, part, and spacing relative to the spacing `revolve` is called with.
    pieces: Vec<(Vec<[f32; 2]>, Part, f32)>,
    cursor: [f32; 2],
}

impl Profile {
    pub fn start(at: [f32; 2]) -> Self {
        Self {
            pieces: Vec::new(),
            cursor: at,
        }
    }

    pub fn line(self, to: [f32; 2], part: Part) -> Self {
        self.line_spaced(to, part, 1.0)
    }

    /// A line sampled `relative_spacing` times as coarsely as the rest.
    pub fn line_spaced(mut self, to: [f32; 2], part: Part, relative_spacing: f32) -> Self {
        self.pieces
            .push((vec![self.cursor, to], part, relative_spacing));
        self.cursor = to;
        self
    }

    /// An elliptical arc around `center` with radii (r, z), from angle `from` to `to` (radians,
    /// counter-clockwise in the (r, z) plane means the outward side is away from the centre). The arc
    /// starts wherever the cursor is; the cursor should be at the arc's start.
    pub fn arc(
        mut self,
        center: [f32; 2],
        radii: [f32; 2],
        from: f32,
        to: f32,
        part: Part,
    ) -> Self {
        let steps = 48;
        let pts: Vec<[f32; 2]> = (0..=steps)
            .map(|i| {
                let t = from + (to - from) * i as f32 / steps as f32;
                [
                    center[0] + radii[0] * t.cos(),
                    center[1] + radii[1] * t.sin(),
                ]
            })
            .collect();
        self.cursor = *pts.last().unwrap_or(&self.cursor);
        self.pieces.push((pts, part, 1.0));
        self
    }

    /// A curve r = f(z) from z0 to z1 (upwards: outward side is +r when z1 > z0).
    pub fn curve(mut self, f: impl Fn(f32) -> f32, z0: f32, z1: f32, part: Part) -> Self {
        let steps = 48;
        let pts: Vec<[f32; 2]> = (0..=steps)
            .map(|i| {
                let z = z0 + (z1 - z0) * i as f32 / steps as f32;
                [f(z).max(0.0), z]
            })
            .collect();
        self.cursor = *pts.last().unwrap_or(&self.cursor);
        self.pieces.push((pts, part, 1.0));
        self
    }
}

/// Samples a surface of revolution about the z axis: rows spaced `spacing` apart along the profile, each
/// row with about one element per `spacing` around, rotated by a random offset so rows do not line up.
pub(crate) fn revolve<R: Rng>(
    profile: &Profile,
    spacing: f32,
    measure: VMeasure,
    rng: &mut R,
    out: &mut Vec<Element>,
) {
    // Rows at an open end of the profile (one off the axis and not closing a loop, such as a cylinder's
    // foot) are made half as wide along the profile, so their tails do not reach past the edge and smear
    // onto what is behind (the floor below an object's foot).
    let first = profile.pieces.first().and_then(|p| p.0.first().copied());
    let last = profile.pieces.last().and_then(|p| p.0.last().copied());
    let closed = first.is_some() && first == last;
    let open_start = !closed && first.is_some_and(|p| p[0] > 1e-6);
    let open_end = !closed && last.is_some_and(|p| p[0] > 1e-6);
    let pieces = profile.pieces.len();
    let mut arc_offset = 0.0;
    for (index, (pts, part, relative)) in profile.pieces.iter().enumerate() {
        let spacing = spacing * relative;
        let seg_len: Vec<f32> = pts.windows(2).map(|w| dist2(w[0], w[1])).collect();
        let length: f32 = seg_len.iter().sum();
        if length <= 0.0 {
            continue;
        }
        let rows = ((length / spacing).round() as usize).max(1);
        let step = length / rows as f32;
        let mut seg = 0;
        let mut seg_start = 0.0;
        for row in 0..rows {
            let s = (row as f32 + 0.5) * step;
            while seg + 1 < seg_len.len() && s > seg_start + seg_len[seg] {
                seg_start += seg_len[seg];
                seg += 1;
            }
            let (a, b) = (pts[seg], pts[seg + 1]);
            let t = ((s - seg_start) / seg_len[seg].max(1e-12)).clamp(0.0, 1.0);
            let r = a[0] + (b[0] - a[0]) * t;
            let z = a[1] + (b[1] - a[1]) * t;
            let d = [
                (b[0] - a[0]) / seg_len[seg].max(1e-12),
                (b[1] - a[1]) / seg_len[seg].max(1e-12),
            ];
            let n_rz = [d[1], -d[0]];
            let count = ((TAU * r / spacing).round() as usize).max(3);
            let around = TAU * r / count as f32;
            let offset: f32 = rng.gen_range(0.0..1.0);
            let at_open_end = (open_start && index == 0 && row == 0)
                || (open_end && index + 1 == pieces && row + 1 == rows);
            let along = if at_open_end { 0.5 * step } else { step };
            let v = match measure {
                VMeasure::ArcLength => arc_offset + s,
                VMeasure::Height => z,
            };
            for j in 0..count {
                let turn = (j as f32 + offset) / count as f32;
                let (sin, cos) = (TAU * turn).sin_cos();
                out.push(Element {
                    pos: [r * cos, r * sin, z],
                    normal: [n_rz[0] * cos, n_rz[0] * sin, n_rz[1]],
                    tangent: [-sin, cos, 0.0],
                    // Near the axis the row is tiny; keep elements at least a fraction of the spacing wide.
                    extent: [around.max(0.25 * spacing), along],
                    surface: SurfacePoint { turn, v },
                    part: *part,
                });
            }
        }
        arc_offset += length;
    }
}

/// Samples the faces of the box [-hx, hx] x [-hy, hy] x [z0, z1] on grids of about `spacing` (the bottom
/// only when `bottom` is set).
/// `turn` is the position along the perimeter (projected radially onto it on the top and bottom faces) and
/// `v` is the height on the sides, continuing inwards across the top and bottom (distance to the nearest
/// edge), so bands run around the box and close into square rings on its top.
pub(crate) fn box_faces(
    half: [f32; 2],
    z: [f32; 2],
    spacing: f32,
    bottom: bool,
    part: Part,
    out: &mut Vec<Element>,
) {
    let [hx, hy] = half;
    let [z0, z1] = z;
    let perimeter = 4.0 * (hx + hy);
    let grid = |len: f32| ((len / spacing).round() as usize).max(1);
    // Sides: walk the perimeter counter-clockwise starting at (hx, -hy).
    let sides: [([f32; 2], [f32; 2], [f32; 2]); 4] = [
        ([hx, -hy], [0.0, 1.0], [1.0, 0.0]),
        ([hx, hy], [-1.0, 0.0], [0.0, 1.0]),
        ([-hx, hy], [0.0, -1.0], [-1.0, 0.0]),
        ([-hx, -hy], [1.0, 0.0], [0.0, -1.0]),
    ];
    let nz = grid(z1 - z0);
    let dz = (z1 - z0) / nz as f32;
    let mut along_start = 0.0;
    for (start, dir, normal) in sides {
        let len = if dir[0] != 0.0 { 2.0 * hx } else { 2.0 * hy };
        let nu = grid(len);
        let du = len / nu as f32;
        for i in 0..nu {
            let u = (i as f32 + 0.5) * du;
            let xy = [start[0] + dir[0] * u, start[1] + dir[1] * u];
            for k in 0..nz {
                let zz = z0 + (k as f32 + 0.5) * dz;
                // Without a bottom face the lowest row is an open edge: keep its tails above it.
                let along = if !bottom && k == 0 { 0.5 * dz } else { dz };
                out.push(Element {
                    pos: [xy[0], xy[1], zz],
                    normal: [normal[0], normal[1], 0.0],
                    tangent: [dir[0], dir[1], 0.0],
                    extent: [du, along],
                    surface: SurfacePoint {
                        turn: (along_start + u) / perimeter,
                        v: zz,
                    },
                    part,
                });
            }
        }
        along_start += len;
    }
    // Top and bottom.
    let (nx, ny) = (grid(2.0 * hx), grid(2.0 * hy));
    let (dx, dy) = (2.0 * hx / nx as f32, 2.0 * hy / ny as f32);
    let caps: &[(f32, f32)] = if bottom {
        &[(z1, 1.0), (z0, -1.0)]
    } else {
        &[(z1, 1.0)]
    };
    for &(zz, up) in caps {
        for i in 0..nx {
            for j in 0..ny {
                let x = -hx + (i as f32 + 0.5) * dx;
                let y = -hy + (j as f32 + 0.5) * dy;
                let inset = (hx - x.abs()).min(hy - y.abs());
                out.push(Element {
                    pos: [x, y, zz],
                    normal: [0.0, 0.0, up],
                    tangent: [1.0, 0.0, 0.0],
                    extent: [dx, dy],
                    surface: SurfacePoint {
                        turn: perimeter_turn(x, y, hx, hy),
                        v: zz + up * inset,
                    },
                    part,
                });
            }
        }
    }
}

/// Perimeter position in [0, 1) of the point where the ray from the centre through (x, y) leaves the
/// rectangle, measured as in [`box_faces`].
fn perimeter_turn(x: f32, y: f32, hx: f32, hy: f32) -> f32 {
    let s = (x.abs() / hx).max(y.abs() / hy);
    if s <= 1e-9 {
        return 0.0;
    }
    let (bx, by) = (x / s, y / s);
    let p = if x.abs() / hx >= y.abs() / hy {
        if bx > 0.0 {
            by + hy
        } else {
            2.0 * hy + 2.0 * hx + (hy - by)
        }
    } else if by > 0.0 {
        2.0 * hy + (hx - bx)
    } else {
        4.0 * hy + 2.0 * hx + (bx + hx)
    };
    (p / (4.0 * (hx + hy))).rem_euclid(1.0)
}

/// A rigid motion: rotation (row-major) then translation.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Motion {
    pub rot: [[f32; 3]; 3],
    pub shift: [f32; 3],
}

impl Motion {
    pub fn identity() -> Self {
        Self {
            rot: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            shift: [0.0; 3],
        }
    }

    pub fn yaw(angle: f32, shift: [f32; 3]) -> Self {
        let (s, c) = angle.sin_cos();
        Self {
            rot: [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]],
            shift,
        }
    }

    /// Turns the z axis into the +x axis (rotation about y by +90°), then shifts.
    pub fn z_to_x(shift: [f32; 3]) -> Self {
        Self {
            rot: [[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]],
            shift,
        }
    }

    pub fn rotate(&self, v: [f32; 3]) -> [f32; 3] {
        std::array::from_fn(|a| {
            self.rot[a][0] * v[0] + self.rot[a][1] * v[1] + self.rot[a][2] * v[2]
        })
    }

    pub fn apply(&self, e: &mut Element) {
        let p = self.rotate(e.pos);
        e.pos = std::array::from_fn(|a| p[a] + self.shift[a]);
        e.normal = self.rotate(e.normal);
        e.tangent = self.rotate(e.tangent);
    }
}

/// Unit quaternion (w, x, y, z) of the rotation whose columns are the orthonormal right-handed axes
/// `t1, t2, n` (Shepperd's method: pivot on the largest diagonal term for stability).
pub(crate) fn frame_quaternion(t1: [f32; 3], t2: [f32; 3], n: [f32; 3]) -> [f32; 4] {
    // m[row][col]; columns are the axes.
    let m = [
        [t1[0], t2[0], n[0]],
        [t1[1], t2[1], n[1]],
        [t1[2], t2[2], n[2]],
    ];
    let trace = m[0][0] + m[1][1] + m[2][2];
    let q = if trace > 0.0 {
        let s = (trace + 1.0).sqrt() * 2.0;
        [
            0.25 * s,
            (m[2][1] - m[1][2]) / s,
            (m[0][2] - m[2][0]) / s,
            (m[1][0] - m[0][1]) / s,
        ]
    } else if m[0][0] > m[1][1] && m[0][0] > m[2][2] {
        let s = (1.0 + m[0][0] - m[1][1] - m[2][2]).sqrt() * 2.0;
        [
            (m[2][1] - m[1][2]) / s,
            0.25 * s,
            (m[0][1] + m[1][0]) / s,
            (m[0][2] + m[2][0]) / s,
        ]
    } else if m[1][1] > m[2][2] {
        let s = (1.0 + m[1][1] - m[0][0] - m[2][2]).sqrt() * 2.0;
        [
            (m[0][2] - m[2][0]) / s,
            (m[0][1] + m[1][0]) / s,
            0.25 * s,
            (m[1][2] + m[2][1]) / s,
        ]
    } else {
        let s = (1.0 + m[2][2] - m[0][0] - m[1][1]).sqrt() * 2.0;
        [
            (m[1][0] - m[0][1]) / s,
            (m[0][2] + m[2][0]) / s,
            (m[1][2] + m[2][1]) / s,
            0.25 * s,
        ]
    };
    let norm = q.iter().map(|c| c * c).sum::<f32>().sqrt();
    if norm.is_finite() && norm > 0.0 {
        q.map(|c| c / norm)
    } else {
        [1.0, 0.0, 0.0, 0.0]
    }
}

/// `v` scaled to unit length, +z when it is (nearly) zero. Divides by the length where glam's `normalize`
/// multiplies by its reciprocal, so the built scenes keep their bits.
pub(crate) fn unit_or_z(v: Vec3) -> Vec3 {
    let n = v.length();
    if n > 1e-12 {
        v / n
    } else {
        Vec3::Z
    }
}

fn dist2(a: [f32; 2], b: [f32; 2]) -> f32 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn frame_quaternion_reproduces_the_frame() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        for _ in 0..200 {
            let n = unit_or_z(Vec3::new(
                rng.gen_range(-1.0..1.0),
                rng.gen_range(-1.0..1.0),
                rng.gen_range(-1.0..1.0),
            ));
            let t1 = unit_or_z(n.cross(Vec3::new(
                rng.gen_range(-1.0..1.0),
                rng.gen_range(-1.0..1.0),
                0.3,
            )));
            let t2 = n.cross(t1);
            let [w, x, y, z] = frame_quaternion(t1.into(), t2.into(), n.into());
            let r = glam::Mat3::from_quat(glam::Quat::from_xyzw(x, y, z, w));
            for (col, axis) in [t1, t2, n].iter().enumerate() {
                assert!(
                    r.col(col).abs_diff_eq(*axis, 1e-4),
                    "{r:?} {t1:?} {t2:?} {n:?}"
                );
            }
        }
    }

    #[test]
    fn sphere_revolution_has_outward_normals_on_the_surface_and_uniform_density() {
        let radius = 0.5;
        let profile = Profile::start([0.0, 0.0]).arc(
            [0.0, radius],
            [radius, radius],
            -std::f32::consts::FRAC_PI_2,
            std::f32::consts::FRAC_PI_2,
            Part::Body,
        );
        let mut out = Vec::new();
        let spacing = 0.02;
        revolve(
            &profile,
            spacing,
            VMeasure::ArcLength,
            &mut rand_chacha::ChaCha8Rng::seed_from_u64(2),
            &mut out,
        );
        let area = 4.0 * std::f32::consts::PI * radius * radius;
        let expected = area / (spacing * spacing);
        assert!(
            (out.len() as f32 - expected).abs() < 0.05 * expected,
            "{} vs {expected}",
            out.len()
        );
        for e in &out {
            let c = [e.pos[0], e.pos[1], e.pos[2] - radius];
            let len = (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt();
            assert!((len - radius).abs() < 1e-3);
            let dot: f32 = (0..3).map(|a| c[a] / len * e.normal[a]).sum();
            assert!(dot > 0.99, "normal not outward: {dot}");
            let tn: f32 = (0..3).map(|a| e.tangent[a] * e.normal[a]).sum();
            assert!(tn.abs() < 1e-4);
            assert!(e.surface.v >= 0.0 && e.surface.v <= std::f32::consts::PI * radius + 1e-4);
        }
    }

    #[test]
    fn box_faces_cover_the_surface_with_outward_normals() {
        let mut out = Vec::new();
        box_faces([0.3, 0.2], [0.0, 0.5], 0.05, true, Part::Body, &mut out);
        let area = 2.0 * (0.6 * 0.4) + 2.0 * (0.6 + 0.4) * 0.5;
        let cells: f32 = out.iter().map(|e| e.extent[0] * e.extent[1]).sum();
        assert!((cells - area).abs() < 1e-3, "{cells} vs {area}");
        let mut open = Vec::new();
        box_faces([0.3, 0.2], [0.0, 0.5], 0.05, false, Part::Body, &mut open);
        assert!(open.iter().all(|e| e.normal[2] > -0.5));
        assert_eq!(out.len() - open.len(), 12 * 8);
        for e in &out {
            // The normal points away from the box centre.
            let c = [e.pos[0], e.pos[1], e.pos[2] - 0.25];
            assert!((0..3).map(|a| c[a] * e.normal[a]).sum::<f32>() > 0.0);
            assert!((0.0..1.0).contains(&e.surface.turn));
        }
        // Perimeter positions on the sides agree with the radial projection used on the top.
        for (x, y) in [(0.3, 0.1), (-0.1, 0.2), (-0.3, -0.05), (0.2, -0.2)] {
            let side = out
                .iter()
                .filter(|e| e.normal[2] == 0.0)
                .min_by(|a, b| {
                    let da = (a.pos[0] - x).powi(2) + (a.pos[1] - y).powi(2);
                    let db = (b.pos[0] - x).powi(2) + (b.pos[1] - y).powi(2);
                    da.total_cmp(&db)
                })
                .unwrap();
            let t = perimeter_turn(x, y, 0.3, 0.2);
            let d = (side.surface.turn - t).abs();
            assert!(
                d.min(1.0 - d) < 0.03,
                "{x},{y}: {} vs {t}",
                side.surface.turn
            );
        }
    }
}
