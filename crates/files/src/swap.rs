//! Outputs of several files (a SOG folder) replaced as a whole: the new folder is written beside the
//! old one and swapped in, so a reader — or a failure half-way, or a second run at the same time —
//! sees the old scene or the new one, never a mix.

use std::io;
use std::path::Path;

use crate::temp::{create_dir_beside, parent_dir};

/// Replaces the folder `dir` with what `fill` writes into an empty temporary folder beside it. On Linux
/// the two folders are exchanged in one step (`renameat2(RENAME_EXCHANGE)`); elsewhere (or on a file
/// system without it) the old folder is renamed aside first and renamed back if the new one cannot take
/// its place. A failure in `fill` leaves `dir` as it was.
///
/// After the swap, `discardable` is asked which files of the old folder may be removed (it decides by
/// content: a folder can have changed since the caller checked it); the old folder is removed when that
/// empties it, and left under its temporary name otherwise (nothing unknown is deleted).
pub fn replace_folder(
    dir: &Path,
    fill: impl FnOnce(&Path) -> io::Result<()>,
    discardable: impl Fn(&Path) -> Vec<String>,
) -> io::Result<()> {
    // Absolute, so that `.` or `..` name a folder that has a parent to write beside.
    let dir = &match std::fs::canonicalize(dir) {
        Ok(d) => d,
        Err(_) => std::path::absolute(dir)?,
    };
    std::fs::create_dir_all(parent_dir(dir))?;
    let new = create_dir_beside(dir)?;
    fill(new.path())?;
    sync_folder(new.path())?;
    if !dir.exists() {
        match std::fs::rename(new.path(), dir) {
            Ok(()) => {
                new.keep();
                return sync_parent(dir);
            }
            // Another run made `dir` meanwhile: swap with its folder as with any older one.
            Err(_) if dir.is_dir() => {}
            Err(e) => return Err(e),
        }
    }
    if !std::fs::symlink_metadata(dir)?.is_dir() {
        return Err(io::Error::new(
            io::ErrorKind::AlreadyExists,
            "exists and is not a folder",
        ));
    }
    // From here the temporary name holds the old folder.
    swap(new.path(), dir)?;
    sync_parent(dir)?;
    let old = new;
    for name in discardable(old.path()) {
        if is_plain_name(&name) {
            let _ = std::fs::remove_file(old.path().join(name));
        }
    }
    let old = old.keep();
    if std::fs::remove_dir(&old).is_err() {
        // Something nobody listed (put there after the caller's check): keep it, under a name the
        // clean-up of temporary files never matches.
        let name = old.file_name().unwrap_or_default().to_string_lossy();
        let kept = old.with_file_name(name.replacen("vcedit-tmp-", "vcedit-kept-", 1));
        let _ = std::fs::rename(&old, kept);
    }
    Ok(())
}

fn is_plain_name(name: &str) -> bool {
    !name.is_empty() && name != "." && name != ".." && !name.contains(['/', '\\'])
}

/// Exchanges the folders `a` and `b`.
fn swap(a: &Path, b: &Path) -> io::Result<()> {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        use std::ffi::CString;
        use std::os::unix::ffi::OsStrExt;
        let c = |p: &Path| {
            CString::new(p.as_os_str().as_bytes())
                .map_err(|_| io::Error::new(io::ErrorKind::InvalidInput, "a NUL byte in a path"))
        };
        let (ca, cb) = (c(a)?, c(b)?);
        // SAFETY: two valid NUL-terminated paths, relative to the working directory.
        let rc = unsafe {
            libc::renameat2(
                libc::AT_FDCWD,
                ca.as_ptr(),
                libc::AT_FDCWD,
                cb.as_ptr(),
                libc::RENAME_EXCHANGE,
            )
        };
        if rc == 0 {
            return Ok(());
        }
        let err = io::Error::last_os_error();
        // Not supported here (older kernels, some file systems): fall back to two renames.
        if !matches!(err.raw_os_error(), Some(libc::EINVAL | libc::ENOSYS)) {
            return Err(err);
        }
    }
    let aside = create_dir_beside(b)?;
    std::fs::rename(b, aside.path())?;
    if let Err(e) = std::fs::rename(a, b) {
        std::fs::rename(aside.path(), b)?;
        aside.keep();
        return Err(e);
    }
    std::fs::rename(aside.path(), a)?;
    aside.keep();
    Ok(())
}

