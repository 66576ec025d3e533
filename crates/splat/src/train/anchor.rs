//! GaussianEditor's hierarchical Gaussian splatting (HGS) anchor loss (docs/algorithm.md §3.2).
//!
//! Every Gaussian has a generation: 0 for the loaded ones, and each densification gives the Gaussians it
//! creates a new generation number. A weight schedule w\[g\] pulls older generations harder towards their
//! anchored parameters P̂ (a snapshot refreshed after every densification):
//!
//! - start: w = \[init_g0\];
//! - at every densification: w\[g\] ← min(multiplier·w\[g\], 10) for all g, then the previous newest
//!   generation (weight 0) gets `init` (except at the first densification, when there is none), and a new
//!   entry 0 is appended for the Gaussians just born — they are free until the next densification.
//!
//! L_attr = mean over the masked Gaussians and the attribute's elements of w\[g_j\]·(P_j − P̂_j)², on the raw
//! (trainable) parameters; geo = positions + quaternions, color = SH DC + SH rest, opacity, scale; the total
//! is Σ λ_attr·L_attr.

use crate::layout::{remap_scene, set_scene_sh_degree, Remap};
use crate::render::SceneGrads;
use crate::scene::GaussianScene;
use serde::{Deserialize, Serialize};

/// GaussianEditor caps every generation weight at this value.
pub(crate) const MAX_ANCHOR_WEIGHT: f32 = 10.0;

/// Weights of the anchor loss (serialised as is in training-state checkpoints).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AnchorConfig {
    /// Initial weight of generation 0 (the loaded scene).
    pub weight_init_g0: f32,
    /// Weight a generation gets at the first densification after its birth.
    pub weight_init: f32,
    /// Growth of every weight per densification.
    pub weight_multiplier: f32,
    pub lambda_color: f32,
    pub lambda_geo: f32,
    pub lambda_opacity: f32,
    pub lambda_scale: f32,
}

impl AnchorConfig {
    /// GaussianEditor's defaults: g0 1.0, init 0.1, multiplier 2, λ color/geo/opacity/scale = 5/50/50/50.
    pub fn gaussian_editor() -> Self {
        Self {
            weight_init_g0: 1.0,
            weight_init: 0.1,
            weight_multiplier: 2.0,
            lambda_color: 5.0,
            lambda_geo: 50.0,
            lambda_opacity: 50.0,
            lambda_scale: 50.0,
        }
    }

    /// The VcEdit scripts' values: g0 0.05, init 0.1, multiplier 1.3, λ color/geo/opacity/scale = 0/50/50/50.
    pub fn vcedit() -> Self {
        Self {
            weight_init_g0: 0.05,
            weight_init: 0.1,
            weight_multiplier: 1.3,
            lambda_color: 0.0,
            lambda_geo: 50.0,
            lambda_opacity: 50.0,
            lambda_scale: 50.0,
        }
    }
}

/// The four weighted terms and their λ-weighted sum.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct AnchorLoss {
    pub color: f32,
    pub geo: f32,
    pub opacity: f32,
    pub scale: f32,
    /// Σ λ_attr · term.
    pub total: f32,
}

/// Generations, weight schedule and anchored parameters of a scene.
#[derive(Clone, Debug)]
pub struct Anchor {
    pub config: AnchorConfig,
    /// Generation of each Gaussian.
    pub generations: Vec<u32>,
    /// Weight per generation.
    pub schedule: Vec<f32>,
    pub(crate) snapshot: GaussianScene,
}

impl Anchor {
    /// Everything is generation 0, anchored at the current parameters.
    pub fn new(scene: &GaussianScene, config: AnchorConfig) -> Self {
        Self {
            schedule: vec![config.weight_init_g0],
            config,
            generations: vec![0; scene.len()],
            snapshot: scene.clone(),
        }
    }

    /// The generation number the next densification gives its new Gaussians.
    pub(crate) fn next_generation(&self) -> u32 {
        self.schedule.len() as u32
    }

