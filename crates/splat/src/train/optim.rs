//! Adam over the scene parameters with the INRIA trainer's per-attribute learning rates.
//!
//! The INRIA trainer (and GaussianEditor on top of it) keeps one torch Adam with six parameter groups:
//! positions, SH DC, SH rest, opacity logits, log-scales and quaternions, with eps = 1e-15 and the position
//! rate decaying log-linearly over training and scaled by the scene extent. This module reproduces that
//! update exactly (torch's bias-corrected form), with moments stored in the scene's own layouts.
//!
//! Differences from torch worth knowing:
//! - DC and rest SH coefficients share one array (`GaussianScene::sh`); the group of a coefficient is its
//!   index k (k = 0 is DC).
//! - Per-Gaussian trainable masks skip the masked-out Gaussians entirely: parameters *and* Adam moments stay
//!   untouched. GaussianEditor instead multiplies their gradients by 0 in hooks, which is the same thing as
//!   long as their moments start at zero (then torch's update is exactly 0); skipping also keeps state that
//!   another phase built up from decaying.

use crate::layout::{relayout_sh, Remap};
use crate::render::SceneGrads;
use crate::scene::GaussianScene;
use rayon::prelude::*;

/// The INRIA trainer's parameter groups.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Group {
    Means,
    ShDc,
    ShRest,
    Opacity,
    LogScales,
    Quats,
}

impl Group {
    pub const ALL: [Group; 6] = [
        Group::Means,
        Group::ShDc,
        Group::ShRest,
        Group::Opacity,
        Group::LogScales,
        Group::Quats,
    ];

    /// Position in [`Group::ALL`] (and in per-group arrays such as [`Adam::group_lr_scale`]).
    pub const fn index(self) -> usize {
        self as usize
    }

    /// Whether GaussianEditor's gradient hooks apply to this group (all but rotation,
    /// docs/algorithm.md §3.3).
    pub const fn hooked_by_mask(self) -> bool {
        !matches!(self, Group::Quats)
    }
}

/// The INRIA trainer's `get_expon_lr_func`: log-linear interpolation from `init` to `end` over `max_steps`,
/// optionally damped at the start by `delay_mult`, rising along a half sine over `delay_steps`.
#[derive(Clone, Debug, PartialEq)]
pub struct ExponentialLr {
    pub init: f32,
    pub end: f32,
    pub max_steps: u64,
    pub delay_steps: u64,
    pub delay_mult: f32,
}

impl ExponentialLr {
    /// The rate after `step` steps (clamped to `end` past `max_steps`).
    pub fn at(&self, step: u64) -> f32 {
        if self.init == 0.0 && self.end == 0.0 {
            return 0.0;
        }
        let delay = if self.delay_steps > 0 {
            let t = (step as f64 / self.delay_steps as f64).clamp(0.0, 1.0);
            let m = self.delay_mult as f64;
            m + (1.0 - m) * (0.5 * std::f64::consts::PI * t).sin()
        } else {
            1.0
        };
        let t = if self.max_steps == 0 {
            1.0
        } else {
            (step as f64 / self.max_steps as f64).clamp(0.0, 1.0)
        };
        let log_lerp = ((self.init as f64).ln() * (1.0 - t) + (self.end as f64).ln() * t).exp();
        (delay * log_lerp) as f32
    }
}

/// Per-group learning rates. The position schedule is in units of the scene extent (the trainer's
/// `spatial_lr_scale`); all others are absolute.
#[derive(Clone, Debug, PartialEq)]
pub struct LearningRates {
    pub means: ExponentialLr,
    pub sh_dc: f32,
    pub sh_rest: f32,
    pub opacity: f32,
    pub log_scales: f32,
    pub quats: f32,
}

impl LearningRates {
    /// The INRIA trainer's defaults (arguments/__init__.py): positions 1.6e-4 → 1.6e-6 over `max_steps`,
    /// f_dc 0.0025, f_rest 0.0025/20, opacity 0.05, scaling 0.005, rotation 0.001. Opacity: the original
    /// release and gsplat's simple_trainer use 0.05 (a 2024 INRIA update lowered it to 0.025); we keep 0.05.
    pub fn inria(max_steps: u64) -> Self {
        Self {
            means: ExponentialLr {
                init: 1.6e-4,
                end: 1.6e-6,
                max_steps,
                delay_steps: 0,
                delay_mult: 0.01,
            },
            sh_dc: 0.0025,
            sh_rest: 0.0025 / 20.0,
            opacity: 0.05,
            log_scales: 0.005,
            quats: 0.001,
        }
    }

