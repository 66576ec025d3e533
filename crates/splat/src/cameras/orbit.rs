//! Generated cameras for a bare `.ply`: rings around the scene's bounds, all looking at the bounds' centre.
//!
//! Geometry: cameras sit at an elevation above the horizontal plane through the bounds' centre (20° by
//! default), spaced evenly in azimuth; with several rings the elevations are spread around the main one.
//! All share one distance: the smallest at which all eight corners of the bounds project inside every
//! view, shrunk by `margin`, so the scene fills the frame as far as the orbit allows. Intrinsics: square pixels, principal point at the image centre, `fov_deg` across
//! the shorter image side.
//!
//! Which way is up? A PLY does not say. [`Up::Auto`] looks at the bounds: scenes are usually flatter along
//! their vertical axis, so whichever of y and z has the smaller extent is taken as vertical. z is taken as
//! +z (Blender and most synthetic data are z-up); y is taken as -y (COLMAP-based scenes, which includes
//! everything the INRIA trainer produces, inherit the y-down axis of their cameras). When the guess is
//! wrong, pass the axis explicitly (`Up::PlusY`, `Up::MinusZ`, ... or any vector).

use super::{det, translation_of, unit};
use crate::cameras::camera::Camera;
use crate::scene::GaussianScene;
use glam::DVec3;

/// The world's up direction for orbits.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub enum Up {
    /// Guess from the bounds (see the module docs).
    #[default]
    Auto,
    PlusY,
    MinusY,
    PlusZ,
    MinusZ,
    /// Any non-zero direction.
    Vector([f64; 3]),
}

impl std::str::FromStr for Up {
    type Err = String;

    /// Parses `auto`, `y`, `+y`, `-y`, `z`, `+z`, `-z` or `X,Y,Z`.
    fn from_str(s: &str) -> Result<Self, String> {
        Ok(match s.trim() {
            "auto" => Up::Auto,
            "y" | "+y" => Up::PlusY,
            "-y" => Up::MinusY,
            "z" | "+z" => Up::PlusZ,
            "-z" => Up::MinusZ,
            other => {
                let v: Vec<f64> = other
                    .split(',')
                    .map(|t| t.trim().parse::<f64>())
                    .collect::<Result<_, _>>()
                    .map_err(|_| format!("'{other}' is not auto, ±y, ±z or X,Y,Z"))?;
                let v: [f64; 3] = v
                    .try_into()
                    .map_err(|_| format!("'{other}' is not auto, ±y, ±z or X,Y,Z"))?;
                if !v.iter().all(|c| c.is_finite()) || v.iter().all(|&c| c == 0.0) {
                    return Err(format!("up vector '{other}' must be finite and non-zero"));
                }
                Up::Vector(v)
            }
        })
    }
}

impl Up {
    /// The unit up direction for these bounds.
    pub fn resolve(self, lo: [f32; 3], hi: [f32; 3]) -> [f64; 3] {
        let v = match self {
            Up::Auto => {
                let (ey, ez) = (hi[1] - lo[1], hi[2] - lo[2]);
                if ez <= ey {
                    [0.0, 0.0, 1.0]
                } else {
                    [0.0, -1.0, 0.0]
                }
            }
            Up::PlusY => [0.0, 1.0, 0.0],
            Up::MinusY => [0.0, -1.0, 0.0],
            Up::PlusZ => [0.0, 0.0, 1.0],
            Up::MinusZ => [0.0, 0.0, -1.0],
            Up::Vector(v) => v,
        };
        unit(DVec3::from(v)).map_or([0.0, 0.0, 1.0], <[f64; 3]>::from)
    }
}

