//! The one place vcedit makes temporary files and folders, and the one place it removes those that
//! killed runs left behind.
//!
//! A temporary name is `.NAME.vcedit-tmp-PID-TOKEN`: NAME the output's name (shortened when long), PID
//! the writing process, TOKEN 12 random letters and digits. The name is created exclusively
//! (`O_CREAT | O_EXCL`, and `O_NOFOLLOW`): a file or symbolic link already at that name makes the
//! creation pick another name instead of writing through it, and nobody can know the name in advance.
//!
//! [`clean_stale_temps`] removes only what provably comes from a vcedit run that no longer runs: a name
//! of exactly that shape (no user picks it: the marker, a process id and a 12-character token), a
//! regular file with one link (or a folder of such files, from a folder swap), owned by the user running
//! vcedit, whose writing process has ended. Anything else — another program's temporary file, a file of
//! another user, a link — is left alone. Callers clean a folder only after deciding to write there: a
//! folder vcedit refuses is never touched.

use std::fs::{File, OpenOptions};
use std::io;
use std::path::{Path, PathBuf};

/// Marker between an output's name and the writer's process id.
const MARKER: &str = ".vcedit-tmp-";
/// Random letters and digits at the end of a temporary name.
const TOKEN_LEN: usize = 12;
/// The longest output name kept in a temporary name (file names are limited to 255 bytes).
const NAME_KEEP: usize = 120;

/// The folder `path` is in (`.` for a bare name).
pub(crate) fn parent_dir(path: &Path) -> &Path {
    match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    }
}

/// `.NAME.vcedit-tmp-PID-`, the part of a temporary name before its token.
fn prefix_for(target: &Path) -> String {
    let name = target
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let mut end = name.len().min(NAME_KEEP);
    while !name.is_char_boundary(end) {
        end -= 1;
    }
    format!(".{}{MARKER}{}-", &name[..end], std::process::id())
}

fn builder(prefix: &str) -> tempfile::Builder<'_, '_> {
    let mut b = tempfile::Builder::new();
    b.prefix(prefix).rand_bytes(TOKEN_LEN);
    b
}

/// A new temporary file beside `target` (in the same folder, so that a rename can replace `target`),
/// open for writing. Dropped without [`tempfile::TempPath::persist`], it is removed.
pub(crate) fn create_file_beside(target: &Path) -> io::Result<(File, tempfile::TempPath)> {
    let prefix = prefix_for(target);
    let made = builder(&prefix).make_in(parent_dir(target), |path| {
        let mut options = OpenOptions::new();
        options.write(true).create_new(true);
        #[cfg(unix)]
        {
            use std::os::unix::fs::OpenOptionsExt;
            // Readable as an ordinary new file would be (the umask applies), not 0600: it becomes
            // the output.
            options.mode(0o666).custom_flags(libc::O_NOFOLLOW);
        }
        options.open(path)
    })?;
    Ok(made.into_parts())
}

/// A new, empty temporary folder beside `target`, removed with its content when dropped unless kept.
pub(crate) fn create_dir_beside(target: &Path) -> io::Result<TempFolder> {
    let prefix = prefix_for(target);
    let made = builder(&prefix).make_in(parent_dir(target), |path| std::fs::create_dir(path))?;
    // The builder's guard would remove the folder as a file; this one removes it as a folder.
    let path = made.into_temp_path().keep().map_err(|e| e.error)?;
    Ok(TempFolder { path: Some(path) })
}

/// A temporary folder of ours; removed (with what it holds) when dropped, unless [`TempFolder::keep`].
#[derive(Debug)]
pub(crate) struct TempFolder {
    path: Option<PathBuf>,
}

impl TempFolder {
    pub(crate) fn path(&self) -> &Path {
        self.path.as_deref().expect("present until dropped or kept")
    }

    /// Stops the removal on drop (the folder was renamed away or swapped).
    pub(crate) fn keep(mut self) -> PathBuf {
        self.path.take().expect("present until dropped or kept")
    }
}

impl Drop for TempFolder {
    fn drop(&mut self) {
        if let Some(p) = self.path.take() {
            let _ = std::fs::remove_dir_all(p);
        }
    }
}