    /// GaussianEditor's editing rates (docs/algorithm.md §3.4): positions 1.6e-4 → 1.6e-5 over
    /// `max_steps`, f_dc 0.0125, f_rest 0.0125/20, opacity 0.05, scaling 0.005, rotation 0.001.
    pub fn gaussian_editor(max_steps: u64) -> Self {
        Self {
            means: ExponentialLr {
                init: 1.6e-4,
                end: 1.6e-5,
                max_steps,
                delay_steps: 0,
                delay_mult: 0.01,
            },
            sh_dc: 0.0125,
            sh_rest: 0.0125 / 20.0,
            opacity: 0.05,
            log_scales: 0.005,
            quats: 0.001,
        }
    }
}

/// Adam hyper-parameters (torch defaults with the INRIA trainer's eps).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AdamParams {
    pub beta1: f32,
    pub beta2: f32,
    pub eps: f32,
}

impl Default for AdamParams {
    fn default() -> Self {
        Self {
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-15,
        }
    }
}

/// First and second moments of one parameter array.
#[derive(Clone, Debug, Default, PartialEq)]
pub(crate) struct Moments {
    pub(crate) m: Vec<f32>,
    pub(crate) v: Vec<f32>,
}

impl Moments {
    fn zeros(len: usize) -> Self {
        Self {
            m: vec![0.0; len],
            v: vec![0.0; len],
        }
    }
}

/// Adam over a [`GaussianScene`], one learning rate per [`Group`].
///
/// Learning rate of a group = base × `group_lr_scale[group]` × `lr_scale`, where the base is fixed per
/// group except for positions, whose base follows the exponential schedule at the iteration last given to
/// [`Adam::set_iteration`] times `extent`. The two scale knobs are for callers (e.g. a StepLR that halves
/// every rate every two epochs: multiply `lr_scale` by 0.5).
#[derive(Clone, Debug)]
pub struct Adam {
    pub rates: LearningRates,
    pub params: AdamParams,
    /// Scene extent that scales the position rate (the trainer's `spatial_lr_scale`).
    pub extent: f32,
    /// Multiplier on every group's rate.
    pub lr_scale: f32,
    /// Per-group multipliers, indexed by [`Group::index`].
    pub group_lr_scale: [f32; 6],
    /// Whether rotations of masked-out Gaussians are frozen too. GaussianEditor hooks every attribute but
    /// the rotation (docs/algorithm.md §3.3), so its behaviour is `false`.
    pub mask_rotation: bool,
    pub(crate) means_lr: f32,
    /// Steps taken (torch keeps it per parameter; all groups step together here).
    pub(crate) steps: u64,
    pub(crate) sh_coeffs: usize,
    pub(crate) means: Moments,
    pub(crate) log_scales: Moments,
    pub(crate) quats: Moments,
    pub(crate) opacity: Moments,
    pub(crate) sh: Moments,
}

impl Adam {
    /// Fresh optimiser (zero moments) for `scene`, at iteration 0 of the position schedule.
    pub fn new(scene: &GaussianScene, rates: LearningRates, extent: f32) -> Self {
        let n = scene.len();
        let means_lr = rates.means.at(0) * extent;
        Self {
            rates,
            params: AdamParams::default(),
            extent,
            lr_scale: 1.0,
            group_lr_scale: [1.0; 6],
            mask_rotation: false,
            means_lr,
            steps: 0,
            sh_coeffs: scene.sh_coeffs(),
            means: Moments::zeros(3 * n),
            log_scales: Moments::zeros(3 * n),
            quats: Moments::zeros(4 * n),
            opacity: Moments::zeros(n),
            sh: Moments::zeros(3 * scene.sh_coeffs() * n),
        }
    }

    /// Number of Gaussians the state is sized for.
    pub fn len(&self) -> usize {
        self.opacity.m.len()
    }

    pub fn is_empty(&self) -> bool {
        self.opacity.m.is_empty()
    }

    /// Adam steps taken so far.
    pub fn steps(&self) -> u64 {
        self.steps
    }

