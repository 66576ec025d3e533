//! The file formats people share Gaussian splats in.
//!
//! [`read_scene`] recognises a scene by its content, never by its name, except `.splat`, which has no
//! magic bytes (any file of 32·n bytes would parse): it is read only from a file named `*.splat`.
//!
//! | content | format |
//! | --- | --- |
//! | `ply` header with a `vertex` element of float properties | INRIA PLY ([`ply`]) |
//! | `ply` header with `chunk` + `vertex` (`packed_*`) elements | PlayCanvas/SuperSplat compressed PLY ([`compressed_ply`]) |
//! | gzip stream holding an `NGSP` header, or a plain `NGSP` header | Niantic `.spz` v2/v3, v4 ([`spz`]) |
//! | zip archive with `meta.json`, a `meta.json` file, or a folder holding one | PlayCanvas SOG ([`sog`]) |
//! | a folder with `point_cloud/iteration_N/point_cloud.ply` | INRIA trainer output |
//! | none of the above, named `*.splat`, 32 bytes per Gaussian | antimatter15 `.splat` ([`dot_splat`]) |
//!
//! [`write_scene`] chooses the format by the output name (see [`OutputFormat::for_path`]) and returns a
//! [`WriteReport`]: for a lossy format, the largest error of every quantity, measured by decoding the
//! bytes written exactly as [`read_scene`] will.

pub mod compressed_ply;
pub mod dot_splat;
mod open;
pub mod ply;
pub mod sog;
pub mod spz;

mod codec;
mod report;

pub use open::{open_scene, OpenError};
pub use report::{QuantisationError, WriteReport};

use crate::scene::GaussianScene;
use std::io::Read;
use std::path::{Path, PathBuf};

#[derive(Debug, thiserror::Error)]
pub enum FormatError {
    /// Problems of INRIA PLY files keep the PLY reader's own messages.
    #[error(transparent)]
    Ply(#[from] ply::PlyError),
    #[error("{}: no such file or folder", path.display())]
    NotFound { path: PathBuf },
    #[error("{}: cannot read: {err}", path.display())]
    Read { path: PathBuf, err: std::io::Error },
    #[error("{}: cannot write: {err}", path.display())]
    Write { path: PathBuf, err: std::io::Error },
    #[error("{}: bad {format} file: {msg}", path.display())]
    Malformed {
        path: PathBuf,
        format: &'static str,
        msg: String,
    },
    #[error("{}: not a scene: {msg}", path.display())]
    NotAScene { path: PathBuf, msg: String },
    #[error("{}: the scene decodes to unusable values: {msg}", path.display())]
    BadValues { path: PathBuf, msg: String },
    #[error("{}: cannot write this scene as {format}: {msg}", path.display())]
    Unwritable {
        path: PathBuf,
        format: &'static str,
        msg: String,
    },
    #[error(
        "{}: unknown output format: name it *.ply, *.compressed.ply, *.splat, *.spz, *.sog or meta.json (a SOG folder)",
        path.display()
    )]
    UnknownOutput { path: PathBuf },
}

/// A format [`write_scene`] can produce.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum OutputFormat {
    /// The INRIA trainer's PLY (exact).
    InriaPly,
    /// PlayCanvas/SuperSplat compressed PLY.
    CompressedPly,
    /// antimatter15 `.splat`.
    Splat,
    /// Niantic `.spz`, version 4.
    Spz,
    /// PlayCanvas SOG bundled in one zip file.
    SogZip,
    /// PlayCanvas SOG as a folder: `meta.json` and its WebP textures beside it.
    SogFolder,
}

impl OutputFormat {
    /// The format an output name asks for: `*.compressed.ply`, `*.ply`, `*.splat`, `*.spz`, `*.sog`, or a
    /// file named `meta.json` (a SOG folder). Case-insensitive.
    pub fn for_path(path: &Path) -> Option<Self> {
        let name = path.file_name()?.to_str()?.to_ascii_lowercase();
        Some(if name.ends_with(".compressed.ply") {
            Self::CompressedPly
        } else if name.ends_with(".ply") {
            Self::InriaPly
        } else if name.ends_with(".splat") {
            Self::Splat
        } else if name.ends_with(".spz") {
            Self::Spz
        } else if name.ends_with(".sog") {
            Self::SogZip
        } else if name == "meta.json" {
            Self::SogFolder
        } else {
            return None;
        })
    }

