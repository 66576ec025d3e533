//! The checkpoint written after every iteration, so `--resume` continues an interrupted run and gives the
//! same result as an uninterrupted one.
//!
//! `out/checkpoint/` holds `checkpoint.json` (this state), the scene after iteration k (`scene_k.ply`) and the
//! trainer's own state (`trainer_k.safetensors`). The files of iteration k are written under their own names
//! first and `checkpoint.json` last, atomically: it is the commit point.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use splat::{Camera, GaussianScene};

use crate::eval::metrics::ConsistencySummary;
use crate::fit::{EditTrainer, TrainSettings};

use super::job::{io_err, EditJob, IterationTimes, RunError};
use super::shape::ShapeDecision;

/// Bumped when the format changes.
const VERSION: u32 = 1;

/// The state saved after every iteration.
#[derive(Serialize, Deserialize)]
pub(super) struct Checkpoint {
    /// Bumped when the format changes.
    pub version: u32,
    /// Iterations completed.
    pub iterations_done: usize,
    /// Indices of the edited views among the input cameras.
    pub views: Vec<usize>,
    /// Fingerprint of the settings that determine the result; resuming with others is refused.
    pub fingerprint: String,
    /// Editable Gaussians at the start (None = all).
    pub mask: Option<Vec<bool>>,
    pub times: Vec<IterationTimes>,
    pub guidance_consistency: Vec<Option<ConsistencySummary>>,
    /// What each finished iteration's fit did with the geometry rates.
    #[serde(default)]
    pub shape: Vec<ShapeDecision>,
    /// Per-word attention images of iteration 0: (word, file under `attention/`).
    pub attention: Vec<(String, String)>,
    /// (file name, checksum) of the iteration's scene and trainer state, checked before resuming: a
    /// damaged file is named instead of failing later on what it decoded to. Empty in checkpoints of
    /// earlier versions (nothing to check).
    #[serde(default)]
    pub checksums: Vec<(String, String)>,
}

/// Everything a trainer is rebuilt with besides its saved state.
pub(super) struct TrainerSetup<'a> {
    pub train: &'a TrainSettings,
    pub extent: f32,
    pub background: [f32; 3],
}

fn checkpoint_dir(out: &Path) -> PathBuf {
    out.join("checkpoint")
}

fn meta_path(out: &Path) -> PathBuf {
    checkpoint_dir(out).join("checkpoint.json")
}

impl Checkpoint {
    /// The state before the first iteration.
    pub fn start(views: Vec<usize>, fingerprint: String, mask: Option<Vec<bool>>) -> Self {
        Self {
            version: VERSION,
            iterations_done: 0,
            views,
            fingerprint,
            mask,
            times: vec![],
            guidance_consistency: vec![],
            shape: vec![],
            attention: vec![],
            checksums: vec![],
        }
    }

    /// Whether `out` holds a checkpoint.
    pub fn exists(out: &Path) -> bool {
        meta_path(out).is_file()
    }

    /// Loads the checkpoint in `out` with its trainer; refuses one written by a run with another
    /// `fingerprint`.
    pub fn load(
        out: &Path,
        fingerprint: &str,
        setup: &TrainerSetup<'_>,
    ) -> Result<(Self, EditTrainer), RunError> {
        let path = meta_path(out);
        let text = std::fs::read_to_string(&path).map_err(|e| io_err(&path, e))?;
        let meta: Checkpoint = serde_json::from_str(&text).map_err(|e| io_err(&path, e))?;
        if meta.fingerprint != fingerprint || meta.version != VERSION {
            return Err(RunError::Input(format!(
                "{}: the checkpoint belongs to a run with other inputs or settings; use another --out or drop --resume",
                path.display()
            )));
        }
        let k = meta.iterations_done;
        let dir = checkpoint_dir(out);
        for (name, want) in &meta.checksums {
            let file = dir.join(name);
            let got = checksum(&file).map_err(|e| io_err(&file, e))?;
            if got != *want {
                return Err(RunError::Input(format!(
                    "{}: the checkpoint is damaged (the file does not match its checksum in checkpoint.json); \
                     it cannot be resumed: run again without --resume, with --force",
                    file.display()
                )));
            }
        }
        let scene_path = dir.join(format!("scene_{k}.ply"));
        // Read errors name the file themselves; values are checked as any scene's.
        let saved = splat::ply::read_ply(&scene_path)
            .map_err(|e| RunError::Input(format!("cannot resume: {e}")))?;
        saved.check_values().map_err(|msg| {
            RunError::Input(format!(
                "{}: cannot resume: the checkpoint's scene decodes to unusable values: {msg}",
                scene_path.display()
            ))
        })?;
        let trainer = EditTrainer::load(
            &dir.join(format!("trainer_{k}.safetensors")),
            &saved,
            setup.train.clone(),
            setup.extent,
            setup.background,
        )?;
        Ok((meta, trainer))
    }

