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

/// ‖a − b‖ / ‖b‖.
fn rel_err(a: &[f32], b: &[f32]) -> f64 {
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
    let full = crate::ply::read_ply(&path).unwrap();
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

/// `fit_on` with the device reaches the CPU fit's PSNR on a tiny self-rendered dataset.
#[test]
fn fit_on_the_gpu_tracks_the_cpu_fit() {
    use crate::train::scene_fit::{fit, fit_on, Dataset, FitConfig, View};
    let Some(ctx) = context_or_skip() else {
        return;
    };
    let truth = random_scene(300, 1, 21);
    let settings = RenderSettings::default();
    let views: Vec<View> = (0..4)
        .map(|k| {
            let a = k as f64 * 0.4 - 0.6;
            let cam = look_at(
                format!("v{k}"),
                [3.0 * a.sin(), -0.2, 1.0 - 3.0 * a.cos()],
                [0.0, 0.0, 1.0],
                [0.0, -1.0, 0.0],
                32,
                32,
                30.0,
            );
            let image = render::render(&truth, &cam, &settings, None).frame.rgb;
            View { camera: cam, image }
        })
        .collect();
    let dataset = Dataset {
        train: views[1..].to_vec(),
        test: views[..1].to_vec(),
        points: None,
    };
    let plain = FitConfig {
        init_points: 400,
        ..FitConfig::for_steps(40)
    };
    // Densification at steps 10 and 20: host steps between device-resident runs.
    let mut densifying = plain.clone();
    densifying.strategy.refine_start = 5;
    densifying.strategy.refine_every = 10;
    densifying.strategy.refine_stop = 30;
    densifying.strategy.grow_grad2d = 0.00005;
    // Without densification the two fits agree to float noise; with it, one borderline clone changes the
    // random splits that follow, so the comparison is the criterion (0.3 dB).
    for (config, tolerance) in [(plain, 0.01), (densifying, 0.3)] {
        let cpu = fit(&dataset, &config, &mut |_| {});
        let gpu = fit_on(
            &dataset,
            &config,
            &crate::SplatDevice::Gpu(ctx.clone()),
            &mut |_| {},
        )
        .unwrap();
        eprintln!(
            "fit 40 steps: train PSNR CPU {:.3} GPU {:.3}, test {:?} / {:?}, {} / {} Gaussians",
            cpu.train_psnr,
            gpu.train_psnr,
            cpu.test_psnr,
            gpu.test_psnr,
            cpu.scene.len(),
            gpu.scene.len()
        );
        assert!((cpu.train_psnr - gpu.train_psnr).abs() < tolerance);
        assert!((cpu.test_psnr.unwrap() - gpu.test_psnr.unwrap()).abs() < tolerance);
        let (a, b) = (cpu.scene.len() as f64, gpu.scene.len() as f64);
        assert!((a - b).abs() <= 0.02 * a, "{a} vs {b} Gaussians");
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

/// GPU lifting against `crate::lift::lift` on a constructed scene with three views.
#[test]
fn lifting_matches_the_cpu() {
    let Some(ctx) = context_or_skip() else {
        return;
    };
    let scene = random_scene(300, 0, 5);
    let channels = 3;
    let cams = three_views();
    let maps: Vec<Vec<f32>> = (0..3)
        .map(|k| {
            (0..40 * 34 * channels)
                .map(|i| ((i * 7 + k * 3) % 11) as f32 / 10.0)
                .collect()
        })
        .collect();
    let refs: Vec<&[f32]> = maps.iter().map(|m| &m[..]).collect();
    let want = crate::lift::lift(&scene, &cams, &refs, channels);
    let got = super::lift(&ctx, &scene, &cams, &refs, channels).unwrap();
    assert!(want.counts.iter().filter(|&&c| c > 0.0).count() > 50);
    let mismatched = got
        .counts
        .iter()
        .zip(&want.counts)
        .filter(|(a, b)| a != b)
        .count();
    // exp differs from the CPU's exp_fast in the last bits: a pixel exactly at a threshold may differ.
    assert!(mismatched <= 1, "{mismatched} counts differ");
    let e = rel_err(&got.values, &want.values);
    eprintln!("lifting: {mismatched} counts differ, values relative error {e:.2e}");
    assert!(e < 1e-3, "values relative error {e}");
    // Every layout (pixels per unit) hits the same Gaussians.
    for ppu in [1, 2, 4, 8, 16] {
        let other = super::lift::lift_with(&ctx, &scene, &cams, &refs, channels, ppu).unwrap();
        assert_eq!(other.counts, got.counts, "{ppu} pixels per unit");
        let e = rel_err(&other.values, &got.values);
        assert!(e < 1e-6, "{ppu} pixels per unit: values relative error {e}");
    }
}

/// Lifting a coarse grid's maps through their cells' weights (`lift_accumulate_grid`) against lifting
/// their upsampled versions per pixel: same hits, same sums up to float order; grids from 1/32 of the
/// view (SD's 16² maps at 512²) to about a quarter, odd ratios, both resampling modes, every staging the
/// compiler has.
#[test]
fn lifting_through_the_grid_matches_lifting_per_pixel() {
    use crate::lift::{MapGrid, Resample};
    let Some(ctx) = context_or_skip() else {
        return;
    };
    let scene = random_scene(400, 3, 7);
    let mut stagings = vec![STAGE_BITS];
    if ctx.on_spirv() {
        stagings.push(STAGE_FLOAT);
    }
    let sizes = [(40, 34), (160, 136), (512, 512)];
    for (w, h) in sizes {
        let cams: Vec<Camera> = three_views()
            .into_iter()
            .map(|c| crate::cameras::to_working_resolution(&c, w, h))
            .collect();
        for (gh, gw) in [(9, 10), (16, 16), (5, 3)] {
            for mode in [Resample::Bilinear, Resample::Nearest] {
                let grid = MapGrid {
                    height: gh,
                    width: gw,
                    channels: 7,
                    up: mode,
                    down: mode,
                };
                if super::lift::grid_span(h as usize, gh, mode).is_none()
                    || super::lift::grid_span(w as usize, gw, mode).is_none()
                {
                    continue;
                }
                let maps: Vec<Vec<f32>> = (0..cams.len())
                    .map(|k| {
                        (0..grid.len())
                            .map(|i| ((i * 7 + k * 3) % 11) as f32 / 10.0 - 0.3)
                            .collect()
                    })
                    .collect();
                let want =
                    super::lift::lift_on_grid(&ctx, &scene, &cams, &maps, &grid, None).unwrap();
                assert!(want.counts.iter().filter(|&&c| c > 0.0).count() > 50);
                let scale = want.values.iter().fold(0f32, |m, v| m.max(v.abs()));
                for &staging in &stagings {
                    let got =
                        super::lift::lift_on_grid(&ctx, &scene, &cams, &maps, &grid, Some(staging))
                            .unwrap();
                    let case = format!("{w}x{h}, grid {gh}x{gw} {mode:?}, staging {staging}");
                    assert_eq!(got.counts, want.counts, "{case}: hit counts");
                    let worst = got
                        .values
                        .iter()
                        .zip(&want.values)
                        .map(|(a, b)| (a - b).abs())
                        .fold(0f32, f32::max);
                    // Sums of thousands of pixels per Gaussian at 512² in a different order: ~1e-5 apart; a wrong
                    // cell or weight would be off by a tenth.
                    assert!(
                        worst <= 1e-4 * scale,
                        "{case}: off by {worst} (values up to {scale})"
                    );
                }
            }
        }
    }
}

/// The resampling kernel against `crate::lift::resample`: up and down, integer and odd ratios, both modes.
#[test]
fn resampling_on_the_device_matches_the_cpu() {
    use crate::lift::{resample, Resample};
    let Some(ctx) = context_or_skip() else {
        return;
    };
    let channels = 3;
    for (from, to) in [
        ((4, 6), (32, 48)),
        ((32, 48), (4, 6)),
        ((7, 5), (34, 40)),
        ((34, 40), (7, 5)),
        ((5, 5), (5, 5)),
    ] {
        let src: Vec<f32> = (0..from.0 * from.1 * channels)
            .map(|i| ((i * 37) % 17) as f32 / 16.0)
            .collect();
        for mode in [Resample::Nearest, Resample::Bilinear] {
            let want = resample(&src, from, to, channels, mode);
            let handle = ::gpu::prims::upload_f32(&ctx.client, &src);
            let out = super::lift::resample_on_device(&ctx, &handle, from, to, channels, mode);
            let got = read_f32(&ctx.client, &out, want.len()).unwrap();
            let worst = got
                .iter()
                .zip(&want)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0f32, f32::max);
            assert!(worst < 1e-6, "{from:?} -> {to:?} {mode:?}: off by {worst}");
        }
    }
}

/// The whole 2D → 3D → 2D round on the device against the CPU's: maps on a coarse grid (odd ratios to
/// the cameras' resolution), bilinear and nearest.
#[test]
fn lifting_and_rendering_back_matches_the_cpu() {
    use crate::lift::{MapGrid, Resample};
    use crate::SplatDevice;
    let Some(ctx) = context_or_skip() else {
        return;
    };
    let scene = random_scene(300, 0, 5);
    let cams = three_views();
    for mode in [Resample::Bilinear, Resample::Nearest] {
        let grid = MapGrid {
            height: 9,
            width: 10,
            channels: 5,
            up: mode,
            down: mode,
        };
        let maps: Vec<Vec<f32>> = (0..3)
            .map(|k| {
                (0..grid.len())
                    .map(|i| ((i * 7 + k * 3) % 11) as f32 / 10.0)
                    .collect()
            })
            .collect();
        let round = |device: &SplatDevice| -> Vec<Vec<f32>> {
            let mut back = vec![Vec::new(); cams.len()];
            device
                .lift_and_render_back::<GpuError>(
                    &scene,
                    &cams,
                    &grid,
                    &mut |v| Ok(maps[v].clone()),
                    &mut |v, m| {
                        back[v] = m;
                        Ok(())
                    },
                )
                .unwrap();
            back
        };
        let want = round(&SplatDevice::Cpu);
        let got = round(&SplatDevice::Gpu(ctx.clone()));
        for (v, (g, w)) in got.iter().zip(&want).enumerate() {
            assert_eq!(g.len(), grid.len());
            assert!(w.iter().any(|&x| x > 0.05), "view {v} sees the lifted maps");
            let e = rel_err(g, w);
            assert!(e < 1e-3, "{mode:?}, view {v}: relative error {e}");
        }
    }
}

/// The render-back, dense and sparse, against the CPU renderer at every pixel the resampling to the grid
/// reads, with more than 32 channels: Mesa 22's lavapipe mis-runs the raster forward there (colours
/// included; exact to 1e-7 on Mesa 25), which once made a correct sparse round look wrong. Elsewhere the
/// sparse render-back leaves the channels zero.
#[test]
fn the_render_back_is_right_where_the_grid_reads_it() {
    use crate::lift::{MapGrid, Resample};
    let Some(ctx) = context_or_skip() else {
        return;
    };
    let scene = random_scene(3000, 0, 11);
    let (size, channels) = (128u32, 40usize);
    let cam = look_at(
        "near".into(),
        [0.0, -0.1, -2.0],
        [0.0, 0.0, 1.0],
        [0.0, -1.0, 0.0],
        size,
        size,
        115.0,
    );
    let values: Vec<f32> = (0..scene.len() * channels)
        .map(|i| ((i * 37) % 101) as f32 / 100.0)
        .collect();
    let extra = ExtraChannels {
        values: &values,
        channels,
    };
    let cpu = render::render(&scene, &cam, &RenderSettings::default(), Some(extra)).frame;
    assert!(cpu.extra.iter().filter(|&&v| v > 0.1).count() > cpu.extra.len() / 4);
    for mode in [Resample::Bilinear, Resample::Nearest] {
        let grid = MapGrid {
            height: 16,
            width: 12,
            channels,
            up: mode,
            down: mode,
        };
        for sparse in [false, true] {
            let image =
                lift::render_back_pixels(&ctx, &scene, &cam, &values, &grid, sparse).unwrap();
            let rows = crate::lift::read_by_resampling(size as usize, grid.height, mode);
            let cols = crate::lift::read_by_resampling(size as usize, grid.width, mode);
            let (mut read, mut wrong, mut worst) = (0usize, 0usize, 0.0f32);
            for (y, &row) in rows.iter().enumerate() {
                for (x, &col) in cols.iter().enumerate() {
                    let p = (y * size as usize + x) * channels;
                    let kept = !sparse || row * col == 1;
                    for ch in 0..channels {
                        let want = if kept { cpu.extra[p + ch] } else { 0.0 };
                        let off = (image[p + ch] - want).abs();
                        if off > 1e-4 * want.abs().max(1.0) {
                            wrong += 1;
                            worst = worst.max(off);
                        }
                    }
                    read += (row * col) as usize;
                }
            }
            let all = rows.len() * cols.len();
            assert!(
                read > 0 && read < all / 2,
                "{mode:?}: {read} of {all} pixels read"
            );
            assert_eq!(
                wrong, 0,
                "{mode:?}, sparse {sparse}: {wrong} values wrong, worst by {worst}"
            );
        }
    }
}

/// A lifting session's rounds (different grids and channel counts, the views kept from the first round
/// on) give what a fresh round gives, and what a session without room to keep any view gives.
#[test]
fn lifting_sessions_keep_views_across_rounds() {
    use crate::lift::{MapGrid, Resample};
    use crate::SplatDevice;
    let Some(ctx) = context_or_skip() else {
        return;
    };
    let scene = random_scene(300, 1, 8);
    let cams = three_views();
    let grids = [
        (9, 10, 5, Resample::Bilinear),
        (6, 6, 2, Resample::Nearest),
        (9, 10, 1, Resample::Bilinear),
    ]
    .map(|(height, width, channels, mode)| MapGrid {
        height,
        width,
        channels,
        up: mode,
        down: mode,
    });
    let maps = |grid: &MapGrid, v: usize| -> Vec<f32> {
        (0..grid.len())
            .map(|i| ((i * 5 + v * 7 + grid.channels) % 13) as f32 / 12.0)
            .collect()
    };
    let round = |grid: &MapGrid, run: &mut dyn FnMut(&MapGrid, &mut Vec<Vec<f32>>)| {
        let mut back = vec![Vec::new(); cams.len()];
        run(grid, &mut back);
        back
    };
    let mut session = lift::GpuLiftScene::new(&ctx, &scene);
    let mut starved = lift::GpuLiftScene::with_budget(&ctx, &scene, 0);
    let device = SplatDevice::Gpu(ctx.clone());
    for grid in &grids {
        let via = |lift: &mut lift::GpuLiftScene| {
            round(grid, &mut |g, back| {
                lift.lift_and_render_back::<GpuError>(
                    &ctx,
                    &cams,
                    g,
                    &mut |v| Ok(maps(g, v)),
                    &mut |v, m| {
                        back[v] = m;
                        Ok(())
                    },
                )
                .unwrap()
            })
        };
        let kept = via(&mut session);
        let refused = via(&mut starved);
        let fresh = round(grid, &mut |g, back| {
            device
                .lift_and_render_back::<GpuError>(
                    &scene,
                    &cams,
                    g,
                    &mut |v| Ok(maps(g, v)),
                    &mut |v, m| {
                        back[v] = m;
                        Ok(())
                    },
                )
                .unwrap()
        });
        for v in 0..cams.len() {
            assert!(fresh[v].iter().any(|&x| x > 0.05), "view {v} sees the maps");
            for other in [&kept[v], &refused[v]] {
                let e = rel_err(other, &fresh[v]);
                assert!(
                    e < 1e-5,
                    "{} channels, view {v}: relative error {e}",
                    grid.channels
                );
            }
        }
    }
    assert!(session.kept_bytes() > 0, "the views were kept");
    assert_eq!(starved.kept_bytes(), 0);
}

/// Three device Adam steps land where `Adam::step` does.
#[test]
fn adam_on_the_device_matches_the_cpu() {
    use crate::train::optim::{Adam, LearningRates};
    let Some(ctx) = context_or_skip() else {
        return;
    };
    let scene = random_scene(60, 2, 9);
    let grads = wave_grads(&scene);
    let mut cpu_scene = scene.clone();
    let mut cpu = Adam::new(&scene, LearningRates::inria(100), 2.0);
    let dev = GpuScene::upload(&ctx, &scene);
    let mut gpu_adam = GpuAdam::new(&ctx, &dev);
    let mut gpu_rates = Adam::new(&scene, LearningRates::inria(100), 2.0);
    let dev_grads = upload_grads(&ctx, &grads);
    for _ in 0..3 {
        cpu.step(&mut cpu_scene, &grads, None);
        gpu_adam
            .step(&ctx, &mut gpu_rates, &dev, &dev_grads)
            .unwrap();
    }
    let got = dev.download(&ctx).unwrap();
    for (name, g, w) in [
        ("means", &got.means, &cpu_scene.means),
        ("log_scales", &got.log_scales, &cpu_scene.log_scales),
        ("quats", &got.quats, &cpu_scene.quats),
        ("opacity", &got.opacity_logits, &cpu_scene.opacity_logits),
        ("sh", &got.sh, &cpu_scene.sh),
    ] {
        let e = rel_err(g, w);
        assert!(e < 1e-6, "{name}: relative error {e}");
    }
    assert_ne!(got.means, scene.means);
    assert_eq!(gpu_rates.steps(), cpu.steps());
}

/// Densification statistics accumulated on the device over two views equal `DensifyStats::add` fed with
/// the same gradients read back.
#[test]
fn densify_stats_on_the_device_match_the_cpu() {
    use crate::train::DensifyStats;
    let Some(ctx) = context_or_skip() else {
        return;
    };
    let c = &ctx.client;
    let scene = random_scene(200, 1, 17);
    let settings = RenderSettings::default();
    let dev = GpuScene::upload(&ctx, &scene);
    let mut on_device = GpuDensifyStats::new(&ctx, scene.len());
    let mut on_host = DensifyStats::new(scene.len());
    for (w, h) in [(40, 30), (24, 36)] {
        let cam = camera(w, h);
        let frame = render_device(&ctx, &dev, &cam, &settings, None).unwrap();
        let npix = (w * h) as usize;
        let grad: Vec<f32> = (0..3 * npix).map(|i| (i as f32 * 0.3).sin()).collect();
        let grad = upload_f32(c, &grad);
        let g = render_backward_device(
            &ctx,
            &dev,
            &settings,
            None,
            &frame,
            &GpuOutputGrads {
                rgb: &grad,
                alpha: None,
                depth: None,
                extra: None,
            },
        )
        .unwrap();
        on_device.add(&ctx, &frame, &g, 2).unwrap();
        let host = read_grads(&ctx, &g, scene.len(), scene.sh_degree, None).unwrap();
        let radii = download(&ctx, &frame, scene.len()).unwrap().radii;
        on_host.add(
            &crate::train::RenderedView {
                means2d: &host.means2d,
                radii: &radii,
                width: w,
                height: h,
            },
            2,
        );
    }
    let got = on_device.download(&ctx).unwrap();
    assert!(on_host.count.contains(&2.0));
    assert_eq!(got.count, on_host.count);
    assert_eq!(got.max_radius, on_host.max_radius);
    assert!(rel_err(&got.grad2d, &on_host.grad2d) < 1e-6);
}

/// The device loss against `crate::train::loss::l1_dssim`: value and gradient.
#[test]
fn l1_dssim_on_the_device_matches_the_cpu() {
    let Some(ctx) = context_or_skip() else {
        return;
    };
    let c = &ctx.client;
    let (w, h, ch) = (23, 17, 3);
    let pred: Vec<f32> = (0..w * h * ch)
        .map(|i| ((i as f32 * 0.37).sin() + 1.0) * 0.5)
        .collect();
    let target: Vec<f32> = (0..w * h * ch)
        .map(|i| ((i as f32 * 0.11).cos() + 1.0) * 0.45)
        .collect();
    for weight in [0.0, 0.2, 1.0] {
        let want = crate::train::loss::l1_dssim(&pred, &target, w, h, ch, weight);
        let got = super::l1_dssim(
            &ctx,
            &upload_f32(c, &pred),
            &upload_f32(c, &target),
            w,
            h,
            ch,
            weight,
        )
        .unwrap();
        let grad = read_f32(c, &got.grad, w * h * ch).unwrap();
        let value = got.value(&ctx).unwrap();
        let e = rel_err(&grad, &want.grad);
        assert!(e < 1e-4, "weight {weight}: gradient relative error {e}");
        assert!(
            (value - want.value).abs() < 1e-5,
            "{value} vs {}",
            want.value
        );
    }
}

/// Waves of small gradients shaped like `scene`.
fn wave_grads(scene: &GaussianScene) -> SceneGrads {
    let wave = |len: usize, f: f32| -> Vec<f32> {
        (0..len).map(|i| (i as f32 * f).sin() * 0.01).collect()
    };
    SceneGrads {
        means: wave(scene.means.len(), 0.3),
        log_scales: wave(scene.log_scales.len(), 0.7),
        quats: wave(scene.quats.len(), 1.1),
        opacity_logits: wave(scene.len(), 0.5),
        sh: wave(scene.sh.len(), 0.9),
        extra: vec![],
        means2d: vec![],
    }
}

fn upload_grads(ctx: &GpuContext, g: &SceneGrads) -> GpuSceneGrads {
    let up = |v: &[f32]| upload_f32(&ctx.client, v);
    GpuSceneGrads {
        means: up(&g.means),
        log_scales: up(&g.log_scales),
        quats: up(&g.quats),
        opacity_logits: up(&g.opacity_logits),
        sh: up(&g.sh),
        extra: None,
        splat: zeros32(&ctx.client, GRAD_F * g.opacity_logits.len()),
    }
}

/// The anchor gradient added on the device equals what `Anchor::loss` adds on the host: mixed
/// generations (one of weight 0), a partial mask or none, with and without the colour term.
#[test]
fn anchor_gradient_on_the_device_matches_the_cpu() {
    use crate::train::anchor::{Anchor, AnchorConfig};
    let Some(ctx) = context_or_skip() else {
        return;
    };
    let anchored = random_scene(90, 2, 21);
    // Same size and SH degree, different values everywhere: every term has a non-zero difference.
    let scene = random_scene(90, 2, 22);
    for config in [AnchorConfig::gaussian_editor(), AnchorConfig::vcedit()] {
        let mut anchor = Anchor::new(&anchored, config);
        anchor.schedule = vec![1.5, 0.4, 0.0, 3.0];
        anchor.generations = (0..scene.len() as u32).map(|j| j % 4).collect();
        let mask: Vec<bool> = (0..scene.len()).map(|j| j % 3 != 1).collect();
        for mask in [Some(mask.as_slice()), None] {
            let mut want = wave_grads(&scene);
            let before = want.clone();
            anchor.loss(&scene, mask, Some(&mut want));
            let dev_grads = upload_grads(&ctx, &before);
            GpuAnchor::upload(&ctx, &anchor, mask)
                .add_grad(&ctx, &GpuScene::upload(&ctx, &scene), &dev_grads)
                .unwrap();
            let got = read_grads(&ctx, &dev_grads, scene.len(), scene.sh_degree, None).unwrap();
            for (name, g, w, b) in [
                ("means", &got.means, &want.means, &before.means),
                (
                    "log_scales",
                    &got.log_scales,
                    &want.log_scales,
                    &before.log_scales,
                ),
                ("quats", &got.quats, &want.quats, &before.quats),
                (
                    "opacity",
                    &got.opacity_logits,
                    &want.opacity_logits,
                    &before.opacity_logits,
                ),
                ("sh", &got.sh, &want.sh, &before.sh),
            ] {
                // The anchor's part of the gradient, compared on its own.
                let delta =
                    |x: &[f32]| -> Vec<f32> { x.iter().zip(b).map(|(x, b)| x - b).collect() };
                let e = rel_err(&delta(g), &delta(w));
                assert!(
                    e < 1e-5,
                    "{name} (mask {}): relative error {e}",
                    mask.is_some()
                );
            }
            assert_ne!(want.means, before.means);
        }
    }
}

/// Masked Adam on the device equals `Adam::step` with the same mask: frozen Gaussians keep their
/// parameters and moments bit for bit in the hooked groups (rotations only with `mask_rotation`).
#[test]
fn masked_adam_on_the_device_matches_the_cpu() {
    use crate::train::optim::{Adam, LearningRates};
    let Some(ctx) = context_or_skip() else {
        return;
    };
    let scene = random_scene(70, 1, 31);
    let grads = wave_grads(&scene);
    let mask: Vec<bool> = (0..scene.len()).map(|j| j % 4 != 0).collect();
    let flags: Vec<u32> = mask.iter().map(|&t| u32::from(t)).collect();
    let dev_mask = ::gpu::prims::upload_u32(&ctx.client, &flags);
    for mask_rotation in [false, true] {
        let mut cpu_scene = scene.clone();
        let mut cpu = Adam::new(&scene, LearningRates::gaussian_editor(100), 1.5);
        cpu.mask_rotation = mask_rotation;
        let mut rates = cpu.clone();
        let dev = GpuScene::upload(&ctx, &scene);
        let mut gpu_adam = GpuAdam::new(&ctx, &dev);
        let dev_grads = upload_grads(&ctx, &grads);
        for _ in 0..3 {
            cpu.step(&mut cpu_scene, &grads, Some(&mask));
            gpu_adam
                .step_masked(&ctx, &mut rates, &dev, &dev_grads, Some(&dev_mask))
                .unwrap();
        }
        let got = dev.download(&ctx).unwrap();
        gpu_adam.download_into(&ctx, &mut rates).unwrap();
        for (name, g, w) in [
            ("means", &got.means, &cpu_scene.means),
            ("log_scales", &got.log_scales, &cpu_scene.log_scales),
            ("quats", &got.quats, &cpu_scene.quats),
            ("opacity", &got.opacity_logits, &cpu_scene.opacity_logits),
            ("sh", &got.sh, &cpu_scene.sh),
            ("means m", &rates.means.m, &cpu.means.m),
            ("quats v", &rates.quats.v, &cpu.quats.v),
            ("sh m", &rates.sh.m, &cpu.sh.m),
        ] {
            let e = rel_err(g, w);
            assert!(
                e < 1e-6,
                "{name} (mask_rotation {mask_rotation}): relative error {e}"
            );
        }
        let k = scene.sh_coeffs();
        for j in (0..scene.len()).filter(|&j| !mask[j]) {
            assert_eq!(got.means[3 * j..3 * j + 3], scene.means[3 * j..3 * j + 3]);
            assert_eq!(
                got.log_scales[3 * j..3 * j + 3],
                scene.log_scales[3 * j..3 * j + 3]
            );
            assert_eq!(got.opacity_logits[j], scene.opacity_logits[j]);
            assert_eq!(
                got.sh[3 * k * j..3 * k * (j + 1)],
                scene.sh[3 * k * j..3 * k * (j + 1)]
            );
            assert!(rates.means.m[3 * j..3 * j + 3].iter().all(|&m| m == 0.0));
            let quat_frozen = got.quats[4 * j..4 * j + 4] == scene.quats[4 * j..4 * j + 4];
            assert_eq!(quat_frozen, mask_rotation, "Gaussian {j}: rotation frozen");
        }
        assert_ne!(got.means, scene.means);
        assert_eq!(rates.steps(), cpu.steps());
    }
}