    /// Moves the position rate to the schedule's value at `iteration` (the trainer's
    /// `update_learning_rate`). Callers that want a frozen rate simply stop calling it.
    pub fn set_iteration(&mut self, iteration: u64) {
        self.means_lr = self.rates.means.at(iteration) * self.extent;
    }

    /// The effective learning rate of a group.
    pub fn lr(&self, group: Group) -> f32 {
        let base = match group {
            Group::Means => self.means_lr,
            Group::ShDc => self.rates.sh_dc,
            Group::ShRest => self.rates.sh_rest,
            Group::Opacity => self.rates.opacity,
            Group::LogScales => self.rates.log_scales,
            Group::Quats => self.rates.quats,
        };
        base * self.group_lr_scale[group.index()] * self.lr_scale
    }

    /// Whether a step at these rates leaves the means, scales and rotations as they are (their rates
    /// are all 0), so each view's projected geometry stays valid.
    pub fn geometry_fixed(&self) -> bool {
        [Group::Means, Group::LogScales, Group::Quats]
            .iter()
            .all(|&g| self.lr(g) == 0.0)
    }

    /// One Adam step on every parameter. `trainable` (one flag per Gaussian) freezes the others in the
    /// groups the mask hooks (see [`Group::hooked_by_mask`] and `mask_rotation`).
    ///
    /// # Panics
    /// When the scene, gradients, mask and state disagree in size (programming errors).
    pub fn step(
        &mut self,
        scene: &mut GaussianScene,
        grads: &SceneGrads,
        trainable: Option<&[bool]>,
    ) {
        let n = scene.len();
        assert_eq!(self.len(), n, "optimiser state sized for another scene");
        assert_eq!(
            self.sh_coeffs,
            scene.sh_coeffs(),
            "optimiser state sized for another SH degree"
        );
        assert_eq!(grads.means.len(), 3 * n, "means gradient size");
        assert_eq!(grads.log_scales.len(), 3 * n, "log_scales gradient size");
        assert_eq!(grads.quats.len(), 4 * n, "quats gradient size");
        assert_eq!(grads.opacity_logits.len(), n, "opacity gradient size");
        assert_eq!(grads.sh.len(), scene.sh.len(), "sh gradient size");
        if let Some(t) = trainable {
            assert_eq!(t.len(), n, "trainable mask size");
        }
        self.steps += 1;
        let t = self.steps as i32;
        let p = self.params;
        let bias1 = 1.0 - (p.beta1 as f64).powi(t);
        let bias2 = 1.0 - (p.beta2 as f64).powi(t);
        let hyper = StepHyper {
            beta1: p.beta1,
            beta2: p.beta2,
            eps: p.eps,
            inv_bias1: (1.0 / bias1) as f32,
            inv_sqrt_bias2: (1.0 / bias2.sqrt()) as f32,
        };
        let rot_mask = if self.mask_rotation { trainable } else { None };
        let lr_means = [self.lr(Group::Means)];
        let lr_scales = [self.lr(Group::LogScales)];
        let lr_quats = [self.lr(Group::Quats)];
        let lr_opacity = [self.lr(Group::Opacity)];
        // One rate per SH coefficient k: DC for k = 0, rest otherwise.
        let lr_sh: Vec<f32> = (0..self.sh_coeffs)
            .map(|k| {
                if k == 0 {
                    self.lr(Group::ShDc)
                } else {
                    self.lr(Group::ShRest)
                }
            })
            .collect();
        let k = self.sh_coeffs;
        adam_update(
            &mut scene.means,
            &grads.means,
            &mut self.means,
            3,
            &lr_means,
            trainable,
            hyper,
        );
        adam_update(
            &mut scene.log_scales,
            &grads.log_scales,
            &mut self.log_scales,
            3,
            &lr_scales,
            trainable,
            hyper,
        );
        adam_update(
            &mut scene.quats,
            &grads.quats,
            &mut self.quats,
            4,
            &lr_quats,
            rot_mask,
            hyper,
        );
        adam_update(
            &mut scene.opacity_logits,
            &grads.opacity_logits,
            &mut self.opacity,
            1,
            &lr_opacity,
            trainable,
            hyper,
        );
        adam_update(
            &mut scene.sh,
            &grads.sh,
            &mut self.sh,
            3 * k,
            &lr_sh,
            trainable,
            hyper,
        );
    }

