//! Fuzzing the scene and camera readers (see `testkit::fuzz`): PLY (binary and ASCII), compressed PLY,
//! .splat, .spz (versions 2 and 3 gzip, 4 zstd), SOG (zip, and a folder's meta.json and WebP textures),
//! COLMAP models (.bin and .txt), transforms.json and INRIA cameras.json, each seeded from valid files
//! and mutated for
//! `VCEDIT_FUZZ_SECONDS` (default 5 s) per target. Any error is fine; a panic fails the test and the
//! input is saved under target/fuzz-crashes/.

#[path = "support/camera_files.rs"]
mod camera_files;

use std::path::Path;

use camera_files::{colmap_bin, colmap_txt, inria_json, transforms_json, views};
use splat::cameras::load_cameras;
use splat::ply::{encode_ply, read_ply};
use splat::GaussianScene;

// Every input's allocations are measured (an input that makes its reader claim too much fails).
#[global_allocator]
static ALLOC: testkit::fuzz::CountingAlloc = testkit::fuzz::CountingAlloc;

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
    testkit::fuzz::run_file_and_assert(
        "ply",
        "scene.ply",
        &seeds,
        &testkit::fuzz::crash_dir(),
        |path| {
            let _ = read_ply(path);
        },
    );
}

/// The length a PLY header says its file has: the header plus every element's rows (binary: the
/// property sizes; ASCII: two bytes a value, the least a value takes). `None` for lists or no header.
fn ply_claimed_len(bytes: &[u8]) -> Option<u64> {
    let end = bytes.windows(11).position(|w| w == b"end_header\n")? + 11;
    let header = std::str::from_utf8(&bytes[..end]).ok()?;
    let ascii = header.contains("format ascii");
    let (mut total, mut count, mut row) = (0u64, 0u64, 0u64);
    for line in header.lines() {
        let words: Vec<&str> = line.split_whitespace().collect();
        match words.as_slice() {
            ["element", _, n] => {
                total = total.checked_add(count.checked_mul(row)?)?;
                (count, row) = (n.parse().ok()?, 0);
            }
            ["property", "list", ..] => return None,
            ["property", ty, _] => {
                row += match *ty {
                    _ if ascii => 2,
                    "char" | "uchar" | "int8" | "uint8" => 1,
                    "short" | "ushort" | "int16" | "uint16" => 2,
                    "double" | "float64" => 8,
                    _ => 4,
                }
            }
            _ => {}
        }
    }
    total
        .checked_add(count.checked_mul(row)?)?
        .checked_add(end as u64)
}

/// PLY headers whose counts a sparse file's size matches but no memory holds (issue 69: `inspect`
/// aborted on the allocation). Seeded with such counts; mutations vary them.
#[test]
fn fuzz_ply_sparse() {
    let huge = |bytes: Vec<u8>, from: &str, to: &str| {
        String::from_utf8_lossy(&bytes)
            .replacen(from, to, 1)
            .into_bytes()
    };
    // Past the sparse floor for 68-byte rows (SH degree 0) and for 8-byte ASCII rows.
    let big = (testkit::fuzz::sparse_floor() / 40).to_string();
    let big_ascii = (testkit::fuzz::sparse_floor() / 4).to_string();
    let binary = encode_ply(&scene(0, 1)).unwrap();
    let seeds = vec![
        huge(binary.clone(), "element vertex 1\n", &format!("element vertex {big}\n")),
        huge(binary, "element vertex 1\n", "element vertex 4294967295\n"),
        huge(
            encode_ply(&scene(3, 1)).unwrap(),
            "element vertex 1\n",
            &format!("element vertex {big}\n"),
        ),
        format!(
            "ply\nformat ascii 1.0\nelement vertex {big_ascii}\nproperty float x\nproperty float y\n\
             property float z\nproperty float opacity\nend_header\n0 0 0 1\n"
        )
        .into_bytes(),
    ];
    testkit::fuzz::run_sparse_file_and_assert(
        "ply-sparse",
        "scene.ply",
        &seeds,
        &testkit::fuzz::crash_dir(),
        ply_claimed_len,
        |path| {
            let _ = splat::read_scene(path);
        },
    );
    // The compressed PLY has the same header; its reader reads the whole file.
    let compressed = splat::formats::compressed_ply::encode(&scene(0, 300)).unwrap();
    testkit::fuzz::run_sparse_file_and_assert(
        "compressed-ply-sparse",
        "scene.compressed.ply",
        &[compressed],
        &testkit::fuzz::crash_dir(),
        |b| ply_claimed_len(b).map(|l| l.max(testkit::fuzz::sparse_floor())),
        |path| {
            let _ = splat::read_scene(path);
        },
    );
}

