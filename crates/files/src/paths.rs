//! No output over an input: paths are compared as the files they name, not as strings.

use std::path::{Path, PathBuf};

#[derive(Debug, thiserror::Error)]
pub enum PathError {
    #[error("{}: this output is also an input ({}); write it somewhere else", output.display(), input.display())]
    OverwritesInput { output: PathBuf, input: PathBuf },
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

/// Refuses when writing any of `outputs` would replace one of `inputs`. Outputs that do not exist yet
/// cannot be inputs; an output that is a symbolic link to an input is refused too (replacing the link
/// would be harmless, but a user who pointed it there meant the input).
pub fn check_not_inputs(outputs: &[&Path], inputs: &[&Path]) -> Result<(), PathError> {
    let inputs: Vec<(&Path, FileId)> = inputs
        .iter()
        .filter_map(|p| FileId::of(p).map(|id| (*p, id)))
        .collect();
    for out in outputs {
        let Some(out_id) = FileId::of(out) else {
            continue;
        };
        if let Some((input, _)) = inputs.iter().find(|(_, id)| id.same(&out_id)) {
            return Err(PathError::OverwritesInput {
                output: out.to_path_buf(),
                input: input.to_path_buf(),
            });
        }
    }
    Ok(())
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
}
