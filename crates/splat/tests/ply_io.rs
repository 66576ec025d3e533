//! PLY reading and writing: self-made fixtures for every feature, the real playbot scenes when present,
//! a corpus of malformed files with the message each must produce, and corruption fuzzing.

use proptest::prelude::*;
use splat::ply::{inria_property_names, read_ply, write_ply};
use splat::scene::sh_coeffs;
use splat::GaussianScene;
use std::path::{Path, PathBuf};

// ---------------------------------------------------------------------------------------------------------
// A small PLY writer for fixtures: any format, any property types and order, lists, several elements.

#[derive(Clone, Copy, PartialEq)]
enum Format {
    Ascii,
    Le,
    Be,
}

#[derive(Clone)]
struct Prop {
    name: String,
    ty: &'static str,
    /// Count type for list properties.
    list: Option<&'static str>,
}

fn scalar(name: &str, ty: &'static str) -> Prop {
    Prop {
        name: name.into(),
        ty,
        list: None,
    }
}

fn list(name: &str, count: &'static str, ty: &'static str) -> Prop {
    Prop {
        name: name.into(),
        ty,
        list: Some(count),
    }
}

struct Element {
    name: String,
    props: Vec<Prop>,
    /// rows[r][p]: the values of property p in row r (one for a scalar).
    rows: Vec<Vec<Vec<f64>>>,
}

fn encode_value(out: &mut Vec<u8>, format: Format, ty: &str, v: f64) {
    if format == Format::Ascii {
        let text = match ty {
            "float" => format!("{}", v as f32),
            "double" => format!("{v}"),
            _ => format!("{}", v as i64),
        };
        out.extend_from_slice(text.as_bytes());
        out.push(b' ');
        return;
    }
    macro_rules! put {
        ($x:expr) => {
            if format == Format::Le {
                out.extend_from_slice(&$x.to_le_bytes())
            } else {
                out.extend_from_slice(&$x.to_be_bytes())
            }
        };
    }
    match ty {
        "char" => put!(v as i8),
        "uchar" => put!(v as u8),
        "short" => put!(v as i16),
        "ushort" => put!(v as u16),
        "int" => put!(v as i32),
        "uint" => put!(v as u32),
        "float" => put!(v as f32),
        "double" => put!(v),
        other => panic!("fixture type {other}"),
    }
}

fn encode(format: Format, elements: &[Element]) -> Vec<u8> {
    let mut out = b"ply\n".to_vec();
    out.extend_from_slice(match format {
        Format::Ascii => b"format ascii 1.0\n".as_slice(),
        Format::Le => b"format binary_little_endian 1.0\n",
        Format::Be => b"format binary_big_endian 1.0\n",
    });
    out.extend_from_slice(b"comment made by the vcedit tests\n");
    for e in elements {
        out.extend_from_slice(format!("element {} {}\n", e.name, e.rows.len()).as_bytes());
        for p in &e.props {
            let line = match p.list {
                Some(c) => format!("property list {c} {} {}\n", p.ty, p.name),
                None => format!("property {} {}\n", p.ty, p.name),
            };
            out.extend_from_slice(line.as_bytes());
        }
    }
    out.extend_from_slice(b"end_header\n");
    for e in elements {
        for row in &e.rows {
            for (p, values) in e.props.iter().zip(row) {
                if let Some(count_ty) = p.list {
                    encode_value(&mut out, format, count_ty, values.len() as f64);
                }
                for &v in values {
                    encode_value(&mut out, format, p.ty, v);
                }
            }
            if format == Format::Ascii {
                out.pop();
                out.push(b'\n');
            }
        }
    }
    out
}

/// A deterministic scene with values that exercise signs and magnitudes.
fn scene(sh_degree: u32, n: usize, seed: u32) -> GaussianScene {
    let k = sh_coeffs(sh_degree);
    let v = |i: usize, salt: u32| {
        let h = (i as u32)
            .wrapping_mul(2654435761)
            .wrapping_add(seed.wrapping_mul(40503) + salt);
        ((h >> 8) % 20001) as f32 / 1000.0 - 10.0
    };
    GaussianScene {
        sh_degree,
        means: (0..3 * n).map(|i| v(i, 1)).collect(),
        log_scales: (0..3 * n).map(|i| v(i, 2) * 0.2 - 3.0).collect(),
        quats: (0..4 * n).map(|i| v(i, 3) + 0.25).collect(),
        opacity_logits: (0..n).map(|i| v(i, 4)).collect(),
        sh: (0..3 * k * n).map(|i| v(i, 5) * 0.1).collect(),
    }
}

