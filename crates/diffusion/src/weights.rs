//! Safetensors weight files: the one place that opens them. Headers are parsed and validated by the
//! `safetensors` crate over a memory map (no tensor data is read); tensors are served by candle's
//! memory-mapped backend and converted to the requested dtype when fetched.

use std::fs::File;
use std::path::{Path, PathBuf};

use candle_core::{DType, Device};
use candle_nn::VarBuilder;
use safetensors::{SafeTensorError, SafeTensors};

use crate::loader::LoadError;

/// One tensor as described by a safetensors header.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TensorInfo {
    pub name: String,
    /// The safetensors dtype string: "F32", "F16", "BF16", "I64", ...
    pub dtype: String,
    pub shape: Vec<usize>,
}

impl TensorInfo {
    pub fn num_elements(&self) -> usize {
        self.shape.iter().product()
    }
}

/// Reads the header of a safetensors file and checks it against the file (every tensor's byte range
/// fits its shape and dtype, the ranges tile the data exactly), which catches truncated downloads.
/// Tensors are returned sorted by name.
pub fn read_safetensors_header(path: &Path) -> Result<Vec<TensorInfo>, LoadError> {
    let io = |source| LoadError::Io {
        path: path.to_path_buf(),
        source,
    };
    let file = File::open(path).map_err(io)?;
    // SAFETY: a read-only map that lives only for this call; like every reader of checkpoint files we
    // rely on nobody truncating the file meanwhile.
    let map = unsafe { memmap2::Mmap::map(&file) }.map_err(io)?;
    let (_, metadata) = SafeTensors::read_metadata(&map).map_err(|e| LoadError::BadFile {
        path: path.to_path_buf(),
        message: describe(e, map.len()),
    })?;
    let mut tensors: Vec<TensorInfo> = metadata
        .tensors()
        .into_iter()
        .map(|(name, info)| TensorInfo {
            name,
            dtype: format!("{:?}", info.dtype),
            shape: info.shape.clone(),
        })
        .collect();
    tensors.sort_by(|a, b| a.name.cmp(&b.name));
    Ok(tensors)
}

/// The first tensor of a safetensors file holding a NaN or an infinity, with the index of that value
/// (`None` when every float is finite). A damaged or badly converted checkpoint runs without any error
/// and decodes black images, so a model check looks at every value. The test is on the bits (an
/// all-ones exponent), so f16 and bf16 weights are scanned as stored, without converting.
pub fn first_non_finite(path: &Path) -> Result<Option<(String, usize)>, LoadError> {
    let io = |source| LoadError::Io {
        path: path.to_path_buf(),
        source,
    };
    let file = File::open(path).map_err(io)?;
    // SAFETY: a read-only map that lives only for this call (see `read_safetensors_header`).
    let map = unsafe { memmap2::Mmap::map(&file) }.map_err(io)?;
    let tensors = SafeTensors::deserialize(&map).map_err(|e| LoadError::BadFile {
        path: path.to_path_buf(),
        message: describe(e, map.len()),
    })?;
    let mut names: Vec<String> = tensors.names().into_iter().cloned().collect();
    names.sort();
    for name in names {
        let view = tensors.tensor(&name).map_err(|e| LoadError::BadFile {
            path: path.to_path_buf(),
            message: describe(e, map.len()),
        })?;
        let data = view.data();
        let bad = match view.dtype() {
            safetensors::Dtype::F32 => data.chunks_exact(4).position(|b| {
                u32::from_le_bytes([b[0], b[1], b[2], b[3]]) & 0x7f80_0000 == 0x7f80_0000
            }),
            safetensors::Dtype::F16 => data
                .chunks_exact(2)
                .position(|b| u16::from_le_bytes([b[0], b[1]]) & 0x7c00 == 0x7c00),
            safetensors::Dtype::BF16 => data
                .chunks_exact(2)
                .position(|b| u16::from_le_bytes([b[0], b[1]]) & 0x7f80 == 0x7f80),
            safetensors::Dtype::F64 => data.chunks_exact(8).position(|b| {
                let v = u64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]);
                v & 0x7ff0_0000_0000_0000 == 0x7ff0_0000_0000_0000
            }),
            _ => None,
        };
        if let Some(index) = bad {
            return Ok(Some((name, index)));
        }
    }
    Ok(None)
}