/// How orbits are laid out.
#[derive(Clone, Debug, PartialEq)]
pub struct OrbitSettings {
    pub up: Up,
    /// Elevation of the (middle) ring above the horizontal plane through the centre, degrees.
    pub elevation_deg: f64,
    /// Number of rings; cameras are shared out between them.
    pub rings: usize,
    /// Elevation step between rings, degrees.
    pub ring_spacing_deg: f64,
    /// Field of view across the shorter image side, degrees.
    pub fov_deg: f64,
    /// Extra room around the bounds (1 = the outermost corner touches the image border).
    pub margin: f64,
}

impl Default for OrbitSettings {
    fn default() -> Self {
        Self {
            up: Up::Auto,
            elevation_deg: 20.0,
            rings: 1,
            ring_spacing_deg: 20.0,
            fov_deg: 50.0,
            margin: 1.1,
        }
    }
}

/// `n` cameras of `width` x `height` on one ring around the bounds, with [`OrbitSettings::default`].
pub fn orbit_cameras(lo: [f32; 3], hi: [f32; 3], n: usize, width: u32, height: u32) -> Vec<Camera> {
    orbit_cameras_with(lo, hi, n, width, height, &OrbitSettings::default())
}

/// `n` cameras around the bounds laid out by `settings`. Non-finite or inverted bounds fall back to the
/// cube [-1, 1]³; degenerate (flat or point) bounds get a small minimum size so the cameras stay outside.
pub fn orbit_cameras_with(
    lo: [f32; 3],
    hi: [f32; 3],
    n: usize,
    width: u32,
    height: u32,
    settings: &OrbitSettings,
) -> Vec<Camera> {
    let (lo, hi) = if lo.iter().chain(&hi).all(|v| v.is_finite()) && (0..3).all(|a| lo[a] <= hi[a])
    {
        (lo, hi)
    } else {
        ([-1.0; 3], [1.0; 3])
    };
    let center = DVec3::from_array(std::array::from_fn(|a| 0.5 * (lo[a] as f64 + hi[a] as f64)));
    let fov = settings.fov_deg.clamp(1.0, 170.0).to_radians();
    let focal = 0.5 * width.min(height) as f64 / (0.5 * fov).tan();
    let margin = settings.margin.max(1.0);
    // Bounds corners relative to the centre; flat or point bounds get a small minimum size.
    let half: [f64; 3] = std::array::from_fn(|a| (0.5 * (hi[a] as f64 - lo[a] as f64)).max(1e-3));
    let corners: Vec<DVec3> = (0..8)
        .map(|i| {
            DVec3::from_array(std::array::from_fn(|a| {
                if i >> a & 1 == 1 {
                    half[a]
                } else {
                    -half[a]
                }
            }))
        })
        .collect();
    let radius = half.iter().map(|h| h * h).sum::<f64>().sqrt();

    let up = DVec3::from(settings.up.resolve(lo, hi));
    // A horizontal basis: e1 from the world axis least aligned with up, e2 completing it.
    let e1 = unit(up.cross(least_aligned_axis(up))).unwrap_or(DVec3::X);
    let e2 = up.cross(e1);

    let rings = settings.rings.clamp(1, n.max(1));
    let mut directions = Vec::with_capacity(n);
    for ring in 0..rings {
        let in_ring = n / rings + usize::from(ring < n % rings);
        let offset = ring as f64 - (rings - 1) as f64 / 2.0;
        let elevation = (settings.elevation_deg + offset * settings.ring_spacing_deg)
            .clamp(-85.0, 85.0)
            .to_radians();
        for k in 0..in_ring {
            // Stagger rings so their cameras do not line up.
            let azimuth = std::f64::consts::TAU * (k as f64 + 0.5 * ring as f64) / in_ring as f64;
            directions.push(orbit_direction(elevation, azimuth, e1, e2, up));
        }
    }

    // One distance for the whole orbit: the smallest at which every corner projects inside every view
    // with `margin` to spare (and stays well in front of the camera).
    let (tan_x, tan_y) = (0.5 * width as f64 / focal, 0.5 * height as f64 / focal);
    let mut distance: f64 = 0.0;
    for dir in &directions {
        let probe = look_at(
            String::new(),
            (center + *dir).to_array(),
            center.to_array(),
            up.to_array(),
            width,
            height,
            focal,
        );
        let [right, down, _] = probe.rotation.map(DVec3::from);
        for o in &corners {
            let toward = o.dot(*dir);
            let need =
                (margin * o.dot(right).abs() / tan_x).max(margin * o.dot(down).abs() / tan_y);
            distance = distance.max(toward + need).max(toward + 0.1 * radius);
        }
    }

    directions
        .iter()
        .enumerate()
        .map(|(i, dir)| {
            let eye = center + *dir * distance;
            look_at(
                format!("orbit_{i:03}"),
                eye.to_array(),
                center.to_array(),
                up.to_array(),
                width,
                height,
                focal,
            )
        })
        .collect()
}

