//! `vcedit fit` end to end: the real binary on a small RGBA Blender-style dataset rendered from a known
//! scene, composited on a white background.

use splat::cameras::orbit::look_at;
use splat::ply::read_ply;
use splat::render::{render, RenderSettings};
use splat::{GaussianScene, Image};
use std::path::Path;
use std::process::{Command, Output};

fn vcedit(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_vcedit"))
        .arg("fit")
        .args(args)
        .output()
        .expect("run vcedit")
}

/// A coloured bar of Gaussians along x.
fn bar_scene() -> GaussianScene {
    let mut s = GaussianScene::new(0);
    for i in 0..40 {
        let t = i as f32 / 39.0;
        s.means
            .extend_from_slice(&[t - 0.5, 0.1 * (7.0 * t).sin(), 0.0]);
        s.log_scales.extend_from_slice(&[-2.5, -2.5, -2.5]);
        s.quats.extend_from_slice(&[1.0, 0.0, 0.0, 0.0]);
        s.opacity_logits.push(3.0);
        s.sh.extend_from_slice(&[(t - 0.5) * 3.0, -1.0, (0.5 - t) * 3.0]);
    }
    s
}

/// Renders `views` cameras on a ring and writes them as RGBA PNGs (straight alpha) + transforms.json.
fn write_rgba_dataset(dir: &Path, views: usize) {
    let scene = bar_scene();
    let mut frames = Vec::new();
    for i in 0..views {
        let a = i as f64 * std::f64::consts::TAU / views as f64;
        let cam = look_at(
            format!("r_{i}"),
            [2.5 * a.cos(), 2.5 * a.sin(), 0.7],
            [0.0; 3],
            [0.0, 0.0, 1.0],
            32,
            32,
            30.0,
        );
        let out = render(&scene, &cam, &RenderSettings::default(), None);
        // Black background ⇒ premultiplied colour; PNG stores straight alpha.
        let data: Vec<f32> = out
            .rgb
            .chunks_exact(3)
            .zip(&out.alpha)
            .flat_map(|(c, &a)| {
                let un = |v: f32| if a > 1e-6 { (v / a).min(1.0) } else { 0.0 };
                [un(c[0]), un(c[1]), un(c[2]), a]
            })
            .collect();
        Image::from_data(32, 32, 4, data)
            .save_png(&dir.join(format!("r_{i}.png")))
            .unwrap();
        let r = cam.rotation;
        let c = cam.center();
        let row = |k: usize| serde_json::json!([r[0][k], -r[1][k], -r[2][k], c[k]]);
        frames.push(serde_json::json!({
            "file_path": format!("./r_{i}"),
            "transform_matrix": [row(0), row(1), row(2), [0.0, 0.0, 0.0, 1.0]],
        }));
    }
    let fov = 2.0 * (32.0f64 / 60.0).atan();
    let json = serde_json::json!({ "camera_angle_x": fov, "frames": frames });
    std::fs::write(dir.join("transforms_train.json"), json.to_string()).unwrap();
}

#[test]
fn fits_and_writes_a_readable_ply() {
    let dir = tempfile::tempdir().unwrap();
    write_rgba_dataset(dir.path(), 10);
    // Outside the data folder, which is the input.
    let outs = tempfile::tempdir().unwrap();
    let out = outs.path().join("fitted.ply");
    let o = vcedit(&[
        "--data",
        dir.path().to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--steps",
        "300",
        "--background",
        "white",
        "--sh-degree",
        "0",
        "--init-points",
        "1000",
        "--eval-every",
        "100",
    ]);
    let stdout = String::from_utf8_lossy(&o.stdout);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{stderr}");
    eprintln!("{stderr}{stdout}");
    assert!(
        stderr.contains("8 training and 2 held-out views at 32x32"),
        "{stderr}"
    );
    assert!(stderr.contains("step 100: held-out PSNR"), "{stderr}");
    let psnr: f64 = stdout
        .split("held-out PSNR ")
        .nth(1)
        .and_then(|s| s.split(' ').next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("no PSNR in {stdout}"));
    // Reaches ~25 dB; the random initial cloud is far below (see the splat crate's fit test for that check).
    assert!(psnr > 20.0, "held-out PSNR {psnr}");
    let scene = read_ply(&out).unwrap();
    assert!(!scene.is_empty());
    assert_eq!(scene.sh_degree, 0);
}

#[test]
fn missing_data_is_one_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("nothing-here");
    let o = vcedit(&[
        "--data",
        missing.to_str().unwrap(),
        "--out",
        dir.path().join("x.ply").to_str().unwrap(),
    ]);
    assert_eq!(o.status.code(), Some(1));
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(
        stderr.starts_with("error: cannot load the training data"),
        "{stderr}"
    );
    assert!(stderr.contains("nothing-here"), "{stderr}");
    assert_eq!(stderr.lines().count(), 1, "{stderr}");
}

#[test]
fn resolution_downscales_like_the_inria_trainer() {
    let dir = tempfile::tempdir().unwrap();
    write_rgba_dataset(dir.path(), 5);
    // Outside the data folder, which is the input.
    let outs = tempfile::tempdir().unwrap();
    let out = outs.path().join("r.ply");
    let data = dir.path().to_str().unwrap();
    let fit = |extra: &[&str]| {
        let mut args = vec![
            "--data",
            data,
            "--out",
            out.to_str().unwrap(),
            "--steps",
            "2",
            // Each run replaces the last one's scene.
            "--force",
        ];
        args.extend_from_slice(extra);
        let o = vcedit(&args);
        (
            o.status.code(),
            String::from_utf8_lossy(&o.stderr).into_owned(),
        )
    };
    // 32x32 views: -r 2 halves them, -r 20 makes them 20 wide.
    let (code, stderr) = fit(&["-r", "2"]);
    assert_eq!(code, Some(0), "{stderr}");
    assert!(stderr.contains("held-out views at 16x16"), "{stderr}");
    let (code, stderr) = fit(&["--resolution", "20"]);
    assert_eq!(code, Some(0), "{stderr}");
    assert!(stderr.contains("held-out views at 20x20"), "{stderr}");
    // --iterations, the old name of --steps here (rounds in edit and demo): still works, and says so.
    let renamed = outs.path().join("renamed.ply");
    let o = vcedit(&[
        "--data",
        data,
        "--out",
        renamed.to_str().unwrap(),
        "--iterations",
        "2",
    ]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{stderr}");
    assert!(
        stderr.contains("warning: fit --iterations is deprecated")
            && stderr.contains("use --steps 2"),
        "{stderr}"
    );
    // With --size it is one or the other.
    let (code, stderr) = fit(&["-r", "2", "--size", "16"]);
    assert_eq!(code, Some(2), "{stderr}");
    assert!(stderr.contains("cannot be used with"), "{stderr}");
}