    /// Zeroes the moments of one group (the trainer's `replace_tensor_to_optimizer`, used by the opacity
    /// reset). The step count is kept, as torch keeps it.
    pub(crate) fn reset_group(&mut self, group: Group) {
        fn zero(m: &mut Moments) {
            m.m.iter_mut().for_each(|x| *x = 0.0);
            m.v.iter_mut().for_each(|x| *x = 0.0);
        }
        match group {
            Group::Means => zero(&mut self.means),
            Group::LogScales => zero(&mut self.log_scales),
            Group::Quats => zero(&mut self.quats),
            Group::Opacity => zero(&mut self.opacity),
            Group::ShDc | Group::ShRest => {
                let k = self.sh_coeffs;
                let dc = group == Group::ShDc;
                for (i, (m, v)) in self.sh.m.iter_mut().zip(self.sh.v.iter_mut()).enumerate() {
                    if ((i / 3) % k == 0) == dc {
                        *m = 0.0;
                        *v = 0.0;
                    }
                }
            }
        }
    }

    /// Follows a densification: survivors keep their moments, new Gaussians start at zero (as the
    /// trainer's `cat_tensors_to_optimizer` does).
    pub(crate) fn remap(&mut self, remap: &Remap) {
        assert_eq!(remap.old_len(), self.len(), "remap of another size");
        let k3 = 3 * self.sh_coeffs;
        for (mom, width) in [
            (&mut self.means, 3),
            (&mut self.log_scales, 3),
            (&mut self.quats, 4),
            (&mut self.opacity, 1),
            (&mut self.sh, k3),
        ] {
            remap.apply_fill(&mut mom.m, width, 0.0);
            remap.apply_fill(&mut mom.v, width, 0.0);
        }
    }

    /// A copy of the first moments (torch's `exp_avg`) of one group, in the scene's layout order.
    #[cfg(test)]
    pub(crate) fn exp_avg(&self, group: Group) -> Vec<f32> {
        match group {
            Group::Means => self.means.m.clone(),
            Group::LogScales => self.log_scales.m.clone(),
            Group::Quats => self.quats.m.clone(),
            Group::Opacity => self.opacity.m.clone(),
            Group::ShDc | Group::ShRest => {
                let k = self.sh_coeffs;
                let dc = group == Group::ShDc;
                self.sh
                    .m
                    .iter()
                    .enumerate()
                    .filter(|(i, _)| ((i / 3) % k == 0) == dc)
                    .map(|(_, &v)| v)
                    .collect()
            }
        }
    }

    /// Re-lays the SH moments for a scene whose SH degree changed to `degree` (coefficients kept where
    /// both layouts have them, new ones start at zero).
    pub(crate) fn set_sh_degree(&mut self, degree: u32) {
        let new_k = crate::scene::sh_coeffs(degree);
        self.sh.m = relayout_sh(&self.sh.m, self.sh_coeffs, new_k);
        self.sh.v = relayout_sh(&self.sh.v, self.sh_coeffs, new_k);
        self.sh_coeffs = new_k;
    }
}

#[derive(Clone, Copy)]
struct StepHyper {
    beta1: f32,
    beta2: f32,
    eps: f32,
    inv_bias1: f32,
    inv_sqrt_bias2: f32,
}

