//! Round trips of every format, fixtures written byte by byte from the specifications, and malformed files.

use super::codec::SH_C0;
use super::*;
use crate::scene::sh_coeffs;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// A scene with every quantity varied: positions in [-2, 2], log-scales in [-5, 0], any rotation, opacity
/// logits in [-4, 4], colours inside [0, 1] and higher SH in [-0.9, 0.9].
fn scene(sh_degree: u32, n: usize, seed: u64) -> GaussianScene {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let k = sh_coeffs(sh_degree);
    let mut s = GaussianScene::new(sh_degree);
    for _ in 0..n {
        s.means.extend((0..3).map(|_| rng.gen_range(-2.0..2.0f32)));
        s.log_scales
            .extend((0..3).map(|_| rng.gen_range(-5.0..0.0f32)));
        s.quats.extend((0..4).map(|_| rng.gen_range(-1.0..1.0f32)));
        s.opacity_logits.push(rng.gen_range(-4.0..4.0));
        s.sh.extend((0..3).map(|_| rng.gen_range(-1.6..1.6f32)));
        s.sh.extend((3..3 * k).map(|_| rng.gen_range(-0.9..0.9f32)));
    }
    s
}

const NAMES: [&str; 6] = [
    "s.ply",
    "s.compressed.ply",
    "s.splat",
    "s.spz",
    "s.sog",
    // A SOG folder is a folder of its own: one beside other files is refused.
    "sog/meta.json",
];

/// Writes with `write_scene`, reads back with `read_scene`, and checks the report against what came back.
fn round_trip(dir: &Path, name: &str, s: &GaussianScene) -> (WriteReport, GaussianScene) {
    let path = dir.join(name);
    let report = write_scene(&path, s).unwrap_or_else(|e| panic!("{name}: {e}"));
    let back = read_scene(&path).unwrap_or_else(|e| panic!("{name}: {e}"));
    assert_eq!(back.len(), s.len(), "{name}");
    assert_eq!(report.gaussians, s.len());
    match &report.error {
        None => assert_eq!(&back, s, "{name} claims to be lossless"),
        Some(e) => assert_eq!(
            *e,
            QuantisationError::between(s, &back),
            "{name}: the report must be the error a reader sees"
        ),
    }
    (report, back)
}

/// The bound each format promises for [`scene`]'s value ranges.
fn assert_within_format_bounds(name: &str, s: &GaussianScene, report: &WriteReport) {
    let Some(e) = report.error else {
        assert_eq!(name, "s.ply");
        return;
    };
    let extent = 4.0f32; // positions span [-2, 2]
    let (pos, scale, rot, opacity, colour, sh) = match name {
        // 11/10/11 bits within each chunk's box, 8-bit colour and opacity, 10-bit rotations, SH step 1/32.
        "s.compressed.ply" => (
            extent / 1023.0 / 2.0,
            5.0 / 2047.0,
            0.2,
            0.5 / 255.0,
            3.0 * SH_C0 * 1.6 / 255.0 / 2.0,
            1.0 / 64.0,
        ),
        // f32 positions and scales; 8-bit colour, opacity and rotation; higher SH dropped.
        ".splat" | "s.splat" => (0.0, 1e-5, 1.0, 0.5 / 255.0, 0.5 / 255.0, 0.9),
        // 12 fraction bits, log-scale step 1/16, colour step 1/(0.15·255), SH step 1/128.
        "s.spz" => (
            0.5 / 4096.0,
            1.0 / 32.0,
            0.2,
            0.5 / 255.0,
            SH_C0 * 0.5 / (0.15 * 255.0),
            0.5 / 128.0,
        ),
        // 16 bits of ln(|x|+1), 256-entry codebooks, 8-bit rotations and opacity.
        _ => (
            // half a 16-bit step of ln(|x| + 1) over [-ln 3, ln 3], times d|x|/d ln(|x|+1) ≤ 3
            2.0 * 3.0f32.ln() / 65535.0 / 2.0 * 3.0,
            5.0 / 100.0,
            1.0,
            0.5 / 255.0,
            SH_C0 * 3.2 / 100.0,
            1.8 / 100.0,
        ),
    };
    let slack = 1.0001;
    let checks = [
        ("position", e.position, pos),
        ("log-scale", e.log_scale, scale),
        ("rotation", e.rotation_deg, rot),
        ("opacity", e.opacity, opacity + 1e-5),
        ("colour", e.colour, colour),
        ("SH", e.sh_rest, sh),
    ];
    for (what, got, bound) in checks {
        assert!(
            got <= bound * slack + 1e-6,
            "{name}: {what} error {got} above the format's bound {bound} ({report}), SH {}",
            s.sh_degree
        );
    }
}

