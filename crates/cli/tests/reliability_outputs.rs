//! The output policy of issue 69 (and issue 68's point 3), through the binary: nothing inside an input
//! folder is written; temporary files are made exclusively under unpredictable names and only
//! vcedit's own stale ones are removed, never in a refused folder; a SOG folder is replaced only over a
//! SOG scene and as a whole; an existing output file needs --force; every output is checked before the
//! work; an unwritable stdout is one error line; a header claiming more than memory holds is refused.

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};

use splat::ply::write_ply;
use splat::GaussianScene;
use testkit::output::{assert_one_clear_error, assert_success, stderr};

fn vcedit_in(cwd: &Path, args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_vcedit"))
        .args(args)
        .current_dir(cwd)
        .output()
        .expect("run vcedit")
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// 64 Gaussians around the origin, coloured by `hue`.
fn ball(hue: f32) -> GaussianScene {
    testkit::scenes::ball([hue, -hue, 0.5 * hue])
}

/// A temporary folder holding `p.ply`, the ball of hue 1.
fn folder_with_ball() -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    write_ply(&dir.path().join("p.ply"), &ball(1.0)).unwrap();
    dir
}

fn read(p: &Path) -> Vec<u8> {
    std::fs::read(p).unwrap()
}

/// An INRIA trainer output folder: `point_cloud/iteration_7000/point_cloud.ply` and `cameras.json`.
fn inria_folder(root: &Path) -> PathBuf {
    let ply = root.join("point_cloud/iteration_7000/point_cloud.ply");
    std::fs::create_dir_all(ply.parent().unwrap()).unwrap();
    write_ply(&ply, &ball(1.0)).unwrap();
    std::fs::write(
        root.join("cameras.json"),
        r#"[{"id": 0, "img_name": "a", "width": 16, "height": 16, "position": [0, 0, -3],
            "rotation": [[1,0,0],[0,1,0],[0,0,1]], "fx": 16, "fy": 16},
           {"id": 1, "img_name": "b", "width": 16, "height": 16, "position": [0.3, 0, -3],
            "rotation": [[1,0,0],[0,1,0],[0,0,1]], "fx": 16, "fy": 16}]"#,
    )
    .unwrap();
    ply
}

// --- 1. Nothing inside an input folder --------------------------------------------------------------

#[test]
fn json_outputs_never_go_inside_an_input_folder() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let garden = d.join("garden");
    let ply = inria_folder(&garden);
    let ply_before = read(&ply);
    let cameras_before = read(&garden.join("cameras.json"));
    for target in [
        "garden/point_cloud/iteration_7000/point_cloud.ply",
        "garden/cameras.json",
        "garden/new.json",
    ] {
        for force in [false, true] {
            let json = format!("--json={target}");
            let mut args = vec!["inspect", "garden", &json];
            if force {
                args.push("--force");
            }
            let o = vcedit_in(d, &args);
            if target.ends_with(".json") {
                assert_one_clear_error(&o, 1, &["inside the input folder", "garden"]);
            } else {
                // A JSON file must be named *.json (a usage error, exit 2), which refuses a scene first.
                assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
                assert!(stderr(&o).contains("must end in .json"), "{}", stderr(&o));
            }
        }
    }
    assert_eq!(read(&ply), ply_before);
    assert_eq!(read(&garden.join("cameras.json")), cameras_before);
    assert!(!garden.join("new.json").exists());

    // A SOG folder, named by its folder or its meta.json.
    assert_success(&vcedit_in(d, &["convert", s(&ply), "sog/meta.json"]));
    let quats = read(&d.join("sog/quats.webp"));
    let meta = read(&d.join("sog/meta.json"));
    // (inspect's JSON file must be named *.json: a texture's name is refused before, as a usage error.)
    for (scene, target) in [("sog", "sog/meta.json"), ("sog/meta.json", "sog/new.json")] {
        let json = format!("--json={target}");
        let o = vcedit_in(d, &["inspect", scene, &json, "--force"]);
        assert_one_clear_error(&o, 1, &["inside the input folder"]);
    }
    assert_eq!(read(&d.join("sog/quats.webp")), quats);
    assert_eq!(read(&d.join("sog/meta.json")), meta);
    assert!(!d.join("sog/new.json").exists());

    // A COLMAP text model given by one of its files: the model's folder is the input.
    let model = d.join("model");
    std::fs::create_dir(&model).unwrap();
    std::fs::write(model.join("cameras.txt"), "1 PINHOLE 16 16 20 20 8 8\n").unwrap();
    std::fs::write(
        model.join("images.txt"),
        "1 1 0 0 0 0 0 3 1 a.png\n\n2 1 0 0 0 -0.2 0 3 1 b.png\n\n",
    )
    .unwrap();
    let colmap_before = read(&model.join("cameras.txt"));
    let o = vcedit_in(
        d,
        &[
            "metrics",
            "--source",
            s(&ply),
            "--edited",
            s(&ply),
            "--cameras",
            "model/images.txt",
            "--json=model/cameras.txt",
            "--force",
        ],
    );
    assert_one_clear_error(&o, 1, &["inside the input folder", "model"]);
    assert_eq!(read(&model.join("cameras.txt")), colmap_before);
}

