//! Atomic file replacement: a file appears whole or not at all.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::Path;

use crate::temp::{create_file_beside, parent_dir};

/// Writes `bytes` to `path` atomically: into a temporary file beside it (see [`crate::temp`]: created
/// exclusively under an unpredictable name), flushed to disk, then renamed over `path`. Readers see the
/// old file or the new one, never a partial one; a failure leaves `path` as it was. Creates missing
/// parent folders. Inside an open [`crate::RunDir`] the file is recorded in its manifest, and a write
/// over one of the run's inputs is refused.
pub fn atomic_write(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    atomic_write_with(path, |w| w.write_all(bytes))
}

/// Like [`atomic_write`], for content produced by a writer (large files are streamed, not buffered).
pub fn atomic_write_with(
    path: &Path,
    write: impl FnOnce(&mut BufWriter<File>) -> std::io::Result<()>,
) -> std::io::Result<()> {
    std::fs::create_dir_all(parent_dir(path))?;
    crate::rundir::before_write(path)?;
    // The temporary file is removed when `tmp` is dropped on any error below.
    let (file, tmp) = create_file_beside(path)?;
    let mut w = BufWriter::new(file);
    write(&mut w)?;
    let f = w.into_inner().map_err(|e| e.into_error())?;
    f.sync_all()?;
    tmp.persist(path).map_err(|e| e.error)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn replaces_and_leaves_no_temp() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("sub").join("f.bin");
        atomic_write(&p, b"one").unwrap();
        atomic_write(&p, b"two").unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"two");
        assert_eq!(std::fs::read_dir(p.parent().unwrap()).unwrap().count(), 1);
    }

    #[test]
    fn failed_writer_keeps_the_old_file() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("f.txt");
        atomic_write(&p, b"old").unwrap();
        let err = atomic_write_with(&p, |w| {
            w.write_all(b"partial")?;
            Err(std::io::Error::other("disk on fire"))
        })
        .unwrap_err();
        assert!(err.to_string().contains("disk on fire"));
        assert_eq!(std::fs::read(&p).unwrap(), b"old");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }
}
