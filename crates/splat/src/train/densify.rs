//! Adaptive density control: clone, split and prune Gaussians, and reset opacities, with every per-Gaussian
//! array (optimiser moments, statistics, masks, generations, anchors) following along.
//!
//! Two strategies:
//! - [`DefaultStrategy`]: the INRIA trainer / gsplat `DefaultStrategy` used to fit scenes from images.
//! - [`EditStrategy`]: GaussianEditor's variant used while editing (docs/algorithm.md §3.4): statistics and
//!   pruning restricted to the trainable mask, a top-quantile cut of the gradients, and HGS generations.
//!
//! Both decide on the screen-space gradient statistics of [`crate::train::DensifyStats`], which are in the
//! units of the INRIA rasteriser, so `grow_grad2d = 0.0002` means what it means in the trainer.

use crate::layout::Remap;
use crate::scene::GaussianScene;
use crate::train::optim::Group;
use crate::train::{RenderedView, TrainState};
use glam::{Mat3, Quat, Vec3};
use rand::Rng;
use rand_distr::StandardNormal;

/// What one refinement did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RefineReport {
    pub cloned: usize,
    pub split: usize,
    pub pruned: usize,
    pub opacity_reset: bool,
}

/// Largest world-space standard deviation of Gaussian `i`.
fn max_scale(scene: &GaussianScene, i: usize) -> f32 {
    let s = &scene.log_scales[3 * i..3 * i + 3];
    s[0].max(s[1]).max(s[2]).exp()
}

/// Rotation matrix of Gaussian `i`'s quaternion (w, x, y, z), normalised by division (identity when it
/// is zero or not finite).
fn rotation(scene: &GaussianScene, i: usize) -> Mat3 {
    let q = &scene.quats[4 * i..4 * i + 4];
    let norm = q.iter().map(|v| v * v).sum::<f32>().sqrt();
    if !(norm > 0.0 && norm.is_finite()) {
        return Mat3::IDENTITY;
    }
    let [w, x, y, z] = [q[0] / norm, q[1] / norm, q[2] / norm, q[3] / norm];
    Mat3::from_quat(Quat::from_xyzw(x, y, z, w))
}

/// Appends a copy of each selected Gaussian (parameters copied, optimiser moments zero).
pub fn duplicate(state: &mut TrainState, selected: &[bool]) -> usize {
    let remap = Remap::duplicate(selected);
    let n = remap.appended.len();
    if n > 0 {
        state.apply_remap(&remap);
    }
    n
}

/// Replaces each selected Gaussian by two children drawn from it: mean + R·(s ⊙ z) with z ~ N(0, I),
/// scales s/1.6, everything else copied (INRIA `densify_and_split` with N = 2; gsplat `split`). Random
/// numbers are drawn child-major (all first children, then all second children), x/y/z per child.
pub fn split<R: Rng + ?Sized>(state: &mut TrainState, selected: &[bool], rng: &mut R) -> usize {
    let remap = Remap::split(selected);
    let parents = remap.appended.len() / 2;
    if parents == 0 {
        return 0;
    }
    // Children positions and scales from the parents, before the parents go.
    let scene = &state.scene;
    let mut child_means = Vec::with_capacity(remap.appended.len() * 3);
    for &p in &remap.appended {
        let r = rotation(scene, p);
        let z: [f32; 3] = std::array::from_fn(|_| rng.sample(StandardNormal));
        let local = Vec3::from(scene.scale(p)) * Vec3::from(z);
        // Summed left to right from the mean, column by column.
        let m = Vec3::from(scene.mean(p))
            + r.x_axis * local.x
            + r.y_axis * local.y
            + r.z_axis * local.z;
        child_means.extend_from_slice(&m.to_array());
    }
    let shrink = 1.6f32.ln();
    state.apply_remap(&remap);
    let first = remap.first_appended();
    let scene = &mut state.scene;
    scene.means[3 * first..].copy_from_slice(&child_means);
    for v in &mut scene.log_scales[3 * first..] {
        *v -= shrink;
    }
    parents
}