/// The value a 3DGS property (or an extra one) holds for Gaussian `n`.
fn value_of(scene: &GaussianScene, name: &str, n: usize) -> f64 {
    let k = scene.sh_coeffs();
    let idx = |prefix: &str| {
        name.strip_prefix(prefix)
            .and_then(|s| s.parse::<usize>().ok())
    };
    let v = match name {
        "x" | "y" | "z" => scene.means[3 * n + (name.as_bytes()[0] - b'x') as usize],
        "opacity" => scene.opacity_logits[n],
        "nx" | "ny" | "nz" => 0.0,
        _ => {
            if let Some(c) = idx("f_dc_") {
                scene.sh[n * k * 3 + c]
            } else if let Some(i) = idx("f_rest_") {
                let (c, kk) = (i / (k - 1), i % (k - 1) + 1);
                scene.sh[(n * k + kk) * 3 + c]
            } else if let Some(a) = idx("scale_") {
                scene.log_scales[3 * n + a]
            } else if let Some(a) = idx("rot_") {
                scene.quats[4 * n + a]
            } else {
                // Extra properties: small integers fit every type.
                ((n * 7 + name.len()) % 100) as f32
            }
        }
    };
    v as f64
}

fn vertex_element(scene: &GaussianScene, props: Vec<Prop>) -> Element {
    let rows = (0..scene.len())
        .map(|n| {
            props
                .iter()
                .map(|p| match p.list {
                    Some(_) => (0..n % 4).map(|j| j as f64).collect(),
                    None => vec![value_of(scene, &p.name, n)],
                })
                .collect()
        })
        .collect();
    Element {
        name: "vertex".into(),
        props,
        rows,
    }
}

fn floats(names: &[String]) -> Vec<Prop> {
    names.iter().map(|n| scalar(n, "float")).collect()
}

fn write(dir: &Path, name: &str, bytes: &[u8]) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, bytes).unwrap();
    p
}

// ---------------------------------------------------------------------------------------------------------
// Features

#[test]
fn every_format_and_degree_in_a_shuffled_order() {
    let dir = tempfile::tempdir().unwrap();
    for degree in 0..=3 {
        let s = scene(degree, 37, degree);
        let mut names = inria_property_names(degree);
        // A fixed shuffle: reverse, then rotate, so no property keeps its INRIA position.
        names.reverse();
        names.rotate_left(5);
        for format in [Format::Ascii, Format::Le, Format::Be] {
            let bytes = encode(format, &[vertex_element(&s, floats(&names))]);
            let p = write(dir.path(), "s.ply", &bytes);
            let back = read_ply(&p).unwrap_or_else(|e| panic!("degree {degree}: {e}"));
            assert_eq!(back, s, "degree {degree}");
        }
    }
}

#[test]
fn normals_are_optional_and_extra_properties_of_any_type_are_skipped() {
    let dir = tempfile::tempdir().unwrap();
    let s = scene(1, 23, 7);
    let mut props = vec![
        scalar("red", "uchar"),
        scalar("segment", "short"),
        list("neighbours", "uchar", "int"),
    ];
    props.extend(
        inria_property_names(1)
            .iter()
            .filter(|n| !n.starts_with('n'))
            .map(|n| scalar(n, "float")),
    );
    props.insert(9, scalar("confidence", "double"));
    props.insert(14, list("tags", "int", "uchar"));
    props.push(scalar("flags", "uint"));
    props.push(scalar("delta", "char"));
    props.push(scalar("count", "ushort"));
    for format in [Format::Ascii, Format::Le, Format::Be] {
        let bytes = encode(format, &[vertex_element(&s, props.clone())]);
        let p = write(dir.path(), "extra.ply", &bytes);
        assert_eq!(read_ply(&p).unwrap(), s);
    }
}

#[test]
fn double_properties_are_converted() {
    let dir = tempfile::tempdir().unwrap();
    let s = scene(0, 9, 3);
    let props: Vec<Prop> = inria_property_names(0)
        .iter()
        .enumerate()
        .map(|(i, n)| scalar(n, if i % 2 == 0 { "double" } else { "float" }))
        .collect();
    for format in [Format::Ascii, Format::Le] {
        let p = write(
            dir.path(),
            "d.ply",
            &encode(format, &[vertex_element(&s, props.clone())]),
        );
        assert_eq!(read_ply(&p).unwrap(), s);
    }
}

