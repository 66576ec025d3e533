//! Niantic's `.spz` (<https://github.com/nianticlabs/spz>), versions 2, 3 and 4.
//!
//! Every version stores the same per-Gaussian attributes, as separate arrays in this order: positions
//! (3 × 24-bit signed fixed point with `fractionalBits` fraction bits), alphas (sigmoid · 255), colours
//! (DC · 0.15 · 255 + 127.5), scales ((log-scale + 10) · 16), rotations and SH coefficients (coefficient-
//! major, channel inner, each `value · 128 + 128`). Rotations are, in version 2, the x, y, z of the unit
//! quaternion with w ≥ 0 (3 × u8, `value · 127.5 + 127.5`), and in versions 3 and 4 "smallest three": a
//! u32 holding the index of the largest component of (x, y, z, w) in its top 2 bits, then for each other
//! component in order a sign bit and 9 bits of magnitude / √½.
//!
//! - Versions 2 and 3: one gzip stream holding a 16-byte header (magic `NGSP`, version, count, SH degree,
//!   fractional bits, flags, reserved) and the arrays.
//! - Version 4: a plain 32-byte header (magic, version, count, SH degree, fractional bits, flags, stream
//!   count, table-of-contents offset, 12 reserved bytes), optional extension records up to that offset, the
//!   table of contents (compressed and uncompressed size of each stream, u64 each) and one zstd stream per
//!   non-empty array.
//!
//! Coordinates are stored as given, with no axis conversion (like PlayCanvas splat-transform and the
//! reference library's default). Writing uses all 8 bits for SH coefficients and the most fraction bits
//! (up to 12) that keep every position in range.

use super::codec::{check_quats, largest_component, logit, sigmoid, size_of, unit_quat, Bytes};
use crate::scene::sh_coeffs;
use crate::scene::GaussianScene;
use std::io::Read;

pub(crate) const GZIP_MAGIC: [u8; 2] = [0x1f, 0x8b];
pub(crate) const NGSP_MAGIC: [u8; 4] = *b"NGSP";
/// The version [`super::write_scene`] writes.
pub const LATEST_VERSION: u32 = 4;
const LEGACY_HEADER_BYTES: usize = 16;
const HEADER_BYTES: usize = 32;
const COLOR_SCALE: f32 = 0.15;
const FLAG_HAS_EXTENSIONS: u8 = 0x2;
/// A header's count is believed only if the compressed data could hold it at this ratio (the reference
/// reader's own sanity bound); it keeps a corrupt count from allocating gigabytes.
const MAX_COMPRESSION_RATIO: u64 = 1024;
const MIN_BYTES_PER_POINT: u64 = 9;
const MAX_FRACTIONAL_BITS: u8 = 12;

/// The attribute arrays of a file, still quantised.
struct Packed {
    version: u32,
    count: usize,
    sh_degree: u32,
    fractional_bits: u8,
    positions: Vec<u8>,
    alphas: Vec<u8>,
    colors: Vec<u8>,
    scales: Vec<u8>,
    rotations: Vec<u8>,
    sh: Vec<u8>,
}

fn rotation_bytes(version: u32) -> usize {
    if version >= 3 {
        4
    } else {
        3
    }
}

/// SH bytes per Gaussian: (coefficients per channel - 1) · 3.
fn sh_bytes(sh_degree: u32) -> usize {
    3 * (sh_coeffs(sh_degree) - 1)
}

/// Bytes per Gaussian of each array, in file order.
fn array_sizes(version: u32, sh_degree: u32) -> [usize; 6] {
    [9, 1, 3, 3, rotation_bytes(version), sh_bytes(sh_degree)]
}

// ---------------------------------------------------------------------------------------------------------
// Writing

