//! Where commands write, under one policy (the mechanism is the `files` crate), checked before any work:
//!
//! - an output is never one of the command's inputs, nor inside an input folder (a dataset, a trainer's
//!   output, a SOG folder, a model), however the paths are spelt ([`output_file`], [`OutputDir`]);
//! - an output file that exists is refused unless `--force` ([`ForceArg`]): files and folders alike,
//!   finished work is never replaced without a word;
//! - the output's folder must accept a new file before the work starts (not after a long run);
//! - an output folder holds the files of one run ([`OutputDir`]): a folder holding another run is refused
//!   unless `--force` clears what vcedit wrote there, and a run that fails before writing anything leaves
//!   no folder behind;
//! - temporary files of killed vcedit runs are removed from a folder once it is accepted, never from a
//!   refused one.

use std::fmt::Debug;
use std::path::Path;

use anyhow::{bail, Result};
use files::{RunDir, RunDirMode};

/// `--force` for every command that writes outputs.
#[derive(clap::Args, Debug, Clone)]
pub struct ForceArg {
    /// Replace earlier outputs: an output file that exists, or the files another vcedit run wrote in an
    /// output folder (nothing else there). Without it they are refused, and a finished edit or demo with
    /// the same settings is not done again. Inputs are never replaced.
    #[arg(long)]
    pub force: bool,
}

/// Checks the output file `out` before any work: not one of `inputs` nor inside one of them that is a
/// folder (also through `./`, `..`, symbolic and hard links); not a folder; not an existing file unless
/// `force`; its folder writable (a missing folder can be made). Then removes temporary files that killed
/// vcedit runs left in its folder.
pub fn output_file(out: &Path, inputs: &[&Path], force: bool) -> Result<()> {
    files::check_not_inputs(&[out], inputs)?;
    if out.is_dir() {
        bail!("{}: is a folder; the output must be a file", out.display());
    }
    let dir = parent_of(out);
    if dir.exists() && !dir.is_dir() {
        bail!("{}: {} is not a folder", out.display(), dir.display());
    }
    if !force && std::fs::symlink_metadata(out).is_ok() {
        bail!(
            "{}: exists; add --force to replace it, or choose another name",
            out.display()
        );
    }
    files::check_writable_folder(dir).map_err(|e| {
        anyhow::anyhow!(
            "{}: cannot write into {}: {e}",
            out.display(),
            dir.display()
        )
    })?;
    files::clean_stale_temps(dir).map_err(|e| anyhow::anyhow!("{}: {e}", dir.display()))?;
    Ok(())
}

/// [`output_file`] for a scene written by `splat::write_scene`: a SOG folder output (`DIR/meta.json`)
/// is the whole folder, accepted only when new, empty, or a SOG scene (by content), and replaced only
/// with `force` when it holds one.
pub fn scene_output(out: &Path, inputs: &[&Path], force: bool) -> Result<()> {
    if splat::OutputFormat::for_path(out) == Some(splat::OutputFormat::SogFolder) {
        let dir = parent_of(out);
        files::check_not_inputs(&[dir], inputs)?;
        splat::formats::check_scene_output(out)?;
        let holds_scene = std::fs::read_dir(dir).is_ok_and(|mut e| e.next().is_some());
        if holds_scene && !force {
            bail!(
                "{}: holds a SOG scene; add --force to replace it, or choose another folder",
                dir.display()
            );
        }
        // The new folder is written beside the old one and swapped in.
        let beside = std::fs::canonicalize(dir)
            .ok()
            .and_then(|d| d.parent().map(Path::to_path_buf));
        if let Some(parent) = beside {
            files::check_writable_folder(&parent)
                .map_err(|e| anyhow::anyhow!("{}: cannot write beside it: {e}", dir.display()))?;
        }
    }
    output_file(out, inputs, force)
}

/// Refuses `out` (the value of `option`) unless its name ends in one of `extensions` (any case).
pub fn require_extension(out: &Path, option: &str, extensions: &[&str], what: &str) -> Result<()> {
    let name = out
        .file_name()
        .map(|n| n.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    let ok = extensions
        .iter()
        .any(|ext| name.len() > ext.len() + 1 && name.ends_with(&format!(".{ext}")));
    if !ok {
        let list = extensions
            .iter()
            .map(|e| format!(".{e}"))
            .collect::<Vec<_>>()
            .join(", ");
        bail!("{option} {}: {what} must end in {list}", out.display());
    }
    Ok(())
}

/// Makes sure files can be written into the folder `dir` (creating it if needed), so that a command with
/// several outputs does not fail on the second after writing the first.
pub fn probe_folder(dir: &Path) -> Result<()> {
    if dir.exists() && !dir.is_dir() {
        bail!("{}: exists and is not a folder", dir.display());
    }
    std::fs::create_dir_all(dir)
        .map_err(|e| anyhow::anyhow!("{}: cannot create the folder: {e}", dir.display()))?;
    files::check_writable_folder(dir)
        .map_err(|e| anyhow::anyhow!("{}: cannot write into the folder: {e}", dir.display()))?;
    files::clean_stale_temps(dir)?;
    Ok(())
}

/// [`files::clean_stale_temps`] in every folder under `dir`, down to `depth` levels.
fn clean_stale_temps_below(dir: &Path, depth: usize) -> Result<()> {
    if depth == 0 {
        return Ok(());
    }
    let Ok(entries) = std::fs::read_dir(dir) else {
        return Ok(());
    };
    for entry in entries.flatten() {
        let path = entry.path();
        if entry.file_type().is_ok_and(|t| t.is_dir()) {
            files::clean_stale_temps(&path)
                .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
            clean_stale_temps_below(&path, depth - 1)?;
        }
    }
    Ok(())
}

fn parent_of(path: &Path) -> &Path {
    match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    }
}

