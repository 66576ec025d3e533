//! `vcedit demo-model` end to end: a tiny training run and sampling through the binary, and the committed
//! demo model (`models/demo`) turning a red sphere into a blue one with `vcedit edit-image`.

use std::path::Path;
use std::process::Command;

use demo::world::build::{build_scene, BuildSettings, MAIN};
use demo::world::dataset::{render_view, ring_views};
use demo::world::oracle::render_labels;
use demo::world::{GeneratorSettings, SceneSpec};
use splat::Image;
use testkit::paths::repo;

fn vcedit(args: &[&str]) -> (i32, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_vcedit"))
        .args(args)
        .output()
        .unwrap();
    (
        out.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn tiny_train_then_sample_through_the_cli() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("tiny");
    let out_s = out.to_str().unwrap();
    let args = [
        "demo-model",
        "train",
        "--out",
        out_s,
        "--preset",
        "tiny",
        "--codec-steps",
        "5",
        "--unet-steps",
        "5",
    ];
    let (code, stdout, stderr) = vcedit(&args);
    assert_eq!(code, 0, "{stderr}");
    // The exact command is printed and recorded in the model's README.
    assert!(
        stdout.starts_with("vcedit demo-model train --out"),
        "{stdout}"
    );
    let readme = std::fs::read_to_string(out.join("README.md")).unwrap();
    assert!(
        readme.contains("--preset tiny --codec-steps 5 --unet-steps 5"),
        "{readme}"
    );
    // Plain progress lines when stderr is not a terminal.
    assert!(stderr.contains("unet: 5/5"), "{stderr}");

    let (code, _, stderr) = vcedit(&["model", "check", out_s]);
    assert_eq!(code, 0, "{stderr}");

    let grid = dir.path().join("grid.png");
    let sample =
        |args: &[&str]| vcedit(&[&["demo-model", "sample", "--model", out_s][..], args].concat());
    let (code, _, stderr) = sample(&[
        "--prompt",
        "a red sphere",
        "--prompt",
        "a blue cube",
        "--per-prompt",
        "2",
        "--steps",
        "2",
        "--out",
        grid.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{stderr}");
    let img = Image::load(&grid).unwrap();
    // 2×2 tiles of 32² with 2-pixel gaps.
    assert_eq!((img.width, img.height), (2 * 32 + 6, 2 * 32 + 6));
    let captions = std::fs::read_to_string(grid.with_extension("txt")).unwrap();
    assert_eq!(captions, "a red sphere\na blue cube\n");

    // A prompt outside the text encoder's reach is a one-line error, not a panic.
    let long = "red ".repeat(100);
    let (code, _, stderr) = sample(&[
        "--prompt",
        &long,
        "--steps",
        "1",
        "--out",
        grid.to_str().unwrap(),
        "--force",
    ]);
    assert_eq!(code, 1);
    assert!(
        stderr.starts_with("error:") && stderr.contains("too long"),
        "{stderr}"
    );
}

/// Mean RGB of the pixels where `mask` holds.
fn mean_colour(img: &Image, mask: &[bool]) -> [f32; 3] {
    let mut sum = [0f32; 3];
    let mut n = 0f32;
    for (p, px) in img.data.chunks_exact(img.channels as usize).enumerate() {
        if mask[p] {
            (0..3).for_each(|c| sum[c] += px[c]);
            n += 1.0;
        }
    }
    sum.map(|s| s / n.max(1.0))
}

#[test]
fn demo_model_edits_a_red_sphere_into_a_blue_sphere() {
    let model = repo().join("models/demo");
    if !model
        .join("unet/diffusion_pytorch_model.safetensors")
        .is_file()
    {
        println!("SKIP: {} has no trained demo model", model.display());
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    // A red sphere from the side, at the model's 128² resolution.
    let spec = SceneSpec::from_caption("a red sphere", 3, &GeneratorSettings::default()).unwrap();
    let built = build_scene(&spec, &BuildSettings::default());
    let camera = &ring_views(&spec, 1, 128, 128, 20.0, 30.0)[0];
    let source = render_view(&built, camera);
    let input = dir.path().join("red.png");
    source.save_png(&input).unwrap();
    let labels = render_labels(&built, camera);
    let object: Vec<bool> = labels.object.iter().map(|&o| o == MAIN).collect();
    // The far background (not the object, with a margin) must be kept.
    let outside: Vec<bool> = (0..object.len())
        .map(|p| {
            let (x, y) = ((p % 128) as i64, (p / 128) as i64);
            !(-8..=8).any(|dy| {
                (-8..=8).any(|dx| {
                    let (u, v) = (x + dx, y + dy);
                    (0..128).contains(&u) && (0..128).contains(&v) && object[(v * 128 + u) as usize]
                })
            })
        })
        .collect();
    assert!(object.iter().filter(|&&o| o).count() > 128 * 128 / 10);

    let output = dir.path().join("blue.png");
    // `vcedit edit-image` of the red sphere into "a blue sphere" at 128², writing `out`.
    let edit_image = |extra: &[&str], out: &Path| {
        let mut args = vec![
            "edit-image",
            "--model",
            model.to_str().unwrap(),
            "--image",
            input.to_str().unwrap(),
            "--source",
            "a red sphere",
            "--target",
            "a blue sphere",
            "--size",
            "128",
            "--out",
            out.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        vcedit(&args)
    };
    // The small model's settings (see `demo::run::demo_infedit_settings`): the target's own
    // cross-attention for most steps, a looser blend threshold than SD's defaults, and the maps of the
    // level where its words localize.
    let edit = |thresh: &str| {
        // Both runs write the one output: the second replaces the first (--force).
        let settings = [
            "--cross",
            "0.3",
            "--thresh-e",
            thresh,
            "--blend-level",
            "1",
            "--force",
        ];
        edit_image(&settings, &output)
    };
    // An edit that cannot change anything (an empty blend region) ends with a warning naming the knobs.
    let (code, _, stderr) = edit("1");
    assert_eq!(code, 0, "{stderr}");
    assert!(
        stderr.contains("warning: the edit's blend region is empty"),
        "{stderr}"
    );
    assert!(stderr.contains("--thresh-e"), "{stderr}");
    // A blend level without cross-attention is one error line naming the levels that have it, before
    // any work (no output written).
    let never = dir.path().join("never.png");
    let (code, _, stderr) = edit_image(&["--blend-level", "0"], &never);
    assert_eq!(code, 1, "{stderr}");
    let errors: Vec<&str> = stderr.lines().filter(|l| l.starts_with("error")).collect();
    assert_eq!(errors.len(), 1, "{stderr}");
    assert!(errors[0].contains("--blend-level"), "{stderr}");
    assert!(errors[0].contains("levels with it: 1, 2"), "{stderr}");
    assert!(!never.exists());
    let (code, _, stderr) = edit("0.3");
    assert_eq!(code, 0, "{stderr}");
    assert!(!stderr.contains("warning"), "{stderr}");
    let edited = Image::load(&output).unwrap();
    let before = mean_colour(&source, &object);
    let after = mean_colour(&edited, &object);
    println!("object colour before {before:?} after {after:?}");
    assert!(
        before[0] > 2.0 * before[2],
        "the input sphere is red: {before:?}"
    );
    assert!(
        after[2] > after[0] + 0.15 && after[2] > after[1] + 0.1,
        "the edited sphere is blue: {after:?}"
    );
    let keep_before = mean_colour(&source, &outside);
    let keep_after = mean_colour(&edited, &outside);
    let drift: f32 = (0..3)
        .map(|c| (keep_before[c] - keep_after[c]).abs())
        .sum::<f32>()
        / 3.0;
    println!("background before {keep_before:?} after {keep_after:?} (drift {drift:.3})");
    assert!(
        drift < 0.08,
        "the background is preserved: {keep_before:?} vs {keep_after:?}"
    );
}
