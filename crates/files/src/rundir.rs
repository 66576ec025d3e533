//! One run per output folder.
//!
//! A folder vcedit writes into carries a manifest, `.vcedit-run`: a first line naming the command and a
//! fingerprint of its settings, then one line per file written there. Opening a folder:
//! - new or empty: it becomes this run's folder;
//! - holding a manifest of the same command and settings: the same run again (resumed or redone), and its
//!   files are kept;
//! - holding another run: refused, unless the mode is [`RunDirMode::Force`], which first removes the files
//!   that manifest lists (never an input of this run) and empty folders left behind;
//! - holding files but no manifest: refused always — vcedit did not write them, so it will not mix its
//!   files in or delete them.
//!
//! While a [`RunDir`] is open, every [`crate::atomic_write`] into it is added to its manifest
//! automatically, and a write over one of the run's inputs is refused, whichever crate does the writing.
//! It also holds an exclusive lock on the folder (`flock` on the folder itself, so no lock file is left
//! behind and a killed run frees it): a second run into the same folder at the same time is refused
//! instead of interleaving its files and manifest lines with the first's.

use std::collections::BTreeSet;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use crate::paths::{check_not_inputs, PathError};

/// File name of the manifest in a run folder.
pub const MANIFEST_NAME: &str = ".vcedit-run";

/// How [`RunDir::open`] treats a folder that holds another run.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RunDirMode {
    /// Refuse it.
    Keep,
    /// Remove the files it lists, then start this run.
    Force,
}

/// What the folder held when it was opened.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Previous {
    /// Nothing (new or empty folder).
    Nothing,
    /// Files of a run of the same command and settings.
    SameRun,
    /// Another run's files, removed by `--force`.
    Cleared,
}