#[test]
fn other_elements_before_and_after_the_vertices() {
    let dir = tempfile::tempdir().unwrap();
    let s = scene(2, 11, 5);
    let camera = Element {
        name: "camera".into(),
        props: vec![scalar("view_px", "float"), scalar("id", "int")],
        rows: vec![vec![vec![1.5], vec![7.0]], vec![vec![2.5], vec![8.0]]],
    };
    let empty = Element {
        name: "nothing".into(),
        props: vec![],
        rows: vec![vec![]; 3],
    };
    let face = Element {
        name: "face".into(),
        props: vec![
            list("vertex_indices", "uchar", "int"),
            scalar("w", "double"),
        ],
        rows: (0..5)
            .map(|i| vec![(0..(i % 3 + 1)).map(|j| j as f64).collect(), vec![0.5]])
            .collect(),
    };
    let tail = Element {
        name: "material".into(),
        props: vec![scalar("r", "uchar")],
        rows: vec![vec![vec![3.0]]],
    };
    let vertex = vertex_element(&s, floats(&inria_property_names(2)));
    let elements = [camera, face, empty, vertex, tail];
    for format in [Format::Ascii, Format::Le, Format::Be] {
        let p = write(dir.path(), "multi.ply", &encode(format, &elements));
        assert_eq!(read_ply(&p).unwrap(), s);
    }
}

#[test]
fn written_files_have_the_exact_inria_layout() {
    let dir = tempfile::tempdir().unwrap();
    let s = scene(3, 4, 1);
    let p = dir.path().join("out.ply");
    write_ply(&p, &s).unwrap();
    let bytes = std::fs::read(&p).unwrap();
    let mut expected = format!(
        "ply\nformat binary_little_endian 1.0\nelement vertex {}\n",
        s.len()
    );
    let mut names = vec![
        "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2",
    ]
    .into_iter()
    .map(String::from)
    .collect::<Vec<_>>();
    names.extend((0..45).map(|i| format!("f_rest_{i}")));
    names.extend(
        [
            "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
        ]
        .map(String::from),
    );
    for n in &names {
        expected.push_str(&format!("property float {n}\n"));
    }
    expected.push_str("end_header\n");
    assert!(bytes.starts_with(expected.as_bytes()));
    // Same bytes as the independent fixture writer produces for the INRIA order.
    let reference = encode(Format::Le, &[vertex_element(&s, floats(&names))]);
    let data = &bytes[expected.len()..];
    let reference_data = &reference[reference.len() - data.len()..];
    assert_eq!(data, reference_data);
    assert_eq!(data.len(), s.len() * names.len() * 4);
}

fn shared_scene(name: &str) -> Option<PathBuf> {
    testkit::paths::shared_asset(&format!("scenes/{name}"))
}

#[test]
fn real_playbot_scenes_read_and_roundtrip_bit_for_bit() {
    let dir = tempfile::tempdir().unwrap();
    for (name, count) in [("playbot-3k.ply", 3000), ("playbot-31k.ply", 31000)] {
        let Some(path) = shared_scene(name) else {
            continue;
        };
        let s = read_ply(&path).unwrap();
        assert_eq!(s.sh_degree, 2);
        assert!(s.len() >= count && s.len() < count + 1000, "{}", s.len());
        s.check_shapes().unwrap();

        // Cross-check the first vertex against the raw bytes: the file's order is
        // x y z scale_0..2 f_dc_0..2 opacity rot_0..3 f_rest_0..23.
        let bytes = std::fs::read(&path).unwrap();
        let start = bytes
            .windows(11)
            .position(|w| w == b"end_header\n")
            .unwrap()
            + 11;
        let raw: Vec<f32> = bytes[start..start + 38 * 4]
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
            .collect();
        assert_eq!(&s.means[..3], &raw[0..3]);
        assert_eq!(&s.log_scales[..3], &raw[3..6]);
        assert_eq!(&s.sh[..3], &raw[6..9]);
        assert_eq!(s.opacity_logits[0], raw[9]);
        assert_eq!(&s.quats[..4], &raw[10..14]);
        // f_rest_{c*8 + k-1} -> sh[k*3 + c]
        assert_eq!(s.sh[3], raw[14]); // k=1, c=0
        assert_eq!(s.sh[4], raw[14 + 8]); // k=1, c=1
        assert_eq!(s.sh[8 * 3 + 2], raw[14 + 2 * 8 + 7]); // k=8, c=2

        let out = dir.path().join(name);
        write_ply(&out, &s).unwrap();
        let back = read_ply(&out).unwrap();
        assert_eq!(back, s);
        assert!(back
            .means
            .iter()
            .chain(&back.sh)
            .zip(s.means.iter().chain(&s.sh))
            .all(|(a, b)| a.to_bits() == b.to_bits()));
        let again = dir.path().join(format!("again-{name}"));
        write_ply(&again, &back).unwrap();
        assert_eq!(std::fs::read(&out).unwrap(), std::fs::read(&again).unwrap());
    }
}