    pub fn name(self) -> &'static str {
        match self {
            Self::InriaPly => "PLY",
            Self::CompressedPly => "compressed PLY",
            Self::Splat => ".splat",
            Self::Spz => ".spz",
            Self::SogZip => "SOG (zip)",
            Self::SogFolder => "SOG (folder)",
        }
    }
}

/// Reads a scene from any supported file or folder, recognised by content (see the module docs), and
/// checks that every value decodes to a finite number ([`GaussianScene::check_values`]).
pub fn read_scene(path: &Path) -> Result<GaussianScene, FormatError> {
    checked(path, read_any(path)?)
}

/// `scene` read from `path` if its values are usable.
pub(crate) fn checked(path: &Path, scene: GaussianScene) -> Result<GaussianScene, FormatError> {
    scene.check_values().map_err(|msg| FormatError::BadValues {
        path: path.to_path_buf(),
        msg,
    })?;
    Ok(scene)
}

fn read_any(path: &Path) -> Result<GaussianScene, FormatError> {
    if path.is_dir() {
        return read_folder(path);
    }
    if !path.exists() {
        return Err(FormatError::NotFound {
            path: path.to_path_buf(),
        });
    }
    let read_err = |err| FormatError::Read {
        path: path.to_path_buf(),
        err,
    };
    let mut head = Vec::with_capacity(16);
    files::open_regular(path)
        .map_err(read_err)?
        .take(16)
        .read_to_end(&mut head)
        .map_err(read_err)?;
    let bad = |format: &'static str| {
        move |msg: String| FormatError::Malformed {
            path: path.to_path_buf(),
            format,
            msg,
        }
    };
    if head.is_empty() {
        return Err(FormatError::NotAScene {
            path: path.to_path_buf(),
            msg: "the file is empty".into(),
        });
    }
    if head.starts_with(b"ply") {
        return if compressed_ply::is_compressed_ply(path).map_err(read_err)? {
            let bytes = files::read_regular(path).map_err(read_err)?;
            compressed_ply::decode(&bytes).map_err(bad("compressed PLY"))
        } else {
            Ok(ply::read_ply(path)?)
        };
    }
    if head.starts_with(&spz::GZIP_MAGIC) || head.starts_with(&spz::NGSP_MAGIC) {
        let bytes = files::read_regular(path).map_err(read_err)?;
        return spz::decode(&bytes).map_err(bad(".spz"));
    }
    if head.starts_with(sog::ZIP_MAGIC) {
        return sog::read_zip(path).map_err(bad("SOG"));
    }
    if head.trim_ascii_start().starts_with(b"{") {
        return sog::read_folder(path).map_err(bad("SOG"));
    }
    let named_splat = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("splat"));
    if !named_splat {
        return Err(FormatError::NotAScene {
            path: path.to_path_buf(),
            msg: "not PLY, compressed PLY, .spz or SOG (an antimatter15 .splat file must be named \
                  *.splat: the format has no signature)"
                .into(),
        });
    }
    let bytes = files::read_regular(path).map_err(read_err)?;
    dot_splat::decode(&bytes).map_err(bad(".splat"))
}

/// A folder is a SOG folder (with `meta.json`) or the INRIA trainer's output (its highest iteration).
fn read_folder(dir: &Path) -> Result<GaussianScene, FormatError> {
    let meta = dir.join("meta.json");
    if meta.is_file() {
        return sog::read_folder(&meta).map_err(|msg| FormatError::Malformed {
            path: meta.clone(),
            format: "SOG",
            msg,
        });
    }
    match inria_iteration_ply(dir) {
        Some(ply_path) => Ok(ply::read_ply(&ply_path)?),
        None => Err(FormatError::NotAScene {
            path: dir.to_path_buf(),
            msg: "expected a scene file, an INRIA output folder with point_cloud/iteration_*/point_cloud.ply, or a SOG folder with meta.json".into(),
        }),
    }
}

/// The scene of an INRIA trainer output folder: `point_cloud/iteration_N/point_cloud.ply` with the largest
/// N that exists; `None` for a SOG folder (it has `meta.json`), a file, or a folder without one.
pub(crate) fn inria_iteration_ply(dir: &Path) -> Option<PathBuf> {
    if !dir.is_dir() || dir.join("meta.json").is_file() {
        return None;
    }
    let entries = std::fs::read_dir(dir.join("point_cloud")).ok()?;
    entries
        .filter_map(|e| e.ok())
        .filter_map(|e| {
            let name = e.file_name();
            let n: u64 = name.to_str()?.strip_prefix("iteration_")?.parse().ok()?;
            let ply = e.path().join("point_cloud.ply");
            ply.is_file().then_some((n, ply))
        })
        .max_by_key(|(n, _)| *n)
        .map(|(_, p)| p)
}