/// Encodes a scene as `.spz` of the given version (2, 3 or 4).
pub fn encode(scene: &GaussianScene, version: u32) -> Result<Vec<u8>, String> {
    if !(2..=4).contains(&version) {
        return Err(format!(
            "cannot write .spz version {version}; versions 2, 3 and 4 are supported"
        ));
    }
    if scene.sh_degree > 3 {
        return Err(format!("SH degree {} is above 3", scene.sh_degree));
    }
    check_quats(scene)?;
    let count = u32::try_from(scene.len())
        .map_err(|_| format!("{} Gaussians are more than .spz can count", scene.len()))?;
    let packed = pack(scene, version)?;
    let arrays = [
        &packed.positions,
        &packed.alphas,
        &packed.colors,
        &packed.scales,
        &packed.rotations,
        &packed.sh,
    ];
    let mut header = Vec::with_capacity(HEADER_BYTES);
    header.extend_from_slice(&NGSP_MAGIC);
    header.extend_from_slice(&version.to_le_bytes());
    header.extend_from_slice(&count.to_le_bytes());
    header.push(scene.sh_degree as u8);
    header.push(packed.fractional_bits);
    header.push(0); // flags: not antialiased, no extensions
    if version < 4 {
        header.push(0); // reserved
        let mut raw = header;
        for a in arrays {
            raw.extend_from_slice(a);
        }
        let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
        std::io::Write::write_all(&mut gz, &raw).map_err(|e| e.to_string())?;
        return gz.finish().map_err(|e| e.to_string());
    }
    // Each stream carries zstd's content checksum: version 4 has no checksum of its own (2 and 3 have
    // gzip's CRC), so without it a damaged file decodes to wild positions without a word. Every zstd
    // reader verifies the checksum where a frame has one and accepts frames without.
    let zstd_err = |e: std::io::Error| format!("zstd: {e}");
    let mut zstd = zstd::bulk::Compressor::new(12).map_err(zstd_err)?;
    zstd.set_parameter(zstd::zstd_safe::CParameter::ChecksumFlag(true))
        .map_err(zstd_err)?;
    let streams: Vec<(Vec<u8>, usize)> = arrays
        .iter()
        .filter(|a| !a.is_empty())
        .map(|a| zstd.compress(a).map(|c| (c, a.len())).map_err(zstd_err))
        .collect::<Result<_, _>>()?;
    header.push(streams.len() as u8);
    header.extend_from_slice(&(HEADER_BYTES as u32).to_le_bytes());
    header.extend_from_slice(&[0u8; 12]);
    let mut out = header;
    for (compressed, raw_len) in &streams {
        out.extend_from_slice(&(compressed.len() as u64).to_le_bytes());
        out.extend_from_slice(&(*raw_len as u64).to_le_bytes());
    }
    for (compressed, _) in &streams {
        out.extend_from_slice(compressed);
    }
    Ok(out)
}

/// The most fraction bits (≤ 12) for which every coordinate fits 24 signed bits.
fn fractional_bits_for(means: &[f32]) -> Result<u8, String> {
    let largest = means.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    let limit = ((1 << 23) - 1) as f32;
    (0..=MAX_FRACTIONAL_BITS)
        .rev()
        .find(|&bits| (largest * (1u32 << bits) as f32).round() <= limit)
        .ok_or_else(|| {
            format!("a coordinate of {largest} is beyond the ±8388607 that .spz positions can hold")
        })
}