// ---------------------------------------------------------------------------------------------------------
// Malformed files: each must give one error naming the file and saying what is wrong.

fn header(body: &str) -> Vec<u8> {
    format!("ply\nformat binary_little_endian 1.0\n{body}end_header\n").into_bytes()
}

fn vertex_header(n: u64, names: &[String], ty: &str) -> String {
    let mut h = format!("element vertex {n}\n");
    for name in names {
        h.push_str(&format!("property {ty} {name}\n"));
    }
    h
}

/// A valid little-endian degree-0 file with one vertex per row in `rows` (14 floats each, INRIA order).
fn raw_file(rows: &[[f32; 14]]) -> Vec<u8> {
    let mut b = header(&vertex_header(
        rows.len() as u64,
        &inria_property_names(0),
        "float",
    ));
    for row in rows {
        // INRIA order is x y z nx ny nz dc0..2 opacity s0..2 r0..3 = 17 values; normals are zero.
        let full = [
            row[0], row[1], row[2], 0.0, 0.0, 0.0, row[3], row[4], row[5], row[6], row[7], row[8],
            row[9], row[10], row[11], row[12], row[13],
        ];
        for v in full {
            b.extend_from_slice(&v.to_le_bytes());
        }
    }
    b
}

const GOOD_ROW: [f32; 14] = [
    0.1, 0.2, 0.3, 0.5, 0.5, 0.5, 0.0, -3.0, -3.0, -3.0, 1.0, 0.0, 0.0, 0.0,
];

