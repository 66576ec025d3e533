//! Finite-difference checks of every gradient, run in f64 through the same generic code as production.
//!
//! Compositing is only piecewise smooth: a pair (pixel, Gaussian) switches on/off when alpha crosses 1/255,
//! alpha is clamped at 0.99, pixels stop at T < 1e-4, tile rectangles grow with ceil(radius), colours are
//! clamped at 0, the depth order can swap, and the Jacobian point is clamped to 1.3x the field of view.
//! A central difference across any of those jumps is meaningless, so the scenes here are built (and
//! [`assert_fd_safe`] verifies) to stay clear of every switch: few, large, semi-transparent Gaussians that
//! cover every pixel with alpha well inside (1/255, 0.99), final T far above 1e-4, 3σ rectangles covering
//! all tiles, well separated depths, and colours away from 0. Where a test wants a clamp active (the colour
//! clamp, the field-of-view clamp), the Gaussian sits deep inside the clamped region so the perturbation
//! cannot leave it.

use super::project::{CameraR, Splat};
use super::raster_backward::{ImageGrads, SavedPixels};
use super::segment::sigma_at;
use super::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

#[derive(Clone, Debug)]
pub(crate) struct Scene64 {
    pub degree: u32,
    pub means: Vec<f64>,
    pub log_scales: Vec<f64>,
    pub quats: Vec<f64>,
    pub opacity_logits: Vec<f64>,
    pub sh: Vec<f64>,
    pub extra: Vec<f64>,
    pub channels: usize,
}

impl Scene64 {
    pub fn params(&self) -> Params<'_, f64> {
        Params {
            sh_degree: self.degree,
            means: &self.means,
            log_scales: &self.log_scales,
            quats: &self.quats,
            opacity_logits: &self.opacity_logits,
            sh: &self.sh,
        }
    }

    fn extra(&self) -> Option<(&[f64], usize)> {
        (self.channels > 0).then_some((&self.extra[..], self.channels))
    }
}

/// Random weights defining the scalar loss L = Σ w·rgb + Σ w·alpha + Σ w·depth + Σ w·extra.
pub(crate) struct LossWeights {
    pub rgb: Vec<f64>,
    pub alpha: Vec<f64>,
    pub depth: Vec<f64>,
    pub extra: Vec<f64>,
}

impl LossWeights {
    fn random(npix: usize, channels: usize, rng: &mut ChaCha8Rng) -> Self {
        let mut v = |n: usize| {
            (0..n)
                .map(|_| rng.gen_range(-1.0..1.0))
                .collect::<Vec<f64>>()
        };
        Self {
            rgb: v(3 * npix),
            alpha: v(npix),
            depth: v(npix),
            extra: v(channels * npix),
        }
    }
}

pub(crate) fn camera(width: u32, height: u32, f: f64, angles: [f64; 3]) -> Camera {
    // Small rotation so every entry of R takes part in the chain rule.
    let [a, b, g] = angles;
    let rx = [
        [1.0, 0.0, 0.0],
        [0.0, a.cos(), -a.sin()],
        [0.0, a.sin(), a.cos()],
    ];
    let ry = [
        [b.cos(), 0.0, b.sin()],
        [0.0, 1.0, 0.0],
        [-b.sin(), 0.0, b.cos()],
    ];
    let rz = [
        [g.cos(), -g.sin(), 0.0],
        [g.sin(), g.cos(), 0.0],
        [0.0, 0.0, 1.0],
    ];
    let mul = |p: [[f64; 3]; 3], q: [[f64; 3]; 3]| {
        let mut o = [[0.0; 3]; 3];
        for i in 0..3 {
            for j in 0..3 {
                o[i][j] = (0..3).map(|k| p[i][k] * q[k][j]).sum();
            }
        }
        o
    };
    Camera {
        name: "test".into(),
        width,
        height,
        fx: f,
        fy: f * 1.1,
        cx: width as f64 / 2.0 + 0.3,
        cy: height as f64 / 2.0 - 0.2,
        rotation: mul(mul(rx, ry), rz),
        translation: [0.1, -0.2, 0.3],
    }
}

