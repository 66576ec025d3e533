//! The state of a scene under optimisation: parameters plus everything that has one entry per Gaussian
//! and must follow clone/split/prune (optimiser moments, densification statistics, trainable mask, HGS
//! generations and anchors).

use crate::anchor::{remap_scene, Anchor};
use crate::densify::{DensifyStats, Remap};
use crate::optim::{Adam, LearningRates};
use crate::render::SceneGrads;
use crate::GaussianScene;

/// A scene being trained. Cloning it gives an independent copy with the same optimiser state (what
/// VcEdit's mini-GS fits start from).
#[derive(Clone, Debug)]
pub struct TrainState {
    pub scene: GaussianScene,
    pub adam: Adam,
    pub stats: DensifyStats,
    /// Per-Gaussian trainable flags (`None` = all trainable). New Gaussians inherit their source's flag.
    pub trainable: Option<Vec<bool>>,
    /// HGS generations and anchors, when the anchor loss is used.
    pub anchor: Option<Anchor>,
    /// Scene extent (the INRIA trainer's `cameras_extent`): scales position rates and size thresholds.
    pub extent: f32,
}

impl TrainState {
    /// All Gaussians trainable, fresh optimiser, no anchors.
    pub fn new(scene: GaussianScene, rates: LearningRates, extent: f32) -> Self {
        let adam = Adam::new(&scene, rates, extent);
        let stats = DensifyStats::new(scene.len());
        Self {
            scene,
            adam,
            stats,
            trainable: None,
            anchor: None,
            extent,
        }
    }

    pub fn len(&self) -> usize {
        self.scene.len()
    }

    pub fn is_empty(&self) -> bool {
        self.scene.is_empty()
    }

    /// One optimiser step with `grads` (trainable mask applied).
    pub fn step(&mut self, grads: &SceneGrads) {
        self.adam
            .step(&mut self.scene, grads, self.trainable.as_deref());
    }

    /// Applies a structural change to every per-Gaussian array.
    pub fn apply_remap(&mut self, remap: &Remap) {
        assert_eq!(remap.old_len(), self.len(), "remap of another size");
        remap_scene(&mut self.scene, remap);
        self.adam.remap(remap);
        self.stats.remap(remap);
        if let Some(mask) = &mut self.trainable {
            remap.apply(mask, 1);
        }
        if let Some(anchor) = &mut self.anchor {
            anchor.remap(remap);
        }
    }

    /// Changes the scene's SH degree (the INRIA trainer raises the active degree during fitting); new
    /// coefficients start at zero, removed ones are dropped.
    pub fn set_sh_degree(&mut self, degree: u32) {
        let old_k = self.scene.sh_coeffs();
        let new_k = crate::scene::sh_coeffs(degree);
        if old_k == new_k {
            return;
        }
        self.scene.sh = crate::optim::relayout_sh(&self.scene.sh, old_k, new_k);
        self.scene.sh_degree = degree;
        self.adam.set_sh_degree(degree);
        if let Some(anchor) = &mut self.anchor {
            anchor.set_sh_degree(degree);
        }
    }

    /// Checks that every per-Gaussian array has the scene's length.
    pub fn check(&self) -> Result<(), String> {
        self.scene.check_shapes()?;
        let n = self.len();
        let mut sizes = vec![
            ("optimiser state", self.adam.len()),
            ("densification statistics", self.stats.len()),
        ];
        if let Some(m) = &self.trainable {
            sizes.push(("trainable mask", m.len()));
        }
        if let Some(a) = &self.anchor {
            sizes.push(("generations", a.generations.len()));
        }
        for (what, len) in sizes {
            if len != n {
                return Err(format!("{what} has {len} entries for {n} Gaussians"));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sh_degree_change_relays_everything() {
        let scene = GaussianScene {
            sh_degree: 0,
            means: vec![0.0; 6],
            log_scales: vec![0.0; 6],
            quats: vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0],
            opacity_logits: vec![0.0; 2],
            sh: vec![0.1, 0.2, 0.3, 0.4, 0.5, 0.6],
        };
        let mut st = TrainState::new(scene, LearningRates::inria(10), 1.0);
        st.anchor = Some(Anchor::new(
            &st.scene,
            crate::anchor::AnchorConfig::vcedit(),
        ));
        st.set_sh_degree(2);
        st.check().unwrap();
        assert_eq!(st.scene.sh.len(), 2 * 27);
        assert_eq!(&st.scene.sh[27..30], &[0.4, 0.5, 0.6]);
        assert!(st.scene.sh[3..27].iter().all(|&v| v == 0.0));
        let grads = SceneGrads {
            means: vec![0.0; 6],
            log_scales: vec![0.0; 6],
            quats: vec![0.0; 8],
            opacity_logits: vec![0.0; 2],
            sh: vec![1.0; 54],
            extra: Vec::new(),
            means2d: vec![[0.0; 2]; 2],
        };
        st.step(&grads);
        let anchor = st.anchor.as_ref().unwrap();
        // The SH moved away from its (re-laid) anchor; λ_color = 0 in VcEdit's config keeps it out of the
        // total, and nothing else moved.
        let l = anchor.loss(&st.scene, None, None);
        assert!(l.color > 0.0);
        assert_eq!(l.total, 0.0);
    }
}
