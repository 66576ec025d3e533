//! `vcedit demo` reduced to a few views and steps: the whole mission through the binary, checking every
//! output the full demo promises. Uses the committed demo model when present, otherwise a tiny one trained
//! here in a second, so the pipeline is exercised either way (the full demo is not run in CI).

use std::path::{Path, PathBuf};
use std::process::Command;

fn vcedit(args: &[&str], cwd: &Path) -> (i32, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_vcedit"))
        .args(args)
        .current_dir(cwd)
        .output()
        .unwrap();
    (
        out.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// The committed model, or a tiny freshly trained one.
fn model(dir: &Path) -> PathBuf {
    let committed = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../models/demo");
    if committed
        .join("unet/diffusion_pytorch_model.safetensors")
        .is_file()
    {
        return committed;
    }
    println!("no committed demo model; training a tiny one");
    let out = dir.join("tiny-model");
    let (code, _, stderr) = vcedit(
        &[
            "demo-model",
            "train",
            "--out",
            out.to_str().unwrap(),
            "--preset",
            "tiny",
            "--codec-steps",
            "3",
            "--unet-steps",
            "3",
        ],
        dir,
    );
    assert_eq!(code, 0, "{stderr}");
    out
}

/// `vcedit demo` with 3 views, 1 iteration and 5 fit steps, plus `extra` arguments.
fn reduced_demo(dir: &Path, model: &Path, out: &Path, extra: &[&str]) -> (i32, String, String) {
    let mut args = vec![
        "demo",
        "--model",
        model.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--views",
        "3",
        "--iterations",
        "1",
        "--fit-steps",
        "5",
    ];
    args.extend_from_slice(extra);
    vcedit(&args, dir)
}

#[test]
fn reduced_demo_writes_every_output() {
    let dir = tempfile::tempdir().unwrap();
    let model = model(dir.path());
    let out = dir.path().join("demo-out");
    let (code, stdout, stderr) = reduced_demo(dir.path(), &model, &out, &["--steps", "2"]);
    assert_eq!(code, 0, "{stderr}");
    for file in [
        "edited.ply",
        "report.html",
        "turntable.gif",
        "before/view_000.png",
        "after/view_000.png",
        "run.json",
    ] {
        assert!(out.join(file).is_file(), "{file} missing; stdout {stdout}");
    }
    assert!(stdout.contains("VcEdit (full) ("), "{stdout}");
    assert!(stdout.contains("shape: silhouette IoU"), "{stdout}");
    assert!(
        stdout.lines().all(|l| l.chars().count() <= 80),
        "the summary fits 80 columns: {stdout}"
    );
    assert!(
        stdout.contains(&format!("report: {}", out.join("report.html").display())),
        "{stdout}"
    );
    // The source scene is there too, so the printed `vcedit view` line compares before and after.
    // (Relative to the folder the demo ran in, so that it fits a line.)
    let view_line = "compare in 3D: vcedit view demo-out/source.ply demo-out/edited.ply";
    assert!(stdout.contains(view_line), "{stdout}");
    let page = dir.path().join("compare.html");
    let (code, _, stderr) = vcedit(
        &[
            "view",
            out.join("source.ply").to_str().unwrap(),
            out.join("edited.ply").to_str().unwrap(),
            "--out",
            page.to_str().unwrap(),
        ],
        dir.path(),
    );
    assert_eq!(code, 0, "{stderr}");
    assert!(page.is_file());
    // The same demo again: finished, so nothing is done (and the outputs are named again).
    let edited = std::fs::read(out.join("edited.ply")).unwrap();
    let (code, again, stderr) = reduced_demo(dir.path(), &model, &out, &["--steps", "2"]);
    assert_eq!(code, 0, "{stderr}");
    assert!(
        stderr.contains("holds this run already, finished"),
        "{stderr}"
    );
    assert!(!stderr.contains("work:"), "no plan, no work: {stderr}");
    assert!(again.contains(view_line), "{again}");
    assert_eq!(std::fs::read(out.join("edited.ply")).unwrap(), edited);
    // The edited scene is a valid scene the other commands accept.
    let (code, inspect, stderr) = vcedit(
        &["inspect", out.join("edited.ply").to_str().unwrap()],
        dir.path(),
    );
    assert_eq!(code, 0, "{stderr}");
    assert!(inspect.contains("gaussians"), "{inspect}");

    // `--resume` continues from the last checkpoint: here the run is complete, so nothing is recomputed
    // and the scene is the same.
    let before = std::fs::read(out.join("edited.ply")).unwrap();
    let (code, _, stderr) = reduced_demo(dir.path(), &model, &out, &["--steps", "2", "--resume"]);
    assert_eq!(code, 0, "{stderr}");
    assert_eq!(std::fs::read(out.join("edited.ply")).unwrap(), before);
    assert!(stderr.contains("resuming after iteration 1"), "{stderr}");
    let report = std::fs::read_to_string(out.join("report.html")).unwrap();
    assert!(report.contains("resumed after iteration 1"));
    // The report carries the oracle's scores, shape included.
    assert!(
        report.contains("silhouette IoU against the ideal edit"),
        "no oracle line in the report"
    );
}

/// A reduced `--compare`: five steps, so ECM (every fifth step) runs once in the variants that use it.
#[test]
fn reduced_compare_writes_the_table_and_every_variant() {
    let dir = tempfile::tempdir().unwrap();
    let model = model(dir.path());
    let out = dir.path().join("compare-out");
    let (code, stdout, stderr) =
        reduced_demo(dir.path(), &model, &out, &["--compare", "--steps", "5"]);
    assert_eq!(code, 0, "{stderr}");
    let md = std::fs::read_to_string(out.join("compare.md")).unwrap();
    for row in [
        "| per-view guidance |",
        "| VcEdit without CCM |",
        "| VcEdit without ECM |",
        "| VcEdit (full) |",
        "| source through the autoencoder |",
        "| ideal edit through the autoencoder |",
    ] {
        assert!(md.contains(row), "{row} missing: {md}");
    }
    // The terminal gets a plain summary per run, within 80 columns, and where the table is.
    for run in [
        "per-view guidance (",
        "VcEdit without CCM (",
        "VcEdit without ECM (",
        "VcEdit (full) (",
    ] {
        assert!(stdout.contains(run), "{run} missing: {stdout}");
    }
    assert!(stdout.lines().all(|l| l.chars().count() <= 80), "{stdout}");
    assert!(
        stdout.contains(&format!("table: {}", out.join("compare.md").display())),
        "{stdout}"
    );
    for variant in ["per-view", "no-ccm", "no-ecm", "full"] {
        assert!(out.join(variant).join("report.html").is_file(), "{variant}");
    }
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("compare.json")).unwrap()).unwrap();
    assert_eq!(json["runs"].as_array().unwrap().len(), 4, "{json}");
    assert_eq!(json["references"].as_array().unwrap().len(), 4, "{json}");
    // Every run and reference row has shape scores in 0..=1 (the ideal edit's silhouette is its own).
    for run in json["runs"].as_array().unwrap() {
        for key in ["silhouette_iou", "guidance_silhouette_iou"] {
            let v = run[key].as_f64().unwrap_or(-1.0);
            assert!((0.0..=1.0).contains(&v), "{key} {v}: {run}");
        }
        assert!(run["outside_change"].as_f64().unwrap() >= 0.0, "{run}");
    }
    let ideal = &json["references"][2];
    assert_eq!(ideal["silhouette_iou"].as_f64(), Some(1.0), "{ideal}");
    assert!(md.contains("silhouette IoU"), "{md}");
}

