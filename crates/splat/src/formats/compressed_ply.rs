//! PlayCanvas/SuperSplat compressed PLY: a binary little-endian PLY with three elements.
//!
//! - `chunk`, one row per 256 consecutive Gaussians, `float` properties: `min_x min_y min_z max_x max_y
//!   max_z`, `min_scale_x .. max_scale_z` (log-scales) and optionally `min_r min_g min_b max_r max_g max_b`
//!   (colours 0.5 + C0 · DC; without them colours span [0, 1]).
//! - `vertex`, `uint` properties: `packed_position` (11-10-11 bits of x, y, z within the chunk's box),
//!   `packed_rotation` (2 bits: index of the largest component of (w, x, y, z); then the other three, each
//!   10 bits of value · √½ + ½, largest made positive), `packed_scale` (11-10-11 within the chunk's
//!   log-scale box) and `packed_color` (8-8-8-8: colour within the chunk's colour box, then opacity).
//! - optional `sh`, `uchar f_rest_0..` in the INRIA order (channel-major), value = (byte + ½) / 256 · 8 - 4
//!   (bytes 0 and 255 mean -4 and 4).
//!
//! Writing keeps the scene's order (the reference tool sorts into Morton order first; readers do not care).

use super::codec::{
    check_quats, largest_component, logit, pack_unorm, sigmoid, size_of, unit_quat, unpack_unorm,
    Bytes, SH_C0,
};
use super::ply::{parse_header, Element, Format, PropKind, ScalarType};
use crate::scene::sh_coeffs;
use crate::scene::GaussianScene;
use std::io::BufReader;
use std::path::Path;

/// Gaussians per chunk.
pub const CHUNK_SIZE: usize = 256;
const CHUNK_BOX: [&str; 12] = [
    "min_x",
    "min_y",
    "min_z",
    "max_x",
    "max_y",
    "max_z",
    "min_scale_x",
    "min_scale_y",
    "min_scale_z",
    "max_scale_x",
    "max_scale_y",
    "max_scale_z",
];
const CHUNK_COLOUR: [&str; 6] = ["min_r", "min_g", "min_b", "max_r", "max_g", "max_b"];
const VERTEX: [&str; 4] = [
    "packed_position",
    "packed_rotation",
    "packed_scale",
    "packed_color",
];
/// Log-scales are clamped to this range, as the reference writer does (some trainers leave ±inf).
const SCALE_LIMIT: f32 = 20.0;

/// Whether a PLY file's header describes a compressed PLY (a `chunk` element and `packed_*` vertices).
/// A header that cannot be parsed is not compressed: the plain PLY reader then reports what is wrong.
pub(crate) fn is_compressed_ply(path: &Path) -> std::io::Result<bool> {
    let mut reader = BufReader::new(files::open_regular(path)?);
    Ok(match parse_header(&mut reader) {
        Ok(h) => is_compressed(&h.elements),
        Err(_) => false,
    })
}

fn is_compressed(elements: &[Element]) -> bool {
    let has_chunk = elements.iter().any(|e| e.name == "chunk");
    let packed_vertex = elements
        .iter()
        .any(|e| e.name == "vertex" && e.props.iter().any(|p| p.name == "packed_position"));
    has_chunk && packed_vertex
}

// ---------------------------------------------------------------------------------------------------------
// Reading

/// Column offsets of named properties in a fixed-size row, checked for type.
fn columns(element: &Element, names: &[&str], ty: ScalarType) -> Result<Vec<usize>, String> {
    let mut offsets = Vec::with_capacity(names.len());
    for name in names {
        let mut offset = 0;
        let mut found = None;
        for p in &element.props {
            let PropKind::Scalar(t) = p.kind else {
                return Err(format!(
                    "element '{}' has a list property '{}'",
                    element.name, p.name
                ));
            };
            if p.name == *name {
                if t != ty {
                    return Err(format!(
                        "property '{name}' of element '{}' has the wrong type (expected {ty:?})",
                        element.name
                    ));
                }
                found = Some(offset);
            }
            offset += t.size();
        }
        offsets.push(
            found.ok_or_else(|| format!("element '{}' has no property '{name}'", element.name))?,
        );
    }
    Ok(offsets)
}