/// Removes the selected Gaussians with all their per-Gaussian state.
pub(crate) fn prune(state: &mut TrainState, selected: &[bool]) -> usize {
    let remap = Remap::remove(selected);
    let n = selected.iter().filter(|&&s| s).count();
    if n > 0 {
        state.apply_remap(&remap);
    }
    n
}

/// Clamps every opacity to at most `value` and zeroes the opacity moments (INRIA `reset_opacity`).
pub(crate) fn reset_opacity(state: &mut TrainState, value: f32) {
    let cap = (value / (1.0 - value)).ln();
    for v in &mut state.scene.opacity_logits {
        *v = v.min(cap);
    }
    state.adam.reset_group(Group::Opacity);
}

/// The INRIA trainer's / gsplat's default densification. Step numbers are 0-based (the step just taken),
/// as in gsplat's trainer.
#[derive(Clone, Debug, PartialEq)]
pub struct DefaultStrategy {
    /// Prune Gaussians whose opacity is below this.
    pub prune_opa: f32,
    /// Grow Gaussians whose mean NDC gradient norm is above this.
    pub grow_grad2d: f32,
    /// Clone (rather than split) Gaussians whose largest scale is at most this times the scene extent.
    pub grow_scale3d: f32,
    /// After the first opacity reset, prune Gaussians larger than this times the scene extent.
    pub prune_scale3d: f32,
    pub refine_start: u64,
    pub refine_stop: u64,
    pub refine_every: u64,
    /// Reset opacities every this many steps (0 = never).
    pub reset_every: u64,
    /// Skip refinements this many steps after a reset.
    pub pause_refine_after_reset: u64,
    /// Also reset opacities at `refine_start` (the INRIA trainer does this on white-background datasets).
    pub reset_at_refine_start: bool,
}

impl Default for DefaultStrategy {
    /// gsplat 1.5.3's defaults (= the INRIA trainer's: threshold 0.0002, percent_dense 0.01, densify from
    /// 500 until 15000 every 100, opacity reset every 3000). Unlike gsplat 1.5.3, the opacity reset really
    /// happens: its condition `step % reset_every == 0 & step > 0` parses as a chained comparison that is
    /// always false; the INRIA trainer resets.
    fn default() -> Self {
        Self {
            prune_opa: 0.005,
            grow_grad2d: 0.0002,
            grow_scale3d: 0.01,
            prune_scale3d: 0.1,
            refine_start: 500,
            refine_stop: 15_000,
            refine_every: 100,
            reset_every: 3000,
            pause_refine_after_reset: 0,
            reset_at_refine_start: false,
        }
    }
}

impl DefaultStrategy {
    /// Call after every backward pass with what that view rendered. Accumulates the statistics, and on
    /// refinement steps grows, prunes and resets.
    pub fn after_backward<R: Rng + ?Sized>(
        &self,
        state: &mut TrainState,
        step: u64,
        view: &RenderedView<'_>,
        rng: &mut R,
    ) -> Option<RefineReport> {
        if step >= self.refine_stop {
            return None;
        }
        state.stats.add(view, 1);
        let mut report = None;
        let paused =
            self.reset_every > 0 && step % self.reset_every < self.pause_refine_after_reset;
        if step > self.refine_start
            && self.refine_every > 0
            && step.is_multiple_of(self.refine_every)
            && !paused
        {
            let (cloned, split) = self.grow(state, rng);
            let pruned = self.prune(state, step);
            state.stats.clear();
            report = Some(RefineReport {
                cloned,
                split,
                pruned,
                opacity_reset: false,
            });
        }
        let reset = (self.reset_every > 0 && step > 0 && step.is_multiple_of(self.reset_every))
            || (self.reset_at_refine_start && step == self.refine_start);
        if reset {
            reset_opacity(state, 2.0 * self.prune_opa);
            report
                .get_or_insert_with(RefineReport::default)
                .opacity_reset = true;
        }
        report
    }

