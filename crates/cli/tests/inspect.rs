//! `vcedit inspect` end to end: the real binary on generated scenes, an INRIA output folder and a
//! malformed file.

use splat::ply::write_ply;
use splat::GaussianScene;
use std::path::Path;
use std::process::{Command, Output};

fn vcedit(args: &[&std::ffi::OsStr]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_vcedit"))
        .arg("inspect")
        .args(args)
        .output()
        .expect("run vcedit")
}

/// n Gaussians on a line from 0 to n-1 along x, opacities sigmoid(logit) spread over (0, 1), scales e^(-k).
fn line_scene(n: usize) -> GaussianScene {
    let k = splat::scene::sh_coeffs(1);
    GaussianScene {
        sh_degree: 1,
        means: (0..n).flat_map(|i| [i as f32, 0.5, -1.0]).collect(),
        log_scales: (0..n)
            .flat_map(|i| [-(i as f32) / 10.0, -5.0, -6.0])
            .collect(),
        quats: (0..n).flat_map(|_| [1.0, 0.0, 0.0, 0.0]).collect(),
        opacity_logits: (0..n)
            .map(|i| (i as f32 - (n as f32 - 1.0) / 2.0) / 5.0)
            .collect(),
        sh: vec![0.1; 3 * k * n],
    }
}

fn json(out: &Output) -> serde_json::Value {
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).expect("valid JSON")
}

#[test]
fn reports_statistics_of_a_generated_ply() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("line.ply");
    let n = 101;
    write_ply(&p, &line_scene(n)).unwrap();

    let out = vcedit(&[p.as_os_str()]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8(out.stdout).unwrap();
    assert!(text.contains("gaussians    101  (SH degree 1"), "{text}");
    assert!(text.contains("cameras      none"), "{text}");

    let v = json(&vcedit(&[p.as_os_str(), "--json".as_ref()]));
    assert_eq!(v["count"], 101);
    assert_eq!(v["sh_degree"], 1);
    assert_eq!(v["bounds"][0], serde_json::json!([0.0, 0.5, -1.0]));
    assert_eq!(v["bounds"][1], serde_json::json!([100.0, 0.5, -1.0]));
    assert_eq!(v["bounds_1_99"][0][0], 1.0);
    // Logits are symmetric around 0: the median opacity is 0.5, the mean too.
    let op = &v["opacity"];
    assert!((op["median"].as_f64().unwrap() - 0.5).abs() < 1e-6);
    assert!((op["mean"].as_f64().unwrap() - 0.5).abs() < 1e-5);
    let sigmoid = |x: f64| 1.0 / (1.0 + (-x).exp());
    assert!((op["max"].as_f64().unwrap() - sigmoid(10.0)).abs() < 1e-6);
    // Largest axis is the x scale e^(-i/10): median at i = 50.
    let sc = &v["max_scale"];
    assert!((sc["median"].as_f64().unwrap() - (-5.0f64).exp()).abs() < 1e-6);
    assert!((sc["max"].as_f64().unwrap() - 1.0).abs() < 1e-6);
    assert!(v["cameras"].is_null());
}

#[test]
fn counts_cameras_of_an_inria_output_folder() {
    let dir = tempfile::tempdir().unwrap();
    write_ply(
        &dir.path()
            .join("point_cloud/iteration_30000/point_cloud.ply"),
        &line_scene(5),
    )
    .unwrap();
    write_ply(
        &dir.path()
            .join("point_cloud/iteration_7000/point_cloud.ply"),
        &line_scene(3),
    )
    .unwrap();
    let camera = r#"{"id": 0, "img_name": "x", "width": 8, "height": 6, "position": [0, 0, -3],
        "rotation": [[1,0,0],[0,1,0],[0,0,1]], "fx": 8, "fy": 8}"#;
    std::fs::write(
        dir.path().join("cameras.json"),
        format!("[{camera}, {camera}]"),
    )
    .unwrap();
    let v = json(&vcedit(&[dir.path().as_os_str(), "--json".as_ref()]));
    assert_eq!(v["count"], 5, "the highest iteration wins");
    assert_eq!(v["cameras"], 2);
    let out = vcedit(&[dir.path().as_os_str()]);
    assert!(String::from_utf8_lossy(&out.stdout).contains("cameras      2"));
}