/// One line on what is wrong with a file that is not a valid safetensors file of `file_len` bytes.
fn describe(err: SafeTensorError, file_len: usize) -> String {
    use SafeTensorError as E;
    match err {
        E::HeaderTooSmall => "not a safetensors file (shorter than its 8-byte header length)".into(),
        E::HeaderTooLarge | E::InvalidHeaderLength => format!(
            "not a safetensors file, or a truncated one (its header length does not fit in \
             {file_len} bytes)"
        ),
        E::InvalidHeader | E::InvalidHeaderStart | E::InvalidHeaderDeserialization => {
            "invalid safetensors header (not the JSON tensor table safetensors expects)".into()
        }
        E::InvalidOffset(name) => format!("tensor {name} has invalid data offsets"),
        E::TensorInvalidInfo | E::ValidationOverflow => {
            "a tensor's byte range does not match its shape and dtype".into()
        }
        E::MetadataIncompleteBuffer => format!(
            "the tensors listed in the header do not match the file's {file_len} bytes; truncated download?"
        ),
        other => format!("invalid safetensors file ({other})"),
    }
}

/// A `VarBuilder` over memory-mapped safetensors files; tensors are converted to `dtype` on `device`
/// when fetched. The error names the first file.
pub fn var_builder_from_files(
    files: &[PathBuf],
    dtype: DType,
    device: &Device,
) -> Result<VarBuilder<'static>, LoadError> {
    mmap_var_builder(files, dtype, device).map_err(|source| LoadError::Candle {
        path: files.first().cloned().unwrap_or_default(),
        source,
    })
}

/// [`var_builder_from_files`] with candle's error, for loaders that report their own.
pub(crate) fn mmap_var_builder<P: AsRef<Path>>(
    files: &[P],
    dtype: DType,
    device: &Device,
) -> candle_core::Result<VarBuilder<'static>> {
    // SAFETY: the files are mapped read-only; like every mmap user we rely on nobody truncating or
    // rewriting a checkpoint while vcedit runs (the same contract as candle and diffusers' safetensors).
    unsafe { VarBuilder::from_mmaped_safetensors(files, dtype, device) }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn header_reader_lists_tensors_and_detects_damage() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("w.safetensors");
        let tensors = std::collections::HashMap::from([
            (
                "w".to_string(),
                candle_core::Tensor::zeros((3, 4), DType::F16, &Device::Cpu).unwrap(),
            ),
            (
                "b".to_string(),
                candle_core::Tensor::zeros(3, DType::F32, &Device::Cpu).unwrap(),
            ),
        ]);
        candle_core::safetensors::save(&tensors, &path).unwrap();
        let infos = read_safetensors_header(&path).unwrap();
        assert_eq!(
            infos,
            vec![
                TensorInfo {
                    name: "b".into(),
                    dtype: "F32".into(),
                    shape: vec![3]
                },
                TensorInfo {
                    name: "w".into(),
                    dtype: "F16".into(),
                    shape: vec![3, 4]
                },
            ]
        );
        let bytes = std::fs::read(&path).unwrap();
        let message = |content: &[u8]| {
            std::fs::write(&path, content).unwrap();
            read_safetensors_header(&path).unwrap_err().to_string()
        };
        for (content, expected) in [
            (&bytes[..bytes.len() - 2], "truncated download"),
            (&bytes[..20], "header length does not fit"),
            (&b"abc"[..], "shorter than its 8-byte header"),
            (&b""[..], "shorter than its 8-byte header"),
            (&b"\x04\0\0\0\0\0\0\0{[]}"[..], "invalid safetensors header"),
        ] {
            let m = message(content);
            assert!(m.contains(expected), "{m}");
            assert!(m.starts_with(&path.display().to_string()), "{m}");
            assert!(!m.contains('\n'), "{m}");
        }
    }

    #[test]
    fn var_builder_converts_dtype_and_names_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("w.safetensors");
        let t = candle_core::Tensor::new(&[1.5f32, -2.0], &Device::Cpu)
            .unwrap()
            .to_dtype(DType::F16)
            .unwrap();
        candle_core::safetensors::save(
            &std::collections::HashMap::from([("x".to_string(), t)]),
            &path,
        )
        .unwrap();
        let vb =
            var_builder_from_files(std::slice::from_ref(&path), DType::F32, &Device::Cpu).unwrap();
        let x = vb.get(2, "x").unwrap();
        assert_eq!(x.dtype(), DType::F32);
        assert_eq!(x.to_vec1::<f32>().unwrap(), vec![1.5, -2.0]);
        std::fs::write(&path, b"garbage!").unwrap();
        let err = var_builder_from_files(std::slice::from_ref(&path), DType::F32, &Device::Cpu)
            .err()
            .unwrap()
            .to_string();
        assert!(err.contains("w.safetensors"), "{err}");
    }
}
