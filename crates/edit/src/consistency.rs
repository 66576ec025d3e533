//! 2D → 3D → 2D: the operation both VcEdit consistency modules of attention maps rest on.
//!
//! Per-view maps (any number of channels) are lifted onto the Gaussians (GaussianEditor's `apply_weights`:
//! each Gaussian gets the average of the map over the pixels it is hit at, over all views), then rendered
//! back from every view as extra channels (normal alpha compositing over 0). Maps that disagree across views
//! come back as one map per view of a single 3D quantity, so they agree wherever the views see the same
//! surface.

use splat::render::{render, ExtraChannels, RenderSettings};
use splat::{Camera, GaussianScene};

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
        Resample::Bilinear => crate::viz::bilinear(src, h, w, out_h, out_w, channels),
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

/// Lifts per-view maps onto the Gaussians and renders them back.
///
/// `map_of(v)` gives view v's map at its native size `native` (h, w), `channels` interleaved; it is
/// resampled to the camera's resolution with `up`, lifted over all views, rendered back, resampled to
/// `native` with `down`, and handed to `sink(v, map)`. Cameras must share one resolution.
pub fn make_consistent(
    scene: &GaussianScene,
    cameras: &[Camera],
    native: (usize, usize),
    channels: usize,
    up: Resample,
    down: Resample,
    map_of: &mut dyn FnMut(usize) -> candle_core::Result<Vec<f32>>,
    sink: &mut dyn FnMut(usize, Vec<f32>) -> candle_core::Result<()>,
) -> candle_core::Result<()> {
    if cameras.is_empty() || channels == 0 {
        return Ok(());
    }
    let (rh, rw) = (cameras[0].height as usize, cameras[0].width as usize);
    let mut lift = splat::lift::LiftAccumulator::new(scene, channels);
    for (v, cam) in cameras.iter().enumerate() {
        let native_map = map_of(v)?;
        let full = resample(&native_map, native.0, native.1, rh, rw, channels, up);
        lift.add_view(cam, &full);
    }
    let lifted = lift.finish();
    let settings = RenderSettings::default();
    for (v, cam) in cameras.iter().enumerate() {
        let out = render(
            scene,
            cam,
            &settings,
            Some(ExtraChannels {
                values: &lifted.values,
                channels,
            }),
        );
        let back = resample(&out.extra, rh, rw, native.0, native.1, channels, down);
        sink(v, back)?;
    }
    Ok(())
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
}