/// The folder a SOG folder output `.../meta.json` is.
fn sog_folder(meta: &Path) -> &Path {
    match meta.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    }
}

/// Checks, before any work, that [`write_scene`] may write `path`: for a SOG folder output, that its
/// folder is new, empty or a SOG scene (decided by content: see [`sog::replaceable_files`]). Whether
/// the output may replace an existing one is the caller's policy.
pub fn check_scene_output(path: &Path) -> Result<(), FormatError> {
    if OutputFormat::for_path(path) == Some(OutputFormat::SogFolder) {
        let dir = sog_folder(path);
        if sog::replaceable_files(dir).is_none() {
            return Err(FormatError::Unwritable {
                path: path.to_path_buf(),
                format: OutputFormat::SogFolder.name(),
                msg: sog::not_a_sog_folder(dir),
            });
        }
    }
    Ok(())
}

/// What reading the scene at `path` depends on beyond `path` itself, for the output checks: a SOG
/// `meta.json` (read by content: a JSON file) depends on its folder, whose textures it names.
pub fn scene_sources(path: &Path) -> Vec<PathBuf> {
    let mut sources = vec![path.to_path_buf()];
    let mut head = [0u8; 64];
    let json = path.is_file()
        && files::open_regular(path)
            .and_then(|mut f| f.read(&mut head))
            .is_ok_and(|n| head[..n].trim_ascii_start().starts_with(b"{"));
    if json {
        sources.push(sog_folder(path).to_path_buf());
    }
    sources
}

/// Writes a scene in the format its name asks for ([`OutputFormat::for_path`]), atomically where the
/// output is one file. Lossy formats report their largest errors, measured on what was written.
pub fn write_scene(path: &Path, scene: &GaussianScene) -> Result<WriteReport, FormatError> {
    let format = OutputFormat::for_path(path).ok_or_else(|| FormatError::UnknownOutput {
        path: path.to_path_buf(),
    })?;
    let unwritable = |msg: String| FormatError::Unwritable {
        path: path.to_path_buf(),
        format: format.name(),
        msg,
    };
    let write_err = |err| FormatError::Write {
        path: path.to_path_buf(),
        err,
    };
    if format == OutputFormat::InriaPly {
        ply::write_ply(path, scene)?;
        let bytes = std::fs::metadata(path).map_err(write_err)?.len();
        return Ok(WriteReport::lossless(format, scene, bytes));
    }
    ply::check_writable(scene).map_err(unwritable)?;
    // Each lossy format encodes to memory, then decodes its own bytes with the reader's code: the report
    // is then the error a reader of this very file will see.
    let (bytes, decoded) = match format {
        OutputFormat::CompressedPly => {
            let bytes = compressed_ply::encode(scene).map_err(unwritable)?;
            let back = compressed_ply::decode(&bytes).map_err(unwritable)?;
            (bytes, back)
        }
        OutputFormat::Splat => {
            let bytes = dot_splat::encode(scene).map_err(unwritable)?;
            let back = dot_splat::decode(&bytes).map_err(unwritable)?;
            (bytes, back)
        }
        OutputFormat::Spz => {
            let bytes = spz::encode(scene, spz::LATEST_VERSION).map_err(unwritable)?;
            let back = spz::decode(&bytes).map_err(unwritable)?;
            (bytes, back)
        }
        OutputFormat::SogZip | OutputFormat::SogFolder => {
            let files = sog::encode(scene).map_err(unwritable)?;
            let back = sog::decode_files(&files).map_err(unwritable)?;
            let bytes = if format == OutputFormat::SogZip {
                sog::zip_files(&files).map_err(unwritable)?
            } else {
                let total = sog::write_folder(sog_folder(path), &files).map_err(unwritable)?;
                return Ok(WriteReport::measured(format, scene, &back, total));
            };
            (bytes, back)
        }
        OutputFormat::InriaPly => unreachable!("handled above"),
    };
    files::atomic_write(path, &bytes).map_err(write_err)?;
    Ok(WriteReport::measured(
        format,
        scene,
        &decoded,
        bytes.len() as u64,
    ))
}

#[cfg(test)]
mod tests;