#[test]
fn malformed_files_give_specific_messages() {
    let names0 = inria_property_names(0);
    let without =
        |drop: &str| -> Vec<String> { names0.iter().filter(|n| *n != drop).cloned().collect() };
    let with_rest = |count: usize, skip: Option<usize>| -> Vec<String> {
        let mut v = names0.clone();
        v.extend(
            (0..=count)
                .filter(|i| Some(*i) != skip)
                .map(|i| format!("f_rest_{i}"))
                .take(count),
        );
        v
    };
    let mut nan_row = GOOD_ROW;
    nan_row[6] = f32::NAN;
    let mut inf_row = GOOD_ROW;
    inf_row[0] = f32::INFINITY;
    let mut zero_quat = GOOD_ROW;
    zero_quat[10] = 0.0;
    let mut tiny_quat = GOOD_ROW;
    tiny_quat[10] = 1e-30;
    let ascii = |body: &str, data: &str| -> Vec<u8> {
        let mut h = format!(
            "ply\nformat ascii 1.0\n{}end_header\n",
            vertex_header(2, &names0, "float")
        )
        .into_bytes();
        h.extend_from_slice(body.as_bytes());
        h.extend_from_slice(data.as_bytes());
        h
    };
    let good_ascii_row = "0.1 0.2 0.3 0 0 0 0.5 0.5 0.5 0 -3 -3 -3 1 0 0 0\n";
    let mut truncated = raw_file(&[GOOD_ROW, GOOD_ROW]);
    truncated.truncate(truncated.len() - 3);
    let mut trailing = raw_file(&[GOOD_ROW]);
    trailing.extend_from_slice(&[0; 68]);
    let mut huge_header = b"ply\nformat ascii 1.0\n".to_vec();
    huge_header.extend(
        std::iter::repeat_n(b"comment padding padding padding\n".as_slice(), 40_000).flatten(),
    );
    let mut not_text = b"ply\nformat ascii 1.0\ncomment \xff\xfe\n".to_vec();
    not_text.extend_from_slice(b"end_header\n");
    let mut list_overrun = header(&format!(
        "element face 1\nproperty list uchar int idx\n{}",
        vertex_header(0, &names0, "float")
    ));
    list_overrun.extend_from_slice(&[200, 1, 0, 0, 0]);

    let cases: Vec<(&str, Vec<u8>, &str)> = vec![
        ("empty", vec![], "the file is empty"),
        (
            "magic",
            b"plx\nformat ascii 1.0\nend_header\n".to_vec(),
            "not a PLY file",
        ),
        (
            "binary garbage",
            vec![0x89, b'P', b'N', b'G', 0, 0, 0, 0xff, b'\n'],
            "not a PLY file",
        ),
        (
            "no end",
            b"ply\nformat ascii 1.0\nelement vertex 1\n".to_vec(),
            "ends before end_header",
        ),
        (
            "huge header",
            huge_header,
            "no end_header within the first 1048576 bytes",
        ),
        ("not text", not_text, "line 3 is not text"),
        (
            "format",
            b"ply\nformat binary_middle_endian 1.0\nend_header\n".to_vec(),
            "line 2: unknown format 'binary_middle_endian'",
        ),
        (
            "version",
            b"ply\nformat ascii 2.0\nend_header\n".to_vec(),
            "unsupported PLY version '2.0'",
        ),
        (
            "no format",
            b"ply\nelement vertex 0\nend_header\n".to_vec(),
            "no 'format' line",
        ),
        (
            "two formats",
            b"ply\nformat ascii 1.0\nformat ascii 1.0\nend_header\n".to_vec(),
            "a second 'format' line",
        ),
        (
            "count",
            header("element vertex abc\n"),
            "element 'vertex' has an invalid count 'abc'",
        ),
        (
            "count too big for u64",
            header("element vertex 100000000000000000000000\n"),
            "invalid count",
        ),
        (
            "negative count",
            header("element vertex -5\n"),
            "invalid count '-5'",
        ),
        (
            "orphan property",
            header("property float x\n"),
            "a property before any element",
        ),
        (
            "type",
            header("element vertex 1\nproperty float16 x\n"),
            "unknown property type 'float16'",
        ),
        (
            "list count type",
            header("element vertex 1\nproperty list float int x\n"),
            "non-integer count type 'float'",
        ),
        (
            "short property line",
            header("element vertex 1\nproperty float\n"),
            "expected 'property <type> <name>'",
        ),
        (
            "duplicate property",
            header("element vertex 1\nproperty float x\nproperty float x\n"),
            "property 'x' of element 'vertex' is declared twice",
        ),
        (
            "duplicate element",
            header("element vertex 0\nelement vertex 0\n"),
            "element 'vertex' is declared twice",
        ),
        (
            "keyword",
            header("elephant vertex 1\n"),
            "line 3: unknown keyword 'elephant'",
        ),
        (
            "no vertex",
            header("element face 0\n"),
            "no 'vertex' element",
        ),
        (
            "missing rot_3",
            header(&vertex_header(1, &without("rot_3"), "float")),
            "has no property rot_3",
        ),
        (
            "missing several",
            header(&vertex_header(
                1,
                &without("x")
                    .into_iter()
                    .filter(|n| n != "opacity")
                    .collect::<Vec<_>>(),
                "float",
            )),
            "has no properties x, opacity",
        ),
        (
            "a mesh's vertices",
            header(
                "element vertex 1\nproperty float x\nproperty float y\nproperty float z\n\
                 property float nx\nproperty float ny\nproperty float nz\n\
                 property uchar red\nproperty uchar green\nproperty uchar blue\n",
            ),
            "(a mesh or point cloud, not 3D Gaussians: `vcedit fit` makes a 3DGS scene from posed images)",
        ),
        (
            "int property",
            header(&vertex_header(1, &names0, "int")),
            "property 'x' has type int; 3DGS properties must be float or double",
        ),
        (
            "uchar opacity",
            header(&(vertex_header(1, &without("opacity"), "float") + "property uchar opacity\n")),
            "property 'opacity' has type uchar",
        ),
        (
            "list property",
            header(
                &(vertex_header(1, &without("scale_1"), "float")
                    + "property list uchar float scale_1\n"),
            ),
            "property 'scale_1' is a list",
        ),
        (
            "rest count",
            header(&vertex_header(1, &with_rest(10, None), "float")),
            "found 10 f_rest_* properties; expected 0, 9, 24 or 45",
        ),
        (
            "rest gap",
            header(&vertex_header(1, &with_rest(9, Some(8)), "float")),
            "f_rest_8 is missing",
        ),
        (
            "absurd count",
            header(&vertex_header(1_000_000_000_000, &names0, "float")),
            "declares 1000000000000 'vertex' rows",
        ),
        (
            "overflowing count",
            header(&vertex_header(10_000_000_000_000_000_000, &names0, "float")),
            "more than 2^64",
        ),
        ("truncated", truncated, "only 133 bytes follow the header"),
        ("trailing", trailing, "68 bytes after the last element"),
        (
            "nan",
            raw_file(&[GOOD_ROW, nan_row]),
            "vertex 1: property 'opacity' is NaN",
        ),
        ("inf", raw_file(&[inf_row]), "vertex 0: property 'x' is inf"),
        (
            "zero quaternion",
            raw_file(&[GOOD_ROW, GOOD_ROW, zero_quat]),
            "vertex 2: rotation quaternion (0, 0, 0, 0) is zero",
        ),
        (
            "tiny quaternion",
            raw_file(&[tiny_quat]),
            "too small to normalise",
        ),
        (
            "list overrun",
            list_overrun,
            "the file ends inside row 0 of element 'face'",
        ),
        (
            "ascii number",
            ascii(
                "",
                &format!("{good_ascii_row}0.1 abc 0.3 0 0 0 0.5 0.5 0.5 0 -3 -3 -3 1 0 0 0\n"),
            ),
            "vertex 1: property 'y': cannot parse 'abc' as a number",
        ),
        (
            "ascii short",
            ascii("", good_ascii_row),
            "the file ends inside vertex 1 (of 2)",
        ),
        (
            "ascii extra",
            ascii(
                "",
                &format!("{good_ascii_row}{good_ascii_row}{good_ascii_row}"),
            ),
            "unexpected data '0.1' after the last element",
        ),
        (
            "ascii overflow",
            ascii(
                "",
                &format!("{good_ascii_row}1e300 0 0 0 0 0 0.5 0.5 0.5 0 -3 -3 -3 1 0 0 0\n"),
            ),
            "vertex 1: property 'x' is inf",
        ),
        (
            "ascii nan",
            ascii(
                "",
                &format!("{good_ascii_row}0 0 0 0 0 0 0.5 0.5 0.5 nan -3 -3 -3 1 0 0 0\n"),
            ),
            "property 'opacity' is NaN",
        ),
        (
            "ascii zero quat",
            ascii(
                "",
                &format!("{good_ascii_row}0 0 0 0 0 0 0.5 0.5 0.5 0 -3 -3 -3 0 0 0 0\n"),
            ),
            "vertex 1: rotation quaternion",
        ),
    ];

    let dir = tempfile::tempdir().unwrap();
    for (i, (label, bytes, want)) in cases.iter().enumerate() {
        let p = write(dir.path(), &format!("case{i}.ply"), bytes);
        let e = match read_ply(&p) {
            Ok(s) => panic!("{label}: expected an error, read {} Gaussians", s.len()),
            Err(e) => e.to_string(),
        };
        assert!(e.contains(want), "{label}: wanted '{want}' in: {e}");
        assert!(
            e.starts_with(&p.display().to_string()),
            "{label}: no path in: {e}"
        );
        assert!(!e.contains('\n'), "{label}: multi-line message: {e}");
    }

    let missing = dir.path().join("missing.ply");
    let e = read_ply(&missing).unwrap_err().to_string();
    assert!(
        e.contains("missing.ply") && e.contains("cannot read"),
        "{e}"
    );
}