/// torch's Adam update for one array of `width` values per Gaussian. `lrs` splits a Gaussian's block into
/// equal runs with one rate each (so SH can give each coefficient k, three values, its own rate).
fn adam_update(
    params: &mut [f32],
    grads: &[f32],
    mom: &mut Moments,
    width: usize,
    lrs: &[f32],
    trainable: Option<&[bool]>,
    h: StepHyper,
) {
    if width == 0 || params.is_empty() {
        return;
    }
    let group = width / lrs.len();
    debug_assert_eq!(width, group * lrs.len());
    // Enough Gaussians per task to amortise rayon's overhead.
    let per_task = (8192 / width).max(1);
    let chunk = per_task * width;
    params
        .par_chunks_mut(chunk)
        .zip(grads.par_chunks(chunk))
        .zip(mom.m.par_chunks_mut(chunk))
        .zip(mom.v.par_chunks_mut(chunk))
        .enumerate()
        .for_each(|(ci, (((p, g), m), v))| {
            let first = ci * per_task;
            for (j, (((pb, gb), mb), vb)) in p
                .chunks_exact_mut(width)
                .zip(g.chunks_exact(width))
                .zip(m.chunks_exact_mut(width))
                .zip(v.chunks_exact_mut(width))
                .enumerate()
            {
                if let Some(t) = trainable {
                    if !t[first + j] {
                        continue;
                    }
                }
                for e in 0..width {
                    let lr = lrs[e / group];
                    let gr = gb[e];
                    let mi = h.beta1 * mb[e] + (1.0 - h.beta1) * gr;
                    let vi = h.beta2 * vb[e] + (1.0 - h.beta2) * gr * gr;
                    mb[e] = mi;
                    vb[e] = vi;
                    let denom = vi.sqrt() * h.inv_sqrt_bias2 + h.eps;
                    pb[e] -= lr * h.inv_bias1 * mi / denom;
                }
            }
        });
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scene(n: usize, degree: u32) -> GaussianScene {
        let k = crate::scene::sh_coeffs(degree);
        GaussianScene {
            sh_degree: degree,
            means: (0..3 * n).map(|i| i as f32 * 0.1).collect(),
            log_scales: vec![-2.0; 3 * n],
            quats: (0..n).flat_map(|_| [1.0, 0.0, 0.0, 0.0]).collect(),
            opacity_logits: vec![0.0; n],
            sh: (0..3 * k * n).map(|i| (i % 7) as f32 * 0.01).collect(),
        }
    }

    fn grads_like(s: &GaussianScene, f: impl Fn(usize) -> f32) -> SceneGrads {
        let mk = |len: usize, off: usize| (0..len).map(|i| f(i + off)).collect::<Vec<_>>();
        SceneGrads {
            means: mk(s.means.len(), 0),
            log_scales: mk(s.log_scales.len(), 100),
            quats: mk(s.quats.len(), 200),
            opacity_logits: mk(s.opacity_logits.len(), 300),
            sh: mk(s.sh.len(), 400),
            extra: Vec::new(),
            means2d: vec![[0.0; 2]; s.len()],
        }
    }

    /// Straightforward scalar Adam (torch's formula) in f64 for comparison.
    fn reference_adam(p: &mut f64, m: &mut f64, v: &mut f64, g: f64, lr: f64, t: i32) {
        let (b1, b2, eps) = (0.9f64, 0.999f64, 1e-15f64);
        *m = b1 * *m + (1.0 - b1) * g;
        *v = b2 * *v + (1.0 - b2) * g * g;
        let step = lr / (1.0 - b1.powi(t));
        let denom = (*v).sqrt() / (1.0 - b2.powi(t)).sqrt() + eps;
        *p -= step * *m / denom;
    }

    #[test]
    fn expon_lr_matches_trainer_formula() {
        let s = LearningRates::inria(30_000).means;
        assert!((s.at(0) - 1.6e-4).abs() < 1e-10);
        assert!((s.at(30_000) - 1.6e-6).abs() < 1e-12);
        assert!((s.at(60_000) - 1.6e-6).abs() < 1e-12);
        // Log-linear: the midpoint is the geometric mean.
        assert!((s.at(15_000) - 1.6e-5).abs() < 1e-10);
        let delayed = ExponentialLr {
            delay_steps: 100,
            ..s.clone()
        };
        assert!((delayed.at(0) - 0.01 * 1.6e-4).abs() < 1e-11);
        assert!((delayed.at(100) - s.at(100)).abs() < 1e-12);
        assert!(delayed.at(50) < s.at(50) && delayed.at(50) > delayed.at(0));
    }

    #[test]
    fn step_matches_reference_adam_per_group() {
        let mut s = scene(5, 1);
        let orig = s.clone();
        let extent = 2.5;
        let mut adam = Adam::new(&s, LearningRates::gaussian_editor(1000), extent);
        adam.set_iteration(10);
        let g1 = grads_like(&s, |i| ((i * 31 % 17) as f32 - 8.0) * 0.01);
        let g2 = grads_like(&s, |i| ((i * 13 % 11) as f32 - 5.0) * 0.02);
        adam.step(&mut s, &g1, None);
        adam.step(&mut s, &g2, None);

        let lr_means = LearningRates::gaussian_editor(1000).means.at(10) as f64 * extent as f64;
        let check =
            |got: &[f32], orig: &[f32], ga: &[f32], gb: &[f32], lr: &dyn Fn(usize) -> f64| {
                for i in 0..got.len() {
                    let (mut p, mut m, mut v) = (orig[i] as f64, 0.0, 0.0);
                    reference_adam(&mut p, &mut m, &mut v, ga[i] as f64, lr(i), 1);
                    reference_adam(&mut p, &mut m, &mut v, gb[i] as f64, lr(i), 2);
                    assert!(
                        (got[i] as f64 - p).abs() < 1e-6 * (1.0 + p.abs()),
                        "{i}: {} vs {p}",
                        got[i]
                    );
                }
            };
        check(&s.means, &orig.means, &g1.means, &g2.means, &|_| lr_means);
        check(
            &s.log_scales,
            &orig.log_scales,
            &g1.log_scales,
            &g2.log_scales,
            &|_| 0.005,
        );
        check(&s.quats, &orig.quats, &g1.quats, &g2.quats, &|_| 0.001);
        check(
            &s.opacity_logits,
            &orig.opacity_logits,
            &g1.opacity_logits,
            &g2.opacity_logits,
            &|_| 0.05,
        );
        // Degree 1: 4 coefficients per channel; index (n*4 + k)*3 + c.
        check(&s.sh, &orig.sh, &g1.sh, &g2.sh, &|i| {
            if (i / 3) % 4 == 0 {
                0.0125
            } else {
                0.0125 / 20.0
            }
        });
    }

    #[test]
    fn masked_gaussians_keep_params_and_state() {
        let mut s = scene(4, 0);
        let orig = s.clone();
        let mut adam = Adam::new(&s, LearningRates::inria(100), 1.0);
        let mask = [true, false, true, false];
        let g = grads_like(&s, |_| 0.3);
        adam.step(&mut s, &g, Some(&mask));
        for (i, &m) in mask.iter().enumerate() {
            let moved = s.mean(i) != orig.mean(i);
            assert_eq!(moved, m, "means of {i}");
            assert_eq!(s.opacity_logits[i] != orig.opacity_logits[i], m);
            assert_eq!(s.log_scales[3 * i] != orig.log_scales[3 * i], m);
            assert_eq!(s.sh[3 * i] != orig.sh[3 * i], m);
            // Rotation is not hooked by default: it moves for everyone.
            assert_ne!(s.quats[4 * i], orig.quats[4 * i]);
            assert_eq!(adam.means.m[3 * i] != 0.0, m);
        }
        // With mask_rotation the quaternions follow the mask too.
        let mut s2 = orig.clone();
        let mut adam2 = Adam::new(&s2, LearningRates::inria(100), 1.0);
        adam2.mask_rotation = true;
        adam2.step(&mut s2, &g, Some(&mask));
        for (i, &m) in mask.iter().enumerate() {
            assert_eq!(s2.quats[4 * i] != orig.quats[4 * i], m);
        }
    }

    #[test]
    fn lr_scales_and_group_reset() {
        let s = scene(3, 1);
        let mut adam = Adam::new(&s, LearningRates::inria(100), 3.0);
        assert!((adam.lr(Group::Means) - 1.6e-4 * 3.0).abs() < 1e-9);
        adam.lr_scale = 0.5;
        adam.group_lr_scale[Group::Opacity.index()] = 2.0;
        assert!((adam.lr(Group::Opacity) - 0.05).abs() < 1e-9);
        assert!((adam.lr(Group::ShRest) - 0.0025 / 40.0).abs() < 1e-9);

        let mut s = s;
        let g = grads_like(&s, |_| 0.1);
        adam.step(&mut s, &g, None);
        adam.reset_group(Group::Opacity);
        assert!(adam.opacity.m.iter().all(|&v| v == 0.0));
        assert!(adam.means.m.iter().all(|&v| v != 0.0));
        adam.reset_group(Group::ShDc);
        for (i, &m) in adam.sh.m.iter().enumerate() {
            assert_eq!(m == 0.0, (i / 3) % 4 == 0, "sh moment {i}");
        }
        assert_eq!(adam.steps(), 1);
    }
}
