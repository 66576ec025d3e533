//! The consistency modules do their job on constructed cases.

use edit::compute::Compute;
use edit::consistency::{EcmFitter, EcmParams, EcmScope, EcmSettings, SceneFitter};
use edit::eval::metrics::{multiview_consistency, ViewGeometry, WarpSettings};
use edit::fit::{EditTrainer, ImageLoss, TrainSettings};
use splat::render::{render, RenderSettings};
use splat::{Camera, GaussianScene, Image};
use testkit::diff::max_abs_diff;

/// A textured box of small Gaussians (colour varies with position, so views have structure).
fn textured_blob() -> GaussianScene {
    let mut s = GaussianScene::new(0);
    let n = 14;
    for i in 0..n {
        for j in 0..n {
            for k in 0..n {
                let p = [
                    i as f32 / (n - 1) as f32 - 0.5,
                    j as f32 / (n - 1) as f32 - 0.5,
                    k as f32 / (n - 1) as f32 - 0.5,
                ];
                s.means.extend_from_slice(&p);
                s.log_scales.extend_from_slice(&[(0.05f32).ln(); 3]);
                s.quats.extend_from_slice(&[1.0, 0.0, 0.0, 0.0]);
                s.opacity_logits.push(3.0);
                let c = [
                    0.5 + 0.4 * (6.0 * p[0]).sin(),
                    0.5 + 0.4 * (5.0 * p[1]).cos(),
                    0.5 + 0.4 * p[2],
                ];
                s.sh.extend(c.iter().map(|v| (v - 0.5) / 0.282_094_8));
            }
        }
    }
    s
}

fn cameras(size: u32) -> Vec<Camera> {
    splat::cameras::orbit_cameras([-0.5; 3], [0.5; 3], 8, size, size)
}

fn consistency(images: &[Image], cams: &[Camera], scene: &GaussianScene) -> f64 {
    let renders: Vec<_> = cams
        .iter()
        .map(|c| render(scene, c, &RenderSettings::default(), None))
        .collect();
    let geometry: Vec<ViewGeometry> = cams
        .iter()
        .zip(&renders)
        .map(|(c, r)| ViewGeometry::from_render(c, r))
        .collect();
    let refs: Vec<&Image> = images.iter().collect();
    multiview_consistency(&refs, &geometry, &WarpSettings::default())
        .unwrap()
        .summary
        .mean_abs_error
        .unwrap()
}

#[test]
fn ecm_makes_inconsistent_images_consistent() {
    let scene = textured_blob();
    let cams = cameras(48);
    // Deliberately inconsistent targets: each view's render with its own colour shift.
    let targets: Vec<Image> = cams
        .iter()
        .enumerate()
        .map(|(v, c)| {
            let mut img = render(&scene, c, &RenderSettings::default(), None).rgb_image();
            let shift = [
                0.25 * ((v as f32) * 1.3).sin(),
                0.25 * ((v as f32) * 2.1).cos(),
                -0.2 * ((v % 3) as f32 - 1.0),
            ];
            for p in img.data.chunks_exact_mut(3) {
                for ch in 0..3 {
                    p[ch] = (p[ch] + shift[ch]).clamp(0.0, 1.0);
                }
            }
            img
        })
        .collect();
    let before = consistency(&targets, &cams, &scene);

    let source_renders: Vec<Image> = cams
        .iter()
        .map(|c| render(&scene, c, &RenderSettings::default(), None).rgb_image())
        .collect();
    for params in [EcmParams::Appearance, EcmParams::All] {
        let ecm = EcmSettings {
            scope: EcmScope::All,
            params,
            ..EcmSettings::reference(0)
        };
        let trainer = EditTrainer::new(&scene, None, TrainSettings::new(100), 2.0, [0.0; 3]);
        let loss = ImageLoss::dssim();
        let fitter = EcmFitter::new(&trainer, &loss, &ecm);
        let fitted = fitter.fit(&scene, &cams, &targets, 7).unwrap();
        let renders: Vec<Image> = cams
            .iter()
            .map(|c| render(&fitted, c, &RenderSettings::default(), None).rgb_image())
            .collect();
        let after = consistency(&renders, &cams, &scene);
        eprintln!("ECM ({params:?}): cross-view error {before:.4} → {after:.4}");
        assert!(before > 0.08, "targets must disagree: {before}");
        assert!(
            after < 0.5 * before,
            "{params:?}: ECM renders disagree by {after}, the targets by {before}"
        );
        // The fit follows the targets on average (it is not just the source scene again).
        let moved: f32 = renders
            .iter()
            .zip(&source_renders)
            .map(|(a, b)| splat::train::loss::l1(&a.data, &b.data).value)
            .sum();
        assert!(
            moved > 0.01 * cams.len() as f32,
            "{params:?}: the fit changed the scene ({moved})"
        );
        let geometry_kept = fitted.means == scene.means
            && fitted.log_scales == scene.log_scales
            && fitted.quats == scene.quats;
        assert_eq!(geometry_kept, params == EcmParams::Appearance, "{params:?}");
        assert_ne!(fitted.sh, scene.sh, "{params:?}: colours must change");
    }
}

