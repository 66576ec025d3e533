//! Fuzzing the scene and camera readers (see `files::fuzz`): PLY (binary and ASCII), COLMAP models
//! (.bin and .txt), transforms.json and INRIA cameras.json, each seeded from valid files and mutated for
//! `VCEDIT_FUZZ_SECONDS` (default 5 s) per target. Any error is fine; a panic fails the test and the
//! input is saved under target/fuzz-crashes/.

#[path = "support/camera_files.rs"]
mod camera_files;

use std::path::{Path, PathBuf};

use camera_files::{colmap_bin, colmap_txt, inria_json, transforms_json, views};
use splat::cameras::load_cameras;
use splat::ply::{encode_ply, read_ply};
use splat::GaussianScene;

fn crash_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../target/fuzz-crashes")
}

/// A few Gaussians with SH coefficients up to `degree`.
fn scene(degree: u32, n: usize) -> GaussianScene {
    let mut s = GaussianScene::new(degree);
    let k = s.sh_coeffs() * 3;
    for i in 0..n {
        let t = i as f32;
        s.means.extend_from_slice(&[t.sin(), t.cos(), 0.1 * t]);
        s.log_scales.extend_from_slice(&[-2.0, -2.5, -3.0]);
        s.quats.extend_from_slice(&[1.0, 0.1 * t, 0.0, 0.0]);
        s.opacity_logits.push(0.5 * t - 1.0);
        s.sh.extend((0..k).map(|j| (j as f32 * 0.1 + t).sin()));
    }
    s
}

#[test]
fn fuzz_ply() {
    let ascii = "ply\nformat ascii 1.0\ncomment fuzz seed\nelement vertex 2\nproperty float x\n\
                 property float y\nproperty float z\nproperty float opacity\nend_header\n\
                 0 0 0 1\n1 2 3 -0.5\n";
    let seeds = vec![
        encode_ply(&scene(0, 3)).unwrap(),
        encode_ply(&scene(3, 2)).unwrap(),
        ascii.as_bytes().to_vec(),
    ];
    files::fuzz::run_file_and_assert("ply", "scene.ply", &seeds, &crash_dir(), |path| {
        let _ = read_ply(path);
    });
}

/// Fuzzes a COLMAP model of files `names` written by `write`.
fn fuzz_colmap(target: &str, names: &[&str], write: fn(&Path, &[camera_files::View])) {
    let valid = tempfile::tempdir().unwrap();
    write(valid.path(), &views());
    files::fuzz::run_file_set_and_assert(target, valid.path(), names, &crash_dir(), |dir| {
        let _ = load_cameras(dir);
    });
}

#[test]
fn fuzz_colmap_bin() {
    fuzz_colmap(
        "colmap_bin",
        &["cameras.bin", "images.bin", "points3D.bin"],
        colmap_bin,
    );
}

#[test]
fn fuzz_colmap_txt() {
    fuzz_colmap(
        "colmap_txt",
        &["cameras.txt", "images.txt", "points3D.txt"],
        colmap_txt,
    );
}

/// Fuzzes a JSON camera file written by `write` under `name`.
fn fuzz_json(target: &str, name: &str, write: fn(&Path, &[camera_files::View])) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join(name);
    write(&path, &views());
    let seeds = vec![std::fs::read(&path).unwrap()];
    files::fuzz::run_file_and_assert(target, name, &seeds, &crash_dir(), |path| {
        let _ = load_cameras(path);
    });
}

#[test]
fn fuzz_transforms_json() {
    fuzz_json("transforms_json", "transforms.json", transforms_json);
}

#[test]
fn fuzz_inria_cameras_json() {
    fuzz_json("inria_cameras_json", "cameras.json", inria_json);
}
