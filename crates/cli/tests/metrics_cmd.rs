//! `vcedit metrics` end to end on two generated scenes: a textured sphere, and the same sphere recoloured
//! inside a box.

use splat::ply::write_ply;
use splat::GaussianScene;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use testkit::output::stdout_of_success;

fn vcedit(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_vcedit"))
        .arg("metrics")
        .args(args)
        .output()
        .expect("run vcedit")
}

/// `vcedit metrics --source SOURCE --edited EDITED` and the other `args`.
fn metrics(source: &Path, edited: &Path, args: &[&str]) -> Output {
    vcedit(&[&["--source", s(source), "--edited", s(edited)][..], args].concat())
}

fn s(p: &Path) -> &str {
    p.to_str().expect("a UTF-8 path")
}

/// Opaque Gaussians covering a unit sphere with a smooth texture; `recolour` changes those with x > 0.3.
fn sphere(recolour: bool) -> GaussianScene {
    testkit::scenes::textured_sphere(3000, |p| {
        if recolour && p[0] > 0.3 {
            [0.9, 0.2, 0.1]
        } else {
            [
                0.5 + 0.2 * (1.5 * p[0]).sin(),
                0.5 + 0.2 * (1.2 * p[1]).cos(),
                0.5 + 0.15 * (2.0 * p[2]).sin(),
            ]
        }
    })
}

fn scenes(dir: &Path) -> (PathBuf, PathBuf) {
    let a = dir.join("source.ply");
    let b = dir.join("edited.ply");
    write_ply(&a, &sphere(false)).unwrap();
    write_ply(&b, &sphere(true)).unwrap();
    (a, b)
}

#[test]
fn compares_two_scenes_with_a_mask_box() {
    let dir = tempfile::tempdir().unwrap();
    let (a, b) = scenes(dir.path());
    let json = dir.path().join("m.json");
    let text = stdout_of_success(&metrics(
        &a,
        &b,
        &[
            "--orbit",
            "8",
            "--size",
            "64",
            "--mask-box",
            "0.3,-2,-2,2,2,2",
            "--json",
            s(&json),
        ],
    ));
    assert!(text.contains("cross-view error, source renders"), "{text}");
    assert!(text.contains("preservation, outside the mask"), "{text}");
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    assert_eq!(v["views"], 8);
    assert_eq!(
        (v["width"].as_u64(), v["height"].as_u64()),
        (Some(64), Some(64))
    );
    let m = &v["metrics"];
    // Both scenes are real 3D scenes, so their renders are consistent with themselves.
    for key in ["source_consistency", "final_consistency"] {
        let e = m[key]["mean_abs_error"].as_f64().unwrap();
        assert!(e < 0.02, "{key}: {e}");
        assert_eq!(m[key]["pairs"], 24);
    }
    // The recolouring shows over whole images but hardly outside the box.
    let whole = m["preservation_whole"]["psnr"].as_f64().unwrap();
    let outside = m["preservation_outside_mask"]["psnr"].as_f64().unwrap();
    let outside_ssim = m["preservation_outside_mask"]["ssim"].as_f64().unwrap();
    println!("whole {whole} dB, outside {outside} dB (SSIM {outside_ssim})");
    assert!(whole < 25.0, "whole-image PSNR {whole}");
    assert!(outside > whole + 8.0, "outside {outside} vs whole {whole}");
    assert!(outside_ssim > 0.95);
    let frac = m["preservation_outside_mask"]["fraction"].as_f64().unwrap();
    assert!(frac > 0.5 && frac < 0.98, "{frac}");
    assert!(m["clip"].is_null());
}

#[test]
fn identical_scenes_are_perfectly_preserved() {
    let dir = tempfile::tempdir().unwrap();
    let (a, _) = scenes(dir.path());
    let json = dir.path().join("m.json");
    stdout_of_success(&metrics(
        &a,
        &a,
        &["--orbit", "4", "--size", "48", "--json", s(&json)],
    ));
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let m = &v["metrics"];
    assert_eq!(m["preservation_whole"]["psnr"].as_f64(), Some(100.0));
    assert_eq!(m["preservation_whole"]["ssim"].as_f64(), Some(1.0));
    assert!(m["preservation_outside_mask"].is_null());
    assert_eq!(m["source_consistency"], m["final_consistency"]);
}

#[test]
fn clip_directional_similarity_with_the_tiny_fixture() {
    let dir = tempfile::tempdir().unwrap();
    let (a, b) = scenes(dir.path());
    let clip = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../fixtures/clip/tiny-clip");
    let json = dir.path().join("m.json");
    let text = stdout_of_success(&metrics(
        &a,
        &b,
        &[
            "--orbit",
            "3",
            "--size",
            "40",
            "--clip",
            s(&clip),
            "--source-prompt",
            "a photo of a man",
            "--target-prompt",
            "a red cat",
            "--json",
            s(&json),
        ],
    ));
    assert!(text.contains("CLIP directional similarity"), "{text}");
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let c = &v["metrics"]["clip"];
    let d = c["directional"].as_f64().unwrap();
    assert!(d.is_finite() && d.abs() <= 1.0 && d != 0.0, "{d}");
    assert_eq!(c["per_view"].as_array().unwrap().len(), 3);
    assert_eq!(c["target_prompt"], "a red cat");
}

#[test]
fn bad_inputs_fail_with_one_clear_line() {
    let dir = tempfile::tempdir().unwrap();
    let (a, _) = scenes(dir.path());
    let missing = dir.path().join("nope.ply");
    let out = metrics(&a, &missing, &["--orbit", "4"]);
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("nope.ply"), "{err}");

    // CLIP without prompts is a usage error.
    let out = metrics(&a, &a, &["--clip", s(dir.path())]);
    assert_eq!(out.status.code(), Some(2));

    // A folder that is not a CLIP model is reported before any rendering.
    let out = metrics(
        &a,
        &a,
        &[
            "--clip",
            s(dir.path()),
            "--source-prompt",
            "x",
            "--target-prompt",
            "y",
        ],
    );
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("CLIP") && err.contains("config.json"), "{err}");
    assert!(!err.contains("rendering"), "{err}");

    let out = metrics(&a, &a, &["--mask-box", "1,2,3"]);
    assert_eq!(out.status.code(), Some(2));
}

/// The names that say what they take (`--source-scene`, `--edited-scene`: `--source` is a prompt in
/// `edit`), and `--json` without a file: the JSON alone on stdout, the text on stderr.
#[test]
fn scene_options_by_their_full_names_and_json_on_stdout() {
    let dir = tempfile::tempdir().unwrap();
    let (a, b) = scenes(dir.path());
    let out = vcedit(&[
        "--source-scene",
        s(&a),
        "--edited-scene",
        s(&b),
        "--orbit",
        "4",
        "--size",
        "32",
        "--json",
    ]);
    let stdout = stdout_of_success(&out);
    let v: serde_json::Value = serde_json::from_str(&stdout).expect("stdout is the JSON alone");
    assert_eq!(v["views"], 4);
    assert!(v["metrics"]["preservation_whole"]["psnr"].is_number());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("preservation, whole images"), "{stderr}");
    // No file named "-" or anything else appeared.
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 2);
}