fn assert_one_line_error(out: &Output, names: &Path, want: &str) {
    assert!(!out.status.success());
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(err.trim_end().lines().count(), 1, "{err}");
    assert!(err.starts_with("error: "), "{err}");
    assert!(err.contains(&names.display().to_string()), "{err}");
    assert!(err.contains(want), "{err}");
    assert!(!err.contains("panicked"), "{err}");
}

#[test]
fn malformed_and_missing_scenes_fail_with_one_line() {
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("broken.ply");
    let mut bytes = Vec::new();
    write_ply(&bad, &line_scene(4)).unwrap();
    bytes.extend_from_slice(&std::fs::read(&bad).unwrap());
    bytes.truncate(bytes.len() - 10);
    std::fs::write(&bad, &bytes).unwrap();
    assert_one_line_error(&vcedit(&[bad.as_os_str()]), &bad, "truncated");

    std::fs::write(
        &bad,
        b"ply\nformat ascii 1.0\nelement vertex 1\nproperty int x\nend_header\n1\n",
    )
    .unwrap();
    assert_one_line_error(
        &vcedit(&[bad.as_os_str()]),
        &bad,
        "property 'x' has type int",
    );

    let missing = dir.path().join("missing.ply");
    assert_one_line_error(&vcedit(&[missing.as_os_str()]), &missing, "no such file");

    let empty_dir = dir.path().join("empty");
    std::fs::create_dir(&empty_dir).unwrap();
    assert_one_line_error(&vcedit(&[empty_dir.as_os_str()]), &empty_dir, "not a scene");
}

#[test]
fn help_shows_an_example() {
    let out = Command::new(env!("CARGO_BIN_EXE_vcedit"))
        .args(["inspect", "--help"])
        .output()
        .unwrap();
    assert!(out.status.success());
    let help = String::from_utf8_lossy(&out.stdout);
    assert!(help.contains("vcedit inspect scene.ply"), "{help}");
}

/// A reader that stops early (`vcedit inspect x.ply | head -1`) ends vcedit quietly: no panic message,
/// and the exit status is success or the SIGPIPE one.
#[cfg(unix)]
#[test]
fn a_closed_pipe_ends_quietly() {
    use std::os::unix::process::ExitStatusExt;
    use std::process::Stdio;
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("line.ply");
    write_ply(&p, &line_scene(20)).unwrap();
    for flags in [&[][..], &["--json"][..]] {
        let mut child = Command::new(env!("CARGO_BIN_EXE_vcedit"))
            .arg("inspect")
            .arg(&p)
            .args(flags)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("run vcedit");
        // Close the reading end before vcedit writes anything.
        drop(child.stdout.take());
        let out = child.wait_with_output().unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!stderr.contains("panicked"), "{stderr}");
        assert!(
            out.status.success() || out.status.signal() == Some(libc_sigpipe()),
            "{:?}: {stderr}",
            out.status
        );
    }
}

/// SIGPIPE's number on every Unix vcedit builds for.
#[cfg(unix)]
fn libc_sigpipe() -> i32 {
    13
}