#[test]
fn crlf_headers_and_ascii_without_final_newline_are_fine() {
    let dir = tempfile::tempdir().unwrap();
    let s = scene(0, 2, 9);
    let mut bytes = encode(
        Format::Le,
        &[vertex_element(&s, floats(&inria_property_names(0)))],
    );
    let end = bytes
        .windows(11)
        .position(|w| w == b"end_header\n")
        .unwrap()
        + 11;
    let head = String::from_utf8(bytes[..end].to_vec())
        .unwrap()
        .replace('\n', "\r\n");
    bytes.splice(..end - 1, head[..head.len() - 1].bytes());
    let p = write(dir.path(), "crlf.ply", &bytes);
    assert_eq!(read_ply(&p).unwrap(), s);

    let mut ascii = encode(
        Format::Ascii,
        &[vertex_element(&s, floats(&inria_property_names(0)))],
    );
    assert_eq!(ascii.pop(), Some(b'\n'));
    let p = write(dir.path(), "nonl.ply", &ascii);
    assert_eq!(read_ply(&p).unwrap(), s);
}

// ---------------------------------------------------------------------------------------------------------
// Fuzzing: corrupted or truncated valid files must give errors, never panics.

/// Valid files in every format, with a list-bearing element before the vertices and extras.
fn fuzz_sources() -> Vec<(Format, Vec<u8>)> {
    let s = scene(1, 6, 11);
    let mut props = floats(&inria_property_names(1));
    props.insert(3, list("ids", "uchar", "short"));
    props.push(scalar("tag", "uchar"));
    let face = Element {
        name: "face".into(),
        props: vec![list("vertex_indices", "uchar", "int")],
        rows: vec![vec![vec![0.0, 1.0, 2.0]], vec![vec![3.0]]],
    };
    [Format::Ascii, Format::Le, Format::Be]
        .into_iter()
        .map(|f| {
            (
                f,
                encode(f, &[face_clone(&face), vertex_element(&s, props.clone())]),
            )
        })
        .collect()
}