/// Checks that a file can be created in `dir` (the folder of an output, before any work), by creating
/// and removing a temporary file there. A missing folder is checked by creating and removing a temporary
/// folder in its nearest existing ancestor: nothing is left behind either way.
pub fn check_writable_folder(dir: &Path) -> io::Result<()> {
    if dir.is_dir() {
        let probe = dir.join("probe");
        return create_file_beside(&probe).map(drop);
    }
    let mut ancestor = dir;
    loop {
        match ancestor.parent() {
            Some(p) if !p.as_os_str().is_empty() => ancestor = p,
            _ => ancestor = Path::new("."),
        }
        if ancestor.exists() || ancestor == Path::new(".") {
            break;
        }
    }
    if !ancestor.is_dir() {
        return Err(io::Error::new(
            io::ErrorKind::NotADirectory,
            format!("{} is not a folder", ancestor.display()),
        ));
    }
    create_dir_beside(&ancestor.join("probe")).map(drop)
}

/// Removes the temporary files (and swap folders) of vcedit runs that no longer run, in `dir` only
/// (see the module documentation for what counts as one). Returns how many were removed; a missing
/// folder is not an error.
pub fn clean_stale_temps(dir: &Path) -> io::Result<usize> {
    let entries = match std::fs::read_dir(dir) {
        Ok(e) => e,
        Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(0),
        Err(e) => return Err(e),
    };
    let mut removed = 0;
    for entry in entries {
        let entry = entry?;
        let name = entry.file_name().to_string_lossy().into_owned();
        let Some(pid) = temp_owner(&name) else {
            continue;
        };
        if pid == std::process::id() || process_alive(pid) {
            continue;
        }
        let path = entry.path();
        let Ok(meta) = std::fs::symlink_metadata(&path) else {
            continue;
        };
        if meta.is_file() && ours(&meta) {
            std::fs::remove_file(&path)?;
            removed += 1;
        } else if meta.is_dir() && ours(&meta) && holds_only_our_files(&path) {
            std::fs::remove_dir_all(&path)?;
            removed += 1;
        }
    }
    Ok(removed)
}

/// Whether `name` has the shape of a vcedit temporary name (`.NAME.vcedit-tmp-PID-TOKEN`): a file a
/// vcedit run is writing or probing with, which another run's check of the same folder passes over.
pub fn is_temporary_name(name: &str) -> bool {
    temp_owner(name).is_some()
}

/// The process id in a temporary name of ours (`.NAME.vcedit-tmp-PID-TOKEN`), if it is one.
fn temp_owner(name: &str) -> Option<u32> {
    if !name.starts_with('.') {
        return None;
    }
    let at = name.rfind(MARKER)?;
    let (pid, token) = name[at + MARKER.len()..].split_once('-')?;
    let token_ok = token.len() == TOKEN_LEN && token.bytes().all(|b| b.is_ascii_alphanumeric());
    let pid_ok = !pid.is_empty() && pid.bytes().all(|b| b.is_ascii_digit());
    (token_ok && pid_ok).then(|| pid.parse().ok()).flatten()
}

/// A regular file with one name (or a folder), owned by the user running vcedit.
fn ours(meta: &std::fs::Metadata) -> bool {
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        // SAFETY: geteuid has no preconditions and touches no memory.
        let me = unsafe { libc::geteuid() };
        meta.uid() == me && (meta.is_dir() || meta.nlink() == 1)
    }
    #[cfg(not(unix))]
    {
        let _ = meta;
        false
    }
}