/// Gaussians in front of `cam` at distinct depths, covering the whole image with large footprints.
fn big_gaussians(
    n: usize,
    degree: u32,
    channels: usize,
    cam: &Camera,
    screen_sigma: f64,
    rng: &mut ChaCha8Rng,
) -> Scene64 {
    let k = sh_coeffs_of(degree);
    let mut s = Scene64 {
        degree,
        means: vec![],
        log_scales: vec![],
        quats: vec![],
        opacity_logits: vec![],
        sh: vec![],
        extra: vec![],
        channels,
    };
    for i in 0..n {
        // Camera-space position, then to world: m = Rᵀ (p − t).
        let z = 3.0 + 0.6 * i as f64 + rng.gen_range(0.0..0.2);
        let u = cam.cx + rng.gen_range(-0.25..0.25) * cam.width as f64;
        let v = cam.cy + rng.gen_range(-0.25..0.25) * cam.height as f64;
        let pc = [(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z];
        let r = cam.rotation;
        let q: Vec<f64> = (0..3).map(|a| pc[a] - cam.translation[a]).collect();
        for a in 0..3 {
            s.means
                .push(r[0][a] * q[0] + r[1][a] * q[1] + r[2][a] * q[2]);
        }
        let world_sigma = screen_sigma * z / cam.fx;
        for _ in 0..3 {
            s.log_scales
                .push((world_sigma * rng.gen_range(0.85..1.2)).ln());
        }
        for _ in 0..4 {
            s.quats.push(rng.gen_range(-1.0..1.0));
        }
        s.opacity_logits.push(rng.gen_range(-1.3..0.4)); // o in [0.21, 0.6]
        for kk in 0..k {
            for _ in 0..3 {
                s.sh.push(if kk == 0 {
                    rng.gen_range(-0.5..0.5)
                } else {
                    rng.gen_range(-0.15..0.15)
                });
            }
        }
        for _ in 0..channels {
            s.extra.push(rng.gen_range(-1.0..1.0));
        }
    }
    s
}

/// Asserts that no discontinuity of the renderer is within reach of a finite difference (see module doc).
fn assert_fd_safe(scene: &Scene64, cam: &Camera, allow_clamped_color: bool) {
    let p = scene.params();
    let camr = CameraR::<f64>::new(cam);
    let splats = project_all(&p, &camr, true);
    let (tx, ty) = camr.tiles();
    let mut depths: Vec<f64> = splats.iter().map(|s| s.depth).collect();
    for (i, s) in splats.iter().enumerate() {
        assert!(s.radius > 0, "Gaussian {i} culled");
        assert_eq!(
            s.tile_rect(),
            [0, 0, tx, ty],
            "Gaussian {i} does not cover all tiles"
        );
        // The radius must not be about to change tiles either: covered with a margin.
        assert!(s.mean[0] - s.radius as f64 <= -2.0 && s.mean[1] - s.radius as f64 <= -2.0);
        assert!(s.mean[0] + s.radius as f64 >= (16 * tx) as f64 + 2.0);
        assert!(s.mean[1] + s.radius as f64 >= (16 * ty) as f64 + 2.0);
        if !allow_clamped_color {
            assert_eq!(s.clamped, 0, "Gaussian {i} colour clamped");
        }
    }
    depths.sort_by(|a, b| a.partial_cmp(b).unwrap());
    for w in depths.windows(2) {
        assert!(w[1] - w[0] > 0.1, "depths too close");
    }
    let mut min_t = 1.0f64;
    for y in 0..cam.height {
        for x in 0..cam.width {
            let mut t = 1.0;
            for (i, s) in splats.iter().enumerate() {
                let dx = s.mean[0] - (x as f64 + 0.5);
                let dy = s.mean[1] - (y as f64 + 0.5);
                let sigma = sigma_at(&s.conic, dx, dy);
                let alpha = s.opacity * (-sigma).exp();
                assert!(
                    alpha > 2.0 / 255.0 && alpha < 0.98,
                    "pixel ({x},{y}) Gaussian {i}: alpha {alpha} near a threshold"
                );
                t *= 1.0 - alpha;
            }
            min_t = min_t.min(t);
        }
    }
    assert!(min_t > 3e-4, "transmittance {min_t} near the 1e-4 stop");
}

fn loss(scene: &Scene64, cam: &Camera, bg: [f64; 3], w: &LossWeights) -> f64 {
    let fwd = forward(&scene.params(), cam, bg, scene.extra());
    let r = &fwd.raster;
    let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
    dot(&r.rgb, &w.rgb)
        + dot(&r.alpha, &w.alpha)
        + dot(&r.depth, &w.depth)
        + dot(&r.extra, &w.extra)
}

pub(crate) fn analytic(scene: &Scene64, cam: &Camera, bg: [f64; 3], w: &LossWeights) -> Grads<f64> {
    let p = scene.params();
    let fwd = forward(&p, cam, bg, scene.extra());
    backward(
        &p,
        cam,
        bg,
        scene.extra(),
        &fwd.splats,
        &fwd.bins,
        SavedPixels {
            t_final: &fwd.raster.t_final,
            last: &fwd.raster.last,
        },
        &ImageGrads {
            rgb: &w.rgb,
            alpha: Some(&w.alpha),
            depth: Some(&w.depth),
            extra: (scene.channels > 0).then_some(&w.extra[..]),
        },
        true,
    )
}

/// Which parameter array of [`Scene64`] to perturb.
#[derive(Clone, Copy, Debug)]
enum Kind {
    Means,
    LogScales,
    Quats,
    Opacity,
    Sh,
    Extra,
}

fn param_mut(s: &mut Scene64, kind: Kind) -> &mut Vec<f64> {
    match kind {
        Kind::Means => &mut s.means,
        Kind::LogScales => &mut s.log_scales,
        Kind::Quats => &mut s.quats,
        Kind::Opacity => &mut s.opacity_logits,
        Kind::Sh => &mut s.sh,
        Kind::Extra => &mut s.extra,
    }
}

fn grad_of(g: &Grads<f64>, kind: Kind) -> &[f64] {
    match kind {
        Kind::Means => &g.means,
        Kind::LogScales => &g.log_scales,
        Kind::Quats => &g.quats,
        Kind::Opacity => &g.opacity_logits,
        Kind::Sh => &g.sh,
        Kind::Extra => &g.extra,
    }
}

/// Compares every analytic gradient entry with a central difference; returns the worst relative error
/// per kind. The relative error of an entry is |fd − an| / max(|fd|, |an|, 1e-6·max|an| of its kind).
fn check_all(scene: &Scene64, cam: &Camera, bg: [f64; 3], w: &LossWeights) -> Vec<(Kind, f64)> {
    let an = analytic(scene, cam, bg, w);
    let mut worst = vec![];
    for kind in [
        Kind::Means,
        Kind::LogScales,
        Kind::Quats,
        Kind::Opacity,
        Kind::Sh,
        Kind::Extra,
    ] {
        let ga = grad_of(&an, kind);
        let len = param_mut(&mut scene.clone(), kind).len();
        assert_eq!(ga.len(), len, "{kind:?} gradient length");
        let scale = ga.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let mut kind_worst = 0.0f64;
        for j in 0..len {
            // Central differences have O(h²) truncation error and O(eps·|L|/h) rounding error; h = 1e-5
            // balances both at ~1e-10 for these losses (|L| ~ 100).
            let h = 1e-5;
            let mut sp = scene.clone();
            param_mut(&mut sp, kind)[j] += h;
            let mut sm = scene.clone();
            param_mut(&mut sm, kind)[j] -= h;
            let fd = (loss(&sp, cam, bg, w) - loss(&sm, cam, bg, w)) / (2.0 * h);
            let denom = fd.abs().max(ga[j].abs()).max(1e-6 * scale).max(1e-12);
            let rel = (fd - ga[j]).abs() / denom;
            assert!(
                rel < 1e-3,
                "{kind:?}[{j}]: analytic {} vs finite difference {fd} (rel {rel:.2e})",
                ga[j]
            );
            kind_worst = kind_worst.max(rel);
        }
        worst.push((kind, kind_worst));
    }
    worst
}

#[test]
fn gradients_match_finite_differences_single_tile_all_degrees() {
    for degree in 0..=3 {
        let mut rng = ChaCha8Rng::seed_from_u64(10 + degree as u64);
        let cam = camera(13, 11, 14.0, [0.1, -0.2, 0.15]);
        let scene = big_gaussians(6, degree, 3, &cam, 14.0, &mut rng);
        assert_fd_safe(&scene, &cam, false);
        let w = LossWeights::random(13 * 11, 3, &mut rng);
        let worst = check_all(&scene, &cam, [0.2, 0.5, 0.9], &w);
        eprintln!("degree {degree}: worst relative errors {worst:?}");
    }
}

#[test]
fn gradients_match_finite_differences_multi_tile() {
    let mut rng = ChaCha8Rng::seed_from_u64(77);
    let cam = camera(40, 27, 30.0, [-0.05, 0.1, 0.3]);
    let scene = big_gaussians(5, 2, 2, &cam, 30.0, &mut rng);
    assert_fd_safe(&scene, &cam, false);
    let w = LossWeights::random(40 * 27, 2, &mut rng);
    let worst = check_all(&scene, &cam, [0.0, 0.0, 0.0], &w);
    eprintln!("multi-tile: worst relative errors {worst:?}");
}

/// A Gaussian whose mean lies far outside the field of view (Jacobian clamp active) but whose huge
/// footprint still covers the image, plus one with a colour channel clamped at 0.
#[test]
fn gradients_match_finite_differences_with_clamps() {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let cam = camera(12, 12, 12.0, [0.0, 0.0, 0.0]);
    let mut scene = big_gaussians(4, 1, 1, &cam, 12.0, &mut rng);
    // Gaussian 0: camera-space (x/z = 1.6 > 1.3·tan), very wide.
    let z = 3.2;
    let pc = [1.6 * z, 0.1 * z, z];
    let world: Vec<f64> = (0..3).map(|a| pc[a] - cam.translation[a]).collect();
    scene.means[0..3].copy_from_slice(&world);
    scene.log_scales[0..3].copy_from_slice(&[(7.0f64).ln(), (5.0f64).ln(), (6.0f64).ln()]);
    // Gaussian 1: red channel far below zero.
    scene.sh[3 * 4] = -3.0;
    let camr = CameraR::<f64>::new(&cam);
    let s0 = project::project_one(&scene.params(), 0, &camr, true);
    let s1 = project::project_one(&scene.params(), 1, &camr, true);
    assert!(
        s0.mean[0] > 12.0 + 1.3 * 6.0,
        "Gaussian 0 not in the clamped region"
    );
    assert_eq!(s1.clamped & 1, 1, "colour clamp not active");
    assert_fd_safe(&scene, &cam, true);
    let w = LossWeights::random(144, 1, &mut rng);
    check_all(&scene, &cam, [0.3, 0.3, 0.3], &w);
    // The clamped channel's SH gradient is exactly zero.
    let g = analytic(&scene, &cam, [0.3, 0.3, 0.3], &w);
    let k = sh_coeffs_of(1);
    for kk in 0..k {
        assert_eq!(g.sh[(k + kk) * 3], 0.0);
    }
}

/// The screen-space gradient reported for densification is dL/d(mean2d): check it against a finite
/// difference that shifts a projected mean directly.
#[test]
fn means2d_gradient_matches_shifted_splat() {
    let mut rng = ChaCha8Rng::seed_from_u64(8);
    let cam = camera(14, 12, 14.0, [0.05, 0.0, -0.1]);
    let scene = big_gaussians(4, 0, 0, &cam, 14.0, &mut rng);
    assert_fd_safe(&scene, &cam, false);
    let w = LossWeights::random(14 * 12, 0, &mut rng);
    let g = analytic(&scene, &cam, [0.0; 3], &w);
    let p = scene.params();
    let camr = CameraR::<f64>::new(&cam);
    let splats = project_all(&p, &camr, true);
    let (tx, ty) = camr.tiles();
    let bins = tiles::bin(&splats, tx, ty);
    let render_loss = |splats: &[Splat<f64>]| {
        let r = raster::rasterize(splats, &bins, cam.width, cam.height, [0.0; 3], None, None);
        let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
        dot(&r.rgb, &w.rgb) + dot(&r.alpha, &w.alpha) + dot(&r.depth, &w.depth)
    };
    for i in 0..splats.len() {
        for a in 0..2 {
            let h = 1e-6;
            let mut sp = splats.clone();
            sp[i].mean[a] += h;
            let mut sm = splats.clone();
            sm[i].mean[a] -= h;
            let fd = (render_loss(&sp) - render_loss(&sm)) / (2.0 * h);
            let an = g.means2d[i][a];
            assert!(
                (fd - an).abs() <= 1e-4 * fd.abs().max(an.abs()).max(1e-6),
                "means2d[{i}][{a}]: {an} vs {fd}"
            );
        }
    }
}

#[path = "../../tests/support/reference.rs"]
#[allow(dead_code)]
mod reference;

/// The f64 renderer against torch autograd (gsplat's projection/SH + a brute-force compositor) on the
/// committed random scene: outputs and every gradient must agree to near f64 precision.
#[test]
fn matches_torch_autograd_on_random_fixture() {
    let m = reference::manifest();
    let info = &m["random_scene"];
    let t =
        reference::Tensors::load(&reference::fixture_dir().join(info["file"].as_str().unwrap()));
    let cam = reference::camera_from_json(&info["camera"]);
    let bg = reference::background_f64(&info["background"]);
    let channels = info["channels"].as_u64().unwrap() as usize;
    let scene = Scene64 {
        degree: info["sh_degree"].as_u64().unwrap() as u32,
        means: t.f64("scene.means"),
        log_scales: t.f64("scene.log_scales"),
        quats: t.f64("scene.quats"),
        opacity_logits: t.f64("scene.opacity_logits"),
        sh: t.f64("scene.sh"),
        extra: t.f64("scene.extra"),
        channels,
    };
    let fwd = forward(&scene.params(), &cam, bg, scene.extra());
    for (name, ours) in [
        ("out.rgb", &fwd.raster.rgb),
        ("out.alpha", &fwd.raster.alpha),
        ("out.depth", &fwd.raster.depth),
        ("out.extra", &fwd.raster.extra),
    ] {
        let want = t.f64(name);
        let worst = ours
            .iter()
            .zip(&want)
            .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
        assert!(worst < 1e-10, "{name}: max abs difference {worst:e}");
    }
    let w = LossWeights {
        rgb: t.f64("weight.rgb"),
        alpha: t.f64("weight.alpha"),
        depth: t.f64("weight.depth"),
        extra: t.f64("weight.extra"),
    };
    let g = analytic(&scene, &cam, bg, &w);
    for (name, ours) in [
        ("grad.means", &g.means),
        ("grad.log_scales", &g.log_scales),
        ("grad.quats", &g.quats),
        ("grad.opacity_logits", &g.opacity_logits),
        ("grad.sh", &g.sh),
        ("grad.extra", &g.extra),
    ] {
        let want = t.f64(name);
        let err = reference::relative_error(ours, &want);
        eprintln!("{name}: relative error vs autograd {err:.2e}");
        assert!(err < 1e-8, "{name}: relative error {err:e}");
        assert!(
            want.iter().any(|v| v.abs() > 1e-6),
            "{name}: reference gradient is all zero"
        );
    }
}

/// The AVX2 kernels (used for f32 on this machine) and the portable kernels agree on f32 renders and
/// gradients of a scene with saturated pixels, extra channels and a background.
#[test]
fn simd_and_portable_kernels_agree() {
    use crate::render::cpu::force_portable;
    let m = reference::manifest();
    let info = &m["random_scene"];
    let t =
        reference::Tensors::load(&reference::fixture_dir().join(info["file"].as_str().unwrap()));
    let cam = reference::camera_from_json(&info["camera"]);
    let scene = t.scene(3);
    let values = t.f32("scene.extra");
    let extra = ExtraChannels {
        values: &values,
        channels: 4,
    };
    let settings = RenderSettings {
        background: [0.3, 0.1, 0.6],
    };
    let (wr, wa, wd, we) = (
        t.f32("weight.rgb"),
        t.f32("weight.alpha"),
        t.f32("weight.depth"),
        t.f32("weight.extra"),
    );
    let grads = OutputGrads {
        rgb: &wr,
        alpha: Some(&wa),
        depth: Some(&wd),
        extra: Some(&we),
    };
    let run = || {
        let out = render(&scene, &cam, &settings, Some(extra));
        let g = render_backward(&scene, &cam, &settings, Some(extra), &out, &grads);
        (out, g)
    };
    let (fast, fast_g) = run();
    force_portable(true);
    let (portable, portable_g) = run();
    force_portable(false);
    let close = |a: &[f32], b: &[f32], what: &str| {
        let a64: Vec<f64> = a.iter().map(|&v| v as f64).collect();
        let b64: Vec<f64> = b.iter().map(|&v| v as f64).collect();
        let err = reference::relative_error(&a64, &b64);
        assert!(err < 1e-5, "{what}: relative difference {err:e}");
    };
    close(&fast.rgb, &portable.rgb, "rgb");
    close(&fast.alpha, &portable.alpha, "alpha");
    close(&fast.depth, &portable.depth, "depth");
    close(&fast.extra, &portable.extra, "extra");
    close(&fast_g.means, &portable_g.means, "means");
    close(&fast_g.log_scales, &portable_g.log_scales, "log_scales");
    close(&fast_g.quats, &portable_g.quats, "quats");
    close(
        &fast_g.opacity_logits,
        &portable_g.opacity_logits,
        "opacity",
    );
    close(&fast_g.sh, &portable_g.sh, "sh");
    close(&fast_g.extra, &portable_g.extra, "extra grads");
}
