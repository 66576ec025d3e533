//! Where vcedit keeps what it can always make again (the extracted demo model, compiled GPU kernels and
//! tuning results): one user cache folder, never the working directory.

use std::path::PathBuf;

/// `$XDG_CACHE_HOME/vcedit`, else `~/.cache/vcedit`, else `vcedit` in the temporary folder.
pub fn cache_dir() -> PathBuf {
    let nonempty = |name: &str| std::env::var_os(name).filter(|v| !v.is_empty());
    if let Some(dir) = nonempty("XDG_CACHE_HOME") {
        return PathBuf::from(dir).join("vcedit");
    }
    if let Some(home) = nonempty("HOME") {
        return PathBuf::from(home).join(".cache").join("vcedit");
    }
    std::env::temp_dir().join("vcedit")
}