fn row_size(element: &Element) -> usize {
    element
        .props
        .iter()
        .map(|p| match p.kind {
            PropKind::Scalar(t) => t.size(),
            PropKind::List { .. } => 0,
        })
        .sum()
}

fn f32_at(row: &[u8], offset: usize) -> f32 {
    f32::from_le_bytes(row[offset..offset + 4].try_into().expect("4 bytes"))
}

fn u32_at(row: &[u8], offset: usize) -> u32 {
    u32::from_le_bytes(row[offset..offset + 4].try_into().expect("4 bytes"))
}

fn lerp(a: f32, b: f32, t: f32) -> f32 {
    a * (1.0 - t) + b * t
}

/// Unpacks 11-10-11 bits into three values in [0, 1].
fn unpack_111011(v: u32) -> [f32; 3] {
    [
        unpack_unorm(v >> 21, 11),
        unpack_unorm(v >> 11, 10),
        unpack_unorm(v, 11),
    ]
}

fn pack_111011(v: [f32; 3]) -> u32 {
    (pack_unorm(v[0], 11) << 21) | (pack_unorm(v[1], 10) << 11) | pack_unorm(v[2], 11)
}

/// Unpacks a rotation into (w, x, y, z).
fn unpack_rotation(v: u32) -> [f32; 4] {
    let norm = std::f32::consts::FRAC_1_SQRT_2;
    let a = (unpack_unorm(v >> 20, 10) - 0.5) / norm;
    let b = (unpack_unorm(v >> 10, 10) - 0.5) / norm;
    let c = (unpack_unorm(v, 10) - 0.5) / norm;
    let m = (1.0 - (a * a + b * b + c * c)).max(0.0).sqrt();
    match v >> 30 {
        0 => [m, a, b, c],
        1 => [a, m, b, c],
        2 => [a, b, m, c],
        _ => [a, b, c, m],
    }
}

fn pack_rotation(q: [f32; 4]) -> u32 {
    let largest = largest_component(&q);
    let sign = if q[largest] < 0.0 { -1.0 } else { 1.0 };
    let mut packed = largest as u32;
    for (i, v) in q.iter().enumerate() {
        if i != largest {
            packed =
                (packed << 10) | pack_unorm(sign * v * std::f32::consts::FRAC_1_SQRT_2 + 0.5, 10);
        }
    }
    packed
}

fn sh_byte_to_value(b: u8) -> f32 {
    let n = match b {
        0 => 0.0,
        255 => 1.0,
        _ => (f32::from(b) + 0.5) / 256.0,
    };
    (n - 0.5) * 8.0
}

fn sh_value_to_byte(v: f32) -> u8 {
    ((v / 8.0 + 0.5) * 256.0).trunc().clamp(0.0, 255.0) as u8
}