#[test]
fn output_folders_never_go_inside_an_input_folder() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    inria_folder(&d.join("garden"));
    let o = vcedit_in(
        d,
        &[
            "render",
            "garden",
            "--out",
            "garden/renders",
            "--orbit",
            "2",
        ],
    );
    assert_one_clear_error(&o, 1, &["inside the input folder"]);
    assert!(!d.join("garden/renders").exists());
}

// --- 2. The clean-up of temporary files ----------------------------------------------------------------

#[test]
fn users_files_named_like_temporaries_survive() {
    let dir = folder_with_ball();
    let d = dir.path();
    let docs = d.join("docs");
    std::fs::create_dir(&docs).unwrap();
    // The user's file of issue 69, and one named exactly as a killed vcedit's (a pid not running).
    let thesis = docs.join(".thesis.tex.tmp-2024");
    let lookalike = docs.join(".thesis.tex.vcedit-tmp-4194305-Ab3dE5fG7hJ9");
    for p in [&thesis, &lookalike] {
        std::fs::write(p, "important").unwrap();
    }
    std::fs::write(docs.join("photo.jpg"), "x").unwrap();
    // A refused folder is not touched at all.
    let o = vcedit_in(d, &["render", "p.ply", "--out", "docs", "--orbit", "2"]);
    assert_one_clear_error(&o, 1, &["not written by vcedit"]);
    assert!(thesis.exists() && lookalike.exists());
    // A single-file output there removes only what is provably vcedit's.
    assert_success(&vcedit_in(d, &["convert", "p.ply", "docs/p.spz"]));
    assert_eq!(std::fs::read_to_string(&thesis).unwrap(), "important");
    assert!(!lookalike.exists(), "a dead vcedit temporary is cleaned");
}

// --- 4. Temporary names cannot be planted ----------------------------------------------------------------

#[cfg(target_os = "linux")]
#[test]
fn a_link_planted_at_a_temporary_name_is_never_followed() {
    let dir = folder_with_ball();
    let d = dir.path();
    let od = d.join("od");
    std::fs::create_dir(&od).unwrap();
    let victim = d.join("victim.txt");
    std::fs::write(&victim, "keep").unwrap();
    // Links at the names earlier versions used, for the next process ids.
    let last: u32 = std::fs::read_to_string("/proc/sys/kernel/ns_last_pid")
        .ok()
        .and_then(|t| t.trim().parse().ok())
        .unwrap_or(0);
    for pid in last + 1..last + 400 {
        let link = od.join(format!(".x.ply.vcedit-tmp-{pid}"));
        std::os::unix::fs::symlink(&victim, link).unwrap();
    }
    assert_success(&vcedit_in(d, &["convert", "p.ply", "od/x.ply"]));
    assert_eq!(std::fs::read_to_string(&victim).unwrap(), "keep");
    let meta = std::fs::symlink_metadata(od.join("x.ply")).unwrap();
    assert!(meta.is_file(), "od/x.ply is not a plain file");
    assert_eq!(splat::read_scene(&od.join("x.ply")).unwrap(), ball(1.0));
}

