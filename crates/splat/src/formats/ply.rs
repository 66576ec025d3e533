//! 3DGS scenes as PLY files.
//!
//! Reading accepts what real tools write: ASCII and binary (little- or big-endian) PLY, vertex properties in
//! any order, optional normals, SH degree 0-3 inferred from the number of `f_rest_*` properties (0, 9, 24 or
//! 45), extra properties of any type (lists included) and other elements before or after `vertex`. The
//! properties a scene needs must be `float` (or `double`, converted to f32).
//!
//! Writing produces exactly the INRIA trainer's layout, so results open in the INRIA viewer, SuperSplat and
//! brush: binary little-endian `x y z nx ny nz f_dc_0..2 f_rest_0.. opacity scale_0..2 rot_0..3` (normals are
//! written as 0).
//!
//! The INRIA trainer stores the higher-order SH coefficients channel-major: `f_rest_{c*(K-1) + (k-1)}` is
//! coefficient k (1..K) of colour channel c, and `f_dc_c` is coefficient 0. [`GaussianScene`] keeps them
//! as `sh[(n*K + k)*3 + c]`.
//!
//! Every problem with a file is one [`PlyError`] naming the file; the header's claims are checked against
//! the file size before anything is allocated, so a corrupt count cannot exhaust memory.

use crate::scene::{sh_coeffs, GaussianScene};
use rayon::prelude::*;
use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};

/// A header longer than this is garbage (real headers are a few KiB even with many comments).
const MAX_HEADER_BYTES: u64 = 1 << 20;
/// Rows read at once in the fixed-row-size binary path (a few MiB for typical rows).
const ROWS_PER_CHUNK: usize = 16384;
/// Rows decoded (or encoded) per parallel task.
const ROWS_PER_BLOCK: usize = 1024;

#[derive(Debug, thiserror::Error)]
pub enum PlyError {
    #[error("{}: cannot read: {err}", path.display())]
    Read { path: PathBuf, err: std::io::Error },
    #[error("{}: cannot write: {err}", path.display())]
    Write { path: PathBuf, err: std::io::Error },
    #[error("{}: bad PLY header: {msg}", path.display())]
    Header { path: PathBuf, msg: String },
    #[error("{}: not a 3DGS scene: {msg}", path.display())]
    NotGaussians { path: PathBuf, msg: String },
    #[error("{}: bad PLY data: {msg}", path.display())]
    Data { path: PathBuf, msg: String },
    #[error("{}: cannot write this scene: {msg}", path.display())]
    InvalidScene { path: PathBuf, msg: String },
}

/// Which kind of problem, before the path is attached.
pub(crate) enum Problem {
    Io(std::io::Error),
    Header(String),
    NotGaussians(String),
    Data(String),
}

impl Problem {
    /// The problem as text, for readers that attach the path themselves.
    pub(crate) fn describe(self) -> String {
        match self {
            Problem::Io(err) => format!("cannot read: {err}"),
            Problem::Header(msg) => format!("bad PLY header: {msg}"),
            Problem::NotGaussians(msg) => format!("not a 3DGS scene: {msg}"),
            Problem::Data(msg) => format!("bad PLY data: {msg}"),
        }
    }

    pub(crate) fn at(self, path: &Path) -> PlyError {
        let path = path.to_path_buf();
        match self {
            Problem::Io(err) => PlyError::Read { path, err },
            Problem::Header(msg) => PlyError::Header { path, msg },
            Problem::NotGaussians(msg) => PlyError::NotGaussians { path, msg },
            Problem::Data(msg) => PlyError::Data { path, msg },
        }
    }
}

