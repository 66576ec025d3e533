//! End to end: `vcedit edit` on the tiny conformance model and a small self-made scene.

use std::collections::HashSet;
use std::path::Path;
use std::process::Command;

use splat::GaussianScene;
use testkit::paths::fixtures;

/// Two blobs of small Gaussians: one at the origin (to edit), one at x = 1.6 (to keep).
fn two_blobs() -> GaussianScene {
    let mut s = GaussianScene::new(1);
    let mut k = 0u32;
    let mut rnd = || {
        k = k.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
        (k >> 8) as f32 / (1u32 << 24) as f32
    };
    for centre in [[0.0f32, 0.0, 0.0], [1.6, 0.0, 0.0]] {
        for _ in 0..600 {
            let (u, v, w) = (rnd() * 2.0 - 1.0, rnd() * 2.0 - 1.0, rnd() * 2.0 - 1.0);
            s.means.extend_from_slice(&[
                centre[0] + 0.5 * u,
                centre[1] + 0.5 * v,
                centre[2] + 0.5 * w,
            ]);
            s.log_scales.extend_from_slice(&[(0.06f32).ln(); 3]);
            s.quats.extend_from_slice(&[1.0, 0.1 * rnd(), 0.0, 0.0]);
            s.opacity_logits.push(2.0);
            s.sh.extend_from_slice(&[rnd() - 0.5, rnd() - 0.5, rnd() - 0.5]);
            s.sh.extend(std::iter::repeat_n(0.0, 9));
        }
    }
    s
}

fn inside(p: &[f32]) -> bool {
    p.iter().all(|v| v.abs() <= 0.8)
}

fn gaussian_key(s: &GaussianScene, i: usize) -> Vec<u32> {
    let k = s.sh_coeffs() * 3;
    s.means[3 * i..3 * i + 3]
        .iter()
        .chain(&s.log_scales[3 * i..3 * i + 3])
        .chain(&s.quats[4 * i..4 * i + 4])
        .chain(std::iter::once(&s.opacity_logits[i]))
        .chain(&s.sh[k * i..k * (i + 1)])
        .map(|v| v.to_bits())
        .collect()
}

/// The test runs' settings: 4 views, 4 steps, 2 iterations (40 UNet passes).
const RUN_SETTINGS: [&str; 17] = [
    "--size",
    "64",
    "--steps",
    "4",
    "--max-views",
    "4",
    "--iterations",
    "2",
    "--fit-steps",
    "30",
    "--ccm-steps",
    "1",
    "--ecm-steps",
    "2",
    "--mask-box=-0.8,-0.8,-0.8,0.8,0.8,0.8",
    "--orbit",
    "6",
];

fn run_edit(scene: &Path, out: &Path, extra: &[&str]) -> std::process::Output {
    run_edit_with(scene, out, &RUN_SETTINGS, extra)
}

fn run_edit_with(
    scene: &Path,
    out: &Path,
    settings: &[&str],
    extra: &[&str],
) -> std::process::Output {
    edit_command(scene, out, settings, extra)
        .output()
        .expect("run vcedit")
}

fn edit_command(scene: &Path, out: &Path, settings: &[&str], extra: &[&str]) -> Command {
    let mut command = Command::new(env!("CARGO_BIN_EXE_vcedit"));
    command
        .args(["edit", "--scene"])
        .arg(scene)
        .arg("--model")
        .arg(fixtures().join("models/tiny-lcm"))
        .args(["--source", "a ball", "--target", "a red ball", "--out"])
        .arg(out)
        .args(settings)
        .args(extra);
    command
}