// --- 3. and 5. SOG folders: by content, and whole -------------------------------------------------------

#[test]
fn a_folder_with_someone_elses_meta_json_is_not_taken_over() {
    let dir = folder_with_ball();
    let d = dir.path();
    let site = d.join("site");
    std::fs::create_dir(&site).unwrap();
    std::fs::write(site.join("meta.json"), r#"{"title":"my site"}"#).unwrap();
    std::fs::write(site.join("means_l.webp"), "mine").unwrap();
    for force in [false, true] {
        let mut args = vec!["convert", "p.ply", "site/meta.json"];
        if force {
            args.push("--force");
        }
        assert_one_clear_error(&vcedit_in(d, &args), 1, &["site", "not a SOG scene"]);
    }
    assert_eq!(
        std::fs::read_to_string(site.join("meta.json")).unwrap(),
        r#"{"title":"my site"}"#
    );
    assert_eq!(
        std::fs::read_to_string(site.join("means_l.webp")).unwrap(),
        "mine"
    );
    // A SOG scene with a stranger's file beside it is not replaced either.
    assert_success(&vcedit_in(d, &["convert", "p.ply", "sog/meta.json"]));
    std::fs::write(d.join("sog/notes.txt"), "mine").unwrap();
    let o = vcedit_in(d, &["convert", "p.ply", "sog/meta.json", "--force"]);
    assert_one_clear_error(&o, 1, &["not a SOG scene"]);
    assert!(d.join("sog/notes.txt").exists());
}

#[test]
fn concurrent_sog_writes_leave_one_whole_scene() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let scenes = [ball(1.0), ball(-1.0)];
    for (i, scene) in scenes.iter().enumerate() {
        write_ply(&d.join(format!("{i}.ply")), scene).unwrap();
        assert_success(&vcedit_in(
            d,
            &["convert", &format!("{i}.ply"), &format!("ref{i}/meta.json")],
        ));
    }
    let snapshot = |folder: &Path| -> Vec<(String, Vec<u8>)> {
        let mut v: Vec<(String, Vec<u8>)> = std::fs::read_dir(folder)
            .unwrap()
            .map(|e| {
                let e = e.unwrap();
                (
                    e.file_name().to_string_lossy().into_owned(),
                    read(&e.path()),
                )
            })
            .collect();
        v.sort();
        v
    };
    let references = [snapshot(&d.join("ref0")), snapshot(&d.join("ref1"))];
    for round in 0..6 {
        let children: Vec<_> = (0..2)
            .map(|i| {
                Command::new(env!("CARGO_BIN_EXE_vcedit"))
                    .args(["convert", &format!("{i}.ply"), "s/meta.json", "--force"])
                    .current_dir(d)
                    .stdout(Stdio::null())
                    .stderr(Stdio::piped())
                    .spawn()
                    .unwrap()
            })
            .collect();
        for child in children {
            let o = child.wait_with_output().unwrap();
            assert_success(&o);
        }
        let now = snapshot(&d.join("s"));
        assert!(
            references.contains(&now),
            "round {round}: the folder mixes two scenes: {:?}",
            now.iter().map(|(n, _)| n).collect::<Vec<_>>()
        );
    }
    // Nothing left beside it.
    let mut left: Vec<String> = std::fs::read_dir(d)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    left.sort();
    assert_eq!(left, ["0.ply", "1.ply", "ref0", "ref1", "s"]);
}

// --- 68.3. Existing output files need --force ------------------------------------------------------------