#[test]
fn every_format_round_trips_self_made_scenes_within_its_bound() {
    let dir = tempfile::tempdir().unwrap();
    for (degree, n) in [(0, 1), (3, 1), (0, 257), (3, 257), (1, 300), (2, 40)] {
        let s = scene(degree, n, 7 + n as u64);
        for name in NAMES {
            let sub = dir.path().join(format!("{degree}-{n}"));
            std::fs::create_dir_all(&sub).unwrap();
            let (report, back) = round_trip(&sub, name, &s);
            let expected_degree = if name.ends_with(".splat") { 0 } else { degree };
            assert_eq!(back.sh_degree, expected_degree, "{name}");
            assert_eq!(report.written_sh_degree, expected_degree, "{name}");
            assert_within_format_bounds(name, &s, &report);
        }
    }
}

#[test]
fn spz_versions_2_3_and_4_round_trip() {
    let s = scene(3, 257, 3);
    for version in [2, 3, 4] {
        let bytes = spz::encode(&s, version).unwrap();
        assert_eq!(bytes.starts_with(&spz::GZIP_MAGIC), version < 4);
        let back = spz::decode(&bytes).unwrap();
        let e = QuantisationError::between(&s, &back);
        // Version 2 derives w from 8-bit x, y, z: near w = 0 (half turns) an error of 1/255 in x, y, z
        // becomes ~0.12 in w. Smallest three (v3+) fixed that.
        let rotation_bound = if version == 2 { 15.0 } else { 0.2 };
        assert!(e.rotation_deg <= rotation_bound, "v{version}: {e}");
        assert!(e.position <= 0.5 / 4096.0 + 1e-6, "v{version}: {e}");
        assert!(e.sh_rest <= 0.5 / 128.0 + 1e-6, "v{version}: {e}");
    }
}

/// Damage anywhere in a written .spz is an error, never a scene with wild values: versions 2 and 3 carry
/// gzip's CRC, and the version 4 streams vcedit writes carry zstd's content checksum.
#[test]
fn spz_detects_damage_in_its_streams() {
    let s = scene(1, 300, 3);
    for version in [2, 3, 4] {
        let bytes = spz::encode(&s, version).unwrap();
        // Past the headers (v4: 32 bytes, table of contents 16 per stream) and inside the compressed data.
        let start = if version == 4 { 32 + 16 * 5 + 8 } else { 16 };
        let mut silent = Vec::new();
        for i in (start..bytes.len()).step_by(7) {
            let mut broken = bytes.clone();
            broken[i] ^= 0x5a;
            if spz::decode(&broken).is_ok() {
                silent.push(i);
            }
        }
        assert!(
            silent.is_empty(),
            "v{version}: damage at {silent:?} went unnoticed"
        );
    }
}

#[test]
fn spz_keeps_far_positions_by_using_fewer_fraction_bits() {
    let mut s = scene(0, 3, 5);
    s.means[0] = 5000.0;
    s.means[4] = -70_000.0;
    let back = spz::decode(&spz::encode(&s, 4).unwrap()).unwrap();
    let e = QuantisationError::between(&s, &back);
    // 70 000 needs 17 integer bits: 6 fraction bits are left (step 1/64).
    assert!(e.position <= 0.5 / 64.0, "{e}");
    s.means[1] = 1e8;
    assert!(spz::encode(&s, 4).unwrap_err().contains("8388607"));
}