    /// Clones small and splits large Gaussians with a high mean gradient. Returns (cloned, split).
    pub fn grow<R: Rng + ?Sized>(&self, state: &mut TrainState, rng: &mut R) -> (usize, usize) {
        let grads = state.stats.average();
        let limit = self.grow_scale3d * state.extent;
        let n = state.len();
        let high: Vec<bool> = grads.iter().map(|&g| g > self.grow_grad2d).collect();
        let small: Vec<bool> = (0..n)
            .map(|i| max_scale(&state.scene, i) <= limit)
            .collect();
        let dup: Vec<bool> = (0..n).map(|i| high[i] && small[i]).collect();
        let mut to_split: Vec<bool> = (0..n).map(|i| high[i] && !small[i]).collect();
        let cloned = duplicate(state, &dup);
        // Copies made just now are not split.
        to_split.resize(state.len(), false);
        let split = split(state, &to_split, rng);
        (cloned, split)
    }

    /// Prunes transparent Gaussians and, after the first opacity reset, too large ones.
    pub(crate) fn prune(&self, state: &mut TrainState, step: u64) -> usize {
        let big = self.prune_scale3d * state.extent;
        let check_big = step > self.reset_every;
        let sel: Vec<bool> = (0..state.len())
            .map(|i| {
                state.scene.opacity(i) < self.prune_opa
                    || (check_big && max_scale(&state.scene, i) > big)
            })
            .collect();
        prune(state, &sel)
    }
}

/// GaussianEditor's densification during editing (docs/algorithm.md §3.4). Step numbers are GaussianEditor's
/// `true_global_step` (0-based).
#[derive(Clone, Debug, PartialEq)]
pub struct EditStrategy {
    pub densify_from: u64,
    /// Statistics and densification stop at this step (exclusive).
    pub densify_until: u64,
    pub interval: u64,
    /// Clone/split threshold on the mean gradient (GaussianEditor's `max_grad`; an empirical knob, see
    /// docs/algorithm.md §3.4 on loss scaling).
    pub max_grad: f32,
    /// Only the top fraction of the non-zero gradients may densify.
    pub max_densify_percent: f32,
    /// Prune masked Gaussians below this opacity.
    pub min_opacity: f32,
    /// Clone when the largest scale is at most this times the extent, else split.
    pub percent_dense: f32,
    /// Prune masked Gaussians larger than this times the extent.
    pub prune_scale3d: f32,
    /// Prune masked Gaussians whose screen radius exceeded this many pixels. GaussianEditor passes 5, but its
    /// `densification_postfix` zeroes the radii right before the check, so it never fires there; `None`
    /// reproduces that.
    pub max_screen_radius: Option<f32>,
}

impl Default for EditStrategy {
    /// The VcEdit scripts' values (densify from 100 until 1501 every 100, max_densify_percent 0.01,
    /// min_opacity 0.005, max_grad 5; percent_dense 0.01).
    fn default() -> Self {
        Self {
            densify_from: 100,
            densify_until: 1501,
            interval: 100,
            max_grad: 5.0,
            max_densify_percent: 0.01,
            min_opacity: 0.005,
            percent_dense: 0.01,
            prune_scale3d: 0.1,
            max_screen_radius: None,
        }
    }
}

impl EditStrategy {
    /// Call after every backward pass with what that view rendered. Accumulates statistics and densifies
    /// on densification steps.
    pub fn after_backward<R: Rng + ?Sized>(
        &self,
        state: &mut TrainState,
        step: u64,
        view: &RenderedView<'_>,
        rng: &mut R,
    ) -> Option<RefineReport> {
        if !self.tracks_stats_at(step) {
            return None;
        }
        state.stats.add(view, 1);
        if self.densifies_at(step) {
            Some(self.densify_and_prune(state, rng))
        } else {
            None
        }
    }