#[test]
fn demo_rejects_bad_options_with_one_line() {
    let dir = tempfile::tempdir().unwrap();
    let (code, stdout, _) = vcedit(&["demo", "--list"], dir.path());
    assert_eq!(code, 0);
    assert!(
        stdout.starts_with("0: \"a red sphere\" → \"a blue sphere\""),
        "{stdout}"
    );

    let missing = dir.path().join("no-such-model");
    let (code, _, stderr) = vcedit(
        &["demo", "--model", missing.to_str().unwrap(), "--out", "x"],
        dir.path(),
    );
    assert_eq!(code, 1);
    assert!(
        stderr.starts_with("error:") && stderr.contains("not a model folder"),
        "{stderr}"
    );
    assert_eq!(stderr.trim_end().lines().count(), 1, "{stderr}");

    let (code, _, stderr) = vcedit(&["demo", "--pair", "99", "--out", "x"], dir.path());
    assert_eq!(code, 2, "a usage error");
    assert!(stderr.contains("--pair 99"), "{stderr}");
}

/// The demo model is built into the binary: a copy of `vcedit` alone, run in an empty folder far from the
/// checkout, runs the demo (its model written once into the cache folder, reused the next time).
#[test]
fn a_copied_binary_runs_its_own_demo() {
    let dir = tempfile::tempdir().unwrap();
    let bin = dir.path().join("vcedit");
    std::fs::copy(env!("CARGO_BIN_EXE_vcedit"), &bin).unwrap();
    let work = dir.path().join("work");
    std::fs::create_dir(&work).unwrap();
    let cache = dir.path().join("cache");
    let run = |out: &str| {
        Command::new(&bin)
            .args([
                "demo",
                "--out",
                out,
                "--views",
                "2",
                "--iterations",
                "1",
                "--fit-steps",
                "3",
                "--steps",
                "2",
                "--device",
                "cpu",
            ])
            .env("XDG_CACHE_HOME", &cache)
            .current_dir(&work)
            .output()
            .unwrap()
    };
    let o = run("a");
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(0), "{stderr}");
    assert!(work.join("a/edited.ply").is_file());
    let models: Vec<_> = std::fs::read_dir(cache.join("vcedit")).unwrap().collect();
    assert_eq!(models.len(), 1);
    let model = models[0].as_ref().unwrap().path();
    assert!(model
        .join("unet/diffusion_pytorch_model.safetensors")
        .is_file());
    let written = std::fs::metadata(model.join("unet/config.json"))
        .unwrap()
        .modified()
        .unwrap();
    let o = run("b");
    assert_eq!(
        o.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
    let again = std::fs::metadata(model.join("unet/config.json"))
        .unwrap()
        .modified()
        .unwrap();
    assert_eq!(
        written, again,
        "the cached model is reused, not written again"
    );

    // `--model demo` names the same built-in model in the model commands (where no folder `demo` exists).
    let check = Command::new(&bin)
        .args(["model", "check", "demo", "--headers-only"])
        .env("XDG_CACHE_HOME", &cache)
        .current_dir(&work)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&check.stdout);
    assert_eq!(
        check.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&check.stderr)
    );
    assert!(stdout.contains(&model.display().to_string()), "{stdout}");
    let edited = work.join("blue.png");
    let o = Command::new(&bin)
        .args([
            "edit-image",
            "--model",
            "demo",
            "--image",
            work.join("a/before/view_000.png").to_str().unwrap(),
            "--source",
            "a red sphere",
            "--target",
            "a blue sphere",
            "--size",
            "128",
            "--steps",
            "2",
            "--device",
            "cpu",
            "--out",
            edited.to_str().unwrap(),
        ])
        .env("XDG_CACHE_HOME", &cache)
        .current_dir(&work)
        .output()
        .unwrap();
    assert_eq!(
        o.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(edited.is_file());
}
