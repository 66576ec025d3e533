//! No output over an input, nor inside an input folder: paths are compared as the files and folders
//! they name, not as strings.

use std::path::{Path, PathBuf};

#[derive(Debug, thiserror::Error)]
pub enum PathError {
    #[error("{}: this output is also an input ({}); write it somewhere else", output.display(), input.display())]
    OverwritesInput { output: PathBuf, input: PathBuf },
    #[error("{}: this output lies inside the input folder {}; write it somewhere else", output.display(), input.display())]
    InsideInput { output: PathBuf, input: PathBuf },
}

/// The identity of an existing file: its canonical path and, on Unix, its device and inode (which also
/// catches hard links).
#[derive(Clone, Debug, PartialEq, Eq)]
struct FileId {
    canonical: PathBuf,
    #[cfg(unix)]
    dev_ino: (u64, u64),
}

impl FileId {
    fn of(path: &Path) -> Option<Self> {
        let canonical = std::fs::canonicalize(path).ok()?;
        #[cfg(unix)]
        {
            use std::os::unix::fs::MetadataExt;
            let meta = std::fs::metadata(&canonical).ok()?;
            Some(Self {
                canonical,
                dev_ino: (meta.dev(), meta.ino()),
            })
        }
        #[cfg(not(unix))]
        Some(Self { canonical })
    }

    fn same(&self, other: &Self) -> bool {
        #[cfg(unix)]
        if self.dev_ino == other.dev_ino {
            return true;
        }
        self.canonical == other.canonical
    }
}

/// True when `a` and `b` name the same existing file (through `.`/`..`, symbolic links or hard links).
/// False when either does not exist.
pub fn same_file(a: &Path, b: &Path) -> bool {
    match (FileId::of(a), FileId::of(b)) {
        (Some(a), Some(b)) => a.same(&b),
        _ => false,
    }
}

/// Refuses when writing any of `outputs` would replace one of `inputs` or put a file inside an input
/// that is a folder (a dataset, a trainer's output, a SOG folder: everything in it belongs to the input,
/// at any depth, whether it exists yet or not). Outputs that do not exist yet cannot be inputs; an output
/// that is a symbolic link to an input (or into an input folder) is refused too (replacing the link would
/// be harmless, but a user who pointed it there meant the input).
pub fn check_not_inputs(outputs: &[&Path], inputs: &[&Path]) -> Result<(), PathError> {
    let files: Vec<(&Path, FileId)> = inputs
        .iter()
        .filter_map(|p| FileId::of(p).map(|id| (*p, id)))
        .collect();
    let folders: Vec<(&Path, PathBuf)> = inputs
        .iter()
        .filter(|p| p.is_dir())
        .filter_map(|p| std::fs::canonicalize(p).ok().map(|c| (*p, c)))
        .collect();
    for out in outputs {
        if let Some(out_id) = FileId::of(out) {
            if let Some((input, _)) = files.iter().find(|(_, id)| id.same(&out_id)) {
                return Err(PathError::OverwritesInput {
                    output: out.to_path_buf(),
                    input: input.to_path_buf(),
                });
            }
        }
        let places = [location(out), std::fs::canonicalize(out).ok()];
        for place in places.iter().flatten() {
            if let Some((input, _)) = folders.iter().find(|(_, f)| place.starts_with(f)) {
                return Err(PathError::InsideInput {
                    output: out.to_path_buf(),
                    input: input.to_path_buf(),
                });
            }
        }
    }
    Ok(())
}

