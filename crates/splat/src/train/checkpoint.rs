//! Saving and restoring a [`TrainState`] without its scene (the scene goes to a PLY), so an interrupted
//! edit resumes with the exact optimiser moments, statistics, masks and anchors it had.
//!
//! Format: the magic line `VCEDIT-TRAINSTATE 1\n`, a little-endian u64 length, a JSON header (scalars and
//! the list of arrays with their lengths), then the arrays' raw little-endian bytes in header order.

use serde::{Deserialize, Serialize};

use crate::scene::GaussianScene;
use crate::train::anchor::{Anchor, AnchorConfig};
use crate::train::optim::{Adam, LearningRates, Moments};
use crate::train::{DensifyStats, TrainState};

const MAGIC: &[u8] = b"VCEDIT-TRAINSTATE 1\n";

#[derive(Serialize, Deserialize)]
struct Header {
    user_step: u64,
    extent: f32,
    adam_steps: u64,
    means_lr: f32,
    lr_scale: f32,
    group_lr_scale: [f32; 6],
    mask_rotation: bool,
    sh_degree: u32,
    has_trainable: bool,
    anchor: Option<AnchorConfig>,
    arrays: Vec<(String, usize)>,
}

struct Writer {
    names: Vec<(String, usize)>,
    data: Vec<u8>,
}

impl Writer {
    fn put(&mut self, name: &str, values: &[f32]) {
        self.names.push((name.to_string(), values.len()));
        for v in values {
            self.data.extend_from_slice(&v.to_le_bytes());
        }
    }
}

impl TrainState {
    /// Serialises everything but `scene` (and the learning-rate schedule, which callers recreate), with a
    /// caller value `user_step` (e.g. the global step).
    pub fn to_bytes(&self, user_step: u64) -> Result<Vec<u8>, String> {
        self.check()?;
        let mut w = Writer {
            names: Vec::new(),
            data: Vec::new(),
        };
        let a = &self.adam;
        for (name, m) in [
            ("means", &a.means),
            ("log_scales", &a.log_scales),
            ("quats", &a.quats),
            ("opacity", &a.opacity),
            ("sh", &a.sh),
        ] {
            w.put(&format!("adam.{name}.m"), &m.m);
            w.put(&format!("adam.{name}.v"), &m.v);
        }
        w.put("stats.grad2d", &self.stats.grad2d);
        w.put("stats.count", &self.stats.count);
        w.put("stats.max_radius", &self.stats.max_radius);
        if let Some(t) = &self.trainable {
            w.put(
                "trainable",
                &t.iter()
                    .map(|&b| if b { 1.0 } else { 0.0 })
                    .collect::<Vec<_>>(),
            );
        }
        let anchor = self.anchor.as_ref().map(|an| {
            w.put(
                "anchor.generations",
                &an.generations.iter().map(|&g| g as f32).collect::<Vec<_>>(),
            );
            w.put("anchor.schedule", &an.schedule);
            let s = &an.snapshot;
            w.put("anchor.means", &s.means);
            w.put("anchor.log_scales", &s.log_scales);
            w.put("anchor.quats", &s.quats);
            w.put("anchor.opacity_logits", &s.opacity_logits);
            w.put("anchor.sh", &s.sh);
            an.config.clone()
        });
        let header = Header {
            user_step,
            extent: self.extent,
            adam_steps: a.steps,
            means_lr: a.means_lr,
            lr_scale: a.lr_scale,
            group_lr_scale: a.group_lr_scale,
            mask_rotation: a.mask_rotation,
            sh_degree: self.scene.sh_degree,
            has_trainable: self.trainable.is_some(),
            anchor,
            arrays: w.names,
        };
        let json = serde_json::to_vec(&header).map_err(|e| e.to_string())?;
        let mut out = Vec::with_capacity(MAGIC.len() + 8 + json.len() + w.data.len());
        out.extend_from_slice(MAGIC);
        out.extend_from_slice(&(json.len() as u64).to_le_bytes());
        out.extend_from_slice(&json);
        out.extend_from_slice(&w.data);
        Ok(out)
    }