fn face_clone(e: &Element) -> Element {
    Element {
        name: e.name.clone(),
        props: e.props.clone(),
        rows: e.rows.clone(),
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 300, ..ProptestConfig::default() })]

    #[test]
    fn corrupted_bytes_never_panic(which in 0usize..3, edits in prop::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 1..6)) {
        let (_, mut bytes) = fuzz_sources().swap_remove(which);
        for (at, b) in &edits {
            let i = at.index(bytes.len());
            bytes[i] = *b;
        }
        let dir = tempfile::tempdir().unwrap();
        let p = write(dir.path(), "fuzz.ply", &bytes);
        if let Err(e) = read_ply(&p) {
            let e = e.to_string();
            prop_assert!(e.contains("fuzz.ply") && !e.contains('\n'), "{}", e);
        }
    }

    #[test]
    fn corrupted_headers_never_panic(which in 0usize..3, edits in prop::collection::vec((0usize..400, prop::sample::select(b" \n0123456789-abcdeflinstpy_".to_vec())), 1..4)) {
        let (_, mut bytes) = fuzz_sources().swap_remove(which);
        let header_len = bytes.windows(11).position(|w| w == b"end_header\n").unwrap();
        for (at, b) in &edits {
            let i = at % header_len;
            bytes[i] = *b;
        }
        let dir = tempfile::tempdir().unwrap();
        let p = write(dir.path(), "fuzz.ply", &bytes);
        let _ = read_ply(&p);
    }

    #[test]
    fn truncated_files_are_errors(which in 0usize..3, cut in any::<prop::sample::Index>()) {
        let (format, bytes) = fuzz_sources().swap_remove(which);
        // For ASCII, cutting inside the last number can leave a valid shorter number; cut before it.
        let limit = if format == Format::Ascii {
            let body = bytes.trim_ascii_end();
            body.iter().rposition(|b| b.is_ascii_whitespace()).unwrap() + 1
        } else {
            bytes.len()
        };
        let len = cut.index(limit);
        let dir = tempfile::tempdir().unwrap();
        let p = write(dir.path(), "cut.ply", &bytes[..len]);
        let e = read_ply(&p);
        prop_assert!(e.is_err(), "cut at {} of {} read fine", len, bytes.len());
    }

    #[test]
    fn random_bodies_after_a_plausible_header_never_panic(body in prop::collection::vec(any::<u8>(), 0..600), ascii in any::<bool>()) {
        let mut bytes = format!(
            "ply\nformat {} 1.0\nelement face 2\nproperty list uchar int idx\n{}element extra 1\nproperty double d\nend_header\n",
            if ascii { "ascii" } else { "binary_little_endian" },
            vertex_header(3, &inria_property_names(0), "float"),
        ).into_bytes();
        bytes.extend_from_slice(&body);
        let dir = tempfile::tempdir().unwrap();
        let p = write(dir.path(), "rand.ply", &bytes);
        let _ = read_ply(&p);
    }
}