/// Ctrl-C in the middle of a run: one line naming the folder and `--resume`, the shell's status for
/// SIGINT (130), and `--resume` then finishes the run.
#[cfg(unix)]
#[test]
fn ctrl_c_says_how_to_resume_and_the_run_resumes() {
    use std::io::{BufRead, Read};
    let dir = tempfile::tempdir().unwrap();
    let scene_path = dir.path().join("blobs.ply");
    splat::ply::write_ply(&scene_path, &two_blobs()).unwrap();
    let out = dir.path().join("out");
    let mut child = edit_command(&scene_path, &out, &RUN_SETTINGS, &[])
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let mut stderr = std::io::BufReader::new(child.stderr.take().unwrap());
    let mut seen = String::new();
    // Interrupt during the second of two iterations, after the first one's checkpoint.
    loop {
        let mut line = String::new();
        assert!(
            stderr.read_line(&mut line).unwrap() > 0,
            "no iteration line: {seen}"
        );
        seen.push_str(&line);
        if line.contains("iteration 1 done") {
            break;
        }
    }
    // SAFETY: a signal to the child this test spawned.
    unsafe { libc::kill(child.id() as libc::pid_t, libc::SIGINT) };
    stderr.read_to_string(&mut seen).unwrap();
    let status = child.wait().unwrap();
    assert_eq!(status.code(), Some(130), "{seen}");
    let said = format!(
        "interrupted: {} keeps every finished iteration; the same command with --resume continues",
        out.display()
    );
    assert!(seen.contains(&said), "{seen}");
    assert!(!out.join("edited.ply").exists());

    let o = run_edit(&scene_path, &out, &["--resume"]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "--resume failed: {stderr}");
    assert!(out.join("edited.ply").exists());
}

/// A run of 52 UNet passes (4 views × 13) is timed first: the estimate is printed with the work plan and
/// kept in run.json beside the measured timings; `--no-estimate` skips it.
#[test]
fn a_long_run_prints_a_time_estimate_first() {
    let dir = tempfile::tempdir().unwrap();
    let scene_path = dir.path().join("blobs.ply");
    splat::ply::write_ply(&scene_path, &two_blobs()).unwrap();
    let mut long = RUN_SETTINGS;
    for (option, value) in [
        ("--steps", "12"),
        ("--iterations", "1"),
        ("--fit-steps", "5"),
    ] {
        let at = long.iter().position(|a| *a == option).unwrap();
        long[at + 1] = value;
    }
    let out = dir.path().join("out");
    let o = run_edit_with(&scene_path, &out, &long, &[]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "vcedit edit failed: {stderr}");
    let plan = stderr.find("52 UNet passes").expect("work plan");
    // The UNet is timed on one view at small latents first, then larger while that stays quick, and
    // each probe is said (the run's own 16² latents are quick here, so the last probe is the run's size).
    assert!(
        stderr.contains("UNet, one view, from 8×8 latents up (≤ 30 s), scaled to 16×16 × 1 view:")
            && stderr.contains("UNet at 8×8: ")
            && stderr.contains("UNet at 16×16: "),
        "{stderr}"
    );
    let estimate = stderr.find("time ≈").expect("time estimate");
    let first_iteration = stderr.find("iteration 1 done").expect("iteration line");
    assert!(plan < estimate && estimate < first_iteration, "{stderr}");
    let run: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("run.json")).unwrap()).unwrap();
    let e = &run["estimate"];
    let unit = |k: &str| e["calibration"][k].as_f64().unwrap();
    assert!(
        unit("unet_call") > 0.0 && unit("render") > 0.0 && unit("lift") > 0.0,
        "{e}"
    );
    assert!(
        e["total"].as_f64().unwrap() >= e["unet"].as_f64().unwrap(),
        "{e}"
    );
    let probe = &e["calibration"]["probe"];
    assert_eq!(probe["latent"], serde_json::json!([16, 16]), "{e}");
    assert_eq!(probe["scale"].as_f64(), Some(1.0), "{e}");

    let skipped = dir.path().join("skipped");
    let o = run_edit_with(&scene_path, &skipped, &long, &["--no-estimate"]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success() && !stderr.contains("time ≈"), "{stderr}");
    let run: serde_json::Value =
        serde_json::from_slice(&std::fs::read(skipped.join("run.json")).unwrap()).unwrap();
    assert!(run.get("estimate").is_none());
}