#[test]
fn blend_map_consistency_makes_masks_agree() {
    use edit::consistency::{make_consistent, MapGrid, Resample};
    let scene = textured_blob();
    let cams = cameras(32);
    let n = 32 * 32;
    // Per-view "blend maps": a different noisy region in each view.
    let maps: Vec<Vec<f32>> = (0..cams.len())
        .map(|v| {
            (0..n)
                .map(|p| {
                    if ((p * 31 + v * 977) % 7) < 3 {
                        1.0
                    } else {
                        0.0
                    }
                })
                .collect()
        })
        .collect();
    let as_images = |m: &[Vec<f32>]| -> Vec<Image> {
        m.iter()
            .map(|x| Image::from_data(32, 32, 3, x.iter().flat_map(|&v| [v, v, v]).collect()))
            .collect()
    };
    let before = consistency(&as_images(&maps), &cams, &scene);
    let mut back = vec![Vec::new(); cams.len()];
    make_consistent(
        &mut Compute::cpu().splat().lift_session(&scene, &cams),
        &MapGrid {
            height: 32,
            width: 32,
            channels: 1,
            up: Resample::Nearest,
            down: Resample::Nearest,
        },
        &mut |v| Ok(maps[v].clone()),
        &mut |v, m| {
            // Threshold as the local blend does.
            let max = m.iter().copied().fold(0.0f32, f32::max).max(1e-6);
            back[v] = m
                .iter()
                .map(|&x| if x / max > 0.5 { 1.0 } else { 0.0 })
                .collect();
            Ok(())
        },
    )
    .unwrap();
    let after = consistency(&as_images(&back), &cams, &scene);
    eprintln!("blend masks: cross-view error {before:.4} → {after:.4}");
    assert!(
        after < 0.5 * before,
        "masks disagree by {after} after, {before} before"
    );
}

/// ECM's pair of fits: the textured blob, its cameras at 32², and two sets of targets (its renders with
/// red and blue moved two ways).
fn ecm_pair_case() -> (GaussianScene, Vec<Camera>, [Vec<Image>; 2]) {
    let scene = textured_blob();
    let cams = cameras(32);
    let renders: Vec<Image> = cams
        .iter()
        .map(|c| render(&scene, c, &RenderSettings::default(), None).rgb_image())
        .collect();
    let shifted = |d: f32| -> Vec<Image> {
        let mut out = renders.clone();
        for img in &mut out {
            for p in img.data.chunks_exact_mut(3) {
                p[0] = (p[0] + d).clamp(0.0, 1.0);
                p[2] = (p[2] - d).clamp(0.0, 1.0);
            }
        }
        out
    };
    let targets = [shifted(0.3), shifted(-0.2)];
    (scene, cams, targets)
}

/// Every parameter of `s`, one array after the other.
fn parameters(s: &GaussianScene) -> Vec<f32> {
    s.means
        .iter()
        .chain(&s.log_scales)
        .chain(&s.quats)
        .chain(&s.opacity_logits)
        .chain(&s.sh)
        .copied()
        .collect()
}