/// The point the cameras look at: the least-squares closest point to all their optical axes. `None` when
/// the axes are (nearly) parallel, e.g. a forward-facing capture, or there are no cameras.
pub fn focus_point(cameras: &[Camera]) -> Option<[f64; 3]> {
    // Minimise Σ |(I − d dᵀ)(x − c)|²: solve (Σ I − d dᵀ) x = Σ (I − d dᵀ) c.
    let mut a = [[0.0f64; 3]; 3];
    let mut b = [0.0f64; 3];
    for cam in cameras {
        let (c, d) = (cam.center(), cam.rotation[2]);
        for r in 0..3 {
            for k in 0..3 {
                let p = f64::from(u8::from(r == k)) - d[r] * d[k];
                a[r][k] += p;
                b[r] += p * c[k];
            }
        }
    }
    let d = det(&a);
    // Parallel axes make the system singular; relative to n³ (the determinant of n·I) it is then tiny.
    let n = cameras.len() as f64;
    if d.is_nan() || d.abs() <= 1e-6 * n * n * n {
        return None;
    }
    // Cramer's rule.
    let x: [f64; 3] = std::array::from_fn(|col| {
        let mut m = a;
        for r in 0..3 {
            m[r][col] = b[r];
        }
        det(&m) / d
    });
    x.iter().all(|v| v.is_finite()).then_some(x)
}

/// `n` cameras of `width` x `height` on a circle around `target`, laid out like `cameras`: their mean up
/// direction, their median distance from `target` and elevation above it, their median field of view
/// (across the shorter side), starting at the first camera's azimuth. A full turn when the cameras go most
/// of the way round; for a partial arc (a forward-facing capture) a sweep over the arc and back. For a
/// turntable of what the user's own views show. `None` without cameras or when they sit on `target`.
pub fn orbit_like(
    cameras: &[Camera],
    target: [f64; 3],
    n: usize,
    width: u32,
    height: u32,
) -> Option<Vec<Camera>> {
    let first = cameras.first()?;
    let median = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    // OpenCV cameras: image y points down, so the world's up is minus the camera's y axis.
    let up_sum = cameras
        .iter()
        .fold(DVec3::ZERO, |acc, c| acc + -DVec3::from(c.rotation[1]));
    let up = unit(up_sum)?;
    let target = DVec3::from(target);
    let offsets: Vec<DVec3> = cameras
        .iter()
        .map(|c| DVec3::from(c.center()) - target)
        .collect();
    let distance = median(offsets.iter().map(|o| o.length()).collect());
    if !distance.is_finite() || distance <= 1e-9 {
        return None;
    }
    let elevation = median(
        offsets
            .iter()
            .filter_map(|o| unit(*o))
            .map(|o| o.dot(up).clamp(-1.0, 1.0).asin())
            .collect(),
    )
    .clamp(-85f64.to_radians(), 85f64.to_radians());
    let half_fov = median(
        cameras
            .iter()
            .map(|c| {
                let (w, h) = (c.width as f64, c.height as f64);
                if w <= h {
                    (0.5 * w / c.fx).atan()
                } else {
                    (0.5 * h / c.fy).atan()
                }
            })
            .collect(),
    );
    let focal = 0.5 * width.min(height) as f64 / half_fov.tan();
    // Horizontal basis with e1 toward the first camera, so frame 0 looks like view 0.
    let first_offset = DVec3::from(first.center()) - target;
    let flat = first_offset - first_offset.dot(up) * up;
    let e1 = unit(flat).or_else(|| unit(up.cross(least_aligned_axis(up))))?;
    let e2 = up.cross(e1);
    let azimuths = orbit_azimuths(offsets.iter().map(|o| o.dot(e2).atan2(o.dot(e1))), n);
    Some(
        azimuths
            .into_iter()
            .enumerate()
            .map(|(i, azimuth)| {
                let dir = orbit_direction(elevation, azimuth, e1, e2, up);
                let eye = target + dir * distance;
                look_at(
                    format!("orbit_{i:03}"),
                    eye.to_array(),
                    target.to_array(),
                    up.to_array(),
                    width,
                    height,
                    focal,
                )
            })
            .collect(),
    )
}

