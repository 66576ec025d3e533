//! The device-resident training pieces against their host twins in [`crate::train`]: the fit, Adam
//! (masked too), the densification statistics, the loss and the anchor gradient. Runs on any Vulkan
//! device (lavapipe in CI) and skips with one line without one.

use super::*;
use crate::cameras::orbit::look_at;
use crate::render::gpu::project::GRAD_F;
use crate::render::gpu::tests::{bits, camera, max_rel, random_scene, rel_err};
use crate::render::gpu::{download, read_grads, GpuFrozenGeometry, GpuSceneGrads};
use crate::render::{self, SceneGrads};
use crate::scene::GaussianScene;
use crate::train::optim::{Group, LearningRates};
use ::gpu::prims::{read_f32, upload_f32, zeros32};
use ::gpu::testing::context_or_skip;

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
            &crate::device::SplatDevice::Gpu(ctx.clone()),
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

/// Three Adam steps with `grads` from `scene`, on the CPU with `adam` and on the device with a copy of it,
/// both with the trainable flags of `mask` (host and device copies) where given. Returns the CPU's
/// scene and Adam, then the device's scene and Adam (its moments read back).
fn three_adam_steps(
    ctx: &GpuContext,
    scene: &GaussianScene,
    grads: &SceneGrads,
    adam: Adam,
    mask: Option<(&[bool], &Handle)>,
) -> (GaussianScene, Adam, GaussianScene, Adam) {
    let (mut cpu_scene, mut cpu, mut rates) = (scene.clone(), adam.clone(), adam);
    let dev = GpuScene::upload(ctx, scene);
    let mut gpu_adam = GpuAdam::new(ctx, &dev);
    let dev_grads = upload_grads(ctx, grads);
    for _ in 0..3 {
        cpu.step(&mut cpu_scene, grads, mask.map(|m| m.0));
        gpu_adam
            .step_masked(ctx, &mut rates, &dev, &dev_grads, mask.map(|m| m.1))
            .unwrap();
    }
    gpu_adam.download_into(ctx, &mut rates).unwrap();
    (cpu_scene, cpu, dev.download(ctx).unwrap(), rates)
}

