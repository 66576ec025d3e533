//! Where test data lives: the repository's committed fixtures (tiny random models made by `tools/`, with
//! the reference outputs of diffusers/transformers) and the machine's shared third-party assets beside the
//! checkout (`../shared/assets`: a trained scene, TAESD weights, never committed).

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use candle_core::{Device, Tensor};

/// The repository's root folder.
pub fn repo() -> PathBuf {
    // This crate sits at crates/testkit: the root is two levels up, whichever crate's test calls this.
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// The committed fixtures folder, `fixtures/` at the repository's root.
pub fn fixtures() -> PathBuf {
    repo().join("fixtures")
}

/// One fixture by its path under `fixtures/`.
pub fn fixture(relative: &str) -> PathBuf {
    fixtures().join(relative)
}

/// The tiny random LCM pipeline made by `tools/` (an SD-1.5-shaped model folder in diffusers' layout).
pub fn tiny_lcm() -> PathBuf {
    fixture("models/tiny-lcm")
}

/// The shared third-party assets beside the checkout (`../shared/assets`), which may be absent: tests
/// that need them skip with a line when it is.
pub fn shared_assets() -> PathBuf {
    repo().join("../shared/assets")
}

/// One of the shared assets (`relative` under [`shared_assets`]), or `None` after one printed line
/// naming the path when this machine does not have it: tests of real third-party data skip, not fail, in
/// a user's clone.
pub fn shared_asset(relative: &str) -> Option<PathBuf> {
    let path = shared_assets().join(relative);
    if path.exists() {
        Some(path)
    } else {
        println!("skipping: {} not present", path.display());
        None
    }
}

/// Every tensor of a safetensors file on the CPU; a missing or unreadable file panics naming it.
pub fn load_tensors(path: &Path) -> HashMap<String, Tensor> {
    candle_core::safetensors::load(path, &Device::Cpu)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// Every file under `dir`, at any depth (folders themselves not listed), sorted.
pub fn files_under(dir: &Path) -> Vec<PathBuf> {
    fn walk(dir: &Path, out: &mut Vec<PathBuf>) {
        let entries = std::fs::read_dir(dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display()));
        for entry in entries {
            let path = entry.unwrap().path();
            if path.is_dir() {
                walk(&path, out);
            } else {
                out.push(path);
            }
        }
    }
    let mut out = Vec::new();
    walk(dir, &mut out);
    out.sort();
    out
}

#[cfg(test)]
mod tests {
    #[test]
    fn the_fixtures_are_found_from_here() {
        assert!(
            super::fixtures().is_dir(),
            "{}",
            super::fixtures().display()
        );
        assert!(super::repo().join("Cargo.toml").is_file());
    }
}