    /// Whether [`EditStrategy::after_backward`] densifies at `step` (a fit that keeps its state elsewhere
    /// brings it back to the host for those steps).
    pub fn densifies_at(&self, step: u64) -> bool {
        step < self.densify_until
            && step >= self.densify_from
            && self.interval > 0
            && step.is_multiple_of(self.interval)
    }

    /// Whether [`EditStrategy::after_backward`] accumulates statistics at `step`.
    pub fn tracks_stats_at(&self, step: u64) -> bool {
        step < self.densify_until
    }

    /// GaussianEditor's `densify_and_prune`: masked gradient statistics, top-quantile cut, clone, split,
    /// masked prune, then statistics cleared, anchors refreshed and the generation schedule advanced.
    pub(crate) fn densify_and_prune<R: Rng + ?Sized>(
        &self,
        state: &mut TrainState,
        rng: &mut R,
    ) -> RefineReport {
        let n = state.len();
        let mut grads = state.stats.average();
        if let Some(mask) = &state.trainable {
            for (g, &m) in grads.iter_mut().zip(mask) {
                if !m {
                    *g = 0.0;
                }
            }
        }
        if self.max_densify_percent < 1.0 && n > 0 {
            let nonzero = grads.iter().filter(|&&g| g != 0.0).count();
            let valid = nonzero as f64 * self.max_densify_percent as f64 / n as f64;
            let cut = quantile(&grads, 1.0 - valid);
            for g in &mut grads {
                if *g < cut {
                    *g = 0.0;
                }
            }
        }
        let limit = self.percent_dense * state.extent;
        let trainable =
            |state: &TrainState, i: usize| state.trainable.as_ref().is_none_or(|m| m[i]);
        let dup: Vec<bool> = (0..n)
            .map(|i| {
                grads[i] >= self.max_grad
                    && max_scale(&state.scene, i) <= limit
                    && trainable(state, i)
            })
            .collect();
        let cloned = duplicate(state, &dup);
        // The clones have no gradient yet (GaussianEditor pads with zeros).
        let split_sel: Vec<bool> = (0..state.len())
            .map(|i| {
                i < n
                    && grads[i] >= self.max_grad
                    && max_scale(&state.scene, i) > limit
                    && trainable(state, i)
            })
            .collect();
        let split = split(state, &split_sel, rng);

        let big = self.prune_scale3d * state.extent;
        let prune_sel: Vec<bool> = (0..state.len())
            .map(|i| {
                let bad = state.scene.opacity(i) < self.min_opacity
                    || max_scale(&state.scene, i) > big
                    || self
                        .max_screen_radius
                        .is_some_and(|r| state.stats.max_radius[i] > r);
                bad && trainable(state, i)
            })
            .collect();
        let pruned = prune(state, &prune_sel);
        state.stats.clear();
        if let Some(anchor) = &mut state.anchor {
            anchor.finish_densify(&state.scene);
        }
        RefineReport {
            cloned,
            split,
            pruned,
            opacity_reset: false,
        }
    }
}

