//! Synthetic scenes and cameras for the renderer benches.
//!
//! Synthetic scenes fill a unit ball the way trained scenes fill their volume: log-normal, anisotropic
//! scales around the typical neighbour spacing, random rotations, opacities spread over (0, 1) with many
//! near-opaque Gaussians, and SH degree 3.

use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal};
use splat::cameras::orbit::look_at;
use splat::{Camera, GaussianScene};

/// `n` Gaussians in the unit ball with SH degree 3.
pub fn ball_scene(n: usize, seed: u64) -> GaussianScene {
    ball_scene_with_degree(n, seed, 3)
}

/// [`ball_scene`] with SH degree `degree` (the colours of degree 3's first coefficients).
pub fn ball_scene_with_degree(n: usize, seed: u64, degree: u32) -> GaussianScene {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let normal = Normal::new(0.0f32, 1.0).unwrap();
    // Typical spacing of n points in the unit ball; scales are log-normal around half of it.
    let spacing = (4.19f32 / n as f32).cbrt();
    let coeffs = (degree as usize + 1).pow(2);
    let mut s = GaussianScene::new(degree);
    for _ in 0..n {
        let dir: [f32; 3] = std::array::from_fn(|_| normal.sample(&mut rng));
        let len = (dir[0] * dir[0] + dir[1] * dir[1] + dir[2] * dir[2])
            .sqrt()
            .max(1e-6);
        let r = rng.gen::<f32>().cbrt();
        s.means.extend(dir.map(|v| v / len * r));
        let base = (0.5 * spacing).ln() + 0.5 * normal.sample(&mut rng);
        for _ in 0..3 {
            s.log_scales.push(base + 0.4 * normal.sample(&mut rng));
        }
        s.quats.extend((0..4).map(|_| normal.sample(&mut rng)));
        s.opacity_logits.push(1.0 + 2.0 * normal.sample(&mut rng));
        for k in 0..16 {
            for _ in 0..3 {
                let v = if k == 0 {
                    normal.sample(&mut rng)
                } else {
                    0.1 * normal.sample(&mut rng)
                };
                if k < coeffs {
                    s.sh.push(v);
                }
            }
        }
    }
    s
}

pub fn camera(size: u32) -> Camera {
    camera_wh(size, size)
}

/// A camera `width`x`height` with a 50° vertical field of view, looking at the ball from distance 3:
/// the ball fills most of the frame.
pub fn camera_wh(width: u32, height: u32) -> Camera {
    let focal = height as f64 / 2.0 / (25f64.to_radians()).tan();
    look_at(
        "bench".into(),
        [0.6, -0.8, -2.8],
        [0.0; 3],
        [0.0, -1.0, 0.0],
        width,
        height,
        focal,
    )
}
