//! `vcedit edit-image` end to end: outputs, determinism, and clear errors for bad input.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use testkit::paths::{repo, shared_assets};

fn vcedit(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_vcedit"))
        .args(args)
        .output()
        .expect("run vcedit")
}

/// A lego view when the shared assets are there, else a generated RGBA image.
fn input_image(dir: &Path) -> PathBuf {
    let lego = shared_assets().join("lego-200/train/r_0.png");
    if lego.is_file() {
        return lego;
    }
    let mut img = splat::Image::new(80, 60, 4);
    for (i, v) in img.data.iter_mut().enumerate() {
        *v = ((i * 7) % 255) as f32 / 255.0;
    }
    let p = dir.join("in.png");
    img.save_png(&p).unwrap();
    p
}

#[test]
fn writes_image_attention_and_mask_deterministically() {
    let dir = tempfile::tempdir().unwrap();
    let image = input_image(dir.path());
    let model = repo().join("fixtures/models/tiny-lcm");
    let taesd = shared_assets().join("taesd");
    let mut args: Vec<String> = vec![
        "edit-image".into(),
        "--model".into(),
        model.display().to_string(),
        "--image".into(),
        image.display().to_string(),
        "--source".into(),
        "a yellow toy".into(),
        "--target".into(),
        "a red toy".into(),
        "--size".into(),
        "64".into(),
        "--steps".into(),
        "4".into(),
    ];
    if taesd.join("taesd_encoder.safetensors").is_file() {
        args.extend(["--taesd".into(), taesd.display().to_string()]);
    } else {
        eprintln!("{} absent: using the tiny model's own VAE", taesd.display());
    }
    let run = |out: &Path, attn: Option<&Path>| {
        let mut a = args.clone();
        a.extend(["--out".into(), out.display().to_string()]);
        if let Some(d) = attn {
            a.extend(["--save-attention".into(), d.display().to_string()]);
        }
        let refs: Vec<&str> = a.iter().map(String::as_str).collect();
        let o = vcedit(&refs);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    };
    let (a, b) = (dir.path().join("a.png"), dir.path().join("b.png"));
    let attn = dir.path().join("attn");
    run(&a, Some(&attn));
    run(&b, None);
    let img = splat::Image::load(&a).unwrap();
    assert_eq!((img.width, img.height), (64, 64));
    assert_eq!(
        std::fs::read(&a).unwrap(),
        std::fs::read(&b).unwrap(),
        "same seed, same image"
    );
    let names: Vec<String> = std::fs::read_dir(&attn)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert!(
        names
            .iter()
            .any(|n| n.starts_with("attn_") && n.contains("red")),
        "{names:?}"
    );
    assert!(names.iter().any(|n| n == "mask.png"), "{names:?}");
}

#[test]
fn bad_inputs_give_one_clear_line() {
    let dir = tempfile::tempdir().unwrap();
    let image = input_image(dir.path());
    let model = repo().join("fixtures/models/tiny-lcm");
    let long = "a red sphere ".repeat(40);
    let cases: Vec<(Vec<String>, &str)> = vec![
        (
            vec![
                "--model".into(),
                model.display().to_string(),
                "--image".into(),
                image.display().to_string(),
                "--source".into(),
                "a ball".into(),
                "--target".into(),
                long.clone(),
            ],
            "target prompt",
        ),
        (
            vec![
                "--model".into(),
                dir.path().join("nowhere").display().to_string(),
                "--image".into(),
                image.display().to_string(),
                "--source".into(),
                "a".into(),
                "--target".into(),
                "b".into(),
            ],
            "nowhere",
        ),
        (
            vec![
                "--model".into(),
                model.display().to_string(),
                "--image".into(),
                dir.path().join("missing.png").display().to_string(),
                "--source".into(),
                "a".into(),
                "--target".into(),
                "b".into(),
            ],
            "missing.png",
        ),
        (
            vec![
                "--model".into(),
                model.display().to_string(),
                "--image".into(),
                dir.path().display().to_string(),
                "--source".into(),
                "a".into(),
                "--target".into(),
                "b".into(),
            ],
            "is a folder; give one image file (PNG or JPEG)",
        ),
    ];
    for (mut args, needle) in cases {
        args.insert(0, "edit-image".into());
        args.extend([
            "--out".into(),
            dir.path().join("o.png").display().to_string(),
            "--size".into(),
            "64".into(),
        ]);
        let refs: Vec<&str> = args.iter().map(String::as_str).collect();
        let o = vcedit(&refs);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success(), "{needle}: should fail");
        assert!(err.contains(needle), "{needle}: {err}");
        assert!(!err.contains("panicked"), "{err}");
        assert_eq!(
            err.trim()
                .lines()
                .filter(|l| l.starts_with("error"))
                .count(),
            1,
            "{err}"
        );
        assert!(!dir.path().join("o.png").exists(), "no output on failure");
    }
}