/// Flushes every file in `dir`, then the folder itself, so the swap never exposes unwritten data.
fn sync_folder(dir: &Path) -> io::Result<()> {
    for entry in std::fs::read_dir(dir)? {
        let path = entry?.path();
        if path.is_file() {
            std::fs::File::open(&path)?.sync_all()?;
        }
    }
    sync_dir(dir)
}

fn sync_parent(dir: &Path) -> io::Result<()> {
    sync_dir(parent_dir(dir))
}

fn sync_dir(dir: &Path) -> io::Result<()> {
    #[cfg(unix)]
    std::fs::File::open(dir)?.sync_all()?;
    #[cfg(not(unix))]
    let _ = dir;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(dir: &Path) -> Vec<String> {
        let mut v: Vec<String> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        v.sort();
        v
    }

    fn write(dir: &Path, files: &[(&str, &str)]) -> io::Result<()> {
        for (n, t) in files {
            std::fs::write(dir.join(n), t)?;
        }
        Ok(())
    }

    #[test]
    fn a_folder_is_made_or_replaced_whole() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("scene");
        replace_folder(
            &dir,
            |d| write(d, &[("meta.json", "1"), ("a", "1")]),
            |_| vec![],
        )
        .unwrap();
        assert_eq!(names(&dir), ["a", "meta.json"]);
        replace_folder(
            &dir,
            |d| write(d, &[("meta.json", "2"), ("b", "2")]),
            |_| vec!["meta.json".into(), "a".into()],
        )
        .unwrap();
        assert_eq!(names(&dir), ["b", "meta.json"]);
        assert_eq!(std::fs::read_to_string(dir.join("meta.json")).unwrap(), "2");
        // Nothing else is left beside it.
        assert_eq!(names(tmp.path()), ["scene"]);
    }

    #[test]
    fn a_failed_fill_keeps_the_old_folder() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("scene");
        replace_folder(&dir, |d| write(d, &[("meta.json", "1")]), |_| vec![]).unwrap();
        let err = replace_folder(
            &dir,
            |d| {
                write(d, &[("meta.json", "2")])?;
                Err(io::Error::other("disk full"))
            },
            |_| vec!["meta.json".into()],
        )
        .unwrap_err();
        assert!(err.to_string().contains("disk full"));
        assert_eq!(std::fs::read_to_string(dir.join("meta.json")).unwrap(), "1");
        assert_eq!(names(tmp.path()), ["scene"]);
    }

    #[test]
    fn unlisted_files_of_the_old_folder_are_kept() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("scene");
        std::fs::create_dir(&dir).unwrap();
        write(&dir, &[("meta.json", "1"), ("notes.txt", "mine")]).unwrap();
        replace_folder(
            &dir,
            |d| write(d, &[("meta.json", "2")]),
            |_| vec!["meta.json".into()],
        )
        .unwrap();
        assert_eq!(names(&dir), ["meta.json"]);
        let kept: Vec<String> = names(tmp.path());
        assert_eq!(kept.len(), 2, "{kept:?}");
        let old = kept.iter().find(|n| *n != "scene").unwrap();
        assert!(old.contains("vcedit-kept-"), "{old}");
        assert_eq!(names(&tmp.path().join(old)), ["notes.txt"]);
        assert_eq!(crate::clean_stale_temps(tmp.path()).unwrap(), 0);
    }
}