    /// Anchors the current parameters (GaussianEditor's `update_anchor`).
    pub(crate) fn refresh(&mut self, scene: &GaussianScene) {
        self.snapshot.clone_from(scene);
    }

    /// Follows a clone/split/prune: survivors keep their generation and anchors, new Gaussians belong to
    /// [`Anchor::next_generation`] and copy their source's anchors until the next [`Anchor::refresh`].
    pub(crate) fn remap(&mut self, remap: &Remap) {
        let g = self.next_generation();
        remap.apply_fill(&mut self.generations, 1, g);
        remap_scene(&mut self.snapshot, remap);
    }

    /// Advances the weight schedule after a densification (GaussianEditor's `update_anchor_loss_schedule`)
    /// and anchors the densified scene.
    pub(crate) fn finish_densify(&mut self, scene: &GaussianScene) {
        let c = &self.config;
        for w in &mut self.schedule {
            *w = (c.weight_multiplier * *w).min(MAX_ANCHOR_WEIGHT);
        }
        if self.schedule.len() > 1 {
            // The generation born at the previous densification starts being anchored now.
            *self.schedule.last_mut().expect("non-empty") = c.weight_init;
        }
        self.schedule.push(0.0);
        self.refresh(scene);
    }

    /// Re-lays the anchored SH coefficients after the scene's SH degree changed.
    pub(crate) fn set_sh_degree(&mut self, degree: u32) {
        set_scene_sh_degree(&mut self.snapshot, degree);
    }