#[test]
fn reading_goes_by_content_not_name() {
    let dir = tempfile::tempdir().unwrap();
    let s = scene(1, 20, 9);
    for name in ["s.compressed.ply", "s.spz", "s.sog"] {
        let path = dir.path().join(name);
        write_scene(&path, &s).unwrap();
        let renamed = dir.path().join(format!("renamed-{name}.bin"));
        std::fs::rename(&path, &renamed).unwrap();
        assert_eq!(read_scene(&renamed).unwrap().len(), 20, "{name}");
    }
    // `.splat` has no signature: only its name says what it is (any upper/lower case).
    let splat = dir.path().join("s.splat");
    write_scene(&splat, &s).unwrap();
    let upper = dir.path().join("S.SPLAT");
    std::fs::copy(&splat, &upper).unwrap();
    assert_eq!(read_scene(&upper).unwrap().len(), 20);
    let renamed = dir.path().join("renamed-s.splat.bin");
    std::fs::rename(&splat, &renamed).unwrap();
    let err = read_scene(&renamed).unwrap_err().to_string();
    assert!(err.contains("must be named *.splat"), "{err}");
    // A text file whose size is a multiple of 32 bytes is not a scene.
    let text = dir.path().join("notes.txt");
    std::fs::write(&text, "x".repeat(96)).unwrap();
    let err = read_scene(&text).unwrap_err().to_string();
    assert!(err.contains("not PLY"), "{err}");
    // A SOG folder is read from the folder or from its meta.json.
    let sog = dir.path().join("sog");
    std::fs::create_dir(&sog).unwrap();
    write_scene(&sog.join("meta.json"), &s).unwrap();
    assert_eq!(
        read_scene(&sog).unwrap(),
        read_scene(&sog.join("meta.json")).unwrap()
    );
    let (opened, cams) = crate::formats::open_scene(&sog).unwrap();
    assert_eq!(opened.len(), 20);
    assert!(cams.is_none());
}

#[test]
fn unknown_output_names_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let e = write_scene(&dir.path().join("scene.obj"), &scene(0, 1, 1))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("scene.obj") && e.contains("unknown output format"),
        "{e}"
    );
}

#[test]
fn lossy_writers_refuse_zero_rotations_and_non_finite_values() {
    let dir = tempfile::tempdir().unwrap();
    let mut s = scene(0, 2, 1);
    s.quats[4..8].fill(0.0);
    for name in &NAMES[1..] {
        let e = write_scene(&dir.path().join(name), &s)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("zero rotation") && e.contains("Gaussian 1"),
            "{name}: {e}"
        );
    }
    let mut s = scene(0, 2, 1);
    s.means[2] = f32::NAN;
    for name in NAMES {
        let e = write_scene(&dir.path().join(name), &s)
            .unwrap_err()
            .to_string();
        assert!(e.contains("non-finite"), "{name}: {e}");
    }
}

#[test]
fn splat_records_match_the_layout() {
    let s = GaussianScene {
        sh_degree: 0,
        means: vec![1.0, -2.0, 3.5],
        log_scales: vec![0.0, 1.0f32.ln() - 1.0, 2.0f32.ln()],
        quats: vec![-2.0, 0.0, 0.0, 0.0],
        opacity_logits: vec![0.0],
        sh: vec![0.0, 0.5 / SH_C0, -0.5 / SH_C0],
    };
    let r = dot_splat::encode_record(&s, 0);
    let f = |k: usize| f32::from_le_bytes(r[4 * k..4 * k + 4].try_into().unwrap());
    assert_eq!([f(0), f(1), f(2)], [1.0, -2.0, 3.5]);
    assert_eq!(f(3), 1.0);
    assert!((f(5) - 2.0).abs() < 1e-6);
    assert_eq!(&r[24..28], &[128, 255, 0, 128]);
    // -w is made positive: the identity rotation.
    assert_eq!(&r[28..32], &[255, 128, 128, 128]);
}

// ---------------------------------------------------------------------------------------------------------
// Files built byte by byte from the specifications (the reference tools' layout).

fn unorm(v: u32, bits: u32) -> f32 {
    v as f32 / ((1u32 << bits) - 1) as f32
}

