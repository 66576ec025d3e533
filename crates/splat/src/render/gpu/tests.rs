//! GPU renderer against the CPU reference. Runs on any Vulkan device (lavapipe in CI) and skips with
//! one line without one. Scenes are tiny: lavapipe is ~100x slower than the CPU path.

// `super::render` is the GPU renderer; `render` alone names the CPU module imported below.
#![allow(unused_qualifications)]
use super::raster::{STAGE_BITS, STAGE_FLOAT, STAGE_NONE};
use super::*;
use crate::cameras::orbit::{look_at, robust_bounds};
use crate::render;
use ::gpu::testing::context_or_skip;
use rand::{Rng, SeedableRng};

/// Random Gaussians in front of the camera: sizes from sub-pixel to a few tiles, all opacities, some
/// behind the camera, SH degree `degree`.
pub(crate) fn random_scene(n: usize, degree: u32, seed: u64) -> GaussianScene {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let k = crate::scene::sh_coeffs(degree);
    let mut s = GaussianScene::new(degree);
    for _ in 0..n {
        s.means.extend([
            rng.gen_range(-1.6f32..1.6),
            rng.gen_range(-1.2f32..1.2),
            rng.gen_range(-0.5f32..3.0),
        ]);
        for _ in 0..3 {
            s.log_scales.push(rng.gen_range(-4.0f32..-1.2));
        }
        for _ in 0..4 {
            s.quats.push(rng.gen_range(-1.0f32..1.0));
        }
        s.opacity_logits.push(rng.gen_range(-5.0f32..4.0));
        for kk in 0..k {
            for _ in 0..3 {
                s.sh.push(if kk == 0 {
                    rng.gen_range(-1.0f32..1.5)
                } else {
                    rng.gen_range(-0.3f32..0.3)
                });
            }
        }
    }
    s
}

pub(crate) fn camera(width: u32, height: u32) -> Camera {
    look_at(
        "t".into(),
        [0.2, -0.1, -3.0],
        [0.0, 0.0, 1.0],
        [0.0, -1.0, 0.0],
        width,
        height,
        0.9 * width as f64,
    )
}

fn psnr(a: &[f32], b: &[f32]) -> f64 {
    assert_eq!(a.len(), b.len());
    let mse = a
        .iter()
        .zip(b)
        .map(|(x, y)| ((x - y) as f64).powi(2))
        .sum::<f64>()
        / a.len().max(1) as f64;
    10.0 * (1.0 / mse.max(1e-20)).log10()
}

pub(crate) fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

/// Largest |a − b| over the largest |b|.
pub(crate) fn max_rel(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    let scale = b.iter().fold(0f32, |m, v| m.max(v.abs())).max(1e-30);
    a.iter().zip(b).fold(0f32, |m, (x, y)| m.max((x - y).abs())) / scale
}

/// ‖a − b‖ / ‖b‖.
pub(crate) fn rel_err(a: &[f32], b: &[f32]) -> f64 {
    assert_eq!(a.len(), b.len());
    let num: f64 = a.iter().zip(b).map(|(x, y)| ((x - y) as f64).powi(2)).sum();
    let den: f64 = b.iter().map(|y| (*y as f64).powi(2)).sum();
    (num / den.max(1e-30)).sqrt()
}