    /// The anchor loss over the Gaussians selected by `mask` (all when `None`). When `grads` is given, the
    /// gradient of `total` is added to it.
    ///
    /// # Panics
    /// When the scene does not match the anchored one in size or SH degree (programming errors: call
    /// `Anchor::remap` / `Anchor::set_sh_degree` alongside the scene's changes; `TrainState` does).
    pub fn loss(
        &self,
        scene: &GaussianScene,
        mask: Option<&[bool]>,
        grads: Option<&mut SceneGrads>,
    ) -> AnchorLoss {
        let n = scene.len();
        assert_eq!(self.generations.len(), n, "anchor generations size");
        assert_eq!(self.snapshot.len(), n, "anchor snapshot size");
        assert_eq!(self.snapshot.sh_degree, scene.sh_degree, "anchor SH degree");
        if let Some(m) = mask {
            assert_eq!(m.len(), n, "mask size");
        }
        let selected = |j: usize| mask.is_none_or(|m| m[j]);
        let count = (0..n).filter(|&j| selected(j)).count();
        if count == 0 {
            return AnchorLoss::default();
        }
        let weight = |j: usize| self.schedule[self.generations[j] as usize];
        let c = &self.config;
        let k = scene.sh_coeffs();

        // One attribute: per Gaussian `width` values at `offset` within a block of `stride`. Returns the
        // mean weighted squared difference and adds λ·gradient into `grad`.
        let term = |cur: &[f32],
                    anchor: &[f32],
                    stride: usize,
                    offset: usize,
                    width: usize,
                    lambda: f32,
                    grad: Option<&mut Vec<f32>>|
         -> f32 {
            if width == 0 {
                return 0.0;
            }
            let denom = (count * width) as f64;
            let mut sum = 0.0f64;
            let mut grad = grad;
            for j in 0..n {
                if !selected(j) {
                    continue;
                }
                let w = weight(j);
                if w == 0.0 {
                    continue;
                }
                for e in 0..width {
                    let i = j * stride + offset + e;
                    let d = cur[i] - anchor[i];
                    sum += (w * d * d) as f64;
                    if let Some(g) = grad.as_deref_mut() {
                        g[i] += (lambda as f64 * 2.0 * (w * d) as f64 / denom) as f32;
                    }
                }
            }
            (sum / denom) as f32
        };
        let s = &self.snapshot;
        let mut g = grads;
        let geo = term(
            &scene.means,
            &s.means,
            3,
            0,
            3,
            c.lambda_geo,
            g.as_mut().map(|g| &mut g.means),
        ) + term(
            &scene.quats,
            &s.quats,
            4,
            0,
            4,
            c.lambda_geo,
            g.as_mut().map(|g| &mut g.quats),
        );
        let color = term(
            &scene.sh,
            &s.sh,
            3 * k,
            0,
            3,
            c.lambda_color,
            g.as_mut().map(|g| &mut g.sh),
        ) + term(
            &scene.sh,
            &s.sh,
            3 * k,
            3,
            3 * (k - 1),
            c.lambda_color,
            g.as_mut().map(|g| &mut g.sh),
        );
        let opacity = term(
            &scene.opacity_logits,
            &s.opacity_logits,
            1,
            0,
            1,
            c.lambda_opacity,
            g.as_mut().map(|g| &mut g.opacity_logits),
        );
        let scale = term(
            &scene.log_scales,
            &s.log_scales,
            3,
            0,
            3,
            c.lambda_scale,
            g.as_mut().map(|g| &mut g.log_scales),
        );
        AnchorLoss {
            color,
            geo,
            opacity,
            scale,
            total: c.lambda_color * color
                + c.lambda_geo * geo
                + c.lambda_opacity * opacity
                + c.lambda_scale * scale,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scene(n: usize) -> GaussianScene {
        let k = 4;
        GaussianScene {
            sh_degree: 1,
            means: (0..3 * n).map(|i| (i as f32 * 0.37).sin()).collect(),
            log_scales: (0..3 * n).map(|i| -2.0 + (i as f32 * 0.11).cos()).collect(),
            quats: (0..4 * n).map(|i| 0.5 + (i as f32 * 0.7).sin()).collect(),
            opacity_logits: (0..n).map(|i| i as f32 * 0.3 - 0.5).collect(),
            sh: (0..3 * k * n)
                .map(|i| (i as f32 * 0.23).cos() * 0.3)
                .collect(),
        }
    }

    fn zero_grads(s: &GaussianScene) -> SceneGrads {
        SceneGrads {
            means: vec![0.0; s.means.len()],
            log_scales: vec![0.0; s.log_scales.len()],
            quats: vec![0.0; s.quats.len()],
            opacity_logits: vec![0.0; s.len()],
            sh: vec![0.0; s.sh.len()],
            extra: Vec::new(),
            means2d: vec![[0.0; 2]; s.len()],
        }
    }

    #[test]
    fn schedule_follows_gaussian_editor() {
        let s = scene(3);
        let mut a = Anchor::new(&s, AnchorConfig::gaussian_editor());
        assert_eq!(a.schedule, vec![1.0]);
        a.finish_densify(&s);
        assert_eq!(a.schedule, vec![2.0, 0.0]);
        a.finish_densify(&s);
        assert_eq!(a.schedule, vec![4.0, 0.1, 0.0]);
        a.finish_densify(&s);
        assert_eq!(a.schedule, vec![8.0, 0.2, 0.1, 0.0]);
        a.finish_densify(&s);
        assert_eq!(a.schedule[0], MAX_ANCHOR_WEIGHT);
        assert_eq!(a.next_generation(), 5);
    }

    #[test]
    fn remap_assigns_new_generation_and_copies_anchor() {
        let s = scene(3);
        let mut a = Anchor::new(&s, AnchorConfig::vcedit());
        let r = Remap {
            keep: vec![true, false, true],
            appended: vec![1, 1, 2],
        };
        a.remap(&r);
        assert_eq!(a.generations, vec![0, 0, 1, 1, 1]);
        assert_eq!(a.snapshot.len(), 5);
        assert_eq!(a.snapshot.mean(2), s.mean(1));
        assert_eq!(a.snapshot.mean(4), s.mean(2));
    }

    #[test]
    fn loss_is_zero_at_anchor_and_gradient_matches_finite_differences() {
        let s0 = scene(4);
        let mut a = Anchor::new(&s0, AnchorConfig::gaussian_editor());
        // Mixed generations with distinct weights.
        a.schedule = vec![1.5, 0.4, 0.0];
        a.generations = vec![0, 1, 2, 0];
        let mask = [true, true, true, false];
        assert_eq!(a.loss(&s0, Some(&mask), None).total, 0.0);

        let mut s = s0.clone();
        for (i, v) in s.means.iter_mut().enumerate() {
            *v += 0.05 * (i as f32 * 1.3).cos();
        }
        for (i, v) in s.sh.iter_mut().enumerate() {
            *v -= 0.04 * (i as f32 * 0.9).sin();
        }
        for (i, v) in s.quats.iter_mut().enumerate() {
            *v += 0.03 * (i as f32).sin();
        }
        s.opacity_logits.iter_mut().for_each(|v| *v += 0.2);
        s.log_scales.iter_mut().for_each(|v| *v -= 0.1);

        let mut g = zero_grads(&s);
        let l = a.loss(&s, Some(&mask), Some(&mut g));
        assert!(l.total > 0.0 && l.geo > 0.0 && l.color > 0.0 && l.opacity > 0.0 && l.scale > 0.0);

        // Central differences in f32 on a quadratic: exact up to rounding.
        let eps = 1e-2f32;
        let total = |s: &GaussianScene| a.loss(s, Some(&mask), None).total as f64;
        type Field = fn(&mut GaussianScene) -> &mut Vec<f32>;
        type GradField = fn(&SceneGrads) -> &Vec<f32>;
        let fields: [(&str, Field, GradField); 5] = [
            ("means", |s| &mut s.means, |g| &g.means),
            ("quats", |s| &mut s.quats, |g| &g.quats),
            ("sh", |s| &mut s.sh, |g| &g.sh),
            ("opacity", |s| &mut s.opacity_logits, |g| &g.opacity_logits),
            ("scales", |s| &mut s.log_scales, |g| &g.log_scales),
        ];
        for (name, field, gfield) in fields {
            let len = field(&mut s.clone()).len();
            for i in 0..len {
                let mut sp = s.clone();
                field(&mut sp)[i] += eps;
                let mut sm = s.clone();
                field(&mut sm)[i] -= eps;
                let fd = (total(&sp) - total(&sm)) / (2.0 * eps as f64);
                let an = gfield(&g)[i] as f64;
                assert!(
                    (fd - an).abs() < 2e-3 * (1.0 + an.abs()),
                    "{name}[{i}]: fd {fd} analytic {an}"
                );
            }
        }
        // Masked-out Gaussian 3 and weight-0 generation (Gaussian 2) get no gradient.
        assert!(g.means[9..12].iter().all(|&v| v == 0.0));
        assert!(g.means[6..9].iter().all(|&v| v == 0.0));
        assert!(g.means[0..3].iter().any(|&v| v != 0.0));
    }

    #[test]
    fn loss_value_matches_definition() {
        let s0 = scene(2);
        let mut a = Anchor::new(&s0, AnchorConfig::gaussian_editor());
        let mut s = s0.clone();
        s.opacity_logits[0] += 1.0;
        s.opacity_logits[1] += 2.0;
        a.generations = vec![0, 0];
        a.schedule = vec![3.0];
        // mean over 2 Gaussians of 3·d²: (3·1 + 3·4) / 2.
        let l = a.loss(&s, None, None);
        assert!((l.opacity - 7.5).abs() < 1e-5);
        assert!((l.total - 50.0 * 7.5).abs() < 1e-3);
        // Only Gaussian 1 selected.
        let l = a.loss(&s, Some(&[false, true]), None);
        assert!((l.opacity - 12.0).abs() < 1e-5);
    }
}