#[derive(Debug, thiserror::Error)]
pub enum RunDirError {
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{}: exists and is not a folder", path.display())]
    NotAFolder { path: PathBuf },
    #[error("{}: holds the outputs of another run ({previous}); add --force to replace them, or choose another folder", path.display())]
    OtherRun { path: PathBuf, previous: String },
    #[error("{}: is not empty and was not written by vcedit; choose a new or empty folder", path.display())]
    Foreign { path: PathBuf },
    #[error("{}: another vcedit run is writing into this folder now; wait for it to end or choose another folder", path.display())]
    Busy { path: PathBuf },
    #[error(transparent)]
    Input(#[from] PathError),
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> RunDirError + '_ {
    move |source| RunDirError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// The header line of a manifest.
#[derive(Clone, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
struct Header {
    command: String,
    settings: String,
}

/// An open run folder; see the module documentation. Closing (dropping) it stops recording writes.
#[derive(Debug)]
pub struct RunDir {
    dir: PathBuf,
    previous: Previous,
    /// The folder opened for its lock; closing it releases the lock.
    _lock: FolderLock,
}

/// Open run folders: (canonical folder, inputs of the run), consulted by every atomic write.
static OPEN: Mutex<Vec<(PathBuf, Vec<PathBuf>)>> = Mutex::new(Vec::new());

impl RunDir {
    /// Opens `dir` for a run of `command` whose settings have the fingerprint `settings` (any string
    /// that differs when the outputs would differ). `inputs` are the files the run reads: none of them
    /// may be removed or replaced. Stale temporary files of killed runs are removed.
    pub fn open(
        dir: &Path,
        command: &str,
        settings: &str,
        mode: RunDirMode,
        inputs: &[&Path],
    ) -> Result<Self, RunDirError> {
        if dir.exists() && !dir.is_dir() {
            return Err(RunDirError::NotAFolder {
                path: dir.to_path_buf(),
            });
        }
        std::fs::create_dir_all(dir).map_err(io_err(dir))?;
        // Before anything is read or removed: another run may be writing here right now.
        let lock = FolderLock::acquire(dir)?;
        let header = Header {
            command: command.to_string(),
            settings: settings.to_string(),
        };
        let manifest = dir.join(MANIFEST_NAME);
        let previous = match read_manifest(&manifest)? {
            Some((old, _)) if old == header => Previous::SameRun,
            Some((old, files)) => {
                if mode == RunDirMode::Keep {
                    let what = if old.command == header.command {
                        format!("vcedit {} with other settings", old.command)
                    } else {
                        format!("vcedit {}", old.command)
                    };
                    return Err(RunDirError::OtherRun {
                        path: dir.to_path_buf(),
                        previous: what,
                    });
                }
                let doomed: Vec<PathBuf> = files.iter().map(|f| dir.join(f)).collect();
                let doomed_refs: Vec<&Path> = doomed.iter().map(PathBuf::as_path).collect();
                check_not_inputs(&doomed_refs, inputs)?;
                remove_listed(dir, &files)?;
                Previous::Cleared
            }
            None => {
                let mut entries = std::fs::read_dir(dir).map_err(io_err(dir))?;
                if entries.next().is_some() {
                    return Err(RunDirError::Foreign {
                        path: dir.to_path_buf(),
                    });
                }
                Previous::Nothing
            }
        };
        // Only now that the folder is ours to write into (a refused folder is never touched).
        crate::clean_stale_temps(dir).map_err(io_err(dir))?;
        if previous != Previous::SameRun {
            let line = serde_json::to_string(&header).expect("serialisable") + "\n";
            crate::atomic_write(&manifest, line.as_bytes()).map_err(io_err(&manifest))?;
        }
        let canonical = std::fs::canonicalize(dir).map_err(io_err(dir))?;
        let inputs = inputs
            .iter()
            .filter_map(|p| std::fs::canonicalize(p).ok())
            .collect();
        OPEN.lock()
            .unwrap_or_else(|e| e.into_inner())
            .push((canonical, inputs));
        Ok(Self {
            dir: dir.to_path_buf(),
            previous,
            _lock: lock,
        })
    }

    pub fn path(&self) -> &Path {
        &self.dir
    }

    /// What the folder held when it was opened.
    pub fn previous(&self) -> Previous {
        self.previous
    }

    /// The files the manifest lists (relative to the folder), in sorted order.
    pub fn recorded(&self) -> Result<Vec<PathBuf>, RunDirError> {
        let manifest = self.dir.join(MANIFEST_NAME);
        Ok(read_manifest(&manifest)?
            .map(|(_, files)| files.into_iter().collect())
            .unwrap_or_default())
    }
}

impl Drop for RunDir {
    fn drop(&mut self) {
        if let Ok(canonical) = std::fs::canonicalize(&self.dir) {
            let mut open = OPEN.lock().unwrap_or_else(|e| e.into_inner());
            if let Some(i) = open.iter().rposition(|(d, _)| *d == canonical) {
                open.remove(i);
            }
        }
    }
}

/// An exclusive advisory lock on a folder, held while the value lives.
#[derive(Debug)]
struct FolderLock {
    /// Kept open only: the lock lives as long as the descriptor.
    _handle: std::fs::File,
}

impl FolderLock {
    fn acquire(dir: &Path) -> Result<Self, RunDirError> {
        let handle = std::fs::File::open(dir).map_err(io_err(dir))?;
        #[cfg(unix)]
        {
            use std::os::fd::AsRawFd;
            // SAFETY: flock on a descriptor this function owns; no memory is shared with the call.
            let rc = unsafe { libc::flock(handle.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) };
            if rc != 0 {
                let err = std::io::Error::last_os_error();
                return Err(if err.kind() == std::io::ErrorKind::WouldBlock {
                    RunDirError::Busy {
                        path: dir.to_path_buf(),
                    }
                } else {
                    RunDirError::Io {
                        path: dir.to_path_buf(),
                        source: err,
                    }
                });
            }
        }
        // Elsewhere the folder is not locked: two simultaneous runs there are the user's to avoid.
        Ok(Self { _handle: handle })
    }
}

/// Called by every atomic write before it replaces `path`: refuses a write over an input of an open
/// run, and records `path` in the manifest of the open run folder that contains it.
pub(crate) fn before_write(path: &Path) -> std::io::Result<()> {
    let open = OPEN.lock().unwrap_or_else(|e| e.into_inner());
    if open.is_empty() {
        return Ok(());
    }
    let Some(parent) = path.parent().map(|p| {
        if p.as_os_str().is_empty() {
            Path::new(".")
        } else {
            p
        }
    }) else {
        return Ok(());
    };
    let Ok(parent) = std::fs::canonicalize(parent) else {
        return Ok(());
    };
    let Some(name) = path.file_name() else {
        return Ok(());
    };
    let full = parent.join(name);
    let target = std::fs::canonicalize(&full).unwrap_or(full.clone());
    for (_, inputs) in open.iter() {
        // An input folder's content belongs to it, at any depth.
        if inputs
            .iter()
            .any(|i| target == *i || (i.is_dir() && target.starts_with(i)))
        {
            return Err(std::io::Error::other(format!(
                "refusing to write over the input {}",
                target.display()
            )));
        }
    }
    // The innermost open folder that contains the file owns it.
    if let Some((dir, _)) = open
        .iter()
        .filter(|(dir, _)| full.starts_with(dir))
        .max_by_key(|(dir, _)| dir.components().count())
    {
        let rel = full.strip_prefix(dir).expect("checked prefix");
        if rel != Path::new(MANIFEST_NAME) {
            let mut f = std::fs::OpenOptions::new()
                .append(true)
                .open(dir.join(MANIFEST_NAME))?;
            writeln!(f, "{}", rel.display())?;
        }
    }
    Ok(())
}

/// The manifest's header and listed files; `None` when there is no manifest. A manifest that does not
/// parse is treated as foreign files (never deleted).
fn read_manifest(path: &Path) -> Result<Option<(Header, BTreeSet<PathBuf>)>, RunDirError> {
    let text = match std::fs::read_to_string(path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(io_err(path)(e)),
    };
    let mut lines = text.lines();
    let Some(header) = lines
        .next()
        .and_then(|l| serde_json::from_str::<Header>(l).ok())
    else {
        return Ok(None);
    };
    let files = lines
        .filter(|l| !l.is_empty())
        .map(PathBuf::from)
        // Only plain relative paths inside the folder: a tampered manifest must not delete elsewhere.
        .filter(|p| {
            p.components()
                .all(|c| matches!(c, std::path::Component::Normal(_)))
        })
        .collect();
    Ok(Some((header, files)))
}

/// Whether `rel` (plain components only, see `read_manifest`) reaches its file without passing through a
/// symbolic link: a subfolder replaced by a link to elsewhere must not lead `--force` out of the run
/// folder. The file itself may be a link (removing a link removes only the link).
fn stays_inside(dir: &Path, rel: &Path) -> bool {
    let mut p = dir.to_path_buf();
    let folders = rel.parent().into_iter().flat_map(Path::components);
    for c in folders {
        p.push(c);
        match std::fs::symlink_metadata(&p) {
            Ok(m) if m.is_dir() => {}
            _ => return false,
        }
    }
    true
}

/// Removes the listed files (missing ones are fine), then the folders that became empty.
fn remove_listed(dir: &Path, files: &BTreeSet<PathBuf>) -> Result<(), RunDirError> {
    let mut parents = BTreeSet::new();
    for rel in files {
        if !stays_inside(dir, rel) {
            continue;
        }
        let p = dir.join(rel);
        match std::fs::remove_file(&p) {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(e) => return Err(io_err(&p)(e)),
        }
        let mut parent = rel.parent();
        while let Some(q) = parent.filter(|q| !q.as_os_str().is_empty()) {
            parents.insert(q.to_path_buf());
            parent = q.parent();
        }
    }
    // Deepest first; a folder that still holds something (the user's files) stays.
    let mut parents: Vec<PathBuf> = parents.into_iter().collect();
    parents.sort_by_key(|p| std::cmp::Reverse(p.components().count()));
    for q in parents {
        let _ = crate::clean_stale_temps(&dir.join(&q));
        let _ = std::fs::remove_dir(dir.join(q));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(dir: &Path) -> Vec<String> {
        let mut v: Vec<String> = testkit::paths::files_under(dir)
            .into_iter()
            .map(|p| p.strip_prefix(dir).unwrap().display().to_string())
            .collect();
        v.sort();
        v
    }

    #[test]
    fn writes_are_recorded_and_force_clears_only_them() {
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("renders");
        {
            let run = RunDir::open(&out, "render", "orbit=4", RunDirMode::Keep, &[]).unwrap();
            assert_eq!(run.previous(), Previous::Nothing);
            for i in 0..4 {
                crate::atomic_write(&out.join(format!("view_{i}.png")), b"png").unwrap();
            }
            crate::atomic_write(&out.join("depth").join("view_0.png"), b"d").unwrap();
            assert_eq!(run.recorded().unwrap().len(), 5);
        }
        // A write after the folder is closed is not recorded.
        crate::atomic_write(&tmp.path().join("elsewhere.txt"), b"x").unwrap();

        // The same settings again: the same run, files kept.
        let run = RunDir::open(&out, "render", "orbit=4", RunDirMode::Keep, &[]).unwrap();
        assert_eq!(run.previous(), Previous::SameRun);
        drop(run);

        // Other settings: refused without --force.
        let err = RunDir::open(&out, "render", "orbit=2", RunDirMode::Keep, &[])
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("another run") && err.contains("--force"),
            "{err}"
        );
        assert_eq!(names(&out).len(), 6);

        // A file the user put there survives --force.
        std::fs::write(out.join("notes.txt"), b"mine").unwrap();
        let run = RunDir::open(&out, "render", "orbit=2", RunDirMode::Force, &[]).unwrap();
        assert_eq!(run.previous(), Previous::Cleared);
        crate::atomic_write(&out.join("view_0.png"), b"png").unwrap();
        crate::atomic_write(&out.join("view_1.png"), b"png").unwrap();
        assert_eq!(
            names(&out),
            vec![MANIFEST_NAME, "notes.txt", "view_0.png", "view_1.png"]
        );
    }

    #[test]
    fn foreign_folders_and_files_are_refused() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("photos");
        std::fs::create_dir(&dir).unwrap();
        std::fs::write(dir.join("holiday.jpg"), b"jpg").unwrap();
        // Named as a killed vcedit run's temporary file: a refused folder is not cleaned either.
        let temp_like = dir.join(".thesis.tex.vcedit-tmp-4194305-Ab3dE5fG7hJ9");
        std::fs::write(&temp_like, b"mine").unwrap();
        for mode in [RunDirMode::Keep, RunDirMode::Force] {
            let err = RunDir::open(&dir, "render", "x", mode, &[])
                .unwrap_err()
                .to_string();
            assert!(err.contains("not written by vcedit"), "{err}");
        }
        assert!(dir.join("holiday.jpg").exists() && temp_like.exists());
        let file = tmp.path().join("file.ply");
        std::fs::write(&file, b"ply").unwrap();
        let err = RunDir::open(&file, "render", "x", RunDirMode::Keep, &[])
            .unwrap_err()
            .to_string();
        assert!(err.contains("not a folder"), "{err}");
    }

    #[test]
    fn inputs_are_never_removed_or_replaced() {
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("edit");
        {
            let _run = RunDir::open(&out, "edit", "a", RunDirMode::Keep, &[]).unwrap();
            crate::atomic_write(&out.join("edited.ply"), b"scene").unwrap();
        }
        // The previous result is this run's input: --force must not delete it, and no write may replace it.
        let input = out.join("edited.ply");
        let err = RunDir::open(&out, "edit", "b", RunDirMode::Force, &[&input])
            .unwrap_err()
            .to_string();
        assert!(err.contains("also an input"), "{err}");
        assert_eq!(std::fs::read(&input).unwrap(), b"scene");

        let other = tmp.path().join("other");
        let _run = RunDir::open(&other, "edit", "b", RunDirMode::Keep, &[&input]).unwrap();
        let err = crate::atomic_write(&input, b"oops")
            .unwrap_err()
            .to_string();
        assert!(err.contains("refusing to write over the input"), "{err}");
        assert_eq!(std::fs::read(&input).unwrap(), b"scene");
    }

    #[cfg(unix)]
    #[test]
    fn a_folder_in_use_by_another_run_is_refused_until_it_ends() {
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("out");
        let first = RunDir::open(&out, "edit", "a", RunDirMode::Keep, &[]).unwrap();
        crate::atomic_write(&out.join("view_0.png"), b"x").unwrap();
        for mode in [RunDirMode::Keep, RunDirMode::Force] {
            let err = RunDir::open(&out, "edit", "a", mode, &[]).unwrap_err();
            assert!(matches!(err, RunDirError::Busy { .. }), "{err}");
            assert!(err.to_string().contains("another vcedit run"), "{err}");
        }
        // The refused opens changed nothing; once the first run ends the folder opens again.
        assert_eq!(names(&out), vec![MANIFEST_NAME, "view_0.png"]);
        drop(first);
        let again = RunDir::open(&out, "edit", "a", RunDirMode::Keep, &[]).unwrap();
        assert_eq!(again.previous(), Previous::SameRun);
        assert_eq!(again.recorded().unwrap(), vec![PathBuf::from("view_0.png")]);
    }

    #[test]
    fn a_tampered_manifest_cannot_delete_outside_the_folder() {
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("out");
        std::fs::create_dir(&out).unwrap();
        let victim = tmp.path().join("victim.txt");
        std::fs::write(&victim, b"keep").unwrap();
        let header = r#"{"command":"render","settings":"a"}"#;
        std::fs::write(
            out.join(MANIFEST_NAME),
            format!("{header}\n../victim.txt\n{}\n", victim.display()),
        )
        .unwrap();
        let _run = RunDir::open(&out, "render", "b", RunDirMode::Force, &[]).unwrap();
        assert!(victim.exists());
    }

    #[cfg(unix)]
    #[test]
    fn force_never_follows_a_linked_subfolder() {
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("out");
        {
            let _run = RunDir::open(&out, "render", "a", RunDirMode::Keep, &[]).unwrap();
            crate::atomic_write(&out.join("depth").join("view_0.png"), b"d").unwrap();
            crate::atomic_write(&out.join("view_0.png"), b"png").unwrap();
        }
        // The recorded subfolder swapped for a link to a folder outside, holding a file of that name.
        let outside = tmp.path().join("outside");
        std::fs::create_dir(&outside).unwrap();
        std::fs::write(outside.join("view_0.png"), b"keep").unwrap();
        std::fs::remove_dir_all(out.join("depth")).unwrap();
        std::os::unix::fs::symlink(&outside, out.join("depth")).unwrap();
        let _run = RunDir::open(&out, "render", "b", RunDirMode::Force, &[]).unwrap();
        assert_eq!(std::fs::read(outside.join("view_0.png")).unwrap(), b"keep");
        assert!(
            !out.join("view_0.png").exists(),
            "the run's own file is removed"
        );
    }
}