fn pack(scene: &GaussianScene, version: u32) -> Result<Packed, String> {
    let n = scene.len();
    let k = scene.sh_coeffs();
    let fractional_bits = fractional_bits_for(&scene.means)?;
    let scale = (1u32 << fractional_bits) as f32;
    let mut positions = Vec::with_capacity(9 * n);
    for &v in &scene.means {
        let fixed = (v * scale).round() as i32;
        positions.extend_from_slice(&fixed.to_le_bytes()[..3]);
    }
    let alphas = (0..n)
        .map(|i| {
            (sigmoid(scene.opacity_logits[i]) * 255.0)
                .round()
                .clamp(0.0, 255.0) as u8
        })
        .collect();
    let mut colors = Vec::with_capacity(3 * n);
    let mut sh = Vec::with_capacity(n * sh_bytes(scene.sh_degree));
    for i in 0..n {
        let coeffs = &scene.sh[3 * k * i..3 * k * (i + 1)];
        for &dc in &coeffs[..3] {
            colors.push(
                (dc * (COLOR_SCALE * 255.0) + 127.5)
                    .round()
                    .clamp(0.0, 255.0) as u8,
            );
        }
        // Our layout is already coefficient-major with the channel inner, as .spz stores it.
        for &v in &coeffs[3..] {
            sh.push((v * 128.0 + 128.0).round().clamp(0.0, 255.0) as u8);
        }
    }
    let scales = scene
        .log_scales
        .iter()
        .map(|&s| ((s + 10.0) * 16.0).round().clamp(0.0, 255.0) as u8)
        .collect();
    let mut rotations = Vec::with_capacity(rotation_bytes(version) * n);
    for i in 0..n {
        let [w, x, y, z] = unit_quat(&scene.quats, i);
        let q = [x, y, z, w];
        if version >= 3 {
            rotations.extend_from_slice(&pack_smallest_three(q).to_le_bytes());
        } else {
            let sign = if w < 0.0 { -1.0 } else { 1.0 };
            for v in &q[..3] {
                rotations.push((sign * v * 127.5 + 127.5).round().clamp(0.0, 255.0) as u8);
            }
        }
    }
    Ok(Packed {
        version,
        count: n,
        sh_degree: scene.sh_degree,
        fractional_bits,
        positions,
        alphas,
        colors,
        scales,
        rotations,
        sh,
    })
}

/// Packs a unit quaternion (x, y, z, w) as .spz's "smallest three".
fn pack_smallest_three(q: [f32; 4]) -> u32 {
    let largest = largest_component(&q);
    let negate = q[largest] < 0.0;
    let mut packed = largest as u32;
    for (i, &v) in q.iter().enumerate() {
        if i != largest {
            let negative = u32::from((v < 0.0) != negate);
            let magnitude = (511.0 * (v.abs() / std::f32::consts::FRAC_1_SQRT_2) + 0.5)
                .floor()
                .min(511.0) as u32;
            packed = (packed << 10) | (negative << 9) | magnitude;
        }
    }
    packed
}

/// Unpacks "smallest three" into (x, y, z, w).
fn unpack_smallest_three(mut packed: u32) -> [f32; 4] {
    let largest = (packed >> 30) as usize;
    let mut q = [0.0f32; 4];
    let mut sum_sq = 0.0;
    for i in (0..4).rev() {
        if i != largest {
            let magnitude = (packed & 511) as f32;
            let negative = (packed >> 9) & 1 == 1;
            packed >>= 10;
            let v = std::f32::consts::FRAC_1_SQRT_2 * magnitude / 511.0;
            q[i] = if negative { -v } else { v };
            sum_sq += q[i] * q[i];
        }
    }
    q[largest] = (1.0 - sum_sq).max(0.0).sqrt();
    q
}

// ---------------------------------------------------------------------------------------------------------
// Reading

/// Decodes a `.spz` file's bytes (any of versions 2, 3, 4).
pub fn decode(bytes: &[u8]) -> Result<GaussianScene, String> {
    let packed = if bytes.starts_with(&GZIP_MAGIC) {
        read_legacy(bytes)?
    } else if bytes.starts_with(&NGSP_MAGIC) {
        read_v4(bytes)?
    } else {
        return Err("neither a gzip stream nor an NGSP header".into());
    };
    unpack(&packed)
}

/// Checks a header's claims and returns the byte size of each array.
fn check_header(
    version: u32,
    count: u32,
    sh_degree: u8,
    fractional_bits: u8,
    compressed_len: usize,
) -> Result<[usize; 6], String> {
    if !(2..=4).contains(&version) {
        return Err(format!(
            "version {version} is not supported (versions 2, 3 and 4 are)"
        ));
    }
    if sh_degree > 3 {
        return Err(format!("SH degree {sh_degree} is not supported (0-3 are)"));
    }
    if fractional_bits > 23 {
        return Err(format!(
            "{fractional_bits} fractional bits do not fit 24-bit positions"
        ));
    }
    let most = (compressed_len as u64).saturating_mul(MAX_COMPRESSION_RATIO) / MIN_BYTES_PER_POINT;
    if u64::from(count) > most {
        return Err(format!(
            "the header claims {count} Gaussians, more than {compressed_len} compressed bytes can hold (truncated file or bad count)"
        ));
    }
    let sizes = array_sizes(version, u32::from(sh_degree));
    let mut out = [0; 6];
    for (o, per) in out.iter_mut().zip(sizes) {
        *o = size_of(u64::from(count), per as u64, "Gaussians")?;
    }
    // The packed arrays and the decoded scene are both held at the end.
    let packed: u64 = out.iter().map(|&b| b as u64).sum();
    let scene = GaussianScene::memory_bytes(u64::from(count), u32::from(sh_degree));
    files::check_allocation(
        packed + scene,
        &format!("the {count} Gaussians the header declares"),
    )?;
    Ok(out)
}