/// A short, stable fingerprint of a command's settings: a hash of their `Debug` text. Callers pass the
/// settings that decide the outputs (not `--out`, `--force` or `--resume`).
pub fn fingerprint(settings: &impl Debug) -> String {
    let text = format!("{settings:?}");
    // FNV-1a: stable across builds and platforms, unlike std's hasher.
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for b in text.bytes() {
        h ^= b as u64;
        h = h.wrapping_mul(0x100_0000_01b3);
    }
    format!("{h:016x}")
}

/// Whether `dir` holds a finished run of `command` with the settings `fingerprint`: its manifest is this
/// run's and every one of `finals` (the files such a run writes last) is there. Such a run need not be
/// done again. A folder holding another run or foreign files gives the error opening it would.
/// `settings`: this run's, where the command keeps them ([`open_with_settings`]), so that a refusal
/// names the ones that differ.
pub fn finished_run(
    dir: &Path,
    command: &str,
    fingerprint: &str,
    settings: Option<&serde_json::Value>,
    finals: &[&str],
    inputs: &[&Path],
) -> Result<bool> {
    if !finals.iter().all(|f| dir.join(f).is_file()) {
        return Ok(false);
    }
    let run = RunDir::open(dir, command, fingerprint, RunDirMode::Keep, inputs)
        .map_err(|e| naming_differences(e.into(), dir, settings))?;
    Ok(run.previous() == files::Previous::SameRun)
}

/// `e` (a refused folder) with the settings in which the folder's run differs from `settings`, where
/// both are known.
fn naming_differences(
    e: anyhow::Error,
    dir: &Path,
    settings: Option<&serde_json::Value>,
) -> anyhow::Error {
    let previous = std::fs::read(dir.join(SETTINGS_FILE))
        .ok()
        .and_then(|b| serde_json::from_slice::<serde_json::Value>(&b).ok());
    match previous
        .zip(settings)
        .map(|(p, s)| settings_differences(&p, s))
    {
        Some(diff) if !diff.is_empty() => {
            anyhow::anyhow!("{e:#} (the settings that differ: {})", diff.join(", "))
        }
        _ => e,
    }
}

/// The lines a command prints instead of redoing a finished run (see [`finished_run`]).
pub fn say_finished(dir: &Path) {
    eprintln!(
        "{}: holds this run already, finished (the same settings and input paths); nothing to do. \
         --force redoes it.",
        dir.display()
    );
}

/// The file in a run folder that keeps the settings of the run that made it (see [`settings_differences`]).
pub const SETTINGS_FILE: &str = "settings.json";

/// The settings in which `previous` (the `settings.json` a run left in its folder) differs from
/// `current`, as `key: old → new` (nested keys joined by dots), for the refusal of a folder holding
/// another run: a user told only "other settings" cannot tell which one changed.
pub fn settings_differences(
    previous: &serde_json::Value,
    current: &serde_json::Value,
) -> Vec<String> {
    fn walk(key: &str, a: &serde_json::Value, b: &serde_json::Value, out: &mut Vec<String>) {
        use serde_json::Value::Object;
        match (a, b) {
            (Object(x), Object(y)) => {
                let keys: std::collections::BTreeSet<&String> = x.keys().chain(y.keys()).collect();
                for k in keys {
                    let null = serde_json::Value::Null;
                    let sub = if key.is_empty() {
                        k.clone()
                    } else {
                        format!("{key}.{k}")
                    };
                    walk(
                        &sub,
                        x.get(k).unwrap_or(&null),
                        y.get(k).unwrap_or(&null),
                        out,
                    );
                }
            }
            _ if a != b => out.push(format!("{key}: {a} → {b}")),
            _ => {}
        }
    }
    let mut out = Vec::new();
    walk("", previous, current, &mut out);
    out
}

/// [`OutputDir::open`] for a command that keeps its settings (`settings`, whose fingerprint is
/// `fingerprint`) in [`SETTINGS_FILE`]: a folder holding the same command's run with other settings is
/// refused naming the settings that differ, and the opened folder gets this run's settings.
pub fn open_with_settings(
    dir: &Path,
    command: &str,
    fingerprint: &str,
    settings: &serde_json::Value,
    force: bool,
    inputs: &[&Path],
) -> Result<OutputDir> {
    let file = dir.join(SETTINGS_FILE);
    let out = OutputDir::open(dir, command, fingerprint, force, inputs)
        .map_err(|e| naming_differences(e, dir, Some(settings)))?;
    let text = serde_json::to_vec_pretty(settings).expect("JSON values serialise");
    files::atomic_write(&file, &text).map_err(|e| anyhow::anyhow!("{}: {e}", file.display()))?;
    Ok(out)
}