/// Decodes a compressed PLY file's bytes.
pub fn decode(bytes: &[u8]) -> Result<GaussianScene, String> {
    let mut cursor = bytes;
    let header = parse_header(&mut cursor).map_err(|p| p.describe())?;
    if header.format != Format::BinaryLe {
        return Err("compressed PLY must be binary_little_endian".into());
    }
    let find = |name: &str| header.elements.iter().find(|e| e.name == name);
    let chunk = find("chunk").ok_or("no 'chunk' element")?;
    let vertex = find("vertex").ok_or("no 'vertex' element")?;
    let sh = find("sh");
    if let Some(other) = header
        .elements
        .iter()
        .find(|e| !["chunk", "vertex", "sh"].contains(&e.name.as_str()))
    {
        return Err(format!("unexpected element '{}'", other.name));
    }
    let box_cols = columns(chunk, &CHUNK_BOX, ScalarType::F32)?;
    let colour_cols = if chunk.props.iter().any(|p| p.name == "min_r") {
        Some(columns(chunk, &CHUNK_COLOUR, ScalarType::F32)?)
    } else {
        None
    };
    let vertex_cols = columns(vertex, &VERTEX, ScalarType::U32)?;
    let n = vertex.count;
    let want_chunks = n.div_ceil(CHUNK_SIZE as u64);
    if chunk.count != want_chunks {
        return Err(format!(
            "{} chunks for {n} vertices; expected {want_chunks} (one per {CHUNK_SIZE})",
            chunk.count
        ));
    }
    let (sh_degree, sh_cols) = match sh {
        None => (0, Vec::new()),
        Some(sh) => {
            if sh.count != n {
                return Err(format!(
                    "the 'sh' element has {} rows for {n} vertices",
                    sh.count
                ));
            }
            let degree = match sh.props.len() {
                9 => 1,
                24 => 2,
                45 => 3,
                other => {
                    return Err(format!(
                        "the 'sh' element has {other} properties; expected 9, 24 or 45"
                    ))
                }
            };
            let names: Vec<String> = (0..sh.props.len()).map(|i| format!("f_rest_{i}")).collect();
            let names: Vec<&str> = names.iter().map(String::as_str).collect();
            (degree, columns(sh, &names, ScalarType::U8)?)
        }
    };

    // Every size is checked against the bytes present before anything is allocated.
    let chunk_row = row_size(chunk);
    let vertex_row = row_size(vertex);
    let sh_row = sh.map_or(0, row_size);
    let mut data = Bytes::new(&bytes[header.len as usize..]);
    let need = size_of(chunk.count, chunk_row as u64, "chunks")?
        .checked_add(size_of(n, vertex_row as u64, "vertices")?)
        .and_then(|s| s.checked_add(size_of(n, sh_row as u64, "SH rows").ok()?))
        .ok_or("the declared counts overflow")?;
    if need != data.remaining() {
        return Err(format!(
            "the header declares {} chunks and {n} vertices, which need {need} bytes, but {} bytes follow the header ({})",
            chunk.count,
            data.remaining(),
            if need > data.remaining() { "truncated file or wrong count" } else { "wrong count?" }
        ));
    }
    let chunks = data.take(chunk.count as usize * chunk_row, "the chunks")?;
    let vertices = data.take(n as usize * vertex_row, "the vertices")?;
    let sh_rows = data.take(n as usize * sh_row, "the SH rows")?;

    let n = n as usize;
    let k = sh_coeffs(sh_degree);
    let mut scene = GaussianScene::with_capacity(sh_degree, n);
    for (c, chunk_bytes) in chunks.chunks_exact(chunk_row).enumerate() {
        let b: Vec<f32> = box_cols.iter().map(|&o| f32_at(chunk_bytes, o)).collect();
        let colour: Option<Vec<f32>> = colour_cols
            .as_ref()
            .map(|cols| cols.iter().map(|&o| f32_at(chunk_bytes, o)).collect());
        if let Some(bad) = b
            .iter()
            .chain(colour.iter().flatten())
            .find(|v| !v.is_finite())
        {
            return Err(format!("chunk {c} has a non-finite bound ({bad})"));
        }
        let first = c * CHUNK_SIZE;
        for i in first..(first + CHUNK_SIZE).min(n) {
            let row = &vertices[i * vertex_row..(i + 1) * vertex_row];
            let p = unpack_111011(u32_at(row, vertex_cols[0]));
            let s = unpack_111011(u32_at(row, vertex_cols[2]));
            let packed_colour = u32_at(row, vertex_cols[3]);
            for a in 0..3 {
                scene.means.push(lerp(b[a], b[3 + a], p[a]));
                scene.log_scales.push(lerp(b[6 + a], b[9 + a], s[a]));
            }
            scene
                .quats
                .extend_from_slice(&unpack_rotation(u32_at(row, vertex_cols[1])));
            for ch in 0..3 {
                let t = unpack_unorm(packed_colour >> (24 - 8 * ch), 8);
                let rgb = match &colour {
                    Some(col) => lerp(col[ch], col[3 + ch], t),
                    None => t,
                };
                scene.sh.push((rgb - 0.5) / SH_C0);
            }
            scene
                .opacity_logits
                .push(logit(unpack_unorm(packed_colour, 8)));
            let sh_bytes = &sh_rows[i * sh_row..(i + 1) * sh_row];
            let rest = k - 1;
            for kk in 1..k {
                for ch in 0..3 {
                    let byte = sh_bytes[sh_cols[ch * rest + kk - 1]];
                    scene.sh.push(sh_byte_to_value(byte));
                }
            }
        }
    }
    Ok(scene)
}

// ---------------------------------------------------------------------------------------------------------
// Writing