#[test]
fn existing_output_files_are_refused_without_force() {
    let dir = folder_with_ball();
    let d = dir.path();
    let keep = |name: &str| {
        let p = d.join(name);
        std::fs::write(&p, "earlier work").unwrap();
        p
    };
    let cases: [(&str, Vec<&str>); 4] = [
        ("important.ply", vec!["convert", "p.ply", "important.ply"]),
        ("page.html", vec!["view", "p.ply", "--out", "page.html"]),
        ("stats.json", vec!["inspect", "p.ply", "--json=stats.json"]),
        (
            "m.json",
            vec![
                "metrics", "--source", "p.ply", "--edited", "p.ply", "--orbit", "2", "--size",
                "16", "--json", "m.json",
            ],
        ),
    ];
    for (name, args) in &cases {
        let p = keep(name);
        assert_one_clear_error(&vcedit_in(d, args), 1, &[name, "exists", "--force"]);
        assert_eq!(
            std::fs::read_to_string(&p).unwrap(),
            "earlier work",
            "{name}"
        );
        let mut forced = args.clone();
        forced.push("--force");
        assert_success(&vcedit_in(d, &forced));
        assert_ne!(
            std::fs::read_to_string(&p).ok().as_deref(),
            Some("earlier work")
        );
    }
    // --force never replaces an input.
    let before = read(&d.join("p.ply"));
    let o = vcedit_in(d, &["convert", "p.ply", "./p.ply", "--force"]);
    assert_one_clear_error(&o, 1, &["also an input"]);
    assert_eq!(read(&d.join("p.ply")), before);
}

// --- 8. Every output checked before the work -------------------------------------------------------------

/// A folder no file can be created in, even by root: inside /proc.
const UNWRITABLE: &str = "/proc/vcedit-no-such-folder";

#[cfg(target_os = "linux")]
#[test]
fn unwritable_outputs_are_refused_before_any_work() {
    let dir = folder_with_ball();
    let d = dir.path();
    // fit: refused before its data is even used (no "training ... views" line).
    let lego = d.join("lego");
    std::fs::create_dir(&lego).unwrap();
    let mut frames = Vec::new();
    for i in 0..2 {
        let mut img = splat::Image::new(16, 16, 3);
        img.data.iter_mut().for_each(|v| *v = 0.5);
        img.save_png(&lego.join(format!("r_{i}.png"))).unwrap();
        frames.push(format!(
            r#"{{"file_path": "./r_{i}", "transform_matrix": [[1,0,0,{i}],[0,1,0,0],[0,0,1,3],[0,0,0,1]]}}"#
        ));
    }
    std::fs::write(
        lego.join("transforms.json"),
        format!(
            r#"{{"camera_angle_x": 0.8, "frames": [{}]}}"#,
            frames.join(",")
        ),
    )
    .unwrap();
    let fit_out = format!("{UNWRITABLE}/f.ply");
    let o = vcedit_in(
        d,
        &["fit", "--data", "lego", "--out", &fit_out, "--steps", "300"],
    );
    assert_one_clear_error(&o, 1, &["f.ply", "cannot write into"]);
    assert!(!stderr(&o).contains("training"), "{}", stderr(&o));
    // metrics: before any rendering.
    let json = format!("--json={UNWRITABLE}/m.json");
    let o = vcedit_in(
        d,
        &[
            "metrics", "--source", "p.ply", "--edited", "p.ply", "--orbit", "2", &json,
        ],
    );
    assert_one_clear_error(&o, 1, &["m.json", "cannot write into"]);
    // edit-image: before the model is loaded (a missing model would be named otherwise).
    let img = splat::Image::new(16, 16, 3);
    img.save_png(&d.join("a.png")).unwrap();
    let out = format!("{UNWRITABLE}/o.png");
    let o = vcedit_in(
        d,
        &[
            "edit-image",
            "--model",
            "no-model-here",
            "--image",
            "a.png",
            "--source",
            "a cat",
            "--target",
            "a dog",
            "--out",
            &out,
        ],
    );
    assert_one_clear_error(&o, 1, &["o.png", "cannot write into"]);
}

// --- 7. An unwritable stdout ----------------------------------------------------------------------------