/// torch.quantile with linear interpolation (q in [0, 1]).
fn quantile(values: &[f32], q: f64) -> f32 {
    let mut sorted: Vec<f32> = values.to_vec();
    sorted.sort_by(f32::total_cmp);
    let q = q.clamp(0.0, 1.0);
    let pos = q * (sorted.len() - 1) as f64;
    let lo = pos.floor() as usize;
    let hi = pos.ceil() as usize;
    let frac = (pos - lo as f64) as f32;
    sorted[lo] + (sorted[hi] - sorted[lo]) * frac
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::SceneGrads;
    use crate::train::anchor::{Anchor, AnchorConfig};
    use crate::train::optim::LearningRates;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    fn scene(n: usize) -> GaussianScene {
        let k = 4;
        GaussianScene {
            sh_degree: 1,
            means: (0..3 * n).map(|i| i as f32).collect(),
            log_scales: (0..n)
                .flat_map(|i| {
                    let s = (0.004 * (i + 1) as f32).ln();
                    [s, s - 0.5, s - 1.0]
                })
                .collect(),
            quats: (0..n)
                .flat_map(|i| [1.0, 0.1 * i as f32, -0.2, 0.3])
                .collect(),
            opacity_logits: (0..n).map(|i| i as f32 - 2.0).collect(),
            sh: (0..3 * k * n).map(|i| i as f32 * 0.01).collect(),
        }
    }

    fn state(n: usize) -> TrainState {
        let mut st = TrainState::new(scene(n), LearningRates::inria(1000), 1.0);
        st.trainable = Some((0..n).map(|i| i % 4 != 3).collect());
        st.anchor = Some(Anchor::new(&st.scene, AnchorConfig::vcedit()));
        st
    }

    /// A 10 x 10 view with these gradients and radii.
    fn view<'a>(grads: &'a SceneGrads, radii: &'a [u32]) -> RenderedView<'a> {
        RenderedView {
            means2d: &grads.means2d,
            radii,
            width: 10,
            height: 10,
        }
    }

    fn grads_for(st: &TrainState, f: impl Fn(usize) -> f32) -> SceneGrads {
        let s = &st.scene;
        SceneGrads {
            means: vec![0.5; s.means.len()],
            log_scales: vec![0.5; s.log_scales.len()],
            quats: vec![0.5; s.quats.len()],
            opacity_logits: vec![0.5; s.len()],
            sh: vec![0.5; s.sh.len()],
            extra: Vec::new(),
            means2d: (0..s.len()).map(|i| [f(i), 0.0]).collect(),
        }
    }

    #[test]
    fn duplicate_copies_params_with_fresh_moments() {
        let mut st = state(4);
        let g = grads_for(&st, |_| 0.0);
        st.step(&g);
        let before = st.scene.clone();
        let n = duplicate(&mut st, &[false, true, false, true]);
        assert_eq!(n, 2);
        st.check().unwrap();
        assert_eq!(st.len(), 6);
        assert_eq!(st.scene.mean(4), before.mean(1));
        assert_eq!(st.scene.mean(5), before.mean(3));
        assert_eq!(&st.scene.sh[4 * 12..5 * 12], &before.sh[12..24]);
        assert_eq!(st.scene.opacity_logits[5], before.opacity_logits[3]);
        // Survivors keep their moments (Gaussian 3 is masked out, so it has none); copies start at zero.
        let m = st.adam.exp_avg(Group::Means);
        assert!(m[..9].iter().all(|&v| v != 0.0));
        assert!(m[9..].iter().all(|&v| v == 0.0));
        // Masks follow the source; generations are new.
        assert!(!st.trainable.as_ref().unwrap()[5]);
        assert!(st.trainable.as_ref().unwrap()[4]);
        assert_eq!(
            st.anchor.as_ref().unwrap().generations,
            vec![0, 0, 0, 0, 1, 1]
        );
    }

    #[test]
    fn split_children_sample_around_parent() {
        let mut st = state(3);
        let parent = 1;
        let pm = st.scene.mean(parent);
        let ps = st.scene.scale(parent);
        let pq = st.scene.quats[4 * parent..4 * parent + 4].to_vec();
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let n = split(&mut st, &[false, true, false], &mut rng);
        assert_eq!(n, 1);
        st.check().unwrap();
        assert_eq!(st.len(), 4);
        // Survivors first: old 0 and 2.
        assert_eq!(st.scene.mean(0), scene(3).mean(0));
        assert_eq!(st.scene.mean(1), scene(3).mean(2));
        for c in 2..4 {
            let s = st.scene.scale(c);
            for a in 0..3 {
                assert!((s[a] - ps[a] / 1.6).abs() < 1e-6 * ps[a].max(1.0));
            }
            assert_eq!(&st.scene.quats[4 * c..4 * c + 4], &pq[..]);
            // Offset in the parent's local frame is within a few standard deviations.
            let m = st.scene.mean(c);
            let d: Vec<f32> = (0..3).map(|a| m[a] - pm[a]).collect();
            assert!(d.iter().any(|&v| v != 0.0));
            let dist = d.iter().map(|v| v * v).sum::<f32>().sqrt();
            assert!(dist < 6.0 * ps[0], "child {c} at distance {dist}");
        }
        // Children differ from each other.
        assert_ne!(st.scene.mean(2), st.scene.mean(3));

        // Statistically: offsets rotated back into the parent frame have the parent's per-axis spread.
        let mut big = TrainState::new(scene(1), LearningRates::inria(10), 1.0);
        big.scene.log_scales = vec![0.0, (0.5f32).ln(), (0.1f32).ln()];
        big.scene.quats = vec![0.9, 0.3, -0.2, 0.1];
        let r = rotation(&big.scene, 0);
        let copies = 4000;
        let mut st2 = big.clone();
        duplicate_n(&mut st2, copies - 1);
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        split(&mut st2, &vec![true; copies], &mut rng);
        let mut var = [0.0f64; 3];
        for c in 0..st2.len() {
            let m = st2.scene.mean(c);
            for (a, v) in var.iter_mut().enumerate() {
                // local = Rᵀ (m − mean)
                let l: f32 = (0..3)
                    .map(|b| r.col(a)[b] * (m[b] - big.scene.means[b]))
                    .sum();
                *v += (l as f64).powi(2);
            }
        }
        let want = [1.0, 0.25, 0.01];
        for a in 0..3 {
            let v = var[a] / st2.len() as f64;
            assert!(
                (v - want[a]).abs() < 0.08 * want[a],
                "axis {a}: variance {v}"
            );
        }
    }

    fn duplicate_n(st: &mut TrainState, extra: usize) {
        let src = Remap {
            keep: vec![true; st.len()],
            appended: vec![0; extra],
        };
        st.apply_remap(&src);
    }

    #[test]
    fn prune_drops_all_per_gaussian_state() {
        let mut st = state(5);
        let g = grads_for(&st, |i| i as f32);
        st.step(&g);
        st.stats.add(&view(&g, &[1; 5]), 1);
        let before = st.scene.clone();
        let n = prune(&mut st, &[true, false, false, true, false]);
        assert_eq!(n, 2);
        st.check().unwrap();
        assert_eq!(st.len(), 3);
        assert_eq!(st.scene.mean(0), before.mean(1));
        assert_eq!(st.scene.mean(2), before.mean(4));
        assert_eq!(st.stats.grad2d, vec![5.0, 10.0, 20.0]);
        assert_eq!(st.trainable.as_ref().unwrap(), &vec![true, true, true]);
    }

    #[test]
    fn default_strategy_grows_prunes_and_is_deterministic() {
        let run = |seed: u64| {
            let mut st = TrainState::new(scene(8), LearningRates::inria(1000), 1.0);
            let strategy = DefaultStrategy {
                refine_start: 0,
                refine_every: 2,
                ..Default::default()
            };
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            // Even Gaussians get a large gradient: (1e-4 px⁻¹ · 10/2 = 5e-4 > 2e-4).
            let g = grads_for(&st, |i| if i % 2 == 0 { 1e-4 } else { 1e-6 });
            let radii = vec![3; 8];
            assert!(strategy
                .after_backward(&mut st, 1, &view(&g, &radii), &mut rng)
                .is_none());
            let report = strategy
                .after_backward(&mut st, 2, &view(&g, &radii), &mut rng)
                .unwrap();
            (st, report)
        };
        let (st, report) = run(3);
        st.check().unwrap();
        // Max scales are 0.004·(i+1): i = 0 (0.004) clones; i = 2, 4, 6 (≥ 0.012 > 0.01) split.
        assert_eq!(report.cloned, 1);
        assert_eq!(report.split, 3);
        // Opacity sigmoid(i − 2) < 0.005 for none of them.
        assert_eq!(report.pruned, 0);
        assert_eq!(st.len(), 8 + 1 + 3);
        assert!(st.stats.count.iter().all(|&c| c == 0.0));
        let (st2, _) = run(3);
        assert_eq!(st.scene, st2.scene);
        let (st3, _) = run(4);
        assert_ne!(st.scene, st3.scene);
    }

    #[test]
    fn opacity_reset_clamps_and_zeroes_state() {
        let mut st = TrainState::new(scene(4), LearningRates::inria(1000), 1.0);
        let g = grads_for(&st, |_| 0.0);
        st.step(&g);
        let strategy = DefaultStrategy::default();
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let radii = vec![0; 4];
        let r = strategy
            .after_backward(&mut st, 3000, &view(&g, &radii), &mut rng)
            .unwrap();
        assert!(r.opacity_reset);
        for i in 0..4 {
            assert!(st.scene.opacity(i) <= 0.01 + 1e-6);
        }
        // Gaussian 0 had opacity sigmoid(-2) = 0.12 > 0.01, so it was lowered; all moments are zero.
        assert!(st.adam.exp_avg(Group::Opacity).iter().all(|&v| v == 0.0));
        assert!(st.adam.exp_avg(Group::Means).iter().any(|&v| v != 0.0));
    }

    #[test]
    fn edit_strategy_respects_mask_and_quantile() {
        let mut st = state(8);
        // All large gradients; only the top 1% of non-zero ones survive the quantile cut → exactly one.
        let g = grads_for(&st, |i| 1.0 + i as f32);
        let strategy = EditStrategy {
            max_grad: 0.5,
            ..Default::default()
        };
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        st.stats.add(&view(&g, &[2; 8]), 1);
        let report = strategy.densify_and_prune(&mut st, &mut rng);
        st.check().unwrap();
        // Gaussian 7 is masked out (7 % 4 == 3); the largest masked gradient is Gaussian 6 (scale 0.028 >
        // 0.01·extent → split). The prune step removes masked-in Gaussians with opacity < 0.005: none.
        assert_eq!((report.cloned, report.split, report.pruned), (0, 1, 0));
        assert_eq!(st.len(), 9);
        let a = st.anchor.as_ref().unwrap();
        assert_eq!(&a.generations[7..], &[1, 1]);
        assert_eq!(a.schedule.len(), 2);
        assert_eq!(a.loss(&st.scene, st.trainable.as_deref(), None).total, 0.0);

        // Without the cut, every masked Gaussian with a high gradient grows; masked-out ones never.
        let mut st = state(8);
        let strategy = EditStrategy {
            max_grad: 0.5,
            max_densify_percent: 1.0,
            ..Default::default()
        };
        st.stats.add(&view(&g, &[2; 8]), 1);
        let report = strategy.densify_and_prune(&mut st, &mut rng);
        // Masked in: 0, 1, 2, 4, 5, 6. Scale 0.004·(i+1) ≤ 0.01 → clone for 0, 1; split 2, 4, 5, 6.
        assert_eq!((report.cloned, report.split), (2, 4));
        assert_eq!(st.len(), 8 + 2 + 4);
        assert!(st.trainable.as_ref().unwrap()[8..].iter().all(|&m| m));
        st.check().unwrap();
    }

    #[test]
    fn edit_strategy_prunes_only_masked() {
        let mut st = state(8);
        st.scene.opacity_logits = vec![-10.0; 8];
        let strategy = EditStrategy::default();
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let report = strategy.densify_and_prune(&mut st, &mut rng);
        assert_eq!(report.pruned, 6);
        assert_eq!(st.len(), 2);
        assert!(st.trainable.as_ref().unwrap().iter().all(|&m| !m));
    }

    #[test]
    fn quantile_is_linear() {
        assert_eq!(quantile(&[3.0, 1.0, 2.0, 4.0], 0.5), 2.5);
        assert_eq!(quantile(&[3.0, 1.0, 2.0, 4.0], 1.0), 4.0);
        assert_eq!(quantile(&[3.0, 1.0, 2.0, 4.0], 0.0), 1.0);
    }
}