/// `n` azimuths for a turntable, given the views' azimuths (radians, the first view's at 0): a full turn
/// when the views go most of the way round the target, otherwise a sweep over the arc they cover and back
/// (a forward-facing capture has nothing to show behind it).
fn orbit_azimuths(views: impl Iterator<Item = f64>, n: usize) -> Vec<f64> {
    use std::f64::consts::TAU;
    let mut a: Vec<f64> = views.map(|v| v.rem_euclid(TAU)).collect();
    a.sort_by(f64::total_cmp);
    // The covered arc is the circle minus its largest gap between neighbouring views; it starts at the
    // view after that gap.
    let (mut gap, mut arc_start) = (0.0, 0.0);
    for (k, &v) in a.iter().enumerate() {
        let next = if k + 1 < a.len() {
            a[k + 1]
        } else {
            a[0] + TAU
        };
        if next - v > gap {
            gap = next - v;
            arc_start = next;
        }
    }
    if a.len() < 2 || gap < 0.5 * TAU {
        return (0..n).map(|i| TAU * i as f64 / n as f64).collect();
    }
    // The arc as [lo, hi] around the first view's 0, then a triangle wave from 0 up to hi, down to lo and
    // back up to 0.
    let len = TAU - gap;
    let lo = -(-arc_start).rem_euclid(TAU).min(len);
    let hi = lo + len;
    (0..n)
        .map(|i| {
            let d = (i as f64 / n as f64 * 2.0 * len - lo).rem_euclid(2.0 * len);
            if d <= len {
                lo + d
            } else {
                hi - (d - len)
            }
        })
        .collect()
}

/// The world axis least aligned with `up` (the first of equals): a partner for a horizontal basis.
fn least_aligned_axis(up: DVec3) -> DVec3 {
    let least = (0..3)
        .min_by(|&a, &b| up[a].abs().total_cmp(&up[b].abs()))
        .unwrap_or(0);
    DVec3::AXES[least]
}

/// Unit direction at `elevation` above the horizontal plane spanned by `e1`, `e2` and `azimuth` from `e1`.
fn orbit_direction(elevation: f64, azimuth: f64, e1: DVec3, e2: DVec3, up: DVec3) -> DVec3 {
    elevation.cos() * (azimuth.cos() * e1 + azimuth.sin() * e2) + elevation.sin() * up
}

/// An OpenCV camera at `eye` looking at `target`, with `up` appearing upwards in the image.
pub fn look_at(
    name: String,
    eye: [f64; 3],
    target: [f64; 3],
    up: [f64; 3],
    width: u32,
    height: u32,
    focal: f64,
) -> Camera {
    let (eye, target, up) = (DVec3::from(eye), DVec3::from(target), DVec3::from(up));
    let forward = unit(target - eye).unwrap_or(DVec3::Z);
    let right = unit(forward.cross(up))
        .or_else(|| unit(forward.cross(DVec3::X)))
        .or_else(|| unit(forward.cross(DVec3::Y)))
        .unwrap_or(DVec3::X);
    let down = forward.cross(right);
    let rotation = [right, down, forward].map(<[f64; 3]>::from);
    let translation = translation_of(&rotation, eye);
    Camera {
        name,
        width,
        height,
        fx: focal,
        fy: focal,
        cx: width as f64 / 2.0,
        cy: height as f64 / 2.0,
        rotation,
        translation,
    }
}