/// Every command's `--help` examples copy-paste: a line of an example that is not a new `vcedit` command
/// continues one that ends in a backslash, and every line fits an 80-column terminal (so clap never
/// wraps one mid-command).
#[test]
fn help_examples_copy_paste() {
    for command in [
        &["inspect"][..],
        &["demo"],
        &["render"],
        &["view"],
        &["fit"],
        &["edit-image"],
        &["edit"],
        &["metrics"],
        &["convert"],
        &["model", "check"],
        &["demo-model", "train"],
        &["demo-model", "sample"],
        &["bench"],
    ] {
        let out = Command::new(env!("CARGO_BIN_EXE_vcedit"))
            .args(command)
            .arg("--help")
            .output()
            .unwrap();
        let help = String::from_utf8_lossy(&out.stdout);
        let Some((_, examples)) = help.split_once("Examples:\n") else {
            panic!("{command:?} --help has no examples:\n{help}");
        };
        let mut previous = "";
        for line in examples.lines().take_while(|l| !l.trim().is_empty()) {
            assert!(
                line.chars().count() <= 80,
                "{command:?} --help: '{line}' is wider than an 80-column terminal"
            );
            assert!(
                line.starts_with("  vcedit ") || previous.ends_with('\\'),
                "{command:?} --help: '{line}' continues '{previous}' without a backslash"
            );
            previous = line;
        }
    }
}

/// A prompt option has one name in every command that takes prompts (`edit`'s `--source`/`--target` are
/// also `--source-prompt`/`--target-prompt`, as in `metrics`), and no command uses `--source` for a scene.
#[test]
fn prompt_options_share_their_names() {
    for command in ["edit", "edit-image", "metrics"] {
        let out = Command::new(env!("CARGO_BIN_EXE_vcedit"))
            .args([command, "--help"])
            .output()
            .unwrap();
        let help = String::from_utf8_lossy(&out.stdout);
        for name in ["--source-prompt", "--target-prompt"] {
            assert!(help.contains(name), "{command} --help lacks {name}");
        }
    }
    let out = Command::new(env!("CARGO_BIN_EXE_vcedit"))
        .args(["metrics", "--help"])
        .output()
        .unwrap();
    let help = String::from_utf8_lossy(&out.stdout);
    assert!(help.contains("--source-scene <SCENE>"), "{help}");
    assert!(!help.contains("--source <"), "{help}");
}

/// `--json=FILE` or `--json FILE` (as in `metrics`) writes the JSON to a file and prints the text; the
/// file must be named *.json, so a scene named after `--json` is never taken for the output
/// (`inspect --json a.ply b.ply` would overwrite a.ply); `inspect --json scene.ply` prints the JSON.
#[test]
fn json_to_a_file_takes_a_json_name_with_or_without_the_equals_sign() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("line.ply");
    write_ply(&p, &line_scene(20)).unwrap();
    let stats = dir.path().join("stats.json");
    let mut flag = std::ffi::OsString::from("--json=");
    flag.push(&stats);
    let out = vcedit(&[p.as_os_str(), flag.as_os_str()]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(String::from_utf8_lossy(&out.stdout).contains("gaussians"));
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&stats).unwrap()).unwrap();
    assert_eq!(v["count"], 20);

    // The metrics spelling, the value apart.
    let spaced = dir.path().join("spaced.json");
    let out = vcedit(&[p.as_os_str(), "--json".as_ref(), spaced.as_os_str()]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(String::from_utf8_lossy(&out.stdout).contains("gaussians"));
    assert!(std::fs::read_to_string(&spaced)
        .unwrap()
        .contains("\"count\": 20"));
    // The flag first, the scene after it: JSON on stdout.
    let v = json(&vcedit(&["--json".as_ref(), p.as_os_str()]));
    assert_eq!(v["count"], 20);

    let other = dir.path().join("other.ply");
    std::fs::copy(&p, &other).unwrap();
    let before = std::fs::read(&other).unwrap();
    let out = vcedit(&["--json".as_ref(), other.as_os_str(), p.as_os_str()]);
    assert!(!out.status.success());
    assert_eq!(
        std::fs::read(&other).unwrap(),
        before,
        "a scene was overwritten"
    );
    // Nor may the JSON go over the scene it describes.
    let mut over = std::ffi::OsString::from("--json=");
    over.push(&p);
    let before = std::fs::read(&p).unwrap();
    let out = vcedit(&[p.as_os_str(), over.as_os_str()]);
    assert!(!out.status.success());
    assert_eq!(std::fs::read(&p).unwrap(), before);
}