#[cfg(target_os = "linux")]
#[test]
fn a_full_stdout_is_one_error_line_not_a_panic() {
    let dir = folder_with_ball();
    let d = dir.path();
    let model = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../fixtures/models/tiny-lcm");
    let cases: [Vec<&str>; 5] = [
        vec!["inspect", "p.ply"],
        vec!["inspect", "p.ply", "--json"],
        vec!["convert", "p.ply", "q.spz"],
        vec!["model", "check", s(&model)],
        vec!["demo", "--list"],
    ];
    for args in cases {
        let full = std::fs::OpenOptions::new()
            .write(true)
            .open("/dev/full")
            .unwrap();
        let o = Command::new(env!("CARGO_BIN_EXE_vcedit"))
            .args(&args)
            .current_dir(d)
            .stdout(full)
            .output()
            .unwrap();
        assert_one_clear_error(&o, 1, &["cannot write to standard output"]);
        assert!(!stderr(&o).contains("panicked"), "{args:?}: {}", stderr(&o));
    }
}

// --- 6. More than memory holds, from the header ---------------------------------------------------------

#[test]
fn a_sparse_file_as_long_as_a_huge_header_claims_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let bytes = splat::ply::encode_ply(&ball(1.0)).unwrap();
    let end = bytes
        .windows(11)
        .position(|w| w == b"end_header\n")
        .unwrap()
        + 11;
    let row = ((bytes.len() - end) / 64) as u64;
    let count: u64 = 1 << 36;
    let header = String::from_utf8(bytes[..end].to_vec())
        .unwrap()
        .replace("element vertex 64\n", &format!("element vertex {count}\n"));
    let p = d.join("huge.ply");
    std::fs::write(&p, &header).unwrap();
    let f = std::fs::OpenOptions::new().write(true).open(&p).unwrap();
    if f.set_len(header.len() as u64 + count * row).is_err() {
        return; // no sparse files this large here
    }
    let o = vcedit_in(d, &["inspect", "huge.ply"]);
    assert_one_clear_error(&o, 1, &["huge.ply", "memory"]);
}

// --- 10. Messages -------------------------------------------------------------------------------------

#[test]
fn convert_names_a_bad_input_once() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::write(d.join("z.spz"), b"NGSP\x04\x00\x00\x00").unwrap();
    let o = vcedit_in(d, &["convert", "z.spz", "o.ply"]);
    assert_one_clear_error(&o, 1, &["z.spz"]);
    let err = stderr(&o);
    let line = err.lines().last().unwrap();
    assert_eq!(line.matches("z.spz").count(), 1, "{line}");
    assert!(!d.join("o.ply").exists());
}

// --- 9. Same seed, same bytes on the GPU without a usable cache ---------------------------------------

/// With the cache folder unusable (here a file where the folder should be), tuning results cannot be
/// kept: the convolutions take one fixed path instead of being timed in every run (timing chose
/// differently from run to run, and the paths differ in their last bits), and the run says once that
/// the cache is unusable.
#[test]
fn a_gpu_edit_without_a_usable_cache_repeats_bit_for_bit() {
    if gpu::list_adapters().is_empty() {
        println!("skipping: no Vulkan device");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let mut img = splat::Image::new(64, 64, 3);
    for (i, v) in img.data.iter_mut().enumerate() {
        *v = ((i * 7) % 255) as f32 / 255.0;
    }
    img.save_png(&d.join("a.png")).unwrap();
    std::fs::write(d.join("not-a-folder"), "x").unwrap();
    let model = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../fixtures/models/tiny-lcm");
    let mut outputs = Vec::new();
    for run in 0..3 {
        let out = format!("o{run}.png");
        let o = Command::new(env!("CARGO_BIN_EXE_vcedit"))
            .args([
                "edit-image",
                "--model",
                s(&model),
                "--image",
                "a.png",
                "--source",
                "a cat",
                "--target",
                "a dog",
                "--out",
                &out,
                "--size",
                "64",
                "--steps",
                "2",
                "--device",
                "gpu",
            ])
            .env("XDG_CACHE_HOME", d.join("not-a-folder"))
            .current_dir(d)
            .output()
            .unwrap();
        assert_success(&o);
        let warnings = stderr(&o).matches("cannot be written").count();
        assert_eq!(warnings, 1, "{}", stderr(&o));
        outputs.push(read(&d.join(out)));
    }
    assert!(outputs.windows(2).all(|w| w[0] == w[1]), "the runs differ");
}