/// Per-axis quantile bounds of the means: (q-quantile, (1-q)-quantile) with q in [0, 0.5), so a few
/// floaters far from the scene do not blow up orbits or statistics. `None` for an empty scene.
pub fn robust_bounds(scene: &GaussianScene, q: f64) -> Option<([f32; 3], [f32; 3])> {
    let n = scene.len();
    if n == 0 {
        return None;
    }
    let q = q.clamp(0.0, 0.499);
    let lo_i = ((n - 1) as f64 * q).round() as usize;
    let hi_i = ((n - 1) as f64 * (1.0 - q)).round() as usize;
    let mut lo = [0.0; 3];
    let mut hi = [0.0; 3];
    let mut column = Vec::with_capacity(n);
    for a in 0..3 {
        column.clear();
        column.extend(scene.means.chunks_exact(3).map(|p| p[a]));
        lo[a] = *column.select_nth_unstable_by(lo_i, f32::total_cmp).1;
        hi[a] = *column.select_nth_unstable_by(hi_i, f32::total_cmp).1;
    }
    Some((lo, hi))
}

#[cfg(test)]
mod tests {
    #[test]
    fn orbit_like_reproduces_a_ring_and_finds_its_focus() {
        // A ring of 8 cameras around (1, 2, 3), z up, 30° elevation, 60° field of view.
        let target = [1.0, 2.0, 3.0];
        let settings = OrbitSettings {
            up: Up::PlusZ,
            elevation_deg: 30.0,
            fov_deg: 60.0,
            ..OrbitSettings::default()
        };
        let ring = orbit_cameras_with([0.0, 1.0, 2.0], [2.0, 3.0, 4.0], 8, 64, 48, &settings);
        let focus = focus_point(&ring).unwrap();
        for a in 0..3 {
            assert!((focus[a] - target[a]).abs() < 1e-9, "{focus:?}");
        }
        let like = orbit_like(&ring, focus, 16, 32, 32).unwrap();
        assert_eq!(like.len(), 16);
        let d0 = dist(ring[0].center(), target);
        for (k, c) in like.iter().enumerate() {
            let o: [f64; 3] = std::array::from_fn(|a| c.center()[a] - target[a]);
            assert!(
                (dist(c.center(), target) - d0).abs() < 1e-9 * d0,
                "distance of {k}"
            );
            assert!(
                (o[2] / d0 - 30f64.to_radians().sin()).abs() < 1e-9,
                "elevation of {k}"
            );
            // Looks at the target: it projects to the image centre.
            let p = c.world_to_camera(target);
            assert!((c.fx * p[0] / p[2]).abs() < 1e-6 && (c.fy * p[1] / p[2]).abs() < 1e-6);
            // Up stays up: a point above the target appears above the centre.
            let q = c.world_to_camera([target[0], target[1], target[2] + 0.1]);
            assert!(q[1] / q[2] < p[1] / p[2]);
        }
        // 60° across the shorter side (48 px of the ring's 64 x 48) → 60° across 32 px.
        assert!((2.0 * (16.0 / like[0].fx).atan() - 60f64.to_radians()).abs() < 1e-9);
        // Frame 0 sits where view 0 does (same distance and elevation, same azimuth).
        assert!(dist(like[0].center(), ring[0].center()) < 1e-9 * d0);
    }