/// A swap folder holds the files of one output: regular files of ours, nothing else.
fn holds_only_our_files(dir: &Path) -> bool {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return false;
    };
    entries.into_iter().all(|e| {
        e.ok()
            .and_then(|e| std::fs::symlink_metadata(e.path()).ok())
            .is_some_and(|m| m.is_file() && ours(&m))
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

    /// A pid that cannot be running (beyond Linux's pid_max).
    const DEAD: u32 = 4_194_305;

    #[test]
    fn temp_names_are_exclusive_and_unpredictable() {
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("x.ply");
        let (_f1, p1) = create_file_beside(&target).unwrap();
        let (_f2, p2) = create_file_beside(&target).unwrap();
        assert_ne!(p1.to_path_buf(), p2.to_path_buf());
        let name = p1.file_name().unwrap().to_str().unwrap().to_string();
        assert!(name.starts_with(&format!(".x.ply{MARKER}{}-", std::process::id())));
        assert_eq!(temp_owner(&name), Some(std::process::id()));
        drop(p1);
        drop(p2);
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
        // A long name is shortened to keep within file-name limits.
        let long = dir.path().join("é".repeat(120));
        let (_f, p) = create_file_beside(&long).unwrap();
        assert!(p.file_name().unwrap().len() < 255);
    }

    #[test]
    fn only_our_stale_temps_are_removed() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        let dead = d.join(format!(".scene.ply{MARKER}{DEAD}-Ab3dE5fG7hJ9"));
        let live = d.join(format!(
            ".scene.ply{MARKER}{}-Ab3dE5fG7hJ9",
            std::process::id()
        ));
        let keep = [
            // The naming of earlier versions, which users' files matched (issue 69).
            d.join(".thesis.tex.tmp-2024"),
            d.join(format!(".scene.ply{MARKER}{DEAD}")),
            // A token of the wrong length or alphabet.
            d.join(format!(".scene.ply{MARKER}{DEAD}-short")),
            d.join(format!(".scene.ply{MARKER}{DEAD}-Ab3dE5fG7h_9")),
            d.join(format!("scene.ply{MARKER}{DEAD}-Ab3dE5fG7hJ9")),
            d.join("scene.ply"),
        ];
        for p in keep.iter().chain([&dead, &live]) {
            std::fs::write(p, b"x").unwrap();
        }
        // A dead swap folder holding files goes too; one holding a link stays.
        let swap = d.join(format!(".s{MARKER}{DEAD}-Zz3dE5fG7hJ9"));
        std::fs::create_dir(&swap).unwrap();
        std::fs::write(swap.join("meta.json"), b"{}").unwrap();
        #[cfg(unix)]
        let linked = {
            let linked = d.join(format!(".t{MARKER}{DEAD}-Yy3dE5fG7hJ9"));
            std::fs::create_dir(&linked).unwrap();
            std::os::unix::fs::symlink(d.join("scene.ply"), linked.join("l")).unwrap();
            linked
        };
        let removed = clean_stale_temps(d).unwrap();
        if cfg!(target_os = "linux") {
            assert_eq!(removed, 2);
            assert!(!dead.exists() && !swap.exists());
        }
        assert!(live.exists() && keep.iter().all(|p| p.exists()));
        #[cfg(unix)]
        assert!(linked.exists());
        assert_eq!(clean_stale_temps(&d.join("missing")).unwrap(), 0);
    }

    #[cfg(unix)]
    #[test]
    fn a_stale_name_that_is_a_link_or_a_second_name_is_kept() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        let victim = d.join("victim.txt");
        std::fs::write(&victim, b"keep").unwrap();
        let link = d.join(format!(".a{MARKER}{DEAD}-Ab3dE5fG7hJ9"));
        std::os::unix::fs::symlink(&victim, &link).unwrap();
        let hard = d.join(format!(".b{MARKER}{DEAD}-Ab3dE5fG7hJ9"));
        std::fs::hard_link(&victim, &hard).unwrap();
        assert_eq!(clean_stale_temps(d).unwrap(), 0);
        assert!(link.exists() && hard.exists());
    }

    #[test]
    fn writability_is_checked_without_leaving_anything() {
        let dir = tempfile::tempdir().unwrap();
        check_writable_folder(dir.path()).unwrap();
        check_writable_folder(&dir.path().join("new/deeper")).unwrap();
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
        std::fs::write(dir.path().join("file"), b"x").unwrap();
        assert!(check_writable_folder(&dir.path().join("file/sub")).is_err());
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            let ro = dir.path().join("ro");
            std::fs::create_dir(&ro).unwrap();
            std::fs::set_permissions(&ro, std::fs::Permissions::from_mode(0o555)).unwrap();
            // Root may write anyway; the check must then agree with what a write would do.
            let writable = std::fs::write(ro.join("t"), b"").is_ok();
            let _ = std::fs::remove_file(ro.join("t"));
            assert_eq!(check_writable_folder(&ro).is_ok(), writable);
            assert_eq!(check_writable_folder(&ro.join("sub")).is_ok(), writable);
        }
    }
}
