//! The cases of issue 11, through the binary: no input is ever written over, no success is reported on
//! nothing, every prompt word is checked, arguments are checked before any work (no half-made or mixed
//! outputs), and every bad input is one clear line naming the file or option (no repeated text, no
//! backtrace). Inputs are tiny so the whole file runs in seconds.

use std::collections::hash_map::DefaultHasher;
use std::hash::{Hash, Hasher};
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use splat::ply::write_ply;
use splat::Image;
use testkit::output::assert_one_clear_error;
use testkit::paths::tiny_lcm;
use testkit::scenes::red_ball;

fn vcedit_in(cwd: &Path, args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_vcedit"))
        .args(args)
        .current_dir(cwd)
        .output()
        .expect("run vcedit")
}

/// `vcedit edit-image` on `a.png` with the tiny model at 64x64, 2 steps, plus `extra`.
fn edit_image_args<'a>(
    model: &'a str,
    target: &'a str,
    out: &'a str,
    extra: &[&'a str],
) -> Vec<&'a str> {
    let mut v = vec![
        "edit-image",
        "--model",
        model,
        "--image",
        "a.png",
        "--source",
        "a cat",
    ];
    v.extend([
        "--target", target, "--out", out, "--size", "64", "--steps", "2",
    ]);
    v.extend_from_slice(extra);
    v
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// A hash of a file's bytes (to see that an input was left untouched).
fn hash_of(path: &Path) -> u64 {
    let mut h = DefaultHasher::new();
    std::fs::read(path).unwrap().hash(&mut h);
    h.finish()
}

fn write_png(path: &Path, w: u32, h: u32) {
    let mut img = Image::new(w, h, 3);
    for (i, v) in img.data.iter_mut().enumerate() {
        *v = ((i * 7) % 255) as f32 / 255.0;
    }
    img.save_png(path).unwrap();
}

/// A COLMAP text model of three 16x16 views looking along +z, with an empty points3D.
fn colmap_without_points(root: &Path) {
    let sparse = root.join("sparse/0");
    std::fs::create_dir_all(&sparse).unwrap();
    std::fs::create_dir_all(root.join("images")).unwrap();
    std::fs::write(sparse.join("cameras.txt"), "1 PINHOLE 16 16 20 20 8 8\n").unwrap();
    let mut images = String::new();
    for i in 0..3 {
        images += &format!("{} 1 0 0 0 {} 0 3 1 v{i}.png\n\n", i + 1, -0.2 * i as f64);
        write_png(&root.join(format!("images/v{i}.png")), 16, 16);
    }
    std::fs::write(sparse.join("images.txt"), images).unwrap();
    std::fs::write(sparse.join("points3D.txt"), "# no points\n").unwrap();
}

/// A transforms.json dataset of two 16x16 views.
fn transforms_dataset(root: &Path) -> PathBuf {
    std::fs::create_dir_all(root).unwrap();
    let mut frames = Vec::new();
    for i in 0..2 {
        write_png(&root.join(format!("r_{i}.png")), 16, 16);
        frames.push(serde_json::json!({
            "file_path": format!("./r_{i}"),
            "transform_matrix": [[1, 0, 0, i], [0, 1, 0, 0], [0, 0, 1, 3], [0, 0, 0, 1]],
        }));
    }
    let json = serde_json::json!({ "camera_angle_x": 0.8, "frames": frames });
    let path = root.join("transforms.json");
    std::fs::write(&path, json.to_string()).unwrap();
    path
}

// --- 1. No command writes over one of its inputs ------------------------------------------------------

#[test]
fn fit_never_writes_over_its_data() {
    let dir = tempfile::tempdir().unwrap();
    let json = transforms_dataset(&dir.path().join("lego"));
    let before = hash_of(&json);
    let o = vcedit_in(
        dir.path(),
        &["fit", "--data", s(&json), "--out", s(&json), "--steps", "1"],
    );
    assert_one_clear_error(&o, 1, &["--out", "transforms.json", ".ply"]);
    assert_eq!(hash_of(&json), before);

    // A .ply name that is a link to one of the data's images.
    #[cfg(unix)]
    {
        let image = dir.path().join("lego/r_0.png");
        let image_hash = hash_of(&image);
        let link = dir.path().join("lego/scene.ply");
        std::os::unix::fs::symlink(&image, &link).unwrap();
        let o = vcedit_in(
            dir.path(),
            &[
                "fit",
                "--data",
                "lego",
                "--out",
                "lego/scene.ply",
                "--steps",
                "1",
            ],
        );
        assert_one_clear_error(&o, 1, &["scene.ply", "also an input", "r_0.png"]);
        assert_eq!(hash_of(&image), image_hash);
    }
}

