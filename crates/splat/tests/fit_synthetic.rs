//! End-to-end fitting on a tiny synthetic dataset: a known scene rendered by our own renderer from a ring
//! of cameras, written as a Blender `transforms.json` + PNGs, then fitted from random points. The held-out
//! PSNR must rise far above that of the initial scene.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use splat::cameras::orbit::look_at;
use splat::render::{render, RenderSettings};
use splat::train::densify::DefaultStrategy;
use splat::train::scene_fit::{
    evaluate, fit, initial_scene, load_dataset, DatasetOptions, FitConfig,
};
use splat::{Camera, GaussianScene, Image};
use std::path::Path;

const SIZE: u32 = 40;

/// A few hundred opaque coloured Gaussians filling a box, plus a ring of cameras looking at it.
fn known_scene() -> GaussianScene {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let n = 300;
    let mut s = GaussianScene::new(0);
    for _ in 0..n {
        let p: [f32; 3] = std::array::from_fn(|a| {
            let half = [0.6, 0.4, 0.5][a];
            rng.gen_range(-half..half)
        });
        s.means.extend_from_slice(&p);
        let sc: f32 = rng.gen_range(0.05..0.12);
        s.log_scales
            .extend_from_slice(&[sc.ln(), (sc * 0.7).ln(), (sc * 1.2).ln()]);
        let q: [f32; 4] = std::array::from_fn(|_| rng.gen_range(-1.0..1.0));
        s.quats.extend_from_slice(&q);
        s.opacity_logits.push(rng.gen_range(1.0..3.0));
        // Colour varies smoothly with position so the target has structure.
        let col = [0.5 + 0.8 * p[0], 0.5 - 0.9 * p[1], 0.5 + p[2]];
        s.sh.extend(col.map(|c| (c.clamp(0.05, 0.95) - 0.5) / 0.282_094_8));
    }
    s
}

fn ring_cameras(count: usize) -> Vec<Camera> {
    (0..count)
        .map(|i| {
            let a = i as f64 * std::f64::consts::TAU / count as f64;
            let h = if i % 2 == 0 { 0.8 } else { -0.5 };
            look_at(
                format!("view{i}"),
                [3.0 * a.cos(), 3.0 * a.sin(), h],
                [0.0; 3],
                [0.0, 0.0, 1.0],
                SIZE,
                SIZE,
                45.0,
            )
        })
        .collect()
}

/// Writes the rendered views as a Blender-convention dataset (OpenGL camera-to-world matrices).
fn write_dataset(dir: &Path, scene: &GaussianScene, cams: &[Camera]) {
    let settings = RenderSettings::default();
    let mut frames = Vec::new();
    for cam in cams {
        let out = render(scene, cam, &settings, None);
        Image::from_data(SIZE, SIZE, 3, out.frame.rgb)
            .save_png(&dir.join(format!("{}.png", cam.name)))
            .unwrap();
        let r = cam.rotation;
        let c = cam.center();
        // Columns of the camera-to-world rotation are the rows of R; OpenGL flips y and z.
        let row = |i: usize| serde_json::json!([r[0][i], -r[1][i], -r[2][i], c[i]]);
        frames.push(serde_json::json!({
            "file_path": format!("./{}", cam.name),
            "transform_matrix": [row(0), row(1), row(2), [0.0, 0.0, 0.0, 1.0]],
        }));
    }
    let fov = 2.0 * (SIZE as f64 / (2.0 * cams[0].fx)).atan();
    let json = serde_json::json!({ "camera_angle_x": fov, "frames": frames });
    std::fs::write(dir.join("transforms.json"), json.to_string()).unwrap();
}

#[test]
fn fit_recovers_a_known_scene() {
    let dir = tempfile::tempdir().unwrap();
    let scene = known_scene();
    let cams = ring_cameras(16);
    write_dataset(dir.path(), &scene, &cams);

    let data = load_dataset(
        dir.path(),
        &DatasetOptions {
            size: None,
            holdout_every: 4,
            background: [0.0; 3],
        },
    )
    .unwrap();
    assert_eq!((data.train.len(), data.test.len()), (12, 4));
    // The loaded cameras reproduce the ones we rendered with.
    let back = &data.test[1].camera;
    for a in 0..3 {
        assert!((back.center()[a] - cams[4].center()[a]).abs() < 1e-4);
    }

    let config = FitConfig {
        steps: 600,
        sh_degree: 1,
        sh_degree_interval: 300,
        init_points: 2000,
        strategy: DefaultStrategy {
            refine_start: 100,
            refine_every: 50,
            reset_every: 10_000,
            ..Default::default()
        },
        ..Default::default()
    };
    let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
    let init = initial_scene(&data, config.init_points, config.init_opacity, &mut rng);
    let before = evaluate(&init, &data.test, [0.0; 3]);

    let mut steps_seen = 0;
    let mut refined = false;
    let result = fit(&data, &config, &mut |p| {
        steps_seen = p.step;
        refined |= p.refine.is_some_and(|r| r.cloned + r.split > 0);
    });
    let after = result.test_psnr.unwrap();
    eprintln!(
        "held-out PSNR {before:.2} -> {after:.2} dB, train {:.2}, {} Gaussians",
        result.train_psnr,
        result.scene.len()
    );
    assert_eq!(steps_seen, 600);
    assert!(refined, "densification never grew the scene");
    assert!(after > 24.0, "held-out PSNR {after:.2} dB");
    assert!(after > before + 10.0);
    assert_eq!(result.scene.sh_degree, 1);
    result.scene.check_shapes().unwrap();

    // Same seed, same result.
    let again = fit(&data, &config, &mut |_| {});
    assert_eq!(again.scene, result.scene);
}