fn read_legacy(bytes: &[u8]) -> Result<Packed, String> {
    let mut gz = flate2::read::GzDecoder::new(bytes);
    let mut head = [0u8; LEGACY_HEADER_BYTES];
    gz.read_exact(&mut head)
        .map_err(|e| format!("cannot read the header from the gzip stream: {e}"))?;
    let mut h = Bytes::new(&head);
    if h.take(4, "magic")? != NGSP_MAGIC {
        return Err("the gzip stream does not start with the NGSP magic".into());
    }
    let version = h.u32("version")?;
    let count = h.u32("count")?;
    let sh_degree = h.u8("SH degree")?;
    let fractional_bits = h.u8("fractional bits")?;
    if version == 4 {
        return Err("version 4 files are not gzip-compressed".into());
    }
    let sizes = check_header(version, count, sh_degree, fractional_bits, bytes.len())?;
    let total: usize = sizes.iter().sum();
    // Reading through `take` never allocates more than the header promised.
    let mut raw = Vec::with_capacity(total);
    (&mut gz)
        .take(total as u64 + 1)
        .read_to_end(&mut raw)
        .map_err(|e| format!("the gzip stream is damaged: {e}"))?;
    if raw.len() < total {
        return Err(format!(
            "the header declares {count} Gaussians, which need {total} bytes, but the stream holds {} (truncated file or wrong count)",
            raw.len()
        ));
    }
    if raw.len() > total {
        return Err(format!(
            "the stream holds more data than the {count} Gaussians its header declares"
        ));
    }
    let mut r = Bytes::new(&raw);
    let names = [
        "positions",
        "alphas",
        "colours",
        "scales",
        "rotations",
        "SH",
    ];
    let mut arrays: Vec<Vec<u8>> = Vec::with_capacity(6);
    for (size, name) in sizes.iter().zip(names) {
        arrays.push(r.take(*size, name)?.to_vec());
    }
    packed_from(version, count, sh_degree, fractional_bits, arrays)
}

fn packed_from(
    version: u32,
    count: u32,
    sh_degree: u8,
    fractional_bits: u8,
    arrays: Vec<Vec<u8>>,
) -> Result<Packed, String> {
    let mut it = arrays.into_iter();
    let mut next = || it.next().unwrap_or_default();
    Ok(Packed {
        version,
        count: count as usize,
        sh_degree: u32::from(sh_degree),
        fractional_bits,
        positions: next(),
        alphas: next(),
        colors: next(),
        scales: next(),
        rotations: next(),
        sh: next(),
    })
}