/// Where `path` is (or would be created): its folder resolved through links (the nearest existing
/// ancestor, then the missing components as written), joined with its name. `None` when no ancestor
/// resolves.
pub(crate) fn location(path: &Path) -> Option<PathBuf> {
    let absolute = if path.is_absolute() {
        path.to_path_buf()
    } else {
        std::env::current_dir().ok()?.join(path)
    };
    let name = absolute.file_name()?.to_owned();
    let mut base = absolute.parent()?.to_path_buf();
    let mut missing = Vec::new();
    let resolved = loop {
        if let Ok(c) = std::fs::canonicalize(&base) {
            break c;
        }
        missing.push(base.components().next_back()?.as_os_str().to_owned());
        if !base.pop() {
            return None;
        }
    };
    let mut out = resolved;
    for part in missing.into_iter().rev() {
        if part == ".." {
            out.pop();
        } else if part != "." {
            out.push(part);
        }
    }
    Some(out.join(name))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spellings_links_and_hard_links_are_the_same_file() {
        let dir = tempfile::tempdir().unwrap();
        let a = dir.path().join("a.png");
        std::fs::write(&a, b"x").unwrap();
        let dotted = dir.path().join(".").join("sub").join("..").join("a.png");
        std::fs::create_dir(dir.path().join("sub")).unwrap();
        assert!(same_file(&a, &dotted));
        #[cfg(unix)]
        {
            let link = dir.path().join("link.png");
            std::os::unix::fs::symlink(&a, &link).unwrap();
            assert!(same_file(&a, &link));
            let hard = dir.path().join("hard.png");
            std::fs::hard_link(&a, &hard).unwrap();
            assert!(same_file(&a, &hard));
            let err = check_not_inputs(&[&hard], &[&a]).unwrap_err().to_string();
            assert!(err.contains("hard.png") && err.contains("a.png"), "{err}");
        }
        let other = dir.path().join("b.png");
        std::fs::write(&other, b"x").unwrap();
        assert!(!same_file(&a, &other));
        assert!(!same_file(&a, &dir.path().join("missing.png")));
    }

    #[test]
    fn relative_and_absolute_spellings_are_caught() {
        let dir = tempfile::tempdir().unwrap();
        let a = dir.path().join("scene.ply");
        std::fs::write(&a, b"x").unwrap();
        let relative = pathdiff(&a);
        assert!(check_not_inputs(&[&relative], &[&a]).is_err());
        assert!(check_not_inputs(&[&dir.path().join("new.ply")], &[&a]).is_ok());
    }

    /// `a` spelled relative to the current directory through `..` components.
    fn pathdiff(a: &Path) -> PathBuf {
        let cwd = std::env::current_dir().unwrap();
        let mut p = PathBuf::new();
        for _ in cwd.components().skip(1) {
            p.push("..");
        }
        p.join(a.strip_prefix("/").unwrap())
    }

    #[test]
    fn nothing_goes_inside_an_input_folder() {
        let dir = tempfile::tempdir().unwrap();
        let garden = dir.path().join("garden");
        let ply = garden.join("point_cloud/iteration_7000/point_cloud.ply");
        std::fs::create_dir_all(ply.parent().unwrap()).unwrap();
        std::fs::write(&ply, b"ply").unwrap();
        let inputs: [&Path; 1] = [&garden];
        for out in [
            ply.clone(),
            garden.join("new.json"),
            garden.join("new/deeper/x.json"),
            garden.join("point_cloud/../cameras.json"),
            garden.join("new/../y.json"),
        ] {
            let err = check_not_inputs(&[&out], &inputs).unwrap_err().to_string();
            assert!(err.contains("inside the input folder"), "{err}");
        }
        // Beside it is fine; so is a name that only starts like it.
        assert!(check_not_inputs(&[&dir.path().join("garden.json")], &inputs).is_ok());
        assert!(check_not_inputs(&[&dir.path().join("garden2/x.json")], &inputs).is_ok());
        #[cfg(unix)]
        {
            // A linked folder leading into the input, and a link to a file in it.
            std::os::unix::fs::symlink(&garden, dir.path().join("g")).unwrap();
            let through = dir.path().join("g/stats.json");
            assert!(check_not_inputs(&[&through], &inputs).is_err());
            let link = dir.path().join("l.json");
            std::os::unix::fs::symlink(&ply, &link).unwrap();
            assert!(check_not_inputs(&[&link], &inputs).is_err());
        }
    }
}