#[test]
fn edit_image_never_writes_over_its_image() {
    let dir = tempfile::tempdir().unwrap();
    write_png(&dir.path().join("a.png"), 64, 64);
    let before = hash_of(&dir.path().join("a.png"));
    let model = tiny_lcm();
    let mut outs = vec!["a.png".to_string(), "./a.png".to_string()];
    outs.push(s(&dir.path().join("sub/../a.png")).to_string());
    std::fs::create_dir(dir.path().join("sub")).unwrap();
    #[cfg(unix)]
    {
        std::os::unix::fs::symlink(dir.path().join("a.png"), dir.path().join("link.png")).unwrap();
        outs.push("link.png".into());
    }
    for out in &outs {
        let o = vcedit_in(dir.path(), &edit_image_args(s(&model), "a dog", out, &[]));
        assert_one_clear_error(&o, 1, &["also an input", "a.png"]);
        assert_eq!(hash_of(&dir.path().join("a.png")), before, "{out}");
    }
}

#[test]
fn metrics_json_and_view_pages_never_replace_a_scene() {
    let dir = tempfile::tempdir().unwrap();
    let a = dir.path().join("a.ply");
    write_ply(&a, &red_ball()).unwrap();
    let before = hash_of(&a);
    let o = vcedit_in(
        dir.path(),
        &[
            "metrics", "--source", "a.ply", "--edited", "a.ply", "--orbit", "2", "--size", "16",
            "--json", "./a.ply",
        ],
    );
    assert_one_clear_error(&o, 1, &["also an input", "a.ply"]);
    let o = vcedit_in(dir.path(), &["view", "a.ply", "--out", "./a.ply"]);
    assert_one_clear_error(&o, 1, &["--out", "one of the scenes"]);
    assert_eq!(hash_of(&a), before);
}

// --- 2. No success on nothing -------------------------------------------------------------------------

#[test]
fn fit_with_no_initial_points_is_a_usage_error() {
    let dir = tempfile::tempdir().unwrap();
    let json = transforms_dataset(&dir.path().join("d"));
    let o = vcedit_in(
        dir.path(),
        &[
            "fit",
            "--data",
            s(&json),
            "--out",
            "o.ply",
            "--init-points",
            "0",
        ],
    );
    assert_one_clear_error(&o, 2, &["--init-points", "must be positive"]);
    assert!(!dir.path().join("o.ply").exists());
}

#[test]
fn an_empty_points3d_says_what_is_used_instead() {
    let dir = tempfile::tempdir().unwrap();
    colmap_without_points(dir.path());
    // Outside the data folder (the input).
    let outs = tempfile::tempdir().unwrap();
    let out = outs.path().join("o.ply");
    let o = vcedit_in(
        dir.path(),
        &[
            "fit",
            "--data",
            ".",
            "--out",
            s(&out),
            "--steps",
            "2",
            "--init-points",
            "300",
            "--holdout-every",
            "0",
            "--eval-every",
            "0",
        ],
    );
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{stderr}");
    assert!(
        stderr.contains("points3D) is empty: starting from 300 random points"),
        "{stderr}"
    );
    assert!(
        !stderr.contains("0 initial points from the data"),
        "{stderr}"
    );
}

// --- 3. Prompt words are words of their prompts -------------------------------------------------------

#[test]
fn prompt_word_options_name_the_word_and_the_prompt() {
    let dir = tempfile::tempdir().unwrap();
    write_png(&dir.path().join("a.png"), 64, 64);
    let model = tiny_lcm();
    for (extra, says) in [
        (
            ["--blend-words", "dog"],
            "--blend-words: 'dog' is not a word of the target prompt 'a red cat'",
        ),
        (
            ["--keep-words", "red"],
            "--keep-words: 'red' is not a word of the source prompt 'a cat'",
        ),
        (
            ["--keep-words", "dog"],
            "--keep-words: 'dog' is not a word of the source prompt 'a cat'",
        ),
    ] {
        let o = vcedit_in(
            dir.path(),
            &edit_image_args(s(&model), "a red cat", "o.png", &extra),
        );
        // A word the prompt lacks is a usage error, as clap's (issue 69).
        assert_one_clear_error(&o, 2, &[says]);
        assert!(!dir.path().join("o.png").exists());
    }
}