    /// Saves this state with the trainer's scene and state (and their checksums), then drops the
    /// previous iteration's files.
    pub fn save(&mut self, out: &Path, trainer: &EditTrainer) -> Result<(), RunError> {
        let dir = checkpoint_dir(out);
        let k = self.iterations_done;
        let scene_path = dir.join(format!("scene_{k}.ply"));
        splat::ply::write_ply(&scene_path, trainer.scene()).map_err(|e| io_err(&scene_path, e))?;
        let state_path = dir.join(format!("trainer_{k}.safetensors"));
        trainer.save(&state_path)?;
        self.checksums.clear();
        for file in [&scene_path, &state_path] {
            let sum = checksum(file).map_err(|e| io_err(file, e))?;
            let name = file.file_name().expect("a file name").to_string_lossy();
            self.checksums.push((name.into_owned(), sum));
        }
        let path = meta_path(out);
        let json = serde_json::to_vec_pretty(self).expect("serialisable");
        files::atomic_write(&path, &json).map_err(|e| io_err(&path, e))?;
        // Older iterations' files are no longer needed.
        if k > 0 {
            let _ = std::fs::remove_file(dir.join(format!("scene_{}.ply", k - 1)));
            let _ = std::fs::remove_file(dir.join(format!("trainer_{}.safetensors", k - 1)));
        }
        Ok(())
    }
}

/// A checksum of a file's bytes (FNV-1a over 64-bit words): catches damage, not tampering.
fn checksum(path: &Path) -> std::io::Result<String> {
    use std::io::Read;
    let mut file = files::open_regular(path)?;
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    let mut add = |bytes: &[u8]| {
        for word in bytes.chunks(8) {
            let mut w = [0u8; 8];
            w[..word.len()].copy_from_slice(word);
            h ^= u64::from_le_bytes(w);
            h = h.wrapping_mul(0x100_0000_01b3);
        }
    };
    // Whole buffers (a multiple of 8 bytes) whatever the reads return, so only the end is padded.
    let mut buf = vec![0u8; 1 << 20];
    let (mut filled, mut len) = (0, 0u64);
    loop {
        let n = file.read(&mut buf[filled..])?;
        if n == 0 {
            break;
        }
        filled += n;
        len += n as u64;
        if filled == buf.len() {
            add(&buf);
            filled = 0;
        }
    }
    add(&buf[..filled]);
    h ^= len;
    Ok(format!("{:016x}", h.wrapping_mul(0x100_0000_01b3)))
}

/// Fingerprint of a run: its settings and input sizes. Cheap, and good enough to catch resuming into a
/// different run.
pub(super) fn fingerprint(job: &EditJob, scene: &GaussianScene, cameras: &[Camera]) -> String {
    let settings = serde_json::to_string(job).unwrap_or_default();
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for b in settings
        .bytes()
        .chain(scene.len().to_le_bytes())
        .chain(cameras.len().to_le_bytes())
    {
        h ^= b as u64;
        h = h.wrapping_mul(0x100_0000_01b3);
    }
    for v in scene.means.iter().step_by(97) {
        h ^= v.to_bits() as u64;
        h = h.wrapping_mul(0x100_0000_01b3);
    }
    format!("{h:016x}")
}

#[cfg(test)]
mod tests {
    use super::super::job::tests::job;
    use super::*;

    #[test]
    fn the_fingerprint_follows_the_settings_but_not_where_a_run_stops() {
        let scene = GaussianScene::new(0);
        let base = fingerprint(&job(), &scene, &[]);
        let stopping = EditJob {
            stop_after_iteration: Some(1),
            view_batch: Some(3),
            ..job()
        };
        // A run stopped after an iteration must be resumable without the stop, and with another view
        // batch (how the work is scheduled, not what it computes).
        assert_eq!(fingerprint(&stopping, &scene, &[]), base);
        let other = EditJob { seed: 1, ..job() };
        assert_ne!(fingerprint(&other, &scene, &[]), base);
    }
}
