//! 2D → 3D → 2D: the operation CCM and blend-map consistency rest on (docs/algorithm.md §3.1).
//!
//! Per-view maps (any number of channels) are lifted onto the Gaussians (GaussianEditor's `apply_weights`:
//! each Gaussian gets the average of the map over the pixels it is hit at, over all views), then rendered
//! back from every view as extra channels (normal alpha compositing over 0). Maps that disagree across views
//! come back as one map per view of a single 3D quantity, so they agree wherever the views see the same
//! surface. The work is splat's ([`splat::SplatDevice::lift_and_render_back`], on the run's device); this
//! is the sampler's side of it (candle errors in, [`MultiViewError`] out).

use splat::lift::MapGrid;
use splat::LiftSession;

use super::MultiViewError;

/// Lifts per-view maps onto the Gaussians and renders them back: one round of `lift`, a session over the
/// sampler run's scene and cameras (made once per run, so a GPU keeps the scene and each view's
/// projection for every round).
///
/// `map_of(v)` gives view v's map on `grid`; it is resampled to the camera's resolution with `grid.up`,
/// lifted over all views, rendered back, resampled to the grid with `grid.down`, and handed to
/// `sink(v, map)`.
pub fn make_consistent(
    lift: &mut LiftSession<'_>,
    grid: &MapGrid,
    map_of: &mut dyn FnMut(usize) -> candle_core::Result<Vec<f32>>,
    sink: &mut dyn FnMut(usize, Vec<f32>) -> candle_core::Result<()>,
) -> Result<(), MultiViewError> {
    lift.lift_and_render_back::<MultiViewError>(grid, &mut |v| Ok(map_of(v)?), &mut |v, map| {
        Ok(sink(v, map)?)
    })
}

#[cfg(test)]
mod consistency_tests {
    use super::*;
    use splat::lift::Resample;
    use splat::{Camera, GaussianScene, SplatDevice};

    /// A camera at `(x, 0, -3)` looking down +z at the origin (OpenCV axes).
    fn cam(x: f64, size: u32) -> Camera {
        // Rotate about y so the camera looks at the origin.
        let yaw = (-x / 3.0).atan();
        let (s, c) = yaw.sin_cos();
        let r = [[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]];
        let centre = [x, 0.0, -3.0];
        let t = [
            -(r[0][0] * centre[0] + r[0][1] * centre[1] + r[0][2] * centre[2]),
            -(r[1][0] * centre[0] + r[1][1] * centre[1] + r[1][2] * centre[2]),
            -(r[2][0] * centre[0] + r[2][1] * centre[1] + r[2][2] * centre[2]),
        ];
        Camera {
            name: format!("c{x}"),
            width: size,
            height: size,
            fx: size as f64,
            fy: size as f64,
            cx: size as f64 / 2.0,
            cy: size as f64 / 2.0,
            rotation: r,
            translation: t,
        }
    }

    /// A dense plane of small opaque Gaussians at z = 0 covering [-1, 1]².
    fn plane() -> GaussianScene {
        let mut s = GaussianScene::new(0);
        let n = 40;
        for i in 0..n {
            for j in 0..n {
                let x = -1.0 + 2.0 * (i as f32 + 0.5) / n as f32;
                let y = -1.0 + 2.0 * (j as f32 + 0.5) / n as f32;
                s.means.extend_from_slice(&[x, y, 0.0]);
                let sc = (1.2 / n as f32).ln();
                s.log_scales.extend_from_slice(&[sc, sc, (0.002f32).ln()]);
                s.quats.extend_from_slice(&[1.0, 0.0, 0.0, 0.0]);
                s.opacity_logits.push(4.0);
                s.sh.extend_from_slice(&[0.0, 0.0, 0.0]);
            }
        }
        s
    }

    /// Pixel of the world point `p` in `cam`, if inside.
    fn project(cam: &Camera, p: [f64; 3]) -> Option<(usize, usize)> {
        let q = cam.world_to_camera(p);
        let u = cam.fx * q[0] / q[2] + cam.cx;
        let v = cam.fy * q[1] / q[2] + cam.cy;
        (u >= 0.0 && v >= 0.0 && u < cam.width as f64 && v < cam.height as f64)
            .then_some((u as usize, v as usize))
    }

    #[test]
    fn maps_of_the_same_surface_agree_after_lifting_and_rendering() {
        let scene = plane();
        let size = 48u32;
        let cams = [cam(-0.8, size), cam(0.9, size)];
        // Two maps that disagree: view 0 says "left half of the image", view 1 random noise.
        let npx = (size * size) as usize;
        let maps: Vec<Vec<f32>> = vec![
            (0..npx)
                .map(|p| {
                    if (p % size as usize) < size as usize / 2 {
                        1.0
                    } else {
                        0.0
                    }
                })
                .collect(),
            (0..npx).map(|p| ((p * 7919) % 13) as f32 / 12.0).collect(),
        ];
        let mut back = [Vec::new(), Vec::new()];
        make_consistent(
            &mut SplatDevice::Cpu.lift_session(&scene, &cams),
            &MapGrid {
                height: size as usize,
                width: size as usize,
                channels: 1,
                up: Resample::Nearest,
                down: Resample::Nearest,
            },
            &mut |v| Ok(maps[v].clone()),
            &mut |v, m| {
                back[v] = m;
                Ok(())
            },
        )
        .unwrap();
        // Compare both views at world points of the plane visible in both.
        let (mut before, mut after, mut n) = (0.0f32, 0.0f32, 0);
        for i in 0..15 {
            for j in 0..15 {
                let p = [-0.7 + 0.1 * i as f64, -0.7 + 0.1 * j as f64, 0.0];
                let (Some((u0, v0)), Some((u1, v1))) = (project(&cams[0], p), project(&cams[1], p))
                else {
                    continue;
                };
                let (a, b) = (v0 * size as usize + u0, v1 * size as usize + u1);
                before += (maps[0][a] - maps[1][b]).abs();
                after += (back[0][a] - back[1][b]).abs();
                n += 1;
            }
        }
        assert!(n > 50, "{n} co-visible samples");
        let (before, after) = (before / n as f32, after / n as f32);
        assert!(before > 0.25, "the input maps disagree ({before})");
        assert!(
            after < 0.25 * before,
            "lifted maps agree: {after} vs {before} before"
        );
    }
}
