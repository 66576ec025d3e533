//! Atomic file replacement and the clean-up of temporary files left by killed runs.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

/// Marker between a file's name and the writing process id in temporary file names:
/// `.NAME.vcedit-tmp-PID`. Distinctive so that [`clean_stale_temps`] never touches other programs' files.
const TEMP_MARKER: &str = ".vcedit-tmp-";
/// The marker of vcedit versions before 0.2 (`.NAME.tmp-PID`), still cleaned up after them.
const LEGACY_TEMP_MARKER: &str = ".tmp-";

/// The temporary file [`atomic_write`] uses for `path` in this process.
pub fn temp_path_for(path: &Path) -> PathBuf {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    parent_dir(path).join(format!(".{name}{TEMP_MARKER}{}", std::process::id()))
}

fn parent_dir(path: &Path) -> PathBuf {
    match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    }
}

/// Writes `bytes` to `path` atomically: into a temporary file beside it, flushed to disk, then renamed
/// over `path`. Readers see the old file or the new one, never a partial one; a failure leaves `path`
/// as it was. Creates missing parent folders. Inside an open [`crate::RunDir`] the file is recorded in
/// its manifest, and a write over one of the run's inputs is refused.
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
    let tmp = temp_path_for(path);
    let result = (|| {
        let mut w = BufWriter::new(File::create(&tmp)?);
        write(&mut w)?;
        let f = w.into_inner().map_err(|e| e.into_error())?;
        f.sync_all()?;
        std::fs::rename(&tmp, path)
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

/// Removes the temporary files of [`atomic_write`] in `dir` whose writing process no longer runs
/// (a run killed mid-write leaves one). Returns how many were removed. Files of running processes and
/// files of any other naming are left alone; a missing folder is not an error.
pub fn clean_stale_temps(dir: &Path) -> std::io::Result<usize> {
    let entries = match std::fs::read_dir(dir) {
        Ok(e) => e,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(0),
        Err(e) => return Err(e),
    };
    let mut removed = 0;
    for entry in entries {
        let entry = entry?;
        let name = entry.file_name().to_string_lossy().into_owned();
        let Some(pid) = temp_owner(&name) else {
            continue;
        };
        if pid != std::process::id() && !process_alive(pid) && entry.file_type()?.is_file() {
            std::fs::remove_file(entry.path())?;
            removed += 1;
        }
    }
    Ok(removed)
}

/// The process id in a temporary file name of ours, if it is one.
fn temp_owner(name: &str) -> Option<u32> {
    if !name.starts_with('.') {
        return None;
    }
    [TEMP_MARKER, LEGACY_TEMP_MARKER].iter().find_map(|marker| {
        let at = name.rfind(marker)?;
        name[at + marker.len()..].parse().ok()
    })
}

#[cfg(target_os = "linux")]
fn process_alive(pid: u32) -> bool {
    Path::new("/proc").join(pid.to_string()).exists()
}

#[cfg(not(target_os = "linux"))]
fn process_alive(_pid: u32) -> bool {
    // Without a cheap portable check, assume the writer may still run: leaving a stale file is better
    // than removing a live one.
    true
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

    #[test]
    fn stale_temps_of_dead_processes_are_removed_others_kept() {
        let dir = tempfile::tempdir().unwrap();
        // A pid that cannot be running (beyond Linux's pid_max).
        let dead = dir.path().join(format!(".scene.ply{TEMP_MARKER}4194305"));
        let live = dir
            .path()
            .join(format!(".scene.ply{TEMP_MARKER}{}", std::process::id()));
        let legacy = dir.path().join(".lego.ply.tmp-4194306");
        let foreign = dir.path().join(".scene.ply.partial-4194305");
        let plain = dir.path().join("scene.ply");
        for p in [&dead, &live, &legacy, &foreign, &plain] {
            std::fs::write(p, b"x").unwrap();
        }
        let removed = clean_stale_temps(dir.path()).unwrap();
        if cfg!(target_os = "linux") {
            assert_eq!(removed, 2);
            assert!(!dead.exists() && !legacy.exists());
        }
        assert!(live.exists() && foreign.exists() && plain.exists());
        assert_eq!(clean_stale_temps(&dir.path().join("missing")).unwrap(), 0);
    }

    #[test]
    fn temp_names_parse() {
        assert_eq!(temp_owner(".a.png.vcedit-tmp-12"), Some(12));
        assert_eq!(temp_owner(".a.png.tmp-12"), Some(12));
        assert_eq!(temp_owner("a.png.vcedit-tmp-12"), None);
        assert_eq!(temp_owner(".a.png.vcedit-tmp-x"), None);
        assert_eq!(temp_owner(".a.png"), None);
    }
}