    #[test]
    fn turntable_azimuths_turn_fully_or_sweep_the_covered_arc() {
        use std::f64::consts::TAU;
        // Views all round: a full turn from the first view.
        let full = orbit_azimuths((0..8).map(|k| TAU * k as f64 / 8.0), 4);
        assert_eq!(full, vec![0.0, 0.25 * TAU, 0.5 * TAU, 0.75 * TAU]);
        // A forward-facing arc from -30° to +50°, first view at 0: sweep within it, starting at 0.
        let deg = |d: f64| d.to_radians();
        let arc = [0.0, deg(-30.0), deg(50.0), deg(20.0)];
        let sweep = orbit_azimuths(arc.iter().copied(), 16);
        assert!(sweep[0].abs() < 1e-12, "{sweep:?}");
        let (lo, hi) = sweep
            .iter()
            .fold((f64::MAX, f64::MIN), |(l, h), &v| (l.min(v), h.max(v)));
        assert!(
            (lo - deg(-30.0)).abs() < 1e-9 && (hi - deg(50.0)).abs() < 1e-9,
            "{sweep:?}"
        );
        // Evenly spaced along the path (total 160°, 16 frames → 10° apart), no jumps.
        for w in sweep.windows(2) {
            assert!(((w[1] - w[0]).abs() - deg(10.0)).abs() < 1e-9, "{sweep:?}");
        }
        // The same arc seen across the wrap (views at 340°..60°) behaves the same.
        let wrapped = orbit_azimuths(arc.iter().map(|v| v.rem_euclid(TAU)), 16);
        for (a, b) in wrapped.iter().zip(&sweep) {
            assert!((a - b).abs() < 1e-9, "{wrapped:?} vs {sweep:?}");
        }
    }

    #[test]
    fn parallel_cameras_have_no_focus_and_no_cameras_no_orbit() {
        let mut a = orbit_cameras([-1.0; 3], [1.0; 3], 1, 16, 16).remove(0);
        let mut b = a.clone();
        a.translation[0] += 1.0;
        b.translation[1] -= 2.0;
        assert_eq!(focus_point(&[a, b]), None);
        assert_eq!(focus_point(&[]), None);
        assert!(orbit_like(&[], [0.0; 3], 4, 16, 16).is_none());
    }

    use super::super::test_util::project;
    use super::*;

    fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
        (0..3).map(|k| (a[k] - b[k]).powi(2)).sum::<f64>().sqrt()
    }

    fn corners(lo: [f32; 3], hi: [f32; 3]) -> Vec<[f64; 3]> {
        (0..8)
            .map(|i| {
                std::array::from_fn(|a| {
                    if i >> a & 1 == 1 {
                        hi[a] as f64
                    } else {
                        lo[a] as f64
                    }
                })
            })
            .collect()
    }

    #[test]
    fn orbit_sees_all_bounds_and_keeps_up_upwards() {
        let (lo, hi) = ([-1.0, -2.0, 0.0], [3.0, 1.0, 0.5]);
        for (w, h) in [(64, 64), (96, 48), (40, 80)] {
            let cams = orbit_cameras(lo, hi, 7, w, h);
            assert_eq!(cams.len(), 7);
            let center = [1.0, -0.5, 0.25];
            for cam in &cams {
                // The centre projects to the image centre.
                let c = project(cam, center).unwrap();
                assert!(
                    (c[0] - w as f64 / 2.0).abs() < 1e-9 && (c[1] - h as f64 / 2.0).abs() < 1e-9
                );
                for p in corners(lo, hi) {
                    let uv = project(cam, p).expect("corner in front of the camera");
                    assert!(
                        uv[0] > 0.0 && uv[0] < w as f64 && uv[1] > 0.0 && uv[1] < h as f64,
                        "{uv:?}"
                    );
                }
                // z is the flattest axis here, so up is +z: a point above the centre appears higher.
                let above = project(cam, [1.0, -0.5, 1.0]).unwrap();
                assert!(above[1] < c[1]);
                // Elevated: the camera is above the centre.
                assert!(cam.center()[2] > center[2]);
            }
            // Tight framing: the outermost corner sits exactly at 1/margin of the half-size.
            let settings = OrbitSettings::default();
            let extent = cams
                .iter()
                .flat_map(|cam| {
                    corners(lo, hi)
                        .into_iter()
                        .map(move |p| project(cam, p).unwrap())
                })
                .map(|uv| {
                    (2.0 * uv[0] / w as f64 - 1.0)
                        .abs()
                        .max((2.0 * uv[1] / h as f64 - 1.0).abs())
                })
                .fold(0.0, f64::max);
            assert!((extent - 1.0 / settings.margin).abs() < 1e-9, "{extent}");
            // Distinct positions all round.
            let c0 = cams[0].center();
            assert!(cams[1..].iter().all(|c| {
                let d = c.center();
                (0..3).map(|a| (d[a] - c0[a]).powi(2)).sum::<f64>() > 1e-6
            }));
        }
    }

    #[test]
    fn up_guess_and_explicit_up() {
        assert_eq!(Up::Auto.resolve([0.0; 3], [1.0, 1.0, 0.2]), [0.0, 0.0, 1.0]);
        assert_eq!(
            Up::Auto.resolve([0.0; 3], [1.0, 0.2, 1.0]),
            [0.0, -1.0, 0.0]
        );
        assert_eq!("-z".parse::<Up>().unwrap(), Up::MinusZ);
        assert_eq!(
            "0,2,0".parse::<Up>().unwrap().resolve([0.0; 3], [1.0; 3]),
            [0.0, 1.0, 0.0]
        );
        assert!("0,0,0".parse::<Up>().is_err());
        assert!("sideways".parse::<Up>().is_err());
        let settings = OrbitSettings {
            up: Up::PlusY,
            rings: 3,
            ..Default::default()
        };
        let cams = orbit_cameras_with([-1.0; 3], [1.0; 3], 10, 32, 32, &settings);
        assert_eq!(cams.len(), 10);
        let heights: Vec<f64> = cams.iter().map(|c| c.center()[1]).collect();
        // Ring elevations 0, 20 and 40 degrees: three distinct heights, all >= the centre.
        let mut distinct = heights.clone();
        distinct.sort_by(f64::total_cmp);
        distinct.dedup_by(|a, b| (*a - *b).abs() < 1e-9);
        assert_eq!(distinct.len(), 3);
        assert!(heights.iter().all(|&y| y > -1e-9));
    }

    #[test]
    fn degenerate_bounds_still_give_valid_cameras() {
        for (lo, hi) in [
            ([0.0; 3], [0.0; 3]),
            ([f32::NAN; 3], [1.0; 3]),
            ([1.0; 3], [-1.0; 3]),
        ] {
            for cam in orbit_cameras(lo, hi, 3, 16, 16) {
                assert!(cam.rotation.iter().flatten().all(|v| v.is_finite()));
                assert!(cam.translation.iter().all(|v| v.is_finite()));
                assert!(cam.translation[2] > 0.0, "scene centre in front");
            }
        }
        assert!(orbit_cameras([0.0; 3], [1.0; 3], 0, 16, 16).is_empty());
    }

    #[test]
    fn robust_bounds_ignore_floaters() {
        let n = 1000;
        let mut scene = GaussianScene::new(0);
        for i in 0..n {
            let t = i as f32 / n as f32;
            scene.means.extend_from_slice(&[t, -t, 2.0 * t]);
            scene.opacity_logits.push(0.0);
        }
        scene.means[0] = 1e6;
        let (lo, hi) = robust_bounds(&scene, 0.01).unwrap();
        assert!(hi[0] < 1.0 && lo[0] > 0.0 && lo[1] > -1.0 && hi[2] < 2.0);
        let (lo, hi) = robust_bounds(&scene, 0.0).unwrap();
        assert_eq!((lo, hi), scene.bounds().unwrap());
    }
}