fn read_v4(bytes: &[u8]) -> Result<Packed, String> {
    let mut h = Bytes::new(bytes);
    h.take(4, "the magic")?;
    let version = h.u32("the header")?;
    let count = h.u32("the header")?;
    let sh_degree = h.u8("the header")?;
    let fractional_bits = h.u8("the header")?;
    let flags = h.u8("the header")?;
    let stream_count = h.u8("the header")?;
    let toc_offset = h.u32("the header")? as usize;
    h.take(12, "the header")?;
    if version != 4 {
        return Err(format!(
            "an uncompressed NGSP header must be version 4, this one says {version}"
        ));
    }
    let sizes = check_header(version, count, sh_degree, fractional_bits, bytes.len())?;
    if toc_offset < HEADER_BYTES || (flags & FLAG_HAS_EXTENSIONS == 0 && toc_offset != HEADER_BYTES)
    {
        return Err(format!(
            "the table of contents offset {toc_offset} is impossible"
        ));
    }
    let expected: Vec<usize> = sizes.iter().copied().filter(|&s| s > 0).collect();
    if usize::from(stream_count) != expected.len() {
        return Err(format!(
            "{stream_count} streams for {count} Gaussians of SH degree {sh_degree}; expected {}",
            expected.len()
        ));
    }
    let mut toc = Bytes::new(bytes);
    toc.take(toc_offset, "the extension records")?;
    let mut entries = Vec::with_capacity(expected.len());
    for _ in 0..stream_count {
        let compressed = toc.u64("the table of contents")?;
        let raw = toc.u64("the table of contents")?;
        entries.push((compressed, raw));
    }
    let mut data = toc;
    let mut streams = Vec::with_capacity(expected.len());
    for (i, ((compressed, raw), want)) in entries.into_iter().zip(&expected).enumerate() {
        if raw != *want as u64 {
            return Err(format!(
                "stream {i} claims {raw} bytes uncompressed; {count} Gaussians need {want}"
            ));
        }
        let compressed = usize::try_from(compressed)
            .map_err(|_| format!("stream {i} claims an impossible size"))?;
        let chunk = data.take(compressed, &format!("stream {i}"))?;
        let out = zstd::bulk::decompress(chunk, *want)
            .map_err(|e| format!("stream {i} is not valid zstd data: {e}"))?;
        if out.len() != *want {
            return Err(format!(
                "stream {i} holds {} bytes; {count} Gaussians need {want}",
                out.len()
            ));
        }
        streams.push(out);
    }
    if data.remaining() != 0 {
        return Err(format!("{} bytes after the last stream", data.remaining()));
    }
    // Streams of empty arrays are not stored; put the empty arrays back in their places.
    let mut it = streams.into_iter();
    let arrays = sizes
        .iter()
        .map(|&s| {
            if s > 0 {
                it.next().unwrap_or_default()
            } else {
                Vec::new()
            }
        })
        .collect();
    packed_from(version, count, sh_degree, fractional_bits, arrays)
}

fn unpack(p: &Packed) -> Result<GaussianScene, String> {
    let n = p.count;
    let k = sh_coeffs(p.sh_degree);
    let rest = 3 * (k - 1);
    let mut scene = GaussianScene::new(p.sh_degree);
    let scale = 1.0 / (1u32 << p.fractional_bits) as f32;
    scene.means = p
        .positions
        .chunks_exact(3)
        .map(|b| {
            // Sign-extend 24 bits by placing them in the top of an i32.
            let v = i32::from_le_bytes([0, b[0], b[1], b[2]]) >> 8;
            v as f32 * scale
        })
        .collect();
    scene.opacity_logits = p
        .alphas
        .iter()
        .map(|&a| logit(f32::from(a) / 255.0))
        .collect();
    scene.log_scales = p
        .scales
        .iter()
        .map(|&s| f32::from(s) / 16.0 - 10.0)
        .collect();
    scene.sh = Vec::with_capacity(3 * k * n);
    for i in 0..n {
        for &c in &p.colors[3 * i..3 * i + 3] {
            scene.sh.push((f32::from(c) / 255.0 - 0.5) / COLOR_SCALE);
        }
        for &v in &p.sh[rest * i..rest * (i + 1)] {
            scene.sh.push((f32::from(v) - 128.0) / 128.0);
        }
    }
    scene.quats = Vec::with_capacity(4 * n);
    let width = rotation_bytes(p.version);
    for (i, r) in p.rotations.chunks_exact(width).enumerate() {
        let [x, y, z, w] = if width == 4 {
            unpack_smallest_three(u32::from_le_bytes([r[0], r[1], r[2], r[3]]))
        } else {
            let [x, y, z] = [r[0], r[1], r[2]].map(|b| f32::from(b) / 127.5 - 1.0);
            [x, y, z, (1.0 - (x * x + y * y + z * z)).max(0.0).sqrt()]
        };
        if x == 0.0 && y == 0.0 && z == 0.0 && w == 0.0 {
            return Err(format!("Gaussian {i}: the rotation is the zero quaternion"));
        }
        scene.quats.extend_from_slice(&[w, x, y, z]);
    }
    scene.check_shapes()?;
    Ok(scene)
}
