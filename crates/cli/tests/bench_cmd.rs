//! `vcedit bench` end to end on the CPU with the tiny fixture pipeline: each model-folder bench prints its
//! `RESULT` lines (what tools/gpu-check parses), and bad input is one line with a non-zero exit.

use std::process::{Command, Output};
use testkit::paths::tiny_lcm;

fn vcedit(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_vcedit"))
        .args(args)
        .env("XDG_RUNTIME_DIR", std::env::temp_dir())
        .output()
        .unwrap()
}

/// The JSON of every `RESULT` line.
fn results(out: &Output) -> Vec<serde_json::Value> {
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .filter_map(|l| l.strip_prefix("RESULT "))
        .map(|j| serde_json::from_str(j).unwrap())
        .collect()
}

#[test]
fn model_folder_benches_report_first_and_warm_calls() {
    let model = tiny_lcm();
    let model = model.to_str().unwrap();
    let cases: [(&[&str], &str, usize); 3] = [
        (
            &[
                "unet",
                "--model",
                model,
                "--size",
                "8",
                "--batches",
                "1,6",
                "--hooks",
                "none,device",
            ],
            "unet",
            4,
        ),
        (&["codec", "--model", model, "--size", "32"], "codec", 2),
        (&["text", "--model", model, "--batches", "2"], "text", 2),
    ];
    for (args, bench, count) in cases {
        let mut full = vec!["bench"];
        full.extend_from_slice(args);
        full.extend_from_slice(&["--device", "cpu", "--runs", "1"]);
        let out = vcedit(&full);
        assert!(
            out.status.success(),
            "{args:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        let r = results(&out);
        assert_eq!(r.len(), count, "{args:?}: {r:?}");
        for line in &r {
            assert_eq!(line["bench"], bench);
            for field in ["first_s", "best_s", "median_s"] {
                let v = line[field].as_f64().unwrap_or(-1.0);
                assert!(v >= 0.0, "{args:?}: {field} in {line}");
            }
        }
    }
}

#[test]
fn bad_input_is_one_line() {
    let out = vcedit(&["bench", "unet", "--batches", "x", "--device", "cpu"]);
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("--batches: cannot read 'x'"), "{err}");
    let missing = std::env::temp_dir().join("vcedit-no-such-model");
    let out = vcedit(&["bench", "codec", "--model", missing.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("vcedit-no-such-model") && !err.contains("panicked"),
        "{err}"
    );
    let out = vcedit(&["bench", "nonesuch"]);
    assert_eq!(
        out.status.code(),
        Some(2),
        "an unknown bench is a usage error"
    );
}

/// A machine without XDG_RUNTIME_DIR (containers, CI) gets no window-system complaints from the Vulkan
/// driver's probe (Mesa 22's lavapipe printed one line per probe).
#[test]
fn probing_the_gpu_is_quiet_without_a_runtime_dir() {
    let out = Command::new(env!("CARGO_BIN_EXE_vcedit"))
        .args(["bench", "device", "--device", "auto"])
        .env_remove("XDG_RUNTIME_DIR")
        .output()
        .expect("run vcedit");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!stderr.contains("XDG_RUNTIME_DIR"), "{stderr}");
}

/// A GPU run started inside a Rust project leaves the project alone: cubecl's kernel and tuning caches go
/// to vcedit's user cache folder, not to `target/environment` under the outermost `Cargo.toml` (cubecl's
/// default), and a `cubecl.toml` in the working directory is not read.
#[test]
fn gpu_caches_go_to_the_user_cache_folder() {
    let root = tempfile::tempdir().unwrap();
    let (project, cache) = (root.path().join("project"), root.path().join("cache"));
    std::fs::create_dir_all(&project).unwrap();
    std::fs::write(project.join("Cargo.toml"), "[workspace]\n").unwrap();
    // Would turn every launch into a bounds-checking one, and log to a file in the project.
    std::fs::write(
        project.join("cubecl.toml"),
        "[compilation.logger]\nlevel = \"full\"\nfile = \"cubecl.log\"\n",
    )
    .unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_vcedit"))
        .args(["bench", "matmul", "--device", "gpu", "--precisions", "f32"])
        .args(["--shapes", "64x32x32", "--repeat", "1", "--runs", "1"])
        .current_dir(&project)
        .env("XDG_RUNTIME_DIR", std::env::temp_dir())
        .env("XDG_CACHE_HOME", &cache)
        .output()
        .unwrap();
    if !out.status.success() {
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(stderr.contains("no GPU"), "{stderr}");
        println!("SKIP: no GPU adapter");
        return;
    }
    let mut left: Vec<_> = std::fs::read_dir(&project)
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    left.sort();
    assert_eq!(
        left,
        ["Cargo.toml", "cubecl.toml"],
        "the project gained files"
    );
    let kept = cache.join("vcedit").join("cubecl");
    assert!(
        std::fs::read_dir(&kept).is_ok_and(|mut d| d.next().is_some()),
        "nothing cached in {}",
        kept.display()
    );
}

/// `--device cuda` where CUDA cannot run (here: no NVIDIA driver, or a build without the runtime) is one
/// error line naming why, exit code 1, no panic, and no output folder; a bad `VCEDIT_GPU_RUNTIME` is one
/// line too.
#[test]
fn cuda_without_cuda_is_one_line_before_any_output() {
    if std::path::Path::new("/dev/nvidia0").exists() {
        println!("SKIP: this machine has an NVIDIA card");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let out_dir = dir.path().join("demo");
    let out = Command::new(env!("CARGO_BIN_EXE_vcedit"))
        .args(["demo", "--device", "cuda", "--out"])
        .arg(&out_dir)
        .env("XDG_CACHE_HOME", dir.path().join("cache"))
        .output()
        .expect("run vcedit");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    let last = stderr.lines().last().unwrap_or_default();
    assert!(last.starts_with("error: CUDA unavailable: "), "{stderr}");
    assert!(
        last.contains("NVIDIA driver") || last.contains("built without"),
        "{stderr}"
    );
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert!(!out_dir.exists(), "the demo made its folder");

    let out = Command::new(env!("CARGO_BIN_EXE_vcedit"))
        .args(["bench", "device", "--device", "gpu"])
        .env("VCEDIT_GPU_RUNTIME", "opencl")
        .output()
        .expect("run vcedit");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_ne!(out.status.code(), Some(0), "{stderr}");
    assert!(stderr.contains("unknown GPU runtime 'opencl'"), "{stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
}

/// `vcedit bench NAME --help` prints that bench's own help (what it measures, its options), wherever
/// `--help` stands; `vcedit bench --help` the list.
#[test]
fn each_bench_has_its_own_help() {
    for args in [
        &["bench", "unet", "--help"][..],
        &["bench", "unet", "-h"],
        &["bench", "unet", "--batches", "1", "--help"],
    ] {
        let o = vcedit(args);
        let stdout = String::from_utf8_lossy(&o.stdout);
        assert!(
            o.status.success(),
            "{args:?}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        assert!(
            stdout.starts_with("vcedit bench unet: "),
            "{args:?}: {stdout}"
        );
        assert!(
            stdout.contains("--batches") && stdout.contains("--hooks"),
            "{stdout}"
        );
        assert!(!stdout.contains("crates/bench/src"), "{stdout}");
        assert!(results(&o).is_empty(), "nothing is measured: {stdout}");
    }
    let o = vcedit(&["bench", "--help"]);
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success());
    assert!(stdout.contains("vcedit bench NAME --help"), "{stdout}");
    // No bench named: a usage error.
    let o = vcedit(&["bench"]);
    assert_eq!(o.status.code(), Some(2));
}