/// `--steps 4` is shorter than the reference's CCM and ECM periods (7 and 5): both modules still run, at
/// the reference's places rescaled, and the plan printed before the run says where.
#[test]
fn a_short_schedule_keeps_ccm_and_ecm_and_the_plan_says_where() {
    let dir = tempfile::tempdir().unwrap();
    let scene_path = dir.path().join("blobs.ply");
    splat::ply::write_ply(&scene_path, &two_blobs()).unwrap();
    // The test settings without their own module steps, one iteration.
    let mut settings: Vec<&str> = Vec::new();
    let mut args = RUN_SETTINGS.iter();
    while let Some(&a) = args.next() {
        match a {
            "--ccm-steps" | "--ecm-steps" => {
                args.next();
            }
            "--iterations" => {
                args.next();
                settings.extend(["--iterations", "1"]);
            }
            _ => settings.push(a),
        }
    }
    let out = dir.path().join("out");
    let o = run_edit_with(&scene_path, &out, &settings, &[]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "vcedit edit failed: {stderr}");
    assert!(
        stderr.contains(
            "modules (steps 0-3): CCM at 1, 3 (fewer steps than the reference's period 7"
        ) && stderr.contains("ECM at 1, 2, 3 (fewer steps than the reference's period 5"),
        "{stderr}"
    );
    // Progress names its units and the iteration's folder.
    assert!(
        stderr.contains("iteration 1/1 (iter_0/): editing 4 views (4 steps, 2 CCM, 3 ECM, decode)"),
        "{stderr}"
    );
    let run: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("run.json")).unwrap()).unwrap();
    let consistency = &run["settings"]["consistency"];
    assert_eq!(
        consistency["ccm_steps"],
        serde_json::json!([1, 3]),
        "{consistency}"
    );
    assert_eq!(consistency["ecm"]["steps"], serde_json::json!([1, 2, 3]));
    // Both modules took time.
    let stage = |name: &str| {
        run["timings"]
            .as_array()
            .unwrap()
            .iter()
            .find(|t| t["stage"] == name)
            .and_then(|t| t["seconds"].as_f64())
            .unwrap()
    };
    assert!(
        stage("CCM") > 0.0 && stage("ECM") > 0.0,
        "{}",
        run["timings"]
    );
}