/// Maps `v` into [0, 1] within [min, max] as the reference writer does (degenerate ranges map to 0).
fn normalise(v: f32, min: f32, max: f32) -> f32 {
    if v <= min {
        0.0
    } else if v >= max {
        1.0
    } else if max - min < 1e-5 {
        0.0
    } else {
        (v - min) / (max - min)
    }
}

/// Encodes a scene as compressed PLY, with per-chunk colour bounds and an `sh` element when the degree
/// is above 0.
pub fn encode(scene: &GaussianScene) -> Result<Vec<u8>, String> {
    if scene.sh_degree > 3 {
        return Err(format!("SH degree {} is above 3", scene.sh_degree));
    }
    check_quats(scene)?;
    let n = scene.len();
    let k = scene.sh_coeffs();
    let chunks = n.div_ceil(CHUNK_SIZE);
    let rest = 3 * (k - 1);
    let mut header = format!(
        "ply\nformat binary_little_endian 1.0\ncomment Generated by vcedit\nelement chunk {chunks}\n"
    );
    for name in CHUNK_BOX.iter().chain(&CHUNK_COLOUR) {
        header.push_str(&format!("property float {name}\n"));
    }
    header.push_str(&format!("element vertex {n}\n"));
    for name in VERTEX {
        header.push_str(&format!("property uint {name}\n"));
    }
    if rest > 0 {
        header.push_str(&format!("element sh {n}\n"));
        for i in 0..rest {
            header.push_str(&format!("property uchar f_rest_{i}\n"));
        }
    }
    header.push_str("end_header\n");

    let mut chunk_data = Vec::with_capacity(chunks * 18 * 4);
    let mut vertex_data = Vec::with_capacity(n * 16);
    let mut sh_data = Vec::with_capacity(n * rest);
    let colour = |i: usize, ch: usize| 0.5 + SH_C0 * scene.sh[3 * k * i + ch];
    let log_scale =
        |i: usize, a: usize| scene.log_scales[3 * i + a].clamp(-SCALE_LIMIT, SCALE_LIMIT);
    for c in 0..chunks {
        let members = c * CHUNK_SIZE..((c + 1) * CHUNK_SIZE).min(n);
        let bounds = |get: &dyn Fn(usize) -> f32| {
            members
                .clone()
                .map(get)
                .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), v| {
                    (lo.min(v), hi.max(v))
                })
        };
        let pos: Vec<(f32, f32)> = (0..3)
            .map(|a| bounds(&|i| scene.means[3 * i + a]))
            .collect();
        let scl: Vec<(f32, f32)> = (0..3).map(|a| bounds(&|i| log_scale(i, a))).collect();
        let col: Vec<(f32, f32)> = (0..3).map(|ch| bounds(&|i| colour(i, ch))).collect();
        for group in [&pos, &scl, &col] {
            for (lo, _) in group.iter() {
                chunk_data.extend_from_slice(&lo.to_le_bytes());
            }
            for (_, hi) in group.iter() {
                chunk_data.extend_from_slice(&hi.to_le_bytes());
            }
        }
        for i in members {
            let p = std::array::from_fn(|a| normalise(scene.means[3 * i + a], pos[a].0, pos[a].1));
            let s = std::array::from_fn(|a| normalise(log_scale(i, a), scl[a].0, scl[a].1));
            let mut packed_colour = 0u32;
            for (ch, (lo, hi)) in col.iter().enumerate() {
                packed_colour |= pack_unorm(normalise(colour(i, ch), *lo, *hi), 8) << (24 - 8 * ch);
            }
            packed_colour |= pack_unorm(sigmoid(scene.opacity_logits[i]), 8);
            for v in [
                pack_111011(p),
                pack_rotation(unit_quat(&scene.quats, i)),
                pack_111011(s),
                packed_colour,
            ] {
                vertex_data.extend_from_slice(&v.to_le_bytes());
            }
            // INRIA order: channel-major.
            let coeffs = &scene.sh[3 * k * i..3 * k * (i + 1)];
            for ch in 0..3 {
                for kk in 1..k {
                    sh_data.push(sh_value_to_byte(coeffs[3 * kk + ch]));
                }
            }
        }
    }
    let mut out = header.into_bytes();
    out.extend_from_slice(&chunk_data);
    out.extend_from_slice(&vertex_data);
    out.extend_from_slice(&sh_data);
    Ok(out)
}