/// An output folder open for one run; see the module documentation. Call [`OutputDir::finish`] when the
/// run succeeded; dropped without it after a failure, it removes what it created if nothing was written.
pub struct OutputDir {
    run: Option<RunDir>,
    created: bool,
    finished: bool,
}

impl OutputDir {
    /// Opens `dir` for `command` with settings `fingerprint`; `inputs` are never removed or replaced.
    pub fn open(
        dir: &Path,
        command: &str,
        fingerprint: &str,
        force: bool,
        inputs: &[&Path],
    ) -> Result<Self> {
        // The folder itself must not lie inside an input folder (a dataset, a trainer's output).
        files::check_not_inputs(&[dir], inputs)?;
        let created = !dir.exists();
        let mode = if force {
            RunDirMode::Force
        } else {
            RunDirMode::Keep
        };
        let run = RunDir::open(dir, command, fingerprint, mode, inputs)?;
        // RunDir cleans the folder itself; a run killed while writing into a subfolder (a checkpoint,
        // an iteration's guidance) left its temporary file there.
        clean_stale_temps_below(dir, 3)?;
        Ok(Self {
            run: Some(run),
            created,
            finished: false,
        })
    }

    /// The run succeeded: keep the folder.
    pub fn finish(mut self) {
        self.finished = true;
    }
}

impl Drop for OutputDir {
    fn drop(&mut self) {
        let Some(run) = self.run.take() else {
            return;
        };
        let dir = run.path().to_path_buf();
        // The run's settings alone (`open_with_settings`) are not an output.
        let untouched = !self.finished
            && run.previous() == files::Previous::Nothing
            && run
                .recorded()
                .is_ok_and(|r| r.iter().all(|f| f == Path::new(SETTINGS_FILE)));
        drop(run);
        if untouched {
            // Nothing was written: leave the place as it was found.
            let _ = std::fs::remove_file(dir.join(SETTINGS_FILE));
            let _ = std::fs::remove_file(dir.join(files::MANIFEST_NAME));
            if self.created {
                let _ = std::fs::remove_dir(&dir);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn extensions_are_checked_case_insensitively() {
        let ok = |p: &str| {
            require_extension(
                Path::new(p),
                "--out",
                &["compressed.ply", "ply"],
                "the scene",
            )
            .is_ok()
        };
        assert!(ok("a.ply") && ok("dir/A.PLY") && ok("x.compressed.ply"));
        assert!(!ok("transforms.json") && !ok(".ply") && !ok("ply") && !ok("a.ply.bak"));
        let err = require_extension(Path::new("t.json"), "--out", &["ply"], "the scene")
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("--out t.json") && err.contains(".ply"),
            "{err}"
        );
    }

    #[test]
    fn a_failed_run_leaves_no_folder() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("out");
        {
            let _out = OutputDir::open(&dir, "render", "a", false, &[]).unwrap();
            assert!(dir.is_dir());
        }
        assert!(!dir.exists());
        let out = OutputDir::open(&dir, "render", "a", false, &[]).unwrap();
        files::atomic_write(&dir.join("view.png"), b"x").unwrap();
        drop(out);
        assert!(dir.join("view.png").exists());
    }

    #[test]
    fn only_a_finished_run_of_the_same_settings_counts_as_finished() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("out");
        let finals = ["run.json"];
        assert!(!finished_run(&dir, "edit", "a", None, &finals, &[]).unwrap());
        let out = OutputDir::open(&dir, "edit", "a", false, &[]).unwrap();
        files::atomic_write(&dir.join("iter_0.png"), b"x").unwrap();
        // Interrupted: its last file is missing.
        assert!(!finished_run(&dir, "edit", "a", None, &finals, &[]).unwrap());
        files::atomic_write(&dir.join("run.json"), b"{}").unwrap();
        out.finish();
        assert!(finished_run(&dir, "edit", "a", None, &finals, &[]).unwrap());
        // Other settings: the refusal opening the folder gives.
        let err = finished_run(&dir, "edit", "b", None, &finals, &[]).unwrap_err();
        assert!(err.to_string().contains("--force"), "{err}");
    }

    #[test]
    fn the_settings_that_differ_are_named() {
        let a =
            serde_json::json!({"steps": 4, "infedit": {"cross": 0.7, "seed": 0}, "scene": "a.ply"});
        let b =
            serde_json::json!({"steps": 6, "infedit": {"cross": 0.7, "seed": 1}, "scene": "a.ply"});
        assert_eq!(
            settings_differences(&a, &b),
            ["infedit.seed: 0 → 1", "steps: 4 → 6"]
        );
        assert!(settings_differences(&a, &a).is_empty());
    }

    #[test]
    fn fingerprints_follow_the_settings() {
        assert_eq!(fingerprint(&(1, "a")), fingerprint(&(1, "a")));
        assert_ne!(fingerprint(&(1, "a")), fingerprint(&(2, "a")));
    }
}
