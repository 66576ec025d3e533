//! Small generated scenes for end-to-end tests: enough Gaussians to render something recognisable,
//! few enough to run in milliseconds.

use splat::GaussianScene;

/// The SH band-0 constant: a DC coefficient `dc` shows the colour `0.5 + SH_C0 · dc`.
const SH_C0: f32 = 0.282_094_8;

/// 64 opaque-ish Gaussians in a ball of radius ~0.3 around the origin, SH degree 0, every one with the
/// DC coefficients `dc` (`[1.8, -1.8, -1.8]` is red: colour 1, 0, 0).
pub fn ball(dc: [f32; 3]) -> GaussianScene {
    let mut s = GaussianScene::new(0);
    for i in 0..64 {
        let t = i as f32 * 0.7;
        s.means
            .extend_from_slice(&[0.3 * t.sin(), 0.3 * (1.3 * t).cos(), 0.3 * (0.7 * t).sin()]);
        s.log_scales.extend_from_slice(&[-2.0; 3]);
        s.quats.extend_from_slice(&[1.0, 0.0, 0.0, 0.0]);
        s.opacity_logits.push(3.0);
        s.sh.extend_from_slice(&dc);
    }
    s
}

/// The red [`ball`].
pub fn red_ball() -> GaussianScene {
    ball([1.8, -1.8, -1.8])
}

/// A unit sphere covered by `n` small opaque Gaussians on a Fibonacci lattice, each coloured by
/// `color(position)` (SH degree 0, so colours do not depend on the view).
pub fn textured_sphere(n: usize, color: impl Fn([f32; 3]) -> [f32; 3]) -> GaussianScene {
    let mut s = GaussianScene::new(0);
    let golden = std::f32::consts::PI * (3.0 - 5f32.sqrt());
    let spacing = (4.0 * std::f32::consts::PI / n as f32).sqrt();
    for i in 0..n {
        let y = 1.0 - 2.0 * (i as f32 + 0.5) / n as f32;
        let r = (1.0 - y * y).sqrt();
        let t = golden * i as f32;
        let p = [r * t.cos(), y, r * t.sin()];
        s.means.extend_from_slice(&p);
        s.log_scales.extend_from_slice(&[(0.7 * spacing).ln(); 3]);
        s.quats.extend_from_slice(&[1.0, 0.0, 0.0, 0.0]);
        s.opacity_logits.push(5.0);
        s.sh.extend(color(p).iter().map(|v| (v - 0.5) / SH_C0));
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scenes_are_well_formed() {
        for scene in [red_ball(), textured_sphere(100, |p| p)] {
            let n = scene.opacity_logits.len();
            assert!(n > 0);
            assert_eq!(scene.means.len(), 3 * n);
            assert_eq!(scene.log_scales.len(), 3 * n);
            assert_eq!(scene.quats.len(), 4 * n);
            assert_eq!(scene.sh.len(), 3 * n);
        }
        let sphere = textured_sphere(500, |_| [0.5; 3]);
        for p in sphere.means.chunks(3) {
            let r = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
            assert!((r - 1.0).abs() < 1e-5);
        }
    }
}