#[test]
fn reads_a_compressed_ply_built_from_the_specification() {
    // Two Gaussians in one chunk, with the per-chunk colour box and an SH degree 1 element.
    let mut bytes =
        b"ply\nformat binary_little_endian 1.0\ncomment made by hand\nelement chunk 1\n".to_vec();
    // The chunk element's 18 floats: the position box, the scale box (min_x, .., max_z, min_scale_x,
    // .., max_scale_z), then the colour box (min_r, .., max_b).
    let mut chunk_props = Vec::new();
    for (what, axes) in [
        ("", ["x", "y", "z"]),
        ("scale_", ["x", "y", "z"]),
        ("", ["r", "g", "b"]),
    ] {
        for bound in ["min", "max"] {
            for axis in axes {
                chunk_props.push(format!("{bound}_{what}{axis}"));
            }
        }
    }
    for p in chunk_props {
        bytes.extend_from_slice(format!("property float {p}\n").as_bytes());
    }
    bytes.extend_from_slice(b"element vertex 2\nproperty uint packed_position\nproperty uint packed_rotation\nproperty uint packed_scale\nproperty uint packed_color\nelement sh 2\n");
    for i in 0..9 {
        bytes.extend_from_slice(format!("property uchar f_rest_{i}\n").as_bytes());
    }
    bytes.extend_from_slice(b"end_header\n");
    let chunk: [f32; 18] = [
        -1.0, 0.0, 2.0, 1.0, 4.0, 10.0, -3.0, -4.0, -5.0, -1.0, -2.0, -3.0, 0.0, 0.2, 0.4, 1.0,
        0.6, 0.8,
    ];
    for v in chunk {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    // Gaussian 0: x at the top of its range, y at the bottom, z at 1000/2047; rotation: largest is w,
    // the others (x, y, z) stored as 10-bit unorms of v·√½ + ½; scale all at max; colour (255, 0, 128),
    // opacity 51.
    let pos0 = (2047u32 << 21) | (1000);
    // Largest index 0 (w) in the top two bits.
    let rot0 = (600u32 << 20) | (511 << 10) | 400;
    let scale0 = (2047u32 << 21) | (1023 << 11) | 2047;
    let col0 = (255u32 << 24) | (128 << 8) | 51;
    // Gaussian 1: everything at the bottom; rotation with largest index 3 (z).
    let pos1 = 0u32;
    let rot1 = (3u32 << 30) | (511 << 20) | (511 << 10) | 511;
    let scale1 = 0u32;
    let col1 = 255u32;
    for v in [pos0, rot0, scale0, col0, pos1, rot1, scale1, col1] {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    bytes.extend_from_slice(&[0, 255, 128, 1, 2, 3, 4, 5, 6]);
    bytes.extend_from_slice(&[128; 9]);

    let s = compressed_ply::decode(&bytes).unwrap();
    assert_eq!((s.len(), s.sh_degree), (2, 1));
    let close = |a: f32, b: f32| (a - b).abs() < 1e-5;
    assert!(close(s.means[0], 1.0) && close(s.means[1], 0.0));
    assert!(close(s.means[2], 2.0 + 8.0 * unorm(1000, 11)));
    assert_eq!(&s.log_scales[..3], &[-1.0, -2.0, -3.0]);
    assert_eq!(&s.log_scales[3..6], &[-3.0, -4.0, -5.0]);
    let r = std::f32::consts::FRAC_1_SQRT_2;
    let (a, b, c) = (
        (unorm(600, 10) - 0.5) / r,
        (unorm(511, 10) - 0.5) / r,
        (unorm(400, 10) - 0.5) / r,
    );
    let w = (1.0 - a * a - b * b - c * c).sqrt();
    for (got, want) in s.quats[..4].iter().zip([w, a, b, c]) {
        assert!(close(*got, want), "{:?}", &s.quats[..4]);
    }
    assert!(close(s.quats[7], 1.0) && s.quats[4].abs() < 1e-2);
    // Colour: lerp within the chunk's colour box, then DC = (colour - 0.5) / C0.
    let dc = |colour: f32| (colour - 0.5) / SH_C0;
    assert!(close(s.sh[0], dc(1.0)));
    assert!(close(s.sh[1], dc(0.2)));
    assert!(close(s.sh[2], dc(0.4 + 0.4 * unorm(128, 8))));
    assert!(close(codec::sigmoid(s.opacity_logits[0]), 51.0 / 255.0));
    // SH: f_rest_{c·3 + k-1} is coefficient k of channel c; 0 → -4, 255 → 4, b → (b + ½)/256·8 - 4.
    let sh = |b: f32| ((b + 0.5) / 256.0 - 0.5) * 8.0;
    let coeff = |k: usize, c: usize| s.sh[3 * k + c];
    assert_eq!(coeff(1, 0), -4.0);
    assert_eq!(coeff(2, 0), 4.0);
    assert!(close(coeff(3, 0), sh(128.0)));
    assert!(close(coeff(1, 1), sh(1.0)) && close(coeff(3, 2), sh(6.0)));
    assert!(close(s.sh[12 + 3], sh(128.0)));
}

/// The arrays of the .spz fixture: 2 Gaussians, SH degree 1, 12 fraction bits.
fn spz_arrays(version: u32) -> Vec<u8> {
    let mut a = Vec::new();
    // Positions, 24-bit signed little-endian: (1, -1, 0.5) and (-2048 + 1/4096, 0, 2).
    for v in [4096i32, -4096, 2048, -(1 << 23) + 1, 0, 8192] {
        a.extend_from_slice(&v.to_le_bytes()[..3]);
    }
    a.extend_from_slice(&[255, 0]); // alphas
    a.extend_from_slice(&[128, 0, 255, 200, 100, 50]); // colours
    a.extend_from_slice(&[160, 0, 255, 80, 96, 112]); // scales: (s/16 - 10)
    if version == 2 {
        // x, y, z of a unit quaternion with w ≥ 0, as u8 of v·127.5 + 127.5.
        a.extend_from_slice(&[128, 128, 128, 255, 128, 128]);
    } else {
        // Smallest three: largest index (of x, y, z, w) in bits 30-31; then per other component a sign
        // bit and 9 magnitude bits of |v|/√½, first component in the highest bits.
        let identity = 3u32 << 30;
        // x largest (index 0); y negative at full magnitude; z and w zero.
        let x_largest = ((1u32 << 9) | 511) << 20;
        a.extend_from_slice(&identity.to_le_bytes());
        a.extend_from_slice(&x_largest.to_le_bytes());
    }
    // SH: 3 coefficients × 3 channels per Gaussian, channel inner, (b - 128)/128.
    a.extend_from_slice(&[0, 64, 128, 192, 255, 128, 128, 128, 128]);
    a.extend_from_slice(&[128; 9]);
    a
}

fn spz_fixture(version: u32) -> Vec<u8> {
    let arrays = spz_arrays(version);
    let mut header = Vec::new();
    header.extend_from_slice(b"NGSP");
    header.extend_from_slice(&version.to_le_bytes());
    header.extend_from_slice(&2u32.to_le_bytes());
    header.extend_from_slice(&[1, 12, 0]); // SH degree, fraction bits, flags
    if version < 4 {
        header.push(0);
        header.extend_from_slice(&arrays);
        let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::best());
        std::io::Write::write_all(&mut gz, &header).unwrap();
        return gz.finish().unwrap();
    }
    let sizes = [18usize, 2, 6, 6, 8, 18];
    header.push(6); // streams
    header.extend_from_slice(&32u32.to_le_bytes());
    header.extend_from_slice(&[0; 12]);
    let mut rest = &arrays[..];
    let mut compressed = Vec::new();
    for size in sizes {
        let (part, tail) = rest.split_at(size);
        rest = tail;
        compressed.push(zstd::bulk::compress(part, 3).unwrap());
    }
    for (c, size) in compressed.iter().zip(sizes) {
        header.extend_from_slice(&(c.len() as u64).to_le_bytes());
        header.extend_from_slice(&(size as u64).to_le_bytes());
    }
    for c in compressed {
        header.extend_from_slice(&c);
    }
    header
}

#[test]
fn reads_spz_built_from_the_specification() {
    for version in [2, 3, 4] {
        let s = spz::decode(&spz_fixture(version)).unwrap_or_else(|e| panic!("v{version}: {e}"));
        assert_eq!((s.len(), s.sh_degree), (2, 1));
        assert_eq!(&s.means[..3], &[1.0, -1.0, 0.5]);
        assert_eq!(&s.means[3..], &[-2048.0 + 1.0 / 4096.0, 0.0, 2.0]);
        let opacity: Vec<f32> = s
            .opacity_logits
            .iter()
            .map(|&l| codec::sigmoid(l))
            .collect();
        assert!(opacity[0] > 0.9999 && opacity[1] < 1e-4, "{opacity:?}");
        let dc = |b: f32| (b / 255.0 - 0.5) / 0.15;
        assert_eq!(&s.sh[..3], &[dc(128.0), dc(0.0), dc(255.0)]);
        assert_eq!(&s.sh[12..15], &[dc(200.0), dc(100.0), dc(50.0)]);
        assert_eq!(
            &s.sh[3..12],
            &[-1.0, -0.5, 0.0, 0.5, 127.0 / 128.0, 0.0, 0.0, 0.0, 0.0]
        );
        assert_eq!(&s.log_scales[..3], &[0.0, -10.0, 255.0 / 16.0 - 10.0]);
        let q0 = &s.quats[..4];
        let q1 = &s.quats[4..];
        assert!(
            (q0[0] - 1.0).abs() < 1e-2 && q0[1..].iter().all(|v| v.abs() < 1e-2),
            "v{version}: {q0:?}"
        );
        if version == 2 {
            assert!((q1[1] - 1.0).abs() < 1e-2, "{q1:?}");
        } else {
            // x largest; y stored with the sign bit and full magnitude: y = -√½, x = √½.
            let r = std::f32::consts::FRAC_1_SQRT_2;
            assert!(
                (q1[1] - r).abs() < 1e-5 && (q1[2] + r).abs() < 1e-5,
                "{q1:?}"
            );
        }
    }
}

// ---------------------------------------------------------------------------------------------------------
// The real scene

#[test]
fn the_real_scene_round_trips_through_every_format() {
    let path =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/assets/scenes/playbot-3k.ply");
    if !path.is_file() {
        eprintln!("skipped: {} is absent", path.display());
        return;
    }
    let full = read_scene(&path).unwrap();
    assert_eq!(full.sh_degree, 2);
    // Every third Gaussian keeps the test quick and still covers the scene's range of values.
    let keep: Vec<bool> = (0..full.len()).map(|i| i % 3 == 0).collect();
    let mut s = full.clone();
    s.retain(&keep);
    let dir = tempfile::tempdir().unwrap();
    let (lo, hi) = s.bounds().unwrap();
    let extent = (0..3).map(|a| hi[a] - lo[a]).fold(0.0, f32::max);
    for name in NAMES {
        let (report, back) = round_trip(dir.path(), name, &s);
        let Some(e) = report.error else { continue };
        eprintln!("{name}: {report}");
        assert!(e.position <= extent / 1000.0, "{name}: {report}");
        assert!(e.opacity <= 0.5 / 255.0 + 1e-5, "{name}: {report}");
        assert!(e.rotation_deg <= 1.5, "{name}: {report}");
        assert!(back.sh_degree == 2 || name.ends_with(".splat"));
    }
}

// ---------------------------------------------------------------------------------------------------------
// Malformed files

fn assert_clean_error(path: &Path, what: &str) {
    match read_scene(path) {
        Ok(s) => panic!("{what}: read {} Gaussians from a broken file", s.len()),
        Err(e) => {
            let msg = e.to_string();
            assert!(
                msg.contains(&path.display().to_string()) && !msg.contains('\n'),
                "{what}: {msg}"
            );
        }
    }
}

#[test]
fn truncated_files_of_every_format_are_one_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let s = scene(2, 300, 4);
    for name in ["s.compressed.ply", "s.spz", "s.sog"] {
        let path = dir.path().join(name);
        write_scene(&path, &s).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        for cut in [1, 5, 17, 40, bytes.len() / 2, bytes.len() - 1] {
            let broken = dir.path().join(format!("cut-{cut}-{name}"));
            std::fs::write(&broken, &bytes[..cut]).unwrap();
            assert_clean_error(&broken, &format!("{name} cut at {cut}"));
        }
    }
    let path = dir.path().join("s.splat");
    write_scene(&path, &s).unwrap();
    let bytes = std::fs::read(&path).unwrap();
    std::fs::write(&path, &bytes[..bytes.len() - 3]).unwrap();
    assert_clean_error(&path, ".splat cut");
}