// ---------------------------------------------------------------------------------------------------------
// Header

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Format {
    Ascii,
    BinaryLe,
    BinaryBe,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum ScalarType {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl ScalarType {
    fn parse(s: &str) -> Option<Self> {
        Some(match s {
            "char" | "int8" => Self::I8,
            "uchar" | "uint8" => Self::U8,
            "short" | "int16" => Self::I16,
            "ushort" | "uint16" => Self::U16,
            "int" | "int32" => Self::I32,
            "uint" | "uint32" => Self::U32,
            "float" | "float32" => Self::F32,
            "double" | "float64" => Self::F64,
            _ => return None,
        })
    }

    pub(crate) fn size(self) -> usize {
        match self {
            Self::I8 | Self::U8 => 1,
            Self::I16 | Self::U16 => 2,
            Self::I32 | Self::U32 | Self::F32 => 4,
            Self::F64 => 8,
        }
    }

    fn name(self) -> &'static str {
        match self {
            Self::I8 => "char",
            Self::U8 => "uchar",
            Self::I16 => "short",
            Self::U16 => "ushort",
            Self::I32 => "int",
            Self::U32 => "uint",
            Self::F32 => "float",
            Self::F64 => "double",
        }
    }

    fn is_float(self) -> bool {
        matches!(self, Self::F32 | Self::F64)
    }

    /// Decodes one value from the start of `b` (which holds at least `size()` bytes).
    pub(crate) fn decode(self, b: &[u8], big_endian: bool) -> f64 {
        macro_rules! get {
            ($t:ty, $n:expr) => {{
                let mut a = [0u8; $n];
                a.copy_from_slice(&b[..$n]);
                if big_endian {
                    <$t>::from_be_bytes(a) as f64
                } else {
                    <$t>::from_le_bytes(a) as f64
                }
            }};
        }
        match self {
            Self::I8 => b[0] as i8 as f64,
            Self::U8 => b[0] as f64,
            Self::I16 => get!(i16, 2),
            Self::U16 => get!(u16, 2),
            Self::I32 => get!(i32, 4),
            Self::U32 => get!(u32, 4),
            Self::F32 => get!(f32, 4),
            Self::F64 => get!(f64, 8),
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum PropKind {
    Scalar(ScalarType),
    List { count: ScalarType, item: ScalarType },
}

#[derive(Clone, Debug)]
pub(crate) struct Property {
    pub(crate) name: String,
    pub(crate) kind: PropKind,
}

#[derive(Clone, Debug)]
pub(crate) struct Element {
    pub(crate) name: String,
    pub(crate) count: u64,
    pub(crate) props: Vec<Property>,
}

impl Element {
    /// Bytes per row when no property is a list.
    fn fixed_row_size(&self) -> Option<usize> {
        self.props
            .iter()
            .map(|p| match p.kind {
                PropKind::Scalar(t) => Some(t.size()),
                PropKind::List { .. } => None,
            })
            .sum()
    }

    /// The fewest bytes (binary) or tokens (ASCII) a row can take: a list contributes at least its count.
    fn min_row_units(&self, format: Format) -> u64 {
        self.props
            .iter()
            .map(|p| match (format, p.kind) {
                (Format::Ascii, _) => 1,
                (_, PropKind::Scalar(t)) => t.size() as u64,
                (_, PropKind::List { count, .. }) => count.size() as u64,
            })
            .sum()
    }
}

pub(crate) struct Header {
    pub(crate) format: Format,
    pub(crate) elements: Vec<Element>,
    /// Bytes from the start of the file to the first data byte.
    pub(crate) len: u64,
}

pub(crate) fn parse_header(reader: &mut impl BufRead) -> Result<Header, Problem> {
    let mut consumed: u64 = 0;
    let mut line_no = 0usize;
    let mut raw = Vec::new();
    let mut format = None;
    let mut elements: Vec<Element> = Vec::new();
    loop {
        raw.clear();
        let budget = MAX_HEADER_BYTES.saturating_sub(consumed);
        let n = reader
            .by_ref()
            .take(budget)
            .read_until(b'\n', &mut raw)
            .map_err(Problem::Io)? as u64;
        consumed += n;
        line_no += 1;
        if n == 0 || raw.last() != Some(&b'\n') {
            return Err(Problem::Header(if line_no == 1 && n == 0 {
                "the file is empty".into()
            } else if consumed >= MAX_HEADER_BYTES {
                format!("no end_header within the first {MAX_HEADER_BYTES} bytes")
            } else {
                "the file ends before end_header".into()
            }));
        }
        let Ok(text) = std::str::from_utf8(&raw) else {
            return Err(Problem::Header(if line_no == 1 {
                "not a PLY file (it does not start with 'ply')".into()
            } else {
                // Binary bytes inside the header: almost always the vertex data of a header whose
                // `end_header` line is missing.
                format!("no end_header line before the binary data (line {line_no} is not text)")
            }));
        };
        let text = text.trim_end_matches(['\n', '\r']);
        if line_no == 1 {
            if text.trim() != "ply" {
                return Err(Problem::Header(
                    "not a PLY file (it does not start with 'ply')".into(),
                ));
            }
            continue;
        }
        let bad = |msg: String| Problem::Header(format!("line {line_no}: {msg}"));
        let tokens: Vec<&str> = text.split_whitespace().collect();
        let Some(&keyword) = tokens.first() else {
            continue; // tolerate blank lines
        };
        match keyword {
            "comment" | "obj_info" => {}
            "format" => {
                if format.is_some() {
                    return Err(bad("a second 'format' line".into()));
                }
                if tokens.len() != 3 {
                    return Err(bad(format!("expected 'format <type> 1.0', got '{text}'")));
                }
                format = Some(match tokens[1] {
                    "ascii" => Format::Ascii,
                    "binary_little_endian" => Format::BinaryLe,
                    "binary_big_endian" => Format::BinaryBe,
                    other => return Err(bad(format!("unknown format '{other}'"))),
                });
                if tokens[2] != "1.0" {
                    return Err(bad(format!("unsupported PLY version '{}'", tokens[2])));
                }
            }
            "element" => {
                if tokens.len() != 3 {
                    return Err(bad(format!(
                        "expected 'element <name> <count>', got '{text}'"
                    )));
                }
                let name = tokens[1];
                let count: u64 = tokens[2].parse().map_err(|_| {
                    bad(format!(
                        "element '{name}' has an invalid count '{}'",
                        tokens[2]
                    ))
                })?;
                if elements.iter().any(|e| e.name == name) {
                    return Err(bad(format!("element '{name}' is declared twice")));
                }
                elements.push(Element {
                    name: name.to_string(),
                    count,
                    props: Vec::new(),
                });
            }
            "property" => {
                let Some(element) = elements.last_mut() else {
                    return Err(bad("a property before any element".into()));
                };
                let scalar = |s: &str| {
                    ScalarType::parse(s).ok_or_else(|| bad(format!("unknown property type '{s}'")))
                };
                let (kind, name) = match tokens.as_slice() {
                    ["property", "list", count, item, name] => {
                        let count = scalar(count)?;
                        if count.is_float() {
                            return Err(bad(format!(
                                "list '{name}' has a non-integer count type '{}'",
                                count.name()
                            )));
                        }
                        (
                            PropKind::List {
                                count,
                                item: scalar(item)?,
                            },
                            *name,
                        )
                    }
                    ["property", ty, name] if *ty != "list" => {
                        (PropKind::Scalar(scalar(ty)?), *name)
                    }
                    _ => {
                        return Err(bad(format!(
                            "expected 'property <type> <name>' or 'property list <count type> <type> <name>', got '{text}'"
                        )))
                    }
                };
                if element.props.iter().any(|p| p.name == name) {
                    return Err(bad(format!(
                        "property '{name}' of element '{}' is declared twice",
                        element.name
                    )));
                }
                element.props.push(Property {
                    name: name.to_string(),
                    kind,
                });
            }
            "end_header" => {
                let format = format
                    .ok_or_else(|| Problem::Header("no 'format' line before end_header".into()))?;
                return Ok(Header {
                    format,
                    elements,
                    len: consumed,
                });
            }
            other => return Err(bad(format!("unknown keyword '{other}'"))),
        }
    }
}

// ---------------------------------------------------------------------------------------------------------
// Mapping vertex properties onto scene fields

/// Where a vertex property goes in the scene.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Slot {
    Mean(usize),
    Dc(usize),
    Rest(usize),
    Opacity,
    Scale(usize),
    Rot(usize),
}

fn slot_for(name: &str) -> Option<Slot> {
    let indexed = |prefix: &str, n: usize| -> Option<usize> {
        let i: usize = name.strip_prefix(prefix)?.parse().ok()?;
        // Reject "f_dc_01"-style aliases so every slot has exactly one spelling.
        (i < n && name.len() == prefix.len() + i.to_string().len()).then_some(i)
    };
    match name {
        "x" => Some(Slot::Mean(0)),
        "y" => Some(Slot::Mean(1)),
        "z" => Some(Slot::Mean(2)),
        "opacity" => Some(Slot::Opacity),
        _ => indexed("f_dc_", 3)
            .map(Slot::Dc)
            .or_else(|| indexed("f_rest_", usize::MAX).map(Slot::Rest))
            .or_else(|| indexed("scale_", 3).map(Slot::Scale))
            .or_else(|| indexed("rot_", 4).map(Slot::Rot)),
    }
}

fn slot_name(slot: Slot) -> String {
    match slot {
        Slot::Mean(a) => ["x", "y", "z"][a].to_string(),
        Slot::Dc(c) => format!("f_dc_{c}"),
        Slot::Rest(i) => format!("f_rest_{i}"),
        Slot::Opacity => "opacity".into(),
        Slot::Scale(a) => format!("scale_{a}"),
        Slot::Rot(a) => format!("rot_{a}"),
    }
}

/// The vertex element's needed properties: which property index feeds which slot.
struct VertexLayout {
    sh_degree: u32,
    /// (property index, slot, type); every needed slot exactly once.
    fields: Vec<(usize, Slot, ScalarType)>,
}

impl VertexLayout {
    fn new(element: &Element) -> Result<Self, Problem> {
        let mut fields = Vec::new();
        let mut rest_indices = Vec::new();
        for (i, p) in element.props.iter().enumerate() {
            let Some(slot) = slot_for(&p.name) else {
                continue;
            };
            let ty = match p.kind {
                PropKind::Scalar(t) if t.is_float() => t,
                PropKind::Scalar(t) => {
                    return Err(Problem::NotGaussians(format!(
                        "property '{}' has type {}; 3DGS properties must be float or double",
                        p.name,
                        t.name()
                    )))
                }
                PropKind::List { .. } => {
                    return Err(Problem::NotGaussians(format!(
                        "property '{}' is a list; 3DGS properties must be float or double",
                        p.name
                    )))
                }
            };
            if let Slot::Rest(r) = slot {
                rest_indices.push(r);
            }
            fields.push((i, slot, ty));
        }

        rest_indices.sort_unstable();
        let rest = rest_indices.len();
        let sh_degree = match rest {
            0 => 0,
            9 => 1,
            24 => 2,
            45 => 3,
            _ => {
                return Err(Problem::NotGaussians(format!(
                    "found {rest} f_rest_* properties; expected 0, 9, 24 or 45 (SH degree 0-3)"
                )))
            }
        };
        if let Some(missing) = (0..rest).find(|&i| rest_indices[i] != i) {
            return Err(Problem::NotGaussians(format!(
                "the f_rest_* properties must be f_rest_0..f_rest_{}, but f_rest_{missing} is missing",
                rest - 1
            )));
        }

        let mut required: Vec<Slot> = (0..3).map(Slot::Mean).collect();
        required.extend((0..3).map(Slot::Dc));
        required.push(Slot::Opacity);
        required.extend((0..3).map(Slot::Scale));
        required.extend((0..4).map(Slot::Rot));
        let missing: Vec<String> = required
            .into_iter()
            .filter(|s| !fields.iter().any(|f| f.1 == *s))
            .map(slot_name)
            .collect();
        if !missing.is_empty() {
            // Not one Gaussian property: a mesh or a point cloud, which a user may have taken for a scene.
            let hint = if fields.iter().all(|f| matches!(f.1, Slot::Mean(_))) {
                " (a mesh or point cloud, not 3D Gaussians: `vcedit fit` makes a 3DGS scene from posed \
                 images)"
            } else {
                ""
            };
            return Err(Problem::NotGaussians(format!(
                "the '{}' element has no propert{} {}{hint}",
                element.name,
                if missing.len() == 1 { "y" } else { "ies" },
                missing.join(", ")
            )));
        }
        Ok(Self { sh_degree, fields })
    }
}

/// Fills a scene row by row and checks each value as it lands.
struct SceneBuilder {
    scene: GaussianScene,
    coeffs: usize,
    rest_per_channel: usize,
}

impl SceneBuilder {
    fn new(sh_degree: u32, count: usize) -> Self {
        let coeffs = sh_coeffs(sh_degree);
        Self {
            scene: GaussianScene {
                sh_degree,
                means: vec![0.0; 3 * count],
                log_scales: vec![0.0; 3 * count],
                quats: vec![0.0; 4 * count],
                opacity_logits: vec![0.0; count],
                sh: vec![0.0; 3 * coeffs * count],
            },
            coeffs,
            rest_per_channel: coeffs - 1,
        }
    }

    #[inline]
    fn set(&mut self, n: usize, slot: Slot, value: f32) -> Result<(), Problem> {
        if !value.is_finite() {
            return Err(non_finite(n, slot, value));
        }
        let s = &mut self.scene;
        match slot {
            Slot::Mean(a) => s.means[3 * n + a] = value,
            Slot::Scale(a) => s.log_scales[3 * n + a] = value,
            Slot::Rot(a) => s.quats[4 * n + a] = value,
            Slot::Opacity => s.opacity_logits[n] = value,
            Slot::Dc(c) => s.sh[n * self.coeffs * 3 + c] = value,
            Slot::Rest(i) => {
                let (c, k) = (i / self.rest_per_channel, i % self.rest_per_channel + 1);
                s.sh[(n * self.coeffs + k) * 3 + c] = value;
            }
        }
        Ok(())
    }

    /// Checks what only makes sense for the whole row.
    fn finish_row(&self, n: usize) -> Result<(), Problem> {
        check_quaternion(n, &self.scene.quats[4 * n..4 * n + 4])
    }
}

/// Converts a decoded needed value to f32 (doubles out of f32 range become infinite and are rejected).
#[inline]
fn to_f32(v: f64, ty: ScalarType) -> f32 {
    debug_assert!(ty.is_float());
    v as f32
}

/// Where a needed property lands inside one row's slice of a scene array.
#[derive(Clone, Copy)]
enum Dest {
    Mean,
    Scale,
    Quat,
    Opacity,
    Sh,
}

/// A needed property of a fixed-size binary row: its byte offset and where its value goes.
#[derive(Clone, Copy)]
struct RowField {
    offset: usize,
    ty: ScalarType,
    slot: Slot,
    dest: Dest,
    /// Index inside the row's slice of the destination array.
    pos: usize,
}

impl RowField {
    fn new(offset: usize, slot: Slot, ty: ScalarType, coeffs: usize) -> Self {
        let (dest, pos) = match slot {
            Slot::Mean(a) => (Dest::Mean, a),
            Slot::Scale(a) => (Dest::Scale, a),
            Slot::Rot(a) => (Dest::Quat, a),
            Slot::Opacity => (Dest::Opacity, 0),
            Slot::Dc(c) => (Dest::Sh, c),
            Slot::Rest(i) => {
                let rest = coeffs - 1;
                (Dest::Sh, 3 * (i % rest + 1) + i / rest)
            }
        };
        Self {
            offset,
            ty,
            slot,
            dest,
            pos,
        }
    }
}

/// The scene arrays' slices for a block of consecutive rows.
struct RowsMut<'a> {
    means: &'a mut [f32],
    scales: &'a mut [f32],
    quats: &'a mut [f32],
    opacity: &'a mut [f32],
    sh: &'a mut [f32],
}

/// Decodes consecutive fixed-size rows into `out`, checking values as `SceneBuilder` does.
fn decode_rows(
    bytes: &[u8],
    row_size: usize,
    fields: &[RowField],
    big_endian: bool,
    k3: usize,
    first_row: usize,
    out: RowsMut<'_>,
) -> Result<(), Problem> {
    for (r, row) in bytes.chunks_exact(row_size).enumerate() {
        for f in fields {
            let v = to_f32(f.ty.decode(&row[f.offset..], big_endian), f.ty);
            if !v.is_finite() {
                return Err(non_finite(first_row + r, f.slot, v));
            }
            match f.dest {
                Dest::Mean => out.means[3 * r + f.pos] = v,
                Dest::Scale => out.scales[3 * r + f.pos] = v,
                Dest::Quat => out.quats[4 * r + f.pos] = v,
                Dest::Opacity => out.opacity[r] = v,
                Dest::Sh => out.sh[k3 * r + f.pos] = v,
            }
        }
        check_quaternion(first_row + r, &out.quats[4 * r..4 * r + 4])?;
    }
    Ok(())
}

fn non_finite(n: usize, slot: Slot, value: f32) -> Problem {
    Problem::Data(format!(
        "vertex {n}: property '{}' is {value}",
        slot_name(slot)
    ))
}

fn check_quaternion(n: usize, q: &[f32]) -> Result<(), Problem> {
    let norm2: f32 = q.iter().map(|v| v * v).sum();
    // Squared norms below the smallest normal f32 cannot be normalised reliably in f32.
    if !norm2.is_normal() {
        return Err(Problem::Data(format!(
            "vertex {n}: rotation quaternion ({}, {}, {}, {}) is zero or too small to normalise",
            q[0], q[1], q[2], q[3]
        )));
    }
    Ok(())
}

// ---------------------------------------------------------------------------------------------------------
// Reading

/// Reads a 3DGS scene from a PLY file (ASCII or binary, any property order; see the module docs).
pub fn read_ply(path: &Path) -> Result<GaussianScene, PlyError> {
    read_ply_inner(path).map_err(|p| p.at(path))
}

fn read_ply_inner(path: &Path) -> Result<GaussianScene, Problem> {
    let file = files::open_regular(path).map_err(Problem::Io)?;
    let file_len = file.metadata().map_err(Problem::Io)?.len();
    let mut reader = BufReader::with_capacity(1 << 20, file);
    let header = parse_header(&mut reader)?;

    let vertex_index = header
        .elements
        .iter()
        .position(|e| e.name == "vertex")
        .ok_or_else(|| Problem::NotGaussians("the file has no 'vertex' element".into()))?;
    let layout = VertexLayout::new(&header.elements[vertex_index])?;

    // Validate every count against the bytes actually present before allocating anything.
    let data_len = file_len.saturating_sub(header.len);
    let mut min_total: u64 = 0;
    for e in &header.elements {
        let need = e
            .count
            .checked_mul(e.min_row_units(header.format))
            .and_then(|b| b.checked_add(min_total));
        let unit = if header.format == Format::Ascii {
            "values"
        } else {
            "bytes"
        };
        match need {
            Some(total) if total <= data_len => min_total = total,
            _ => {
                return Err(Problem::Data(format!(
                    "the header declares {} '{}' rows, which need at least {} {unit}, but only {data_len} bytes follow the header (truncated file or wrong element count)",
                    e.count,
                    e.name,
                    need.map_or_else(|| "more than 2^64".to_string(), |t| t.to_string()),
                )))
            }
        }
    }
    if header.format != Format::Ascii
        && header.elements.iter().all(|e| e.fixed_row_size().is_some())
    {
        // Without lists the data size is exact; a mismatch means a wrong count or a damaged file.
        if data_len > min_total {
            return Err(Problem::Data(format!(
                "{} bytes after the last element that the header does not describe (wrong element count?)",
                data_len - min_total
            )));
        }
    }

    // A count the file's size allows may still be more than memory holds: a sparse file is as long as
    // its header claims without taking the space. Refused from the header, before allocating.
    let count = header.elements[vertex_index].count;
    files::check_allocation(
        GaussianScene::memory_bytes(count, layout.sh_degree),
        &format!("its {count} Gaussians"),
    )
    .map_err(|msg| Problem::Io(std::io::Error::new(std::io::ErrorKind::OutOfMemory, msg)))?;

    match header.format {
        Format::Ascii => read_ascii(&mut reader, &header, vertex_index, &layout),
        Format::BinaryLe | Format::BinaryBe => read_binary(
            &mut reader,
            &header,
            vertex_index,
            &layout,
            header.format == Format::BinaryBe,
        ),
    }
}

fn truncated(what: &str) -> Problem {
    Problem::Data(format!("the file ends inside {what} (truncated?)"))
}

/// Reads exactly `buf.len()` bytes, mapping a short read to a truncation message.
fn fill(reader: &mut impl Read, buf: &mut [u8], what: impl Fn() -> String) -> Result<(), Problem> {
    reader.read_exact(buf).map_err(|e| {
        if e.kind() == std::io::ErrorKind::UnexpectedEof {
            truncated(&what())
        } else {
            Problem::Io(e)
        }
    })
}

fn skip_bytes(reader: &mut impl Read, n: u64, what: impl Fn() -> String) -> Result<(), Problem> {
    let copied = std::io::copy(&mut reader.take(n), &mut std::io::sink()).map_err(Problem::Io)?;
    if copied != n {
        return Err(truncated(&what()));
    }
    Ok(())
}

/// Reads one binary row of an element whose rows contain lists; `offsets[i]` receives the offset of scalar
/// property i inside `row` (lists are skipped and leave no bytes in `row`).
fn read_binary_list_row(
    reader: &mut impl Read,
    element: &Element,
    big_endian: bool,
    row: &mut Vec<u8>,
    offsets: &mut [usize],
    row_index: u64,
) -> Result<(), Problem> {
    row.clear();
    let what = || format!("row {row_index} of element '{}'", element.name);
    let mut scratch = [0u8; 8];
    for (i, p) in element.props.iter().enumerate() {
        match p.kind {
            PropKind::Scalar(t) => {
                offsets[i] = row.len();
                fill(reader, &mut scratch[..t.size()], what)?;
                row.extend_from_slice(&scratch[..t.size()]);
            }
            PropKind::List { count, item } => {
                fill(reader, &mut scratch[..count.size()], what)?;
                let n = count.decode(&scratch, big_endian);
                if n < 0.0 {
                    return Err(Problem::Data(format!(
                        "{}: list '{}' has a negative length {n}",
                        what(),
                        p.name
                    )));
                }
                skip_bytes(reader, n as u64 * item.size() as u64, what)?;
            }
        }
    }
    Ok(())
}

fn read_binary(
    reader: &mut impl Read,
    header: &Header,
    vertex_index: usize,
    layout: &VertexLayout,
    big_endian: bool,
) -> Result<GaussianScene, Problem> {
    let mut row = Vec::new();
    // Elements before the vertex element only need skipping.
    for e in &header.elements[..vertex_index] {
        skip_element(reader, e, big_endian, &mut row)?;
    }

    let element = &header.elements[vertex_index];
    // The size check above bounds the count by the file size, so this allocation is safe.
    let count = element.count as usize;
    let mut builder = SceneBuilder::new(layout.sh_degree, count);
    match element.fixed_row_size() {
        Some(row_size) => {
            let mut offsets = vec![0usize; element.props.len()];
            let mut at = 0;
            for (i, p) in element.props.iter().enumerate() {
                offsets[i] = at;
                if let PropKind::Scalar(t) = p.kind {
                    at += t.size();
                }
            }
            let fields: Vec<RowField> = layout
                .fields
                .iter()
                .map(|&(i, slot, ty)| RowField::new(offsets[i], slot, ty, builder.coeffs))
                .collect();
            let k3 = 3 * builder.coeffs;
            let mut buf = vec![0u8; row_size * ROWS_PER_CHUNK.min(count.max(1))];
            let mut n0 = 0;
            while n0 < count {
                let rows = ROWS_PER_CHUNK.min(count - n0);
                let chunk = &mut buf[..rows * row_size];
                fill(reader, chunk, || {
                    format!("the 'vertex' element (rows {n0}..{} of {count})", n0 + rows)
                })?;
                let s = &mut builder.scene;
                let range = |width: usize| width * n0..width * (n0 + rows);
                // Decode blocks of rows in parallel; report the first bad row in file order.
                let first_error = chunk
                    .par_chunks(ROWS_PER_BLOCK * row_size)
                    .zip(s.means[range(3)].par_chunks_mut(3 * ROWS_PER_BLOCK))
                    .zip(s.log_scales[range(3)].par_chunks_mut(3 * ROWS_PER_BLOCK))
                    .zip(s.quats[range(4)].par_chunks_mut(4 * ROWS_PER_BLOCK))
                    .zip(s.opacity_logits[range(1)].par_chunks_mut(ROWS_PER_BLOCK))
                    .zip(s.sh[range(k3)].par_chunks_mut(k3 * ROWS_PER_BLOCK))
                    .enumerate()
                    .map(|(j, (((((bytes, means), scales), quats), opacity), sh))| {
                        let block = RowsMut {
                            means,
                            scales,
                            quats,
                            opacity,
                            sh,
                        };
                        let first_row = n0 + j * ROWS_PER_BLOCK;
                        decode_rows(bytes, row_size, &fields, big_endian, k3, first_row, block)
                    })
                    .collect::<Vec<_>>()
                    .into_iter()
                    .find_map(Result::err);
                if let Some(problem) = first_error {
                    return Err(problem);
                }
                n0 += rows;
            }
        }
        None => {
            let mut offsets = vec![0usize; element.props.len()];
            for n in 0..count {
                read_binary_list_row(
                    reader,
                    element,
                    big_endian,
                    &mut row,
                    &mut offsets,
                    n as u64,
                )?;
                for &(i, slot, ty) in &layout.fields {
                    let v = ty.decode(&row[offsets[i]..], big_endian);
                    builder.set(n, slot, to_f32(v, ty))?;
                }
                builder.finish_row(n)?;
            }
        }
    }
    // Elements after it are not used, but a file that ends inside one is damaged (or its header lies).
    for e in &header.elements[vertex_index + 1..] {
        skip_element(reader, e, big_endian, &mut row)?;
    }
    Ok(builder.scene)
}

/// Reads past the rows of binary element `e`, checking that they are all there.
fn skip_element(
    reader: &mut impl Read,
    e: &Element,
    big_endian: bool,
    row: &mut Vec<u8>,
) -> Result<(), Problem> {
    if e.props.is_empty() {
        return Ok(());
    }
    let what = || format!("element '{}'", e.name);
    if let Some(size) = e.fixed_row_size() {
        skip_bytes(reader, e.count * size as u64, what)?;
    } else {
        let mut offsets = vec![0; e.props.len()];
        for r in 0..e.count {
            read_binary_list_row(reader, e, big_endian, row, &mut offsets, r)?;
        }
    }
    Ok(())
}

/// Whitespace-separated tokens of an ASCII PLY body, streamed.
struct Tokens<R> {
    reader: R,
    token: Vec<u8>,
}

impl<R: BufRead> Tokens<R> {
    /// The next token, or `None` at the end of the file.
    fn next(&mut self) -> Result<Option<&str>, Problem> {
        self.token.clear();
        loop {
            let buf = self.reader.fill_buf().map_err(Problem::Io)?;
            if buf.is_empty() {
                break;
            }
            let mut used = 0;
            let mut done = false;
            for &b in buf {
                used += 1;
                if b.is_ascii_whitespace() {
                    if !self.token.is_empty() {
                        done = true;
                        break;
                    }
                } else {
                    self.token.push(b);
                    if self.token.len() > 4096 {
                        return Err(Problem::Data(
                            "a value in the ASCII data is longer than 4096 characters".into(),
                        ));
                    }
                }
            }
            self.reader.consume(used);
            if done {
                break;
            }
        }
        if self.token.is_empty() {
            return Ok(None);
        }
        std::str::from_utf8(&self.token)
            .map(Some)
            .map_err(|_| Problem::Data("the ASCII data contains non-text bytes".into()))
    }

    fn expect(&mut self, what: impl Fn() -> String) -> Result<&str, Problem> {
        match self.next()? {
            Some(t) => Ok(t),
            None => Err(truncated(&what())),
        }
    }

    /// Consumes one row of an element; returns nothing (the values are not needed).
    fn skip_row(&mut self, element: &Element, row_index: u64) -> Result<(), Problem> {
        let what = || format!("row {row_index} of element '{}'", element.name);
        for p in &element.props {
            match p.kind {
                PropKind::Scalar(_) => {
                    self.expect(what)?;
                }
                PropKind::List { .. } => {
                    let len = self.list_len(&what, &p.name)?;
                    for _ in 0..len {
                        self.expect(what)?;
                    }
                }
            }
        }
        Ok(())
    }

    fn list_len(&mut self, what: &impl Fn() -> String, name: &str) -> Result<u64, Problem> {
        let t = self.expect(what)?;
        t.parse::<u64>().map_err(|_| {
            Problem::Data(format!(
                "{}: list '{name}' has an invalid length '{t}'",
                what()
            ))
        })
    }
}

fn read_ascii(
    reader: &mut impl BufRead,
    header: &Header,
    vertex_index: usize,
    layout: &VertexLayout,
) -> Result<GaussianScene, Problem> {
    let mut tokens = Tokens {
        reader,
        token: Vec::new(),
    };
    let skip_element = |tokens: &mut Tokens<_>, e: &Element| -> Result<(), Problem> {
        if !e.props.is_empty() {
            for r in 0..e.count {
                tokens.skip_row(e, r)?;
            }
        }
        Ok(())
    };
    for e in &header.elements[..vertex_index] {
        skip_element(&mut tokens, e)?;
    }

    let element = &header.elements[vertex_index];
    let count = element.count as usize;
    // Property index -> (slot, type) for the needed ones.
    let mut slots: Vec<Option<(Slot, ScalarType)>> = vec![None; element.props.len()];
    for &(i, slot, ty) in &layout.fields {
        slots[i] = Some((slot, ty));
    }
    let mut builder = SceneBuilder::new(layout.sh_degree, count);
    for n in 0..count {
        let what = || format!("vertex {n} (of {count})");
        for (p, slot) in element.props.iter().zip(&slots) {
            match (p.kind, slot) {
                (PropKind::List { .. }, _) => {
                    let len = tokens.list_len(&what, &p.name)?;
                    for _ in 0..len {
                        tokens.expect(what)?;
                    }
                }
                (PropKind::Scalar(_), None) => {
                    tokens.expect(what)?;
                }
                (PropKind::Scalar(_), Some((slot, ty))) => {
                    let t = tokens.expect(what)?;
                    // Parse floats directly as f32 so the value is rounded once, exactly as a binary file holds it.
                    let v = match ty {
                        ScalarType::F32 => t.parse::<f32>().ok(),
                        _ => t.parse::<f64>().ok().map(|v| to_f32(v, *ty)),
                    };
                    let Some(v) = v else {
                        return Err(Problem::Data(format!(
                            "vertex {n}: property '{}': cannot parse '{t}' as a number",
                            p.name
                        )));
                    };
                    builder.set(n, *slot, v)?;
                }
            }
        }
        builder.finish_row(n)?;
    }

    for e in &header.elements[vertex_index + 1..] {
        skip_element(&mut tokens, e)?;
    }
    if let Some(t) = tokens.next()? {
        let t = t.chars().take(40).collect::<String>();
        return Err(Problem::Data(format!(
            "unexpected data '{t}' after the last element (wrong element count?)"
        )));
    }
    Ok(builder.scene)
}

// ---------------------------------------------------------------------------------------------------------
// Writing

/// The INRIA trainer's property names, in its order, for an SH degree.
pub fn inria_property_names(sh_degree: u32) -> Vec<String> {
    let mut names: Vec<String> = ["x", "y", "z", "nx", "ny", "nz"]
        .iter()
        .map(|s| s.to_string())
        .collect();
    names.extend((0..3).map(|c| format!("f_dc_{c}")));
    names.extend((0..3 * (sh_coeffs(sh_degree) - 1)).map(|i| format!("f_rest_{i}")));
    names.push("opacity".into());
    names.extend((0..3).map(|a| format!("scale_{a}")));
    names.extend((0..4).map(|a| format!("rot_{a}")));
    names
}

/// Checks what every writer needs: consistent array lengths and finite values. Returns the first problem.
pub(crate) fn check_writable(scene: &GaussianScene) -> Result<(), String> {
    scene.check_shapes()?;
    let fields: [(&str, &[f32]); 5] = [
        ("position", &scene.means),
        ("log-scale", &scene.log_scales),
        ("quaternion", &scene.quats),
        ("opacity", &scene.opacity_logits),
        ("SH coefficient", &scene.sh),
    ];
    for (name, values) in fields {
        if let Some(i) = values.iter().position(|v| !v.is_finite()) {
            let width = values.len() / scene.len().max(1);
            return Err(format!(
                "Gaussian {} has a non-finite {name} ({})",
                i / width.max(1),
                values[i]
            ));
        }
    }
    Ok(())
}

/// Encodes a scene in the INRIA trainer's PLY layout (binary little-endian).
pub fn encode_ply(scene: &GaussianScene) -> Result<Vec<u8>, String> {
    if scene.sh_degree > 3 {
        return Err(format!(
            "SH degree {} is above 3, which PLY viewers do not understand",
            scene.sh_degree
        ));
    }
    check_writable(scene)?;

    let n = scene.len();
    let k = scene.sh_coeffs();
    let names = inria_property_names(scene.sh_degree);
    let mut header = format!("ply\nformat binary_little_endian 1.0\nelement vertex {n}\n");
    for name in &names {
        header.push_str("property float ");
        header.push_str(name);
        header.push('\n');
    }
    header.push_str("end_header\n");

    let row_bytes = names.len() * 4;
    let mut out = vec![0u8; header.len() + n * row_bytes];
    out[..header.len()].copy_from_slice(header.as_bytes());
    out[header.len()..]
        .par_chunks_mut(ROWS_PER_BLOCK * row_bytes)
        .enumerate()
        .for_each(|(j, block)| {
            for (r, row) in block.chunks_exact_mut(row_bytes).enumerate() {
                let i = j * ROWS_PER_BLOCK + r;
                let mut values = row.chunks_exact_mut(4);
                let mut put = |v: f32| {
                    if let Some(slot) = values.next() {
                        slot.copy_from_slice(&v.to_le_bytes());
                    }
                };
                scene.means[3 * i..3 * i + 3].iter().for_each(|&v| put(v));
                (0..3).for_each(|_| put(0.0));
                let sh = &scene.sh[3 * k * i..3 * k * (i + 1)];
                (0..3).for_each(|c| put(sh[c]));
                // INRIA order: channel-major rest coefficients.
                for c in 0..3 {
                    for kk in 1..k {
                        put(sh[3 * kk + c]);
                    }
                }
                put(scene.opacity_logits[i]);
                scene.log_scales[3 * i..3 * i + 3]
                    .iter()
                    .for_each(|&v| put(v));
                scene.quats[4 * i..4 * i + 4].iter().for_each(|&v| put(v));
            }
        });
    Ok(out)
}

/// Writes a scene in the INRIA trainer's layout, atomically (see [`files::atomic_write`]).
pub fn write_ply(path: &Path, scene: &GaussianScene) -> Result<(), PlyError> {
    let bytes = encode_ply(scene).map_err(|msg| PlyError::InvalidScene {
        path: path.to_path_buf(),
        msg,
    })?;
    files::atomic_write(path, &bytes).map_err(|err| PlyError::Write {
        path: path.to_path_buf(),
        err,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scene(sh_degree: u32, n: usize) -> GaussianScene {
        let k = sh_coeffs(sh_degree);
        let v = |i: usize| ((i * 37 % 101) as f32 - 50.0) / 17.0;
        GaussianScene {
            sh_degree,
            means: (0..3 * n).map(v).collect(),
            log_scales: (0..3 * n).map(|i| v(i + 5) * 0.1 - 3.0).collect(),
            quats: (0..4 * n).map(|i| v(i + 9) + 0.01).collect(),
            opacity_logits: (0..n).map(|i| v(i + 2)).collect(),
            sh: (0..3 * k * n).map(|i| v(i + 7) * 0.3).collect(),
        }
    }

    #[test]
    fn slots_accept_only_canonical_names() {
        assert_eq!(slot_for("f_rest_44"), Some(Slot::Rest(44)));
        assert_eq!(slot_for("f_dc_2"), Some(Slot::Dc(2)));
        assert_eq!(slot_for("f_dc_3"), None);
        assert_eq!(slot_for("f_dc_01"), None);
        assert_eq!(slot_for("rot_3"), Some(Slot::Rot(3)));
        assert_eq!(slot_for("rot_4"), None);
        assert_eq!(slot_for("nx"), None);
        assert_eq!(slot_for("scale_"), None);
    }

    #[test]
    fn encode_places_rest_channel_major() {
        let s = scene(1, 2);
        let bytes = encode_ply(&s).unwrap();
        let header_end = bytes
            .windows(11)
            .position(|w| w == b"end_header\n")
            .unwrap()
            + 11;
        let floats: Vec<f32> = bytes[header_end..]
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
            .collect();
        let per = inria_property_names(1).len();
        assert_eq!(per, 6 + 3 + 9 + 1 + 3 + 4);
        assert_eq!(floats.len(), 2 * per);
        let row = &floats[per..2 * per];
        let names = inria_property_names(1);
        let at = |name: &str| row[names.iter().position(|n| n == name).unwrap()];
        // f_rest_{c*(K-1)+(k-1)} holds sh[(n*K+k)*3+c]; K = 4.
        for c in 0..3 {
            for k in 1..4 {
                assert_eq!(
                    at(&format!("f_rest_{}", c * 3 + k - 1)),
                    s.sh[(4 + k) * 3 + c]
                );
            }
            assert_eq!(at(&format!("f_dc_{c}")), s.sh[4 * 3 + c]);
        }
        assert_eq!(at("nx"), 0.0);
        assert_eq!(at("opacity"), s.opacity_logits[1]);
        assert_eq!(at("rot_0"), s.quats[4]);
    }

    #[test]
    fn write_read_roundtrip_all_degrees() {
        let dir = tempfile::tempdir().unwrap();
        for degree in 0..=3 {
            let s = scene(degree, 5);
            let p = dir.path().join(format!("d{degree}.ply"));
            write_ply(&p, &s).unwrap();
            assert_eq!(read_ply(&p).unwrap(), s);
        }
    }

    #[test]
    fn write_rejects_bad_scenes() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("x.ply");
        let mut s = scene(0, 3);
        s.opacity_logits[2] = f32::NAN;
        let e = write_ply(&p, &s).unwrap_err().to_string();
        assert!(
            e.contains("x.ply") && e.contains("Gaussian 2") && e.contains("opacity"),
            "{e}"
        );
        let mut s = scene(0, 3);
        s.means.pop();
        let e = write_ply(&p, &s).unwrap_err().to_string();
        assert!(e.contains("means"), "{e}");
        assert!(!p.exists());
    }

    #[test]
    fn empty_scene_roundtrips() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("empty.ply");
        let s = GaussianScene::new(2);
        write_ply(&p, &s).unwrap();
        assert_eq!(read_ply(&p).unwrap(), s);
    }

    /// A header whose count the file's (sparse) size matches, but more Gaussians than memory holds
    /// (issue 69: this aborted on the allocation).
    #[test]
    fn a_sparse_file_as_long_as_its_huge_header_claims_is_refused() {
        if files::available_memory().is_none() {
            return;
        }
        let dir = tempfile::tempdir().unwrap();
        let bytes = encode_ply(&scene(0, 1)).unwrap();
        let header_end = bytes
            .windows(11)
            .position(|w| w == b"end_header\n")
            .unwrap()
            + 11;
        let row = (bytes.len() - header_end) as u64;
        let count: u64 = 1 << 36;
        let header = String::from_utf8(bytes[..header_end].to_vec())
            .unwrap()
            .replace("element vertex 1\n", &format!("element vertex {count}\n"));
        let p = dir.path().join("huge.ply");
        std::fs::write(&p, header.as_bytes()).unwrap();
        let f = std::fs::OpenOptions::new().write(true).open(&p).unwrap();
        if f.set_len(header.len() as u64 + count * row).is_err() {
            return; // a file system without sparse files this large
        }
        let e = read_ply(&p).unwrap_err().to_string();
        assert!(
            e.contains("huge.ply") && e.contains(&count.to_string()) && e.contains("memory"),
            "{e}"
        );
    }
}