/// The parameter groups of `got` and `want` side by side, by name.
fn parameters<'a>(
    got: &'a GaussianScene,
    want: &'a GaussianScene,
) -> [(&'static str, &'a [f32], &'a [f32]); 5] {
    [
        ("means", &got.means, &want.means),
        ("log_scales", &got.log_scales, &want.log_scales),
        ("quats", &got.quats, &want.quats),
        ("opacity", &got.opacity_logits, &want.opacity_logits),
        ("sh", &got.sh, &want.sh),
    ]
}

/// Three device Adam steps land where `Adam::step` does.
#[test]
fn adam_on_the_device_matches_the_cpu() {
    let Some(ctx) = context_or_skip() else {
        return;
    };
    let scene = random_scene(60, 2, 9);
    let grads = wave_grads(&scene);
    let adam = Adam::new(&scene, LearningRates::inria(100), 2.0);
    let (cpu_scene, cpu, got, rates) = three_adam_steps(&ctx, &scene, &grads, adam, None);
    for (name, g, w) in parameters(&got, &cpu_scene) {
        let e = rel_err(g, w);
        assert!(e < 1e-6, "{name}: relative error {e}");
    }
    assert_ne!(got.means, scene.means);
    assert_eq!(rates.steps(), cpu.steps());
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
            &GpuOutputGrads::rgb_only(&grad),
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
    let Some(ctx) = context_or_skip() else {
        return;
    };
    let scene = random_scene(70, 1, 31);
    let grads = wave_grads(&scene);
    let mask: Vec<bool> = (0..scene.len()).map(|j| j % 4 != 0).collect();
    let flags: Vec<u32> = mask.iter().map(|&t| u32::from(t)).collect();
    let dev_mask = ::gpu::prims::upload_u32(&ctx.client, &flags);
    for mask_rotation in [false, true] {
        let mut adam = Adam::new(&scene, LearningRates::gaussian_editor(100), 1.5);
        adam.mask_rotation = mask_rotation;
        let (cpu_scene, cpu, got, rates) =
            three_adam_steps(&ctx, &scene, &grads, adam, Some((&mask[..], &dev_mask)));
        let moments: [(&str, &[f32], &[f32]); 3] = [
            ("means m", &rates.means.m, &cpu.means.m),
            ("quats v", &rates.quats.v, &cpu.quats.v),
            ("sh m", &rates.sh.m, &cpu.sh.m),
        ];
        for (name, g, w) in parameters(&got, &cpu_scene).into_iter().chain(moments) {
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

/// A resident appearance fit over two views ends where the full passes end (up to the backward's
/// float sums), its geometry untouched; a step with a position rate forgets the kept views.
#[test]
fn resident_fit_with_kept_views_matches_the_full_fit() {
    let Some(ctx) = context_or_skip() else {
        return;
    };
    let scene = random_scene(400, 2, 9);
    let cams = [camera(48, 40), camera(40, 48)];
    let settings = RenderSettings::default();
    let targets: Vec<_> = cams
        .iter()
        .map(|c| {
            let npix = (c.width * c.height) as usize;
            let t: Vec<f32> = (0..3 * npix).map(|i| (i % 7) as f32 / 7.0).collect();
            upload_f32(&ctx.client, &t)
        })
        .collect();
    let fit = |freeze: bool| {
        let mut state = TrainState::new(scene.clone(), LearningRates::inria(1000), 2.0);
        for g in [Group::Means, Group::LogScales, Group::Quats] {
            state.adam.group_lr_scale[g.index()] = 0.0;
        }
        let mut trainer = DeviceTrainer::upload(&ctx, &state);
        if freeze {
            trainer.freeze_geometry();
        }
        for step in 0..12 {
            let v = step % 2;
            trainer
                .step_weighted(
                    &ctx,
                    &mut state.adam,
                    &cams[v],
                    v,
                    &targets[v],
                    &settings,
                    L1DssimWeights::blend(0.2),
                    false,
                    |_, g| Ok::<_, GpuError>(g),
                )
                .unwrap();
        }
        let kept = trainer.frozen_bytes();
        trainer.download_into(&ctx, &mut state).unwrap();
        (state, trainer, kept)
    };
    let (full, _, none) = fit(false);
    let (frozen, mut trainer, kept) = fit(true);
    assert_eq!(none, 0);
    assert!(kept > 0, "both views kept");
    assert_eq!(bits(&full.scene.means), bits(&frozen.scene.means));
    assert_eq!(bits(&scene.means), bits(&frozen.scene.means));
    assert_eq!(bits(&scene.quats), bits(&frozen.scene.quats));
    for (name, got, want, start) in [
        (
            "opacity",
            &frozen.scene.opacity_logits,
            &full.scene.opacity_logits,
            &scene.opacity_logits,
        ),
        ("sh", &frozen.scene.sh, &full.scene.sh, &scene.sh),
    ] {
        assert_ne!(bits(want), bits(start), "{name}: the fit moved nothing");
        let e = max_rel(got, want);
        assert!(e <= 1e-5, "{name} differs by {e:e}");
    }
    // A step that moves the means forgets the views.
    let mut state = frozen;
    state.adam.group_lr_scale[Group::Means.index()] = 1.0;
    trainer
        .step_weighted(
            &ctx,
            &mut state.adam,
            &cams[0],
            0,
            &targets[0],
            &settings,
            L1DssimWeights::blend(0.2),
            false,
            |_, g| Ok::<_, GpuError>(g),
        )
        .unwrap();
    assert_eq!(trainer.frozen_bytes(), 0);
}

/// Two resident appearance fits stepped together ([`DevicePair`]: both fits' steps in one launch
/// sequence, the kept views shared) end where each fit alone ends ([`DeviceTrainer`] with kept views),
/// up to the backward's float sums: each with its own view order and targets, a trainable mask, the
/// geometry untouched; and the pair keeps each view once.
#[test]
fn a_pair_of_resident_fits_matches_the_fits_in_turn() {
    let Some(ctx) = context_or_skip() else {
        return;
    };
    let scene = random_scene(400, 2, 9);
    let cams = [
        camera(48, 40),
        look_at(
            "u".into(),
            [0.9, 0.2, -2.8],
            [0.0, 0.0, 1.0],
            [0.0, -1.0, 0.0],
            48,
            40,
            40.0,
        ),
        look_at(
            "w".into(),
            [-0.7, -0.4, -2.9],
            [0.0, 0.0, 1.0],
            [0.0, -1.0, 0.0],
            48,
            40,
            45.0,
        ),
    ];
    let npix = 48 * 40;
    let targets: Vec<Vec<Handle>> = (0..2)
        .map(|fit| {
            (0..cams.len())
                .map(|v| {
                    let t: Vec<f32> = (0..3 * npix)
                        .map(|i| ((i * (fit + 2) + v) % 7) as f32 / 7.0)
                        .collect();
                    upload_f32(&ctx.client, &t)
                })
                .collect()
        })
        .collect();
    let mut start = TrainState::new(scene.clone(), LearningRates::inria(1000), 2.0);
    start.trainable = Some((0..scene.len()).map(|i| i % 3 != 0).collect());
    for g in [Group::Means, Group::LogScales, Group::Quats] {
        start.adam.group_lr_scale[g.index()] = 0.0;
    }
    let settings = RenderSettings::default();
    let weights = L1DssimWeights::new(10.0, 2.5);
    // Each fit's own view order: the second visits the views in another order (and twice the same).
    let orders = [[0, 1, 2, 1, 0, 2, 2, 1, 0], [2, 2, 0, 1, 0, 1, 0, 2, 1]];
    let mut alone = Vec::new();
    for fit in 0..2 {
        let mut state = start.clone();
        let mut trainer = DeviceTrainer::upload(&ctx, &state);
        trainer.freeze_geometry();
        for &v in &orders[fit] {
            trainer
                .step_weighted(
                    &ctx,
                    &mut state.adam,
                    &cams[v],
                    v,
                    &targets[fit][v],
                    &settings,
                    weights,
                    false,
                    |_, g| Ok::<_, GpuError>(g),
                )
                .unwrap();
        }
        trainer.download_into(&ctx, &mut state).unwrap();
        alone.push(state.scene);
    }
    let mut state = start.clone();
    let mut pair = DevicePair::upload(&ctx, &state);
    for k in 0..orders[0].len() {
        let views = [orders[0][k], orders[1][k]];
        pair.step(
            &ctx,
            &mut state.adam,
            views.map(|v| &cams[v]),
            views,
            [&targets[0][views[0]], &targets[1][views[1]]],
            &settings,
            weights,
        )
        .unwrap();
    }
    assert_eq!(state.adam.steps, start.adam.steps + orders[0].len() as u64);
    let one_view = GpuFrozenGeometry::view_bytes(scene.len(), 0, 48, 40);
    assert!(
        pair.kept_bytes() >= 3 * one_view && pair.kept_bytes() < 6 * one_view,
        "each view kept once: {} bytes",
        pair.kept_bytes()
    );
    let together = pair.download(&ctx).unwrap();
    for (fit, (got, want)) in together.iter().zip(&alone).enumerate() {
        assert_eq!(bits(&got.means), bits(&scene.means), "fit {fit}");
        assert_eq!(bits(&got.quats), bits(&scene.quats), "fit {fit}");
        assert_eq!(bits(&got.log_scales), bits(&scene.log_scales), "fit {fit}");
        for (name, got, want, start) in [
            (
                "opacity",
                &got.opacity_logits,
                &want.opacity_logits,
                &scene.opacity_logits,
            ),
            ("sh", &got.sh, &want.sh, &scene.sh),
        ] {
            assert_ne!(bits(want), bits(start), "fit {fit} {name}: nothing moved");
            let e = max_rel(got, want);
            assert!(e <= 1e-5, "fit {fit} {name} differs by {e:e}");
        }
    }
}