fn compare_forward(ctx: &GpuContext, scene: &GaussianScene, cam: &Camera, channels: usize) {
    let settings = RenderSettings {
        background: [0.2, 0.1, 0.4],
    };
    let values: Vec<f32> = (0..scene.len() * channels)
        .map(|i| ((i * 37 % 101) as f32) / 100.0)
        .collect();
    let extra = (channels > 0).then_some(ExtraChannels {
        values: &values,
        channels,
    });
    let cpu = render::render(scene, cam, &settings, extra);
    let gpu = super::render(ctx, scene, cam, &settings, extra).unwrap();
    let p = psnr(&gpu.rgb, &cpu.rgb);
    eprintln!(
        "{} Gaussians {}x{}: rgb PSNR {p:.1} dB, {} pairs",
        scene.len(),
        cam.width,
        cam.height,
        cpu.tile_intersections()
    );
    assert!(p >= 40.0, "rgb PSNR {p}");
    assert!(psnr(&gpu.alpha, &cpu.alpha) >= 40.0);
    assert!(rel_err(&gpu.depth, &cpu.depth) < 1e-2);
    assert!(psnr(&gpu.extra, &cpu.extra) >= 40.0);
    assert_eq!(gpu.radii, cpu.radii);
    assert!(
        cpu.alpha.iter().filter(|&&a| a > 0.5).count() > 10,
        "scene too empty"
    );
    // Every raster layout (pixels per unit) composites each pixel with the same operations.
    for ppu in [1, 2, 4, 8, 16] {
        let other = super::render_with(ctx, scene, cam, &settings, extra, ppu).unwrap();
        assert_eq!(other.rgb, gpu.rgb, "{ppu} pixels per unit");
        assert_eq!(other.alpha, gpu.alpha, "{ppu} pixels per unit");
        assert_eq!(other.depth, gpu.depth, "{ppu} pixels per unit");
        assert_eq!(other.extra, gpu.extra, "{ppu} pixels per unit");
    }
}

#[test]
fn forward_matches_the_cpu_on_a_constructed_scene() {
    let Some(ctx) = context_or_skip() else {
        return;
    };
    for degree in [0, 3] {
        let scene = random_scene(400, degree, 7 + degree as u64);
        // 53x37: partial tiles on both edges.
        compare_forward(
            &ctx,
            &scene,
            &camera(53, 37),
            if degree == 0 { 0 } else { 3 },
        );
    }
    // An empty scene shows the background; a scene with nothing visible too.
    compare_empty(&ctx);
}

fn compare_empty(ctx: &GpuContext) {
    let settings = RenderSettings {
        background: [1.0, 0.5, 0.25],
    };
    for scene in [GaussianScene::new(0), {
        let mut s = random_scene(5, 1, 3);
        for z in s.means.iter_mut().skip(2).step_by(3) {
            *z = -10.0; // behind the camera
        }
        s
    }] {
        let out = super::render(ctx, &scene, &camera(20, 7), &settings, None).unwrap();
        assert!(out.rgb.chunks(3).all(|p| p == [1.0, 0.5, 0.25]));
        assert!(out.alpha.iter().all(|&a| a == 0.0));
    }
}

#[test]
fn forward_matches_the_cpu_on_a_real_scene() {
    let Some(ctx) = context_or_skip() else {
        return;
    };
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../../shared/assets/scenes/playbot-3k.ply");
    if !path.exists() {
        println!("skipping: {} not found", path.display());
        return;
    }
    let full = crate::formats::ply::read_ply(&path).unwrap();
    // Every other Gaussian: still a real scene, half the work.
    let keep: Vec<usize> = (0..full.len()).step_by(2).collect();
    let scene = subset(&full, &keep);
    let (lo, hi) = robust_bounds(&scene, 0.02).unwrap();
    let centre: [f64; 3] = std::array::from_fn(|a| 0.5 * (lo[a] + hi[a]) as f64);
    let size = (0..3).map(|a| (hi[a] - lo[a]) as f64).fold(0.0, f64::max);
    for (i, eye_dir) in [[0.0, -0.3, -1.0], [1.0, -0.5, 0.3]].iter().enumerate() {
        let eye: [f64; 3] = std::array::from_fn(|a| centre[a] + 1.4 * size * eye_dir[a]);
        let cam = look_at(format!("v{i}"), eye, centre, [0.0, -1.0, 0.0], 72, 64, 80.0);
        compare_forward(&ctx, &scene, &cam, 0);
    }
}

fn subset(s: &GaussianScene, keep: &[usize]) -> GaussianScene {
    let k = s.sh_coeffs();
    let mut out = GaussianScene::new(s.sh_degree);
    for &i in keep {
        out.means.extend_from_slice(&s.means[3 * i..3 * i + 3]);
        out.log_scales
            .extend_from_slice(&s.log_scales[3 * i..3 * i + 3]);
        out.quats.extend_from_slice(&s.quats[4 * i..4 * i + 4]);
        out.opacity_logits.push(s.opacity_logits[i]);
        out.sh.extend_from_slice(&s.sh[3 * k * i..3 * k * (i + 1)]);
    }
    out
}