/// Fuzzes a COLMAP model of files `names` written by `write`.
fn fuzz_colmap(target: &str, names: &[&str], write: fn(&Path, &[camera_files::View])) {
    let valid = tempfile::tempdir().unwrap();
    write(valid.path(), &views());
    testkit::fuzz::run_file_set_and_assert(
        target,
        valid.path(),
        names,
        &testkit::fuzz::crash_dir(),
        |dir| {
            let _ = load_cameras(dir);
        },
    );
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
    testkit::fuzz::run_file_and_assert(target, name, &seeds, &testkit::fuzz::crash_dir(), |path| {
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

/// A scene file format read through `read_scene` (content detection, decoding, value checks), seeded
/// from `encode`'s output for a few scenes.
fn fuzz_format(target: &str, file_name: &str, encode: &dyn Fn(&GaussianScene) -> Vec<u8>) {
    let seeds = vec![
        encode(&scene(0, 20)),
        encode(&scene(1, 7)),
        encode(&scene(3, 3)),
    ];
    testkit::fuzz::run_file_and_assert(
        target,
        file_name,
        &seeds,
        &testkit::fuzz::crash_dir(),
        |path| {
            let _ = splat::read_scene(path);
        },
    );
}

#[test]
fn fuzz_compressed_ply() {
    fuzz_format("compressed-ply", "scene.compressed.ply", &|s| {
        splat::formats::compressed_ply::encode(s).unwrap()
    });
}

#[test]
fn fuzz_dot_splat() {
    fuzz_format("dot-splat", "scene.splat", &|s| {
        splat::formats::dot_splat::encode(s).unwrap()
    });
}

#[test]
fn fuzz_spz() {
    // One seed per version: 2 and 3 are gzip streams, 4 has an NGSP header and zstd streams.
    let seeds: Vec<Vec<u8>> = [2, 3, 4]
        .iter()
        .flat_map(|&v| {
            [scene(0, 12), scene(3, 3)].map(|s| splat::formats::spz::encode(&s, v).unwrap())
        })
        .collect();
    testkit::fuzz::run_file_and_assert(
        "spz",
        "scene.spz",
        &seeds,
        &testkit::fuzz::crash_dir(),
        |path| {
            let _ = splat::read_scene(path);
        },
    );
}

#[test]
fn fuzz_sog_zip() {
    fuzz_format("sog-zip", "scene.sog", &|s| {
        let files = splat::formats::sog::encode(s).unwrap();
        splat::formats::sog::zip_files(&files).unwrap()
    });
}

#[test]
fn fuzz_sog_folder() {
    let valid = tempfile::tempdir().unwrap();
    let files = splat::formats::sog::encode(&scene(1, 40)).unwrap();
    for (name, bytes) in &files {
        std::fs::write(valid.path().join(name), bytes).unwrap();
    }
    let names: Vec<&str> = files.iter().map(|(n, _)| n.as_str()).collect();
    testkit::fuzz::run_file_set_and_assert(
        "sog-folder",
        valid.path(),
        &names,
        &testkit::fuzz::crash_dir(),
        |dir| {
            let _ = splat::read_scene(&dir.join("meta.json"));
        },
    );
}