/// ECM's two fits side by side (on the CPU) give what they give one after the other, bit for bit.
#[test]
fn ecm_fit_pair_matches_fits_in_turn() {
    let (scene, cams, [a, b]) = ecm_pair_case();
    for params in [EcmParams::Appearance, EcmParams::All] {
        let ecm = EcmSettings {
            params,
            min_steps: 40,
            ..EcmSettings::reference(0)
        };
        let trainer = EditTrainer::new(&scene, None, TrainSettings::new(100), 2.0, [0.0; 3]);
        let loss = ImageLoss::dssim();
        let fitter = EcmFitter::new(&trainer, &loss, &ecm);
        let pair = fitter.fit_pair(&scene, &cams, [&a, &b], 11).unwrap();
        let in_turn = [
            fitter.fit(&scene, &cams, &a, 11).unwrap(),
            fitter.fit(&scene, &cams, &b, 12).unwrap(),
        ];
        let bits =
            |s: &GaussianScene| -> Vec<u32> { parameters(s).iter().map(|v| v.to_bits()).collect() };
        assert_ne!(
            bits(&pair[0]),
            bits(&pair[1]),
            "{params:?}: different targets"
        );
        assert_eq!(bits(&pair[0]), bits(&in_turn[0]), "{params:?}");
        assert_eq!(bits(&pair[1]), bits(&in_turn[1]), "{params:?}");
    }
}

/// On a GPU ECM's appearance fits step together (one launch sequence per step for both, one kept
/// projection per view for both) and give what the two fits give one after the other there, to float
/// rounding (the backward's atomics add in another order), with half the launches; geometry fits stay in
/// turn (the same launches; their runs are not reproducible bit for bit on a GPU: a sum's order moves a
/// mean, which moves a depth order).
#[test]
fn ecm_fit_pair_on_the_gpu_matches_fits_in_turn() {
    let Some(ctx) = gpu::testing::context_or_skip() else {
        return;
    };
    let (scene, cams, [a, b]) = ecm_pair_case();
    // Half the Gaussians editable, as ECM's default scope.
    let mask: Vec<bool> = (0..scene.len()).map(|i| i % 3 != 0).collect();
    for params in [EcmParams::Appearance, EcmParams::All] {
        let ecm = EcmSettings {
            params,
            min_steps: 24,
            ..EcmSettings::reference(0)
        };
        let mut trainer = EditTrainer::new(
            &scene,
            Some(mask.clone()),
            TrainSettings::new(100),
            2.0,
            [0.0; 3],
        );
        trainer.device = splat::SplatDevice::Gpu(ctx.clone());
        let loss = ImageLoss::dssim();
        let fitter = EcmFitter::new(&trainer, &loss, &ecm);
        let before = gpu::traffic::DeviceTraffic::now();
        let pair = fitter.fit_pair(&scene, &cams, [&a, &b], 11).unwrap();
        let paired = gpu::traffic::DeviceTraffic::now().since(before);
        let before = gpu::traffic::DeviceTraffic::now();
        let in_turn = [
            fitter.fit(&scene, &cams, &a, 11).unwrap(),
            fitter.fit(&scene, &cams, &b, 12).unwrap(),
        ];
        let one_by_one = gpu::traffic::DeviceTraffic::now().since(before);
        eprintln!(
            "{params:?}: fit_pair {} launches, the fits in turn {}",
            paired.launches, one_by_one.launches
        );
        if params == EcmParams::All {
            assert_eq!(paired.launches, one_by_one.launches, "the fits in turn");
            continue;
        }
        assert!(
            2 * paired.launches <= one_by_one.launches,
            "{paired:?} against {one_by_one:?}"
        );
        for (k, (got, want)) in pair.iter().zip(&in_turn).enumerate() {
            let (got, want) = (parameters(got), parameters(want));
            let moved = max_abs_diff(&want, &parameters(&scene));
            let worst = max_abs_diff(&got, &want);
            // The backward's atomics add in another order in each run, and Adam normalises every
            // step, so a parameter whose gradient is rounding noise can step differently (seen once in
            // CI under load: one value off by 1.3e-3). All but a few values agree to rounding.
            let off = got
                .iter()
                .zip(&want)
                .filter(|(g, w)| (*g - *w).abs() > 1e-4)
                .count();
            eprintln!(
                "{params:?} fit {k}: moved by {moved:e}, paired off by {worst:e}, {off} of {} values off by more than 1e-4",
                got.len()
            );
            assert!(moved > 0.1, "{params:?} fit {k}: the fit must move");
            // Colours and opacity logits of magnitude ~3 after 24 Adam steps.
            assert!(
                off * 1000 <= got.len() && worst <= 1e-2,
                "{params:?} fit {k}: {off} values off by more than 1e-4, worst {worst:e}"
            );
        }
    }
}