// --- 4. Arguments are checked before any work; a folder never mixes two runs --------------------------

fn edit_args<'a>(scene: &'a str, model: &'a str, out: &'a str, extra: &[&'a str]) -> Vec<&'a str> {
    let mut v = vec![
        "edit",
        "--scene",
        scene,
        "--model",
        model,
        "--source",
        "a ball",
        "--target",
        "a red ball",
        "--out",
        out,
        "--steps",
        "2",
        "--iterations",
        "1",
        "--fit-steps",
        "1",
    ];
    // Defaults the case may replace.
    for (option, value) in [("--orbit", "4"), ("--size", "64")] {
        if !extra.contains(&option) {
            v.extend([option, value]);
        }
    }
    v.extend_from_slice(extra);
    v
}

#[test]
fn edit_refuses_bad_arguments_before_making_its_folder() {
    let dir = tempfile::tempdir().unwrap();
    write_ply(&dir.path().join("ball.ply"), &red_ball()).unwrap();
    let model = tiny_lcm();
    let model = s(&model);
    for (extra, says) in [
        (
            &["--size", "63x65"][..],
            &["--size", "63x65", "multiple of"][..],
        ),
        (
            &["--mask-word", "dog"],
            &["--mask-word: 'dog' is not a word of the source prompt 'a ball'"],
        ),
        (
            &["--mask-dir", "no-such-masks"],
            &["--mask-dir", "no-such-masks"],
        ),
        (
            &["--mask-box=5,5,5,6,6,6"],
            &["--mask-box", "none of the scene's 64 Gaussians"],
        ),
        (&["--blend-words", "dog"], &["--blend-words: 'dog'"]),
        (
            &["--blend-level", "9"],
            &["--blend-level", "blend level 9", "levels with it"],
        ),
    ] {
        let o = vcedit_in(dir.path(), &edit_args("ball.ply", model, "out", extra));
        // A prompt word missing from its prompt is a usage error (exit code 2).
        let words = ["--mask-word", "--blend-words"].contains(&extra[0]);
        assert_one_clear_error(&o, if words { 2 } else { 1 }, says);
        assert!(!dir.path().join("out").exists(), "{extra:?} left a folder");
    }
}

#[test]
fn a_mask_that_selects_nothing_leaves_no_folder() {
    let dir = tempfile::tempdir().unwrap();
    write_ply(&dir.path().join("ball.ply"), &red_ball()).unwrap();
    let masks = dir.path().join("masks");
    std::fs::create_dir(&masks).unwrap();
    for i in 0..4 {
        Image::new(64, 64, 1)
            .save_png(&masks.join(format!("orbit_{i:03}.png")))
            .unwrap();
    }
    let model = tiny_lcm();
    let o = vcedit_in(
        dir.path(),
        &edit_args("ball.ply", s(&model), "out", &["--mask-dir", "masks"]),
    );
    assert_one_clear_error(&o, 1, &["the mask selects no Gaussian"]);
    assert!(!dir.path().join("out").exists());
}

#[test]
fn edit_image_checks_the_attention_folder_before_writing_its_image() {
    let dir = tempfile::tempdir().unwrap();
    write_png(&dir.path().join("a.png"), 64, 64);
    // A folder that cannot be made (its parent is a file), even as root.
    let model = tiny_lcm();
    let o = vcedit_in(
        dir.path(),
        &edit_image_args(
            s(&model),
            "a dog",
            "o.png",
            &["--save-attention", "a.png/attention"],
        ),
    );
    assert_one_clear_error(&o, 1, &["--save-attention", "a.png/attention"]);
    assert!(!dir.path().join("o.png").exists());
}

fn pngs(dir: &Path) -> usize {
    std::fs::read_dir(dir)
        .unwrap()
        .filter(|e| {
            e.as_ref()
                .unwrap()
                .path()
                .extension()
                .is_some_and(|x| x == "png")
        })
        .count()
}

#[test]
fn render_folders_hold_one_run() {
    let dir = tempfile::tempdir().unwrap();
    write_ply(&dir.path().join("ball.ply"), &red_ball()).unwrap();
    let render = |orbit: &str, extra: &[&str]| {
        let mut args = vec![
            "render", "ball.ply", "--out", "r", "--size", "16", "--orbit", orbit,
        ];
        args.extend_from_slice(extra);
        vcedit_in(dir.path(), &args)
    };
    assert!(render("4", &[]).status.success());
    assert_eq!(pngs(&dir.path().join("r")), 4);
    // The same render again is the same run.
    assert!(render("4", &[]).status.success());
    // Other settings: refused, nothing changed; --force replaces vcedit's files and keeps the user's.
    let o = render("2", &[]);
    assert_one_clear_error(&o, 1, &["another run", "--force"]);
    assert_eq!(pngs(&dir.path().join("r")), 4);
    std::fs::write(dir.path().join("r/notes.txt"), "mine").unwrap();
    let o = render("2", &["--force"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(pngs(&dir.path().join("r")), 2);
    assert!(dir.path().join("r/notes.txt").exists());

    // A folder vcedit did not write is never mixed into, even with --force.
    std::fs::create_dir(dir.path().join("photos")).unwrap();
    std::fs::write(dir.path().join("photos/holiday.jpg"), "jpg").unwrap();
    for extra in [&[][..], &["--force"]] {
        let mut args = vec![
            "render", "ball.ply", "--out", "photos", "--orbit", "2", "--size", "16",
        ];
        args.extend_from_slice(extra);
        let o = vcedit_in(dir.path(), &args);
        assert_one_clear_error(&o, 1, &["photos", "not written by vcedit"]);
    }
    assert_eq!(
        std::fs::read_dir(dir.path().join("photos"))
            .unwrap()
            .count(),
        1
    );

    // An edit into a render's folder is another run.
    let model = tiny_lcm();
    let o = vcedit_in(dir.path(), &edit_args("ball.ply", s(&model), "r", &[]));
    assert_one_clear_error(
        &o,
        1,
        &["r: holds the outputs of another run (vcedit render)"],
    );
}

#[test]
fn an_edit_folder_holds_one_run() {
    let dir = tempfile::tempdir().unwrap();
    write_ply(&dir.path().join("ball.ply"), &red_ball()).unwrap();
    let model = tiny_lcm();
    let edit = |extra: &[&str]| {
        let mut extra = extra.to_vec();
        if !extra.contains(&"--iterations") {
            extra.extend(["--iterations", "2"]);
        }
        let mut args = edit_args("ball.ply", s(&model), "e", &[]);
        // edit_args says --iterations 1; this test chooses.
        let at = args.iter().position(|a| *a == "--iterations").unwrap();
        args.drain(at..at + 2);
        args.extend(extra);
        vcedit_in(dir.path(), &args)
    };
    let o = edit(&[]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(dir.path().join("e/iter_1").is_dir());
    let scene_hash = hash_of(&dir.path().join("e/edited.ply"));

    // A killed write in a subfolder is cleaned up when the same run is resumed.
    let stale = dir
        .path()
        .join("e/checkpoint/.scene_2.ply.vcedit-tmp-4194305-Ab3dE5fG7hJ9");
    std::fs::write(&stale, "half").unwrap();
    let o = edit(&["--resume"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(!stale.exists());
    assert_eq!(hash_of(&dir.path().join("e/edited.ply")), scene_hash);

    // One iteration into the two-iteration folder: refused; with --force, nothing of the old run stays.
    let o = edit(&["--iterations", "1"]);
    assert_one_clear_error(&o, 1, &["e: holds the outputs of another run", "--force"]);
    assert!(dir.path().join("e/iter_1").is_dir());
    let o = edit(&["--iterations", "1", "--force"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(!dir.path().join("e/iter_1").exists());
    assert!(dir.path().join("e/iter_0").is_dir());
    assert!(!dir.path().join("e/checkpoint/scene_2.ply").exists());
    assert!(dir.path().join("e/checkpoint/scene_1.ply").exists());
}

#[test]
fn huge_orbits_are_refused_up_front() {
    let dir = tempfile::tempdir().unwrap();
    write_ply(&dir.path().join("ball.ply"), &red_ball()).unwrap();
    let o = vcedit_in(
        dir.path(),
        &["render", "ball.ply", "--out", "r", "--orbit", "100000"],
    );
    assert_one_clear_error(&o, 2, &["--orbit 100000", "1000", "--allow-many-views"]);
    assert!(!dir.path().join("r").exists());
}

/// Values out of their range are usage errors (exit code 2, as clap's), refused before any folder is made,
/// also where the range depends on another option or the input.
#[test]
fn out_of_range_values_are_usage_errors() {
    let dir = tempfile::tempdir().unwrap();
    write_ply(&dir.path().join("ball.ply"), &red_ball()).unwrap();
    let model = tiny_lcm();
    let model = s(&model);
    for (extra, says) in [
        (
            &["--orbit", "100000"][..],
            &["--orbit 100000", "--allow-many-views"][..],
        ),
        (
            &["--guidance-scale", "1"],
            &["--guidance-scale 1", "above 1"],
        ),
        (
            &["--mask-threshold", "1"],
            &["--mask-threshold 1", "[0, 1)"],
        ),
        (
            &["--ccm-steps", "99"],
            &["--ccm-steps: step 99", "last step (1)"],
        ),
    ] {
        let o = vcedit_in(dir.path(), &edit_args("ball.ply", model, "out", extra));
        assert_one_clear_error(&o, 2, says);
        assert!(!dir.path().join("out").exists(), "{extra:?} left a folder");
    }
    for (extra, says) in [
        (&["--views", "1"][..], &["--views 1", "at least 2"][..]),
        (&["--pair", "99"], &["--pair 99", "--list"]),
    ] {
        let mut args = vec!["demo", "--out", "d"];
        args.extend_from_slice(extra);
        let o = vcedit_in(dir.path(), &args);
        assert_one_clear_error(&o, 2, says);
        assert!(!dir.path().join("d").exists(), "{extra:?} left a folder");
    }
    // A level the model lacks is known only once the model is read, still before any folder is made.
    let o = vcedit_in(
        dir.path(),
        &[
            "demo",
            "--out",
            "d",
            "--blend-level",
            "9",
            "--device",
            "cpu",
        ],
    );
    assert_one_clear_error(&o, 1, &["--blend-level", "blend level 9", "levels with it"]);
    assert!(
        !dir.path().join("d").exists(),
        "--blend-level 9 left a folder"
    );
}

#[test]
fn temporary_files_of_killed_runs_are_removed() {
    let dir = tempfile::tempdir().unwrap();
    let json = transforms_dataset(&dir.path().join("d"));
    // What a killed run left (a pid that cannot be running, a random token); names users may pick
    // (the shorter naming of earlier versions among them) are not provably vcedit's and stay.
    let stale = [dir.path().join(".lego.ply.vcedit-tmp-4194305-Ab3dE5fG7hJ9")];
    let foreign = [
        dir.path().join(".lego.ply.partial"),
        dir.path().join(".lego.ply.tmp-4194305"),
        dir.path().join(".lego.ply.vcedit-tmp-4194305"),
    ];
    for p in stale.iter().chain(&foreign) {
        std::fs::write(p, "half").unwrap();
    }
    // Even a run refused for its memory cleans the folder it would write to.
    let o = vcedit_in(
        dir.path(),
        &[
            "fit",
            "--data",
            s(&json),
            "--out",
            "lego.ply",
            "--size",
            "16384",
        ],
    );
    assert_one_clear_error(&o, 1, &["GB", "--size", "--ignore-memory-check"]);
    assert!(stale.iter().all(|p| !p.exists()));
    assert!(foreign.iter().all(|p| p.exists()));
    assert!(!dir.path().join("lego.ply").exists());
}

// --- 5. One clear line for every bad input --------------------------------------------------------------

#[test]
fn a_ply_without_end_header_says_so() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(
        dir.path().join("bad.ply"),
        "ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\n\x01\x02\x03\x04",
    )
    .unwrap();
    let o = vcedit_in(
        dir.path(),
        &["render", "bad.ply", "--out", "r", "--orbit", "2"],
    );
    assert_one_clear_error(&o, 1, &["bad.ply", "end_header"]);
    assert!(!dir.path().join("r").exists());
}

#[test]
fn negative_numbers_are_values_not_flags() {
    let dir = tempfile::tempdir().unwrap();
    for (args, option) in [
        (
            &["render", "s.ply", "--out", "o", "--size", "-64"][..],
            "--size",
        ),
        (
            &["fit", "--data", "d", "--out", "o.ply", "--steps", "-1"],
            "--steps",
        ),
    ] {
        let o = vcedit_in(dir.path(), args);
        let line = assert_one_clear_error(&o, 2, &[option]);
        assert!(!line.contains("unexpected argument"), "{line}");
    }
}

/// A copy of the tiny model with `edit` applied to it.
fn broken_model(dir: &Path, edit: impl FnOnce(&Path)) -> PathBuf {
    let copy = dir.join("model");
    for entry in testkit::paths::files_under(&tiny_lcm()) {
        let rel = entry.strip_prefix(tiny_lcm()).unwrap();
        std::fs::create_dir_all(copy.join(rel).parent().unwrap()).unwrap();
        std::fs::copy(&entry, copy.join(rel)).unwrap();
    }
    edit(&copy);
    copy
}

fn edit_image_with(dir: &Path, model: &Path) -> Output {
    write_png(&dir.join("a.png"), 64, 64);
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_vcedit"));
    // With RUST_BACKTRACE=1: errors must still be one line.
    cmd.args(edit_image_args(s(model), "a dog", "o.png", &[]))
        .env("RUST_BACKTRACE", "1")
        .current_dir(dir);
    cmd.output().unwrap()
}

/// Moves the tensors from the middle of a safetensors file on by 8 bytes: a gap in the data.
fn gap_in_safetensors(path: &Path) -> String {
    let bytes = std::fs::read(path).unwrap();
    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let mut header: serde_json::Map<String, serde_json::Value> =
        serde_json::from_slice(&bytes[8..8 + n]).unwrap();
    let data = &bytes[8 + n..];
    let mut starts: Vec<(u64, String)> = header
        .iter()
        .filter(|(k, _)| *k != "__metadata__")
        .map(|(k, v)| (v["data_offsets"][0].as_u64().unwrap(), k.clone()))
        .collect();
    starts.sort();
    let (cut, after_gap) = starts[starts.len() / 2].clone();
    for (_, v) in header.iter_mut().filter(|(k, _)| *k != "__metadata__") {
        let o = &mut v["data_offsets"];
        let (a, b) = (o[0].as_u64().unwrap(), o[1].as_u64().unwrap());
        if a >= cut {
            *o = serde_json::json!([a + 8, b + 8]);
        }
    }
    let mut text = serde_json::to_vec(&header).unwrap();
    // Headers are padded with spaces to a multiple of 8 bytes.
    text.resize(text.len().div_ceil(8) * 8, b' ');
    let mut out = (text.len() as u64).to_le_bytes().to_vec();
    out.extend(text);
    out.extend(&data[..cut as usize]);
    out.extend([0u8; 8]);
    out.extend(&data[cut as usize..]);
    std::fs::write(path, out).unwrap();
    after_gap
}

#[test]
fn a_gap_in_the_weights_is_named_alike_by_model_check_and_edit_image() {
    let dir = tempfile::tempdir().unwrap();
    let mut tensor = String::new();
    let model = broken_model(dir.path(), |m| {
        tensor = gap_in_safetensors(&m.join("vae/diffusion_pytorch_model.safetensors"));
    });
    let o = vcedit_in(dir.path(), &["model", "check", "model"]);
    assert_one_clear_error(&o, 1, &[&tensor]);
    let o = edit_image_with(dir.path(), &model);
    assert_one_clear_error(&o, 1, &[&tensor, "diffusion_pytorch_model.safetensors"]);
    assert!(!dir.path().join("o.png").exists());
}

#[test]
fn bad_configs_are_one_line_even_with_rust_backtrace() {
    let dir = tempfile::tempdir().unwrap();
    let set = |file: &str, key: &str, value: serde_json::Value| {
        let file = file.to_string();
        let key = key.to_string();
        move |m: &Path| {
            let p = m.join(&file);
            let mut c: serde_json::Value =
                serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap();
            c[&key] = value;
            std::fs::write(&p, c.to_string()).unwrap();
        }
    };
    for (i, (file, key, value, says)) in [
        (
            "unet/config.json",
            "norm_num_groups",
            serde_json::json!(0),
            "norm_num_groups = 0 (must be at least 1)",
        ),
        (
            "vae/config.json",
            "norm_num_groups",
            serde_json::json!(0),
            "norm_num_groups 0 must be at least 1",
        ),
        // A config that does not match its weights: the shapes disagree when the model is built.
        (
            "unet/config.json",
            "cross_attention_dim",
            serde_json::json!(48),
            "unet",
        ),
    ]
    .into_iter()
    .enumerate()
    {
        let case = dir.path().join(i.to_string());
        std::fs::create_dir(&case).unwrap();
        let model = broken_model(&case, set(file, key, value));
        let o = edit_image_with(&case, &model);
        assert_one_clear_error(&o, 1, &[says]);
        assert!(!case.join("o.png").exists());
    }
}

// --- 6. Ranges and sizes ------------------------------------------------------------------------------

#[test]
fn fractions_and_thresholds_are_finite_and_in_range() {
    let dir = tempfile::tempdir().unwrap();
    for option in [
        "--thresh-e",
        "--thresh-m",
        "--cross",
        "--self",
        "--eta",
        "--strength",
    ] {
        for value in ["nan", "2", "-0.5", "inf"] {
            let o = vcedit_in(
                dir.path(),
                &[
                    "edit-image",
                    "--model",
                    "m",
                    "--image",
                    "i.png",
                    "--source",
                    "a",
                    "--target",
                    "b",
                    "--out",
                    "o.png",
                    option,
                    value,
                ],
            );
            assert_one_clear_error(&o, 2, &[option]);
        }
    }
}

#[test]
fn counts_and_durations_out_of_range_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let o = vcedit_in(dir.path(), &["demo", "--views", "1", "--out", "d"]);
    assert_one_clear_error(&o, 2, &["--views 1", "at least 2"]);
    assert!(!dir.path().join("d").exists());
    let o = vcedit_in(
        dir.path(),
        &[
            "demo-model",
            "train",
            "--out",
            "m",
            "--checkpoint-minutes",
            "-5",
        ],
    );
    assert_one_clear_error(&o, 1, &["--checkpoint-minutes -5", "must be positive"]);
    assert!(!dir.path().join("m").exists());
}

#[test]
fn training_configs_that_do_not_parse_or_fit_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let train = |config: &str| {
        vcedit_in(
            dir.path(),
            &["demo-model", "train", "--out", "m", "--config", config],
        )
    };
    std::fs::write(
        dir.path().join("cut.json"),
        r#"{"seed": 0, "image_size": 12"#,
    )
    .unwrap();
    assert_one_clear_error(
        &train("cut.json"),
        1,
        &["cut.json", "not a training config"],
    );
    // Parses, but 102 is no multiple of the codec's downscale (4).
    let mut config: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(
            PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../tools/demo-model/fine.json"),
        )
        .unwrap(),
    )
    .unwrap();
    config["image_size"] = 102.into();
    std::fs::write(dir.path().join("odd.json"), config.to_string()).unwrap();
    assert_one_clear_error(&train("odd.json"), 1, &["odd.json", "image size 102"]);
    config["image_size"] = 128.into();
    config["unet"]["beta_end"] = 0.0001.into();
    std::fs::write(dir.path().join("betas.json"), config.to_string()).unwrap();
    assert_one_clear_error(
        &train("betas.json"),
        1,
        &["betas.json", "unet.beta_end 0.0001"],
    );
    assert_one_clear_error(&train("missing.json"), 1, &["missing.json", "cannot read"]);
    assert!(!dir.path().join("m").exists());
}

#[test]
fn an_empty_merges_file_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let model = broken_model(dir.path(), |m| {
        std::fs::write(m.join("tokenizer/merges.txt"), "").unwrap();
    });
    let o = edit_image_with(dir.path(), &model);
    assert_one_clear_error(&o, 1, &["merges.txt", "no BPE merges"]);
}

/// Issue 26, items 6, 8 and 13: a scene whose values overflow, a PLY whose trailing element is cut
/// short, and a named pipe given as a scene are each refused with one line naming the file (not shown
/// as `inf`, accepted, or waited on forever).
#[test]
fn scenes_that_decode_to_garbage_or_are_not_files_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let cwd = dir.path();

    let mut huge = red_ball();
    huge.log_scales[3 * 5] = 1e30;
    write_ply(&cwd.join("huge.ply"), &huge).unwrap();
    let o = vcedit_in(cwd, &["inspect", "huge.ply"]);
    assert_one_clear_error(&o, 1, &["huge.ply", "Gaussian 5", "log-scale"]);
    let o = vcedit_in(
        cwd,
        &[
            "render", "huge.ply", "--out", "r", "--orbit", "2", "--size", "32",
        ],
    );
    assert_one_clear_error(&o, 1, &["huge.ply", "Gaussian 5"]);
    assert!(!cwd.join("r").exists());

    // A PLY with a trailing face element whose list says 0xffffffff indices that are not there.
    write_ply(&cwd.join("ok.ply"), &red_ball()).unwrap();
    let bytes = std::fs::read(cwd.join("ok.ply")).unwrap();
    let end = bytes
        .windows(11)
        .position(|w| w == b"end_header\n")
        .unwrap();
    let mut faced = bytes[..end].to_vec();
    faced.extend_from_slice(b"element face 1\nproperty list uint int vertex_indices\nend_header\n");
    faced.extend_from_slice(&bytes[end + 11..]);
    faced.extend_from_slice(&u32::MAX.to_le_bytes());
    std::fs::write(cwd.join("faced.ply"), &faced).unwrap();
    let o = vcedit_in(cwd, &["inspect", "faced.ply"]);
    assert_one_clear_error(&o, 1, &["faced.ply", "face"]);

    #[cfg(unix)]
    {
        let made = Command::new("mkfifo").arg(cwd.join("pipe.ply")).status();
        if made.is_ok_and(|s| s.success()) {
            let o = vcedit_in(cwd, &["inspect", "pipe.ply"]);
            assert_one_clear_error(&o, 1, &["pipe.ply", "named pipe"]);
        }
    }
}

/// Issue 26, item 11: every command whose memory grows with its settings estimates it before any work
/// and refuses what does not fit, naming the option that lowers it (the sizes here need terabytes).
#[test]
fn commands_refuse_runs_that_cannot_fit_in_memory() {
    let dir = tempfile::tempdir().unwrap();
    let cwd = dir.path();
    write_ply(&cwd.join("a.ply"), &red_ball()).unwrap();
    let o = vcedit_in(
        cwd,
        &[
            "metrics", "--source", "a.ply", "--edited", "a.ply", "--size", "16384", "--orbit",
            "64", "--device", "cpu",
        ],
    );
    assert_one_clear_error(&o, 1, &["needs about", "reduce --size or --orbit"]);

    let o = vcedit_in(
        cwd,
        &["demo", "--views", "100000", "--out", "d", "--device", "cpu"],
    );
    assert_one_clear_error(&o, 1, &["needs about", "reduce --views"]);
    assert!(!cwd.join("d").exists());

    write_png(&cwd.join("a.png"), 8, 8);
    let model = tiny_lcm();
    let mut args = edit_image_args(s(&model), "a dog", "out.png", &["--device", "cpu"]);
    let size = args.iter().position(|a| *a == "--size").unwrap();
    args[size + 1] = "16384";
    let o = vcedit_in(cwd, &args);
    assert_one_clear_error(&o, 1, &["needs about", "reduce --size"]);
    assert!(!cwd.join("out.png").exists());
}

/// Sets every float of tensor `name` in a safetensors file to NaN (f32 and f16 alike: all bits set).
fn nan_tensor(path: &Path) -> String {
    let mut bytes = std::fs::read(path).unwrap();
    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let header: serde_json::Map<String, serde_json::Value> =
        serde_json::from_slice(&bytes[8..8 + n]).unwrap();
    let (name, info) = header
        .iter()
        .filter(|(k, _)| *k != "__metadata__")
        .max_by_key(|(k, _)| k.to_string())
        .unwrap();
    let (a, b) = (
        info["data_offsets"][0].as_u64().unwrap() as usize,
        info["data_offsets"][1].as_u64().unwrap() as usize,
    );
    bytes[8 + n + a..8 + n + b].fill(0xff);
    std::fs::write(path, bytes).unwrap();
    name.clone()
}

/// Issue 26, item 10: NaN weights and a beta schedule outside [0, 1) are refused by `model check` and
/// `edit-image` (which wrote an all-black image before), naming the file.
#[test]
fn nan_weights_and_impossible_schedules_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let nan = dir.path().join("nan");
    std::fs::create_dir(&nan).unwrap();
    let mut tensor = String::new();
    let model = broken_model(&nan, |m| {
        tensor = nan_tensor(&m.join("vae/diffusion_pytorch_model.safetensors"));
    });
    let o = vcedit_in(&nan, &["model", "check", "model"]);
    assert_one_clear_error(&o, 1, &[&tensor, "NaN"]);
    let o = edit_image_with(&nan, &model);
    assert_one_clear_error(&o, 1, &["NaN", "model check"]);
    assert!(!nan.join("o.png").exists());

    let betas = dir.path().join("betas");
    std::fs::create_dir(&betas).unwrap();
    let model = broken_model(&betas, |m| {
        let p = m.join("scheduler/scheduler_config.json");
        let mut c: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap();
        c["beta_start"] = serde_json::json!(5.0);
        c["beta_end"] = serde_json::json!(-1.0);
        std::fs::write(&p, c.to_string()).unwrap();
    });
    let o = vcedit_in(&betas, &["model", "check", "model"]);
    assert_one_clear_error(&o, 1, &["scheduler_config.json", "beta_start"]);
    let o = edit_image_with(&betas, &model);
    assert_one_clear_error(&o, 1, &["scheduler_config.json", "beta_start"]);
    assert!(!betas.join("o.png").exists());
}