/// The same edit into a folder whose run finished: said, exit 0, no work, outputs untouched; other
/// settings: refused naming the setting that differs; `--force`: done again.
#[test]
fn a_finished_run_is_not_done_again_unless_forced() {
    let dir = tempfile::tempdir().unwrap();
    let scene_path = dir.path().join("blobs.ply");
    splat::ply::write_ply(&scene_path, &two_blobs()).unwrap();
    let mut settings = RUN_SETTINGS;
    let at = settings.iter().position(|a| *a == "--iterations").unwrap();
    settings[at + 1] = "1";
    let out = dir.path().join("out");
    let o = run_edit_with(&scene_path, &out, &settings, &[]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let edited = std::fs::read(out.join("edited.ply")).unwrap();
    let modified = |name: &str| {
        std::fs::metadata(out.join(name))
            .unwrap()
            .modified()
            .unwrap()
    };
    let (report, run) = (modified("report.html"), modified("run.json"));

    let o = run_edit_with(&scene_path, &out, &settings, &[]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{stderr}");
    assert!(
        stderr.contains("holds this run already, finished") && stderr.contains("--force"),
        "{stderr}"
    );
    assert!(
        !stderr.contains("work:") && !stderr.contains("iteration 1"),
        "work was done: {stderr}"
    );
    assert!(String::from_utf8_lossy(&o.stdout).contains("edited scene: "));
    assert_eq!(std::fs::read(out.join("edited.ply")).unwrap(), edited);
    assert_eq!(
        (modified("report.html"), modified("run.json")),
        (report, run)
    );

    // Another setting: refused, naming it.
    let o = run_edit_with(&scene_path, &out, &settings, &["--seed", "7"]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("holds the outputs of another run") && stderr.contains("seed: 0 → 7"),
        "{stderr}"
    );

    // --force: the run is done again (the same result: it is deterministic).
    let o = run_edit_with(&scene_path, &out, &settings, &["--force"]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{stderr}");
    assert!(stderr.contains("iteration 1 done (iter_0/)"), "{stderr}");
    assert!(modified("run.json") > run);
    assert_eq!(std::fs::read(out.join("edited.ply")).unwrap(), edited);
}

#[test]
fn edit_writes_every_output_and_changes_only_the_mask() {
    let dir = tempfile::tempdir().unwrap();
    let scene_path = dir.path().join("blobs.ply");
    let scene = two_blobs();
    splat::ply::write_ply(&scene_path, &scene).unwrap();
    let before_bytes = std::fs::read(&scene_path).unwrap();
    let out = dir.path().join("out");
    let t = std::time::Instant::now();
    let o = run_edit(&scene_path, &out, &[]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "vcedit edit failed: {stderr}");
    assert!(t.elapsed().as_secs() < 60, "took {:?}", t.elapsed());
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(
        stdout.contains(&out.join("edited.ply").display().to_string()),
        "{stdout}"
    );
    assert!(
        stderr.contains("UNet passes") && stderr.contains("memory needed"),
        "work plan printed: {stderr}"
    );
    // 40 UNet passes: too short a run to be worth timing its unit costs first.
    assert!(!stderr.contains("time ≈"), "{stderr}");
    assert_eq!(
        std::fs::read(&scene_path).unwrap(),
        before_bytes,
        "the input must not be modified"
    );

    // Outputs exist and are valid.
    let edited = splat::ply::read_ply(&out.join("edited.ply")).unwrap();
    for k in 0..2 {
        for v in 0..4 {
            let img = splat::Image::load(&out.join(format!("iter_{k}/guidance/view_{v:03}.png")))
                .unwrap();
            assert_eq!((img.width, img.height), (64, 64));
        }
    }
    for sub in [
        "before/view_000.png",
        "after/view_003.png",
        "mask/view_000.png",
        "turntable.gif",
        "report.html",
    ] {
        let p = out.join(sub);
        assert!(
            p.is_file() && std::fs::metadata(&p).unwrap().len() > 0,
            "{sub} missing"
        );
    }
    assert!(
        std::fs::read_dir(out.join("attention")).unwrap().count() >= 2,
        "per-word attention maps"
    );
    let run: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("run.json")).unwrap()).unwrap();
    assert!(
        run["metrics"]["final_consistency"]["mean_abs_error"].is_number(),
        "{run}"
    );
    assert!(run["metrics"]["preservation_outside_mask"]["psnr"].is_number());
    // Each iteration's fit says what it did with the masked region's geometry (measured: a mask is given).
    let shape = run["shape"].as_array().expect("shape decisions");
    assert_eq!(shape.len(), 2, "{run}");
    for s in shape {
        let rate = s["geometry_rate"].as_f64().unwrap();
        assert!(rate == 1.0 || rate == 0.1f32 as f64, "{s}");
        assert!(s["footprint_change"].as_f64().unwrap() >= 0.0, "{s}");
    }
    let html = std::fs::read_to_string(out.join("report.html")).unwrap();
    assert!(html.contains("a red ball") && html.contains("edited.ply"));
    // The cameras as chosen (--orbit 6), and the fit's loss said once.
    assert!(html.contains("an orbit of 6 views"), "cameras not named");
    assert_eq!(html.matches("LPIPS").count(), 1, "the loss note repeats");

    // The work ledger: what the run counted is what the printed plan said, stage by stage.
    let work = &run["work"];
    let sum = |key: &str| -> u64 {
        ["encode", "ccm", "unet", "ecm", "blend", "decode", "fit"]
            .iter()
            .map(|stage| {
                work[stage][key]
                    .as_u64()
                    .unwrap_or_else(|| panic!("{stage}.{key}: {work}"))
            })
            .sum()
    };
    // Per view and iteration: steps 0-3 at progress 1/4 (5 samples: S_u lends T_u its queries and
    // keys) and 2/4-4/4 (4), CCM's recording at step 1 (the conditional 3): 20, where the batch of six
    // took 30. 4 views, 2 iterations.
    assert_eq!(work["unet"]["unet_samples"], 4 * 2 * (5 + 3 * 4), "{work}");
    assert_eq!(work["ccm"]["unet_samples"], 4 * 2 * 3, "{work}");
    let planned = format!(
        "counts: {} UNet samples in {} calls, {} lifting rounds ({} render-backs), {} fit steps, \
         {} VAE encodes, {} decodes",
        sum("unet_samples"),
        sum("unet_calls"),
        sum("lifting_rounds"),
        sum("render_backs"),
        sum("fit_steps"),
        sum("vae_encodes"),
        sum("vae_decodes"),
    );
    assert!(stderr.contains(&planned), "{planned}\n{stderr}");
    assert!(sum("map_reads") > 0, "{work}");
    assert!(
        html.contains("work done: 160 UNet samples"),
        "the report's ledger"
    );

    // Everything outside the box is bit-for-bit the input; something inside changed.
    let kept: HashSet<Vec<u32>> = (0..edited.len())
        .map(|i| gaussian_key(&edited, i))
        .collect();
    let mut outside = 0;
    let mut changed_inside = 0;
    for i in 0..scene.len() {
        let found = kept.contains(&gaussian_key(&scene, i));
        if inside(&scene.means[3 * i..3 * i + 3]) {
            changed_inside += usize::from(!found);
        } else {
            outside += 1;
            assert!(found, "Gaussian {i} outside the mask changed");
        }
    }
    assert!(outside >= 600, "{outside}");
    assert!(
        changed_inside > 100,
        "the edit changed {changed_inside} Gaussians inside the mask"
    );
}

#[test]
fn resume_after_an_interruption_equals_an_uninterrupted_run() {
    let dir = tempfile::tempdir().unwrap();
    let scene_path = dir.path().join("blobs.ply");
    splat::ply::write_ply(&scene_path, &two_blobs()).unwrap();
    let full = dir.path().join("full");
    assert!(run_edit(&scene_path, &full, &[]).status.success());

    // Interrupt after the first iteration's checkpoint, then resume.
    let part = dir.path().join("part");
    let o = run_edit(&scene_path, &part, &["--stop-after-iteration", "1"]);
    assert!(
        !o.status.success(),
        "the simulated interruption must stop the run"
    );
    assert!(!part.join("edited.ply").exists());
    // A damaged checkpoint is named, not resumed from (issue 69): one bit of one value flipped.
    let saved = part.join("checkpoint/scene_1.ply");
    let good = std::fs::read(&saved).unwrap();
    let mut bad = good.clone();
    let at = bad.len() - 10;
    bad[at] ^= 1;
    std::fs::write(&saved, &bad).unwrap();
    let o = run_edit(&scene_path, &part, &["--resume"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.contains("scene_1.ply") && err.contains("damaged"),
        "{err}"
    );
    std::fs::write(&saved, &good).unwrap();
    let o = run_edit(&scene_path, &part, &["--resume"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(String::from_utf8_lossy(&o.stderr).contains("resuming after iteration 1"));
    let (a, b) = (
        std::fs::read(full.join("edited.ply")).unwrap(),
        std::fs::read(part.join("edited.ply")).unwrap(),
    );
    assert!(a == b, "resumed result differs from the uninterrupted one");
}

/// `vcedit edit --device gpu` (on any Vulkan device; CI: Mesa lavapipe) finishes and agrees with the CPU run:
/// the edited scene's PSNR against the source renders (whole images and outside the mask) within 0.5 dB.
/// The runs are not bit-identical: the GPU sums gradients with atomics in another order. Kept small (two
/// views, a short ECM) because lavapipe is slow; every stage still runs: CCM, ECM, blend, fit.
#[test]
fn edit_on_the_gpu_matches_the_cpu() {
    gpu_and_cpu_edits_agree(&[]);
}

/// The same with the reference's 10·L1 + 10·LPIPS fit loss (the narrow fixture network): on the GPU the
/// network runs beside the renderer and the fits stay resident (`FitLoss::device_term`).
#[test]
fn edit_with_lpips_on_the_gpu_matches_the_cpu() {
    let lpips = fixtures().join("lpips/narrow");
    gpu_and_cpu_edits_agree(&["--lpips", lpips.to_str().unwrap()]);
}

/// Runs the small edit on the CPU and the GPU with `extra` options and compares the preservation PSNRs.
fn gpu_and_cpu_edits_agree(extra: &[&str]) {
    if gpu::list_adapters().is_empty() {
        println!("skipping: no Vulkan device");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let scene_path = dir.path().join("blobs.ply");
    splat::ply::write_ply(&scene_path, &two_blobs()).unwrap();
    let psnr = |device: &str| -> (f64, f64) {
        let out = dir.path().join(device);
        let o = Command::new(env!("CARGO_BIN_EXE_vcedit"))
            .args(["edit", "--scene"])
            .arg(&scene_path)
            .args(["--orbit", "4", "--max-views", "2", "--model"])
            .arg(fixtures().join("models/tiny-lcm"))
            .args(["--source", "a ball", "--target", "a red ball", "--out"])
            .arg(&out)
            .args(["--size", "64", "--steps", "3", "--iterations", "1"])
            .args(["--fit-steps", "30", "--ccm-steps", "1", "--ecm-steps", "1"])
            .args(["--ecm-min-steps", "40", "--precision", "f32"])
            .args(["--mask-box=-0.8,-0.8,-0.8,0.8,0.8,0.8", "--device", device])
            .args(extra)
            .output()
            .expect("run vcedit");
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert!(
            o.status.success(),
            "vcedit edit --device {device}: {stderr}"
        );
        let with_lpips = extra.contains(&"--lpips");
        assert_eq!(
            !stderr.contains("no --lpips weights"),
            with_lpips,
            "{stderr}"
        );
        if device == "gpu" {
            assert!(stderr.contains("device: "), "{stderr}");
            assert!(!stderr.contains("device: CPU"), "{stderr}");
            assert!(stderr.contains("GPU memory"), "{stderr}");
        }
        let run: serde_json::Value =
            serde_json::from_slice(&std::fs::read(out.join("run.json")).unwrap()).unwrap();
        // The ledger counts what each stage asked of the device: on the GPU every stage launches
        // kernels and the fit reads its loss; on the CPU nothing.
        let work = &run["work"];
        let launches = |stage: &str| work[stage]["launches"].as_u64().unwrap();
        for stage in ["encode", "ccm", "unet", "ecm", "decode", "fit"] {
            assert_eq!(
                launches(stage) > 0,
                device == "gpu",
                "{device} {stage}: {work}"
            );
        }
        let m = &run["metrics"];
        (
            m["preservation_whole"]["psnr"].as_f64().unwrap(),
            m["preservation_outside_mask"]["psnr"].as_f64().unwrap(),
        )
    };
    let cpu = psnr("cpu");
    let gpu = psnr("gpu");
    eprintln!("preservation PSNR (whole, outside the mask): CPU {cpu:?}, GPU {gpu:?}");
    assert!((cpu.0 - gpu.0).abs() <= 0.5, "CPU {cpu:?} vs GPU {gpu:?}");
    assert!((cpu.1 - gpu.1).abs() <= 0.5, "CPU {cpu:?} vs GPU {gpu:?}");
}