    /// Restores a state saved by [`TrainState::to_bytes`] around `scene`; returns it and the user step.
    pub fn from_bytes(
        bytes: &[u8],
        scene: GaussianScene,
        rates: LearningRates,
        extent: f32,
    ) -> Result<(TrainState, u64), String> {
        let rest = bytes
            .strip_prefix(MAGIC)
            .ok_or("not a vcedit training state (bad magic)")?;
        if rest.len() < 8 {
            return Err("truncated training state".into());
        }
        let len = u64::from_le_bytes(rest[..8].try_into().expect("8 bytes")) as usize;
        let json = rest
            .get(8..8usize.saturating_add(len))
            .ok_or("truncated training state header")?;
        let header: Header =
            serde_json::from_slice(json).map_err(|e| format!("bad training state header: {e}"))?;
        let mut data = &rest[8 + len..];
        let mut arrays = std::collections::HashMap::new();
        for (name, n) in &header.arrays {
            let bytes = n.checked_mul(4).ok_or("array size overflow")?;
            if data.len() < bytes {
                return Err(format!("training state truncated in array {name}"));
            }
            let (head, tail) = data.split_at(bytes);
            let v: Vec<f32> = head
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes(c.try_into().expect("4 bytes")))
                .collect();
            arrays.insert(name.clone(), v);
            data = tail;
        }
        if !data.is_empty() {
            return Err("trailing bytes after the training state".into());
        }
        if header.sh_degree != scene.sh_degree {
            return Err(format!(
                "state has SH degree {}, the scene {}",
                header.sh_degree, scene.sh_degree
            ));
        }
        let mut take = |name: &str| {
            arrays
                .remove(name)
                .ok_or_else(|| format!("training state lacks {name}"))
        };
        let mut adam = Adam::new(&scene, rates, extent);
        for (name, m) in [
            ("means", &mut adam.means),
            ("log_scales", &mut adam.log_scales),
            ("quats", &mut adam.quats),
            ("opacity", &mut adam.opacity),
            ("sh", &mut adam.sh),
        ] {
            *m = Moments {
                m: take(&format!("adam.{name}.m"))?,
                v: take(&format!("adam.{name}.v"))?,
            };
        }
        adam.steps = header.adam_steps;
        adam.means_lr = header.means_lr;
        adam.lr_scale = header.lr_scale;
        adam.group_lr_scale = header.group_lr_scale;
        adam.mask_rotation = header.mask_rotation;
        let stats = DensifyStats {
            grad2d: take("stats.grad2d")?,
            count: take("stats.count")?,
            max_radius: take("stats.max_radius")?,
        };
        let trainable = if header.has_trainable {
            Some(take("trainable")?.into_iter().map(|v| v > 0.5).collect())
        } else {
            None
        };
        let anchor = match header.anchor {
            None => None,
            Some(config) => {
                let mut an = Anchor::new(&scene, config);
                an.generations = take("anchor.generations")?
                    .into_iter()
                    .map(|g| g as u32)
                    .collect();
                an.schedule = take("anchor.schedule")?;
                an.snapshot = GaussianScene {
                    sh_degree: scene.sh_degree,
                    means: take("anchor.means")?,
                    log_scales: take("anchor.log_scales")?,
                    quats: take("anchor.quats")?,
                    opacity_logits: take("anchor.opacity_logits")?,
                    sh: take("anchor.sh")?,
                };
                an.snapshot.check_shapes()?;
                Some(an)
            }
        };
        let state = TrainState {
            scene,
            adam,
            stats,
            trainable,
            anchor,
            extent: header.extent,
        };
        state.check()?;
        Ok((state, header.user_step))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::SceneGrads;

    #[test]
    fn roundtrip_keeps_everything() {
        let scene = GaussianScene {
            sh_degree: 1,
            means: vec![0.0, 1.0, 2.0, 3.0, 4.0, 5.0],
            log_scales: vec![-1.0; 6],
            quats: vec![1.0, 0.0, 0.0, 0.0, 0.5, 0.5, 0.5, 0.5],
            opacity_logits: vec![0.1, 0.2],
            sh: (0..24).map(|i| i as f32 * 0.01).collect(),
        };
        let mut st = TrainState::new(scene.clone(), LearningRates::gaussian_editor(100), 2.0);
        st.trainable = Some(vec![true, false]);
        st.anchor = Some(Anchor::new(&scene, AnchorConfig::vcedit()));
        let grads = SceneGrads {
            means: vec![0.3; 6],
            log_scales: vec![0.1; 6],
            quats: vec![0.2; 8],
            opacity_logits: vec![0.5; 2],
            sh: vec![0.05; 24],
            extra: Vec::new(),
            means2d: vec![[0.1, 0.2]; 2],
        };
        st.step(&grads);
        st.stats.add(
            &crate::train::RenderedView {
                means2d: &grads.means2d,
                radii: &[3, 0],
                width: 64,
                height: 64,
            },
            1,
        );
        st.adam.lr_scale = 0.5;
        let bytes = st.to_bytes(42).unwrap();
        let (back, step) = TrainState::from_bytes(
            &bytes,
            st.scene.clone(),
            LearningRates::gaussian_editor(100),
            2.0,
        )
        .unwrap();
        assert_eq!(step, 42);
        assert_eq!(back.trainable, st.trainable);
        assert_eq!(back.stats, st.stats);
        assert_eq!(back.adam.means.m, st.adam.means.m);
        assert_eq!(back.adam.sh.v, st.adam.sh.v);
        assert_eq!(back.adam.steps, 1);
        assert_eq!(back.adam.lr_scale, 0.5);
        let (a, b) = (back.anchor.unwrap(), st.anchor.unwrap());
        assert_eq!(
            (a.generations, a.schedule, a.snapshot),
            (b.generations, b.schedule, b.snapshot)
        );
        // Corruption is an error, not a panic.
        assert!(TrainState::from_bytes(
            &bytes[..bytes.len() - 3],
            st.scene.clone(),
            LearningRates::inria(1),
            1.0
        )
        .is_err());
        assert!(
            TrainState::from_bytes(b"junk", st.scene.clone(), LearningRates::inria(1), 1.0)
                .is_err()
        );
    }
}