#[test]
fn wrong_magic_and_impossible_counts_are_refused_before_allocating() {
    let dir = tempfile::tempdir().unwrap();
    let write = |name: &str, bytes: &[u8]| {
        let p = dir.path().join(name);
        std::fs::write(&p, bytes).unwrap();
        p
    };
    // .spz v4 claiming four billion Gaussians in a few bytes.
    let mut v4 = spz_fixture(4);
    v4[8..12].copy_from_slice(&u32::MAX.to_le_bytes());
    assert_clean_error(&write("huge.spz", &v4), "huge v4 count");
    let e = read_scene(&dir.path().join("huge.spz"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("4294967295") && e.contains(".spz"), "{e}");
    // .spz v3 with a huge count inside the gzip stream.
    let mut raw = Vec::new();
    flate2::read::GzDecoder::new(&spz_fixture(3)[..])
        .read_to_end(&mut raw)
        .unwrap();
    raw[8..12].copy_from_slice(&u32::MAX.to_le_bytes());
    let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
    std::io::Write::write_all(&mut gz, &raw).unwrap();
    assert_clean_error(&write("huge3.spz", &gz.finish().unwrap()), "huge v3 count");
    // Unknown version, and a gzip stream that is not .spz.
    let mut v9 = spz_fixture(4);
    v9[4] = 9;
    assert_clean_error(&write("v9.spz", &v9), "version 9");
    let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
    std::io::Write::write_all(&mut gz, b"hello, this is not a scene at all").unwrap();
    assert_clean_error(&write("notspz.spz", &gz.finish().unwrap()), "gzip of text");
    // Compressed PLY declaring more vertices than the file holds.
    let s = scene(0, 10, 1);
    let bytes = compressed_ply::encode(&s).unwrap();
    let header_end = bytes
        .windows(11)
        .position(|w| w == b"end_header\n")
        .unwrap()
        + 11;
    let header = String::from_utf8(bytes[..header_end].to_vec()).unwrap();
    let mut huge = header
        .replace("element vertex 10", "element vertex 99999999")
        .into_bytes();
    huge.extend_from_slice(&bytes[header_end..]);
    let p = write("huge.compressed.ply", &huge);
    let e = read_scene(&p).unwrap_err().to_string();
    assert!(
        e.contains("99999999") && e.contains("compressed PLY"),
        "{e}"
    );
    // SOG whose meta.json declares more Gaussians than its textures hold.
    let sog = dir.path().join("sog");
    std::fs::create_dir(&sog).unwrap();
    write_scene(&sog.join("meta.json"), &s).unwrap();
    let meta = std::fs::read_to_string(sog.join("meta.json")).unwrap();
    std::fs::write(
        sog.join("meta.json"),
        meta.replace("\"count\":10", "\"count\":1000000000000"),
    )
    .unwrap();
    assert_clean_error(&sog.join("meta.json"), "huge SOG count");
    std::fs::write(
        sog.join("meta.json"),
        meta.replace("\"version\":2", "\"version\":7"),
    )
    .unwrap();
    assert_clean_error(&sog, "SOG version 7");
    std::fs::write(
        sog.join("meta.json"),
        meta.replace("means_l.webp", "../means_l.webp"),
    )
    .unwrap();
    assert_clean_error(&sog, "SOG path escape");
    std::fs::remove_file(sog.join("quats.webp")).unwrap();
    std::fs::write(sog.join("meta.json"), &meta).unwrap();
    assert_clean_error(&sog, "SOG missing texture");
    // Neither format: text, and an empty file.
    assert_clean_error(&write("notes.txt", b"just some text\n"), "text");
    assert_clean_error(&write("empty.splat", b""), "empty");
    assert_clean_error(&write("zip.sog", b"PK\x03\x04 not really a zip"), "bad zip");
}

#[test]
fn corrupted_files_never_panic() {
    let dir = tempfile::tempdir().unwrap();
    let s = scene(1, 70, 2);
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    for name in ["s.compressed.ply", "s.splat", "s.spz", "s.sog"] {
        let path = dir.path().join(name);
        write_scene(&path, &s).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        for round in 0..40 {
            let mut broken = bytes.clone();
            for _ in 0..1 + round % 4 {
                let i = rng.gen_range(0..broken.len());
                broken[i] = rng.gen();
            }
            let p = dir.path().join(format!("fuzz-{round}-{name}"));
            std::fs::write(&p, &broken).unwrap();
            // Either a scene (the damage hit a value) or one clear error: never a panic.
            if let Err(e) = read_scene(&p) {
                let msg = e.to_string();
                assert!(msg.contains(&p.display().to_string()), "{msg}");
            }
        }
    }
    for version in [2, 3, 4] {
        let bytes = spz_fixture(version);
        for i in 0..bytes.len() {
            let mut broken = bytes.clone();
            broken[i] ^= 0x5a;
            let _ = spz::decode(&broken);
        }
    }
}

/// A SOG folder output is written whole, over a SOG scene only (issue 69): a folder of other files, or a
/// scene with a stranger's file beside it, is refused; a scene is replaced with nothing of it left.
#[test]
fn sog_folders_are_replaced_whole_and_only_over_a_scene() {
    let dir = tempfile::tempdir().unwrap();
    let sog = dir.path().join("sog");
    let meta = sog.join("meta.json");
    write_scene(&meta, &scene(3, 5, 1)).unwrap();
    let with_sh = std::fs::read_dir(&sog).unwrap().count();
    // Degree 0 writes fewer textures: the old scene's SH files must go.
    write_scene(&meta, &scene(0, 5, 2)).unwrap();
    let now = std::fs::read_dir(&sog).unwrap().count();
    assert!(now < with_sh, "{now} files after replacing {with_sh}");
    assert_eq!(read_scene(&meta).unwrap().sh_degree, 0);
    assert_eq!(
        std::fs::read_dir(dir.path()).unwrap().count(),
        1,
        "nothing beside"
    );
    std::fs::write(sog.join("notes.txt"), "mine").unwrap();
    let e = write_scene(&meta, &scene(0, 5, 3)).unwrap_err().to_string();
    assert!(e.contains("not a SOG scene"), "{e}");
    assert!(sog.join("notes.txt").exists());
    assert!(check_scene_output(&meta).is_err());
    let site = dir.path().join("site");
    std::fs::create_dir(&site).unwrap();
    std::fs::write(site.join("meta.json"), r#"{"title": "my site"}"#).unwrap();
    assert!(write_scene(&site.join("meta.json"), &scene(0, 5, 3)).is_err());
    assert_eq!(
        std::fs::read_to_string(site.join("meta.json")).unwrap(),
        r#"{"title": "my site"}"#
    );
}

/// A SOG folder stays replaceable while another vcedit run probes it (its output checks make a
/// temporary file there): two runs writing one folder at once both pass their checks. Anyone else's file
/// still makes the folder off limits, even one that looks like a temporary name of another program.
#[test]
fn another_runs_probe_in_a_sog_folder_does_not_make_it_foreign() {
    let dir = tempfile::tempdir().unwrap();
    let sog = dir.path().join("sog");
    std::fs::create_dir(&sog).unwrap();
    write_scene(&sog.join("meta.json"), &scene(0, 20, 1)).unwrap();
    let textures = sog::replaceable_files(&sog).expect("a SOG folder");
    std::fs::write(sog.join(".probe.vcedit-tmp-4194305-Ab3dE5fG7hJ9"), b"").unwrap();
    assert_eq!(sog::replaceable_files(&sog), Some(textures));
    assert!(check_scene_output(&sog.join("meta.json")).is_ok());
    for foreign in [".probe.vcedit-tmp-4194305-short", "notes.txt"] {
        std::fs::write(sog.join(foreign), b"mine").unwrap();
        assert_eq!(sog::replaceable_files(&sog), None, "{foreign}");
        std::fs::remove_file(sog.join(foreign)).unwrap();
    }
}
