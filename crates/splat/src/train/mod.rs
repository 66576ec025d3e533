//! Training: the state of a scene under optimisation ([`TrainState`]: parameters plus everything that
//! has one entry per Gaussian and must follow clone/split/prune — optimiser moments, densification
//! statistics, trainable mask, HGS generations and anchors), the one [`Trainer`] every fit steps with, and
//! what it is configured by: the optimiser ([`optim`]), densification strategies ([`densify`]), anchors
//! ([`anchor`]) and losses ([`loss`]). [`scene_fit`] is the scene fit from images (`vcedit fit`);
//! [`checkpoint`] saves and resumes it.

pub mod anchor;
pub mod checkpoint;
pub mod densify;
pub(crate) mod gpu;
pub mod loss;
pub mod optim;
pub mod scene_fit;
mod trainer;

pub use gpu::L1DssimWeights;
pub use trainer::{FitLoss, PairTrainer, StageSeconds, StepKind, StepOutcome, Trainer};

use crate::cameras::Camera;
use crate::layout::{remap_scene, set_scene_sh_degree, Remap};
use crate::render::SceneGrads;
use crate::scene::GaussianScene;
use crate::train::anchor::Anchor;
use crate::train::optim::{Adam, LearningRates};

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
    pub(crate) fn apply_remap(&mut self, remap: &Remap) {
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
    pub(crate) fn set_sh_degree(&mut self, degree: u32) {
        if self.scene.sh_coeffs() == crate::scene::sh_coeffs(degree) {
            return;
        }
        set_scene_sh_degree(&mut self.scene, degree);
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

/// What one rendered view tells densification: every Gaussian's screen-space positional gradient and
/// screen radius, and the size of the image they were measured in.
#[derive(Clone, Copy, Debug)]
pub struct RenderedView<'a> {
    /// dL/d(pixel centre) per Gaussian ([`SceneGrads::means2d`]).
    pub means2d: &'a [[f32; 2]],
    /// Screen radius per Gaussian in pixels, 0 = not rendered ([`crate::render::Frame::radii`]).
    pub radii: &'a [u32],
    pub width: u32,
    pub height: u32,
}

impl<'a> RenderedView<'a> {
    /// The view `camera` rendered with these `radii` and backpropagated into `grads`.
    pub fn new(grads: &'a SceneGrads, radii: &'a [u32], camera: &Camera) -> Self {
        Self {
            means2d: &grads.means2d,
            radii,
            width: camera.width,
            height: camera.height,
        }
    }
}

/// Running screen-space statistics per Gaussian between two refinements.
///
/// The gradient norm is taken in the units of the INRIA rasteriser: its `dL/d(mean2D)` is with respect to
/// normalised device coordinates, i.e. the pixel-space gradient times (W/2, H/2) (gsplat's `_update_state`
/// does the same scaling). With a mean-reduced image loss this makes a densification threshold of 0.0002
/// mean what it means in the trainer.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct DensifyStats {
    /// Σ ‖dL/d(mean2D)‖ in NDC units over the views that rendered the Gaussian.
    pub grad2d: Vec<f32>,
    /// Number of views that rendered the Gaussian.
    pub count: Vec<f32>,
    /// Largest screen radius in pixels.
    pub max_radius: Vec<f32>,
}

impl DensifyStats {
    pub fn new(n: usize) -> Self {
        Self {
            grad2d: vec![0.0; n],
            count: vec![0.0; n],
            max_radius: vec![0.0; n],
        }
    }

    pub fn len(&self) -> usize {
        self.count.len()
    }

    pub fn is_empty(&self) -> bool {
        self.count.is_empty()
    }

    /// Adds one rendered view. Loss gradients averaged over a batch of B views should pass `batch = B`
    /// (gsplat multiplies by the number of cameras); otherwise 1.
    pub fn add(&mut self, view: &RenderedView<'_>, batch: usize) {
        assert_eq!(
            view.means2d.len(),
            self.len(),
            "densify stats: means2d size"
        );
        assert_eq!(view.radii.len(), self.len(), "densify stats: radii size");
        let sx = 0.5 * view.width as f32 * batch as f32;
        let sy = 0.5 * view.height as f32 * batch as f32;
        for (i, (&[gx, gy], &r)) in view.means2d.iter().zip(view.radii).enumerate() {
            if r == 0 {
                continue;
            }
            let norm = ((gx * sx).powi(2) + (gy * sy).powi(2)).sqrt();
            if !norm.is_finite() {
                continue;
            }
            self.grad2d[i] += norm;
            self.count[i] += 1.0;
            self.max_radius[i] = self.max_radius[i].max(r as f32);
        }
    }

    /// Mean gradient norm per Gaussian (0 where never rendered).
    pub fn average(&self) -> Vec<f32> {
        self.grad2d
            .iter()
            .zip(&self.count)
            .map(|(&g, &c)| if c > 0.0 { g / c } else { 0.0 })
            .collect()
    }

    pub fn clear(&mut self) {
        for v in [&mut self.grad2d, &mut self.count, &mut self.max_radius] {
            v.iter_mut().for_each(|x| *x = 0.0);
        }
    }

    /// Follows a structural change; new Gaussians copy their source's statistics (gsplat's behaviour; they
    /// are cleared right after a refinement anyway).
    pub(crate) fn remap(&mut self, remap: &Remap) {
        remap.apply(&mut self.grad2d, 1);
        remap.apply(&mut self.count, 1);
        remap.apply(&mut self.max_radius, 1);
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
            crate::train::anchor::AnchorConfig::vcedit(),
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
