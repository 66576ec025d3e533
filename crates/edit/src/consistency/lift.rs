//! 2D → 3D → 2D: the operation CCM and blend-map consistency rest on (docs/algorithm.md §3.1), and the
//! resampling of maps between their native grid and the render resolution.
//!
//! Per-view maps (any number of channels) are lifted onto the Gaussians (GaussianEditor's `apply_weights`:
//! each Gaussian gets the average of the map over the pixels it is hit at, over all views), then rendered
//! back from every view as extra channels (normal alpha compositing over 0). Maps that disagree across views
//! come back as one map per view of a single 3D quantity, so they agree wherever the views see the same
//! surface.

use splat::render::{ExtraChannels, RenderSettings};
use splat::{Camera, GaussianScene};

use super::MultiViewError;
use crate::compute::Compute;

/// How maps are resampled between their native grid and the render resolution.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Resample {
    /// torch `interpolate(mode="nearest")`.
    Nearest,
    /// torch `interpolate(mode="bilinear", align_corners=False)` (no antialiasing).
    Bilinear,
}

/// Resamples a row-major, channel-interleaved map from (h, w) to (out_h, out_w).
pub fn resample(
    src: &[f32],
    h: usize,
    w: usize,
    out_h: usize,
    out_w: usize,
    channels: usize,
    mode: Resample,
) -> Vec<f32> {
    if (h, w) == (out_h, out_w) {
        return src.to_vec();
    }
    match mode {
        Resample::Bilinear => bilinear(src, h, w, out_h, out_w, channels),
        Resample::Nearest => {
            let mut out = vec![0.0; out_h * out_w * channels];
            for oy in 0..out_h {
                // torch's nearest: floor(dst * in / out).
                let y = ((oy as f64 * h as f64 / out_h as f64) as usize).min(h - 1);
                for ox in 0..out_w {
                    let x = ((ox as f64 * w as f64 / out_w as f64) as usize).min(w - 1);
                    let s = (y * w + x) * channels;
                    let d = (oy * out_w + ox) * channels;
                    out[d..d + channels].copy_from_slice(&src[s..s + channels]);
                }
            }
            out
        }
    }
}

/// Bilinear resampling of a row-major, channel-interleaved map (align_corners = false, edge-clamped, as
/// torch's `interpolate(mode="bilinear")` when upsampling).
pub fn bilinear(
    src: &[f32],
    h: usize,
    w: usize,
    out_h: usize,
    out_w: usize,
    channels: usize,
) -> Vec<f32> {
    let mut out = vec![0.0f32; out_h * out_w * channels];
    let sy = h as f32 / out_h as f32;
    let sx = w as f32 / out_w as f32;
    for oy in 0..out_h {
        let fy = ((oy as f32 + 0.5) * sy - 0.5).max(0.0);
        let y0 = (fy as usize).min(h - 1);
        let y1 = (y0 + 1).min(h - 1);
        let ty = fy - y0 as f32;
        for ox in 0..out_w {
            let fx = ((ox as f32 + 0.5) * sx - 0.5).max(0.0);
            let x0 = (fx as usize).min(w - 1);
            let x1 = (x0 + 1).min(w - 1);
            let tx = fx - x0 as f32;
            for c in 0..channels {
                let at = |y: usize, x: usize| src[(y * w + x) * channels + c];
                let top = at(y0, x0) * (1.0 - tx) + at(y0, x1) * tx;
                let bot = at(y1, x0) * (1.0 - tx) + at(y1, x1) * tx;
                out[(oy * out_w + ox) * channels + c] = top * (1.0 - ty) + bot * ty;
            }
        }
    }
    out
}

/// Lifts per-view maps onto the Gaussians and renders them back.
///
/// `map_of(v)` gives view v's map at its native size `native` (h, w), `channels` interleaved; it is
/// resampled to the camera's resolution with `up`, lifted over all views, rendered back, resampled to
/// `native` with `down`, and handed to `sink(v, map)`. Cameras must share one resolution.
pub fn make_consistent(
    compute: &Compute,
    scene: &GaussianScene,
    cameras: &[Camera],
    native: (usize, usize),
    channels: usize,
    up: Resample,
    down: Resample,
    map_of: &mut dyn FnMut(usize) -> candle_core::Result<Vec<f32>>,
    sink: &mut dyn FnMut(usize, Vec<f32>) -> candle_core::Result<()>,
) -> Result<(), MultiViewError> {
    if cameras.is_empty() || channels == 0 {
        return Ok(());
    }
    let (rh, rw) = (cameras[0].height as usize, cameras[0].width as usize);
    let mut lift = compute.splat().lifter(scene, channels);
    for (v, cam) in cameras.iter().enumerate() {
        let native_map = map_of(v)?;
        let full = resample(&native_map, native.0, native.1, rh, rw, channels, up);
        lift.add_view(cam, &full)?;
    }
    let lifted = lift.finish()?;
    let extra = ExtraChannels {
        values: &lifted.values,
        channels,
    };
    compute.splat().for_each_render(
        scene,
        cameras,
        &RenderSettings::default(),
        Some(extra),
        &mut |v, out| {
            let back = resample(&out.extra, rh, rw, native.0, native.1, channels, down);
            Ok(sink(v, back)?)
        },
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nearest_matches_torch_index_rule() {
        // torch: interpolate([[0, 1, 2]], size=2, mode="nearest") picks floor(i * 3/2) = 0, 1.
        let out = resample(&[0.0, 1.0, 2.0], 1, 3, 1, 2, 1, Resample::Nearest);
        assert_eq!(out, vec![0.0, 1.0]);
        let up = resample(&[0.0, 1.0], 1, 2, 1, 4, 1, Resample::Nearest);
        assert_eq!(up, vec![0.0, 0.0, 1.0, 1.0]);
    }

    #[test]
    fn bilinear_matches_torch_on_a_ramp() {
        // torch: F.interpolate(tensor([[[[0., 1.]]]]), size=(1, 4), mode="bilinear") = [0, .25, .75, 1]
        let out = bilinear(&[0.0, 1.0], 1, 2, 1, 4, 1);
        assert_eq!(out, vec![0.0, 0.25, 0.75, 1.0]);
    }
}

#[cfg(test)]
mod consistency_tests {
    use super::*;

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
            &Compute::cpu(),
            &scene,
            &cams,
            (size as usize, size as usize),
            1,
            Resample::Nearest,
            Resample::Nearest,
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