/// Every gradient kind against `render_backward`, with alpha, depth and extra-channel gradients.
#[test]
fn backward_matches_the_cpu_per_parameter_kind() {
    let Some(ctx) = context_or_skip() else {
        return;
    };
    let scene = random_scene(250, 3, 11);
    let cam = camera(40, 34);
    let settings = RenderSettings {
        background: [0.3, 0.6, 0.1],
    };
    let channels = 2;
    let values: Vec<f32> = (0..scene.len() * channels)
        .map(|i| ((i * 13 % 29) as f32) / 29.0 - 0.3)
        .collect();
    let extra = Some(ExtraChannels {
        values: &values,
        channels,
    });
    let npix = (cam.width * cam.height) as usize;
    let wave = |i: usize, f: f32| ((i as f32 * f).sin() + 0.3) * 0.5;
    let rgb: Vec<f32> = (0..3 * npix).map(|i| wave(i, 0.37)).collect();
    let alpha: Vec<f32> = (0..npix).map(|i| wave(i, 0.11)).collect();
    let depth: Vec<f32> = (0..npix).map(|i| 0.1 * wave(i, 0.23)).collect();
    let ex: Vec<f32> = (0..channels * npix).map(|i| wave(i, 0.71)).collect();
    let grads = OutputGrads {
        rgb: &rgb,
        alpha: Some(&alpha),
        depth: Some(&depth),
        extra: Some(&ex),
    };
    let out = render::render(&scene, &cam, &settings, extra);
    let want = render::render_backward(&scene, &cam, &settings, extra, &out, &grads);
    let flat2 = |v: &[[f32; 2]]| v.iter().flatten().copied().collect::<Vec<_>>();
    // The adapter's raster layout, then every other one (pixels per unit of the raster backward, each
    // with and without the batch's shared sums, and with plane reductions where the adapter has them
    // and its units make whole planes: hardware only, cubecl refuses plane operations on lavapipe).
    let default = super::render_backward(&ctx, &scene, &cam, &settings, extra, &grads).unwrap();
    let mut layouts = vec![("default".to_string(), default)];
    for ppu in [1, 2, 4, 8, 16] {
        let spirv = ctx.on_spirv();
        for plane in [false, true] {
            if plane && !(super::plane_reductions(&ctx) && super::plane_fits(&ctx, ppu)) {
                continue;
            }
            for staging in [STAGE_NONE, STAGE_FLOAT, STAGE_BITS] {
                // Float atomics in shared memory are SPIR-V's only.
                if staging == STAGE_FLOAT && !spirv {
                    continue;
                }
                let layout = super::BackwardLayout {
                    ppu,
                    plane,
                    staging,
                };
                let g = super::render_backward_with(
                    &ctx, &scene, &cam, &settings, extra, &grads, layout,
                );
                layouts.push((format!("{layout:?}"), g.unwrap()));
            }
        }
    }
    for (layout, got) in layouts {
        let kinds: [(&str, &[f32], &[f32]); 7] = [
            ("means", &got.means, &want.means),
            ("log_scales", &got.log_scales, &want.log_scales),
            ("quats", &got.quats, &want.quats),
            ("opacity_logits", &got.opacity_logits, &want.opacity_logits),
            ("sh", &got.sh, &want.sh),
            ("extra", &got.extra, &want.extra),
            ("means2d", &flat2(&got.means2d), &flat2(&want.means2d)),
        ];
        for (name, g, w) in kinds {
            let e = rel_err(g, w);
            eprintln!("{layout}, {name}: relative error {e:.2e}");
            assert!(w.iter().any(|v| *v != 0.0), "{name}: no gradient at all");
            assert!(e <= 1e-3, "{name}: relative error {e}");
        }
    }
}

/// Three 40×34 cameras turning around the random scenes' centre, for the lifting tests.
pub(crate) fn three_views() -> Vec<Camera> {
    (0..3)
        .map(|k| {
            let a = k as f64 * 0.3;
            look_at(
                format!("v{k}"),
                [3.0 * a.sin(), -0.1, 1.0 - 3.0 * a.cos()],
                [0.0, 0.0, 1.0],
                [0.0, -1.0, 0.0],
                40,
                34,
                36.0,
            )
        })
        .collect()
}
