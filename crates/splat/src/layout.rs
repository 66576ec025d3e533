//! The per-Gaussian layout of parameter arrays, and the two ways it changes during training:
//!
//! - a structural change of the Gaussian set ([`Remap`]: clone, split, prune), which every array with one
//!   block per Gaussian must follow (parameters, optimiser moments, statistics, masks, anchors);
//! - a change of SH degree ([`relayout_sh`]), which re-lays every per-Gaussian SH block.
//!
//! It sits below everything that owns such arrays (optimiser, anchors, training state, densification), so
//! they can all follow the same change without knowing about each other.

use crate::scene::GaussianScene;

/// One structural change of the Gaussian set: the old Gaussians with `keep` set, in order, followed by
/// copies of the old Gaussians `appended` (old indices, possibly repeated).
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) struct Remap {
    pub keep: Vec<bool>,
    pub appended: Vec<usize>,
}

impl Remap {
    /// Keeps everything and appends a copy of each selected Gaussian.
    pub fn duplicate(selected: &[bool]) -> Self {
        Self {
            keep: vec![true; selected.len()],
            appended: indices(selected),
        }
    }

    /// Removes the selected Gaussians and appends two copies of each (first copies of all, then second
    /// copies, as gsplat orders them).
    pub fn split(selected: &[bool]) -> Self {
        let sel = indices(selected);
        let mut appended = sel.clone();
        appended.extend_from_slice(&sel);
        Self {
            keep: selected.iter().map(|&s| !s).collect(),
            appended,
        }
    }

    /// Removes the selected Gaussians.
    pub fn remove(selected: &[bool]) -> Self {
        Self {
            keep: selected.iter().map(|&s| !s).collect(),
            appended: Vec::new(),
        }
    }

    pub fn old_len(&self) -> usize {
        self.keep.len()
    }

    pub fn new_len(&self) -> usize {
        self.keep.iter().filter(|&&k| k).count() + self.appended.len()
    }

    /// Index in the new order of the first appended Gaussian.
    pub fn first_appended(&self) -> usize {
        self.new_len() - self.appended.len()
    }

    /// Applies the change to an array of `width` values per Gaussian; appended entries copy their source.
    ///
    /// # Panics
    /// When `v` does not hold `old_len() * width` values.
    pub fn apply<T: Clone>(&self, v: &mut Vec<T>, width: usize) {
        assert_eq!(v.len(), self.old_len() * width, "remap: array length");
        let mut extra = Vec::with_capacity(self.appended.len() * width);
        for &src in &self.appended {
            extra.extend_from_slice(&v[src * width..(src + 1) * width]);
        }
        self.retain(v, width);
        v.extend(extra);
    }

    /// Like [`Remap::apply`], but appended entries are set to `fill`.
    pub fn apply_fill<T: Clone>(&self, v: &mut Vec<T>, width: usize, fill: T) {
        assert_eq!(v.len(), self.old_len() * width, "remap: array length");
        self.retain(v, width);
        v.resize(v.len() + self.appended.len() * width, fill);
    }

    fn retain<T: Clone>(&self, v: &mut Vec<T>, width: usize) {
        let mut w = 0;
        for (i, &k) in self.keep.iter().enumerate() {
            if k {
                if w != i {
                    for e in 0..width {
                        v[w * width + e] = v[i * width + e].clone();
                    }
                }
                w += 1;
            }
        }
        v.truncate(w * width);
    }
}

fn indices(selected: &[bool]) -> Vec<usize> {
    selected
        .iter()
        .enumerate()
        .filter_map(|(i, &s)| s.then_some(i))
        .collect()
}

/// Applies a [`Remap`] to every parameter array of a scene (new Gaussians copy their source).
pub(crate) fn remap_scene(scene: &mut GaussianScene, remap: &Remap) {
    let k3 = 3 * scene.sh_coeffs();
    remap.apply(&mut scene.means, 3);
    remap.apply(&mut scene.log_scales, 3);
    remap.apply(&mut scene.quats, 4);
    remap.apply(&mut scene.opacity_logits, 1);
    remap.apply(&mut scene.sh, k3);
}

/// Copies per-Gaussian SH blocks of `old_k` coefficients into blocks of `new_k` (truncating or padding
/// with zeros).
pub(crate) fn relayout_sh(sh: &[f32], old_k: usize, new_k: usize) -> Vec<f32> {
    if old_k == new_k {
        return sh.to_vec();
    }
    let n = sh.len() / (3 * old_k).max(1);
    let keep = 3 * old_k.min(new_k);
    let mut out = vec![0.0; 3 * new_k * n];
    for (dst, src) in out
        .chunks_exact_mut(3 * new_k)
        .zip(sh.chunks_exact(3 * old_k))
    {
        dst[..keep].copy_from_slice(&src[..keep]);
    }
    out
}

/// Changes a scene's SH degree: coefficients both degrees have are kept, new ones start at zero, removed
/// ones are dropped.
pub(crate) fn set_scene_sh_degree(scene: &mut GaussianScene, degree: u32) {
    let new_k = crate::scene::sh_coeffs(degree);
    scene.sh = relayout_sh(&scene.sh, scene.sh_coeffs(), new_k);
    scene.sh_degree = degree;
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn remap_apply_orders_survivors_then_copies() {
        let r = Remap {
            keep: vec![true, false, true, true],
            appended: vec![1, 3, 1],
        };
        let mut v = vec![0, 0, 1, 1, 2, 2, 3, 3];
        r.apply(&mut v, 2);
        assert_eq!(v, vec![0, 0, 2, 2, 3, 3, 1, 1, 3, 3, 1, 1]);
        let mut w = vec![10, 11, 12, 13];
        r.apply_fill(&mut w, 1, -1);
        assert_eq!(w, vec![10, 12, 13, -1, -1, -1]);
        assert_eq!(r.new_len(), 6);
        assert_eq!(r.first_appended(), 3);
    }

    #[test]
    fn sh_degree_change_keeps_low_coefficients() {
        let sh: Vec<f32> = (0..2 * 3 * 4).map(|i| i as f32).collect();
        let up = relayout_sh(&sh, 4, 9);
        assert_eq!(up.len(), 2 * 27);
        assert_eq!(&up[..12], &sh[..12]);
        assert!(up[12..27].iter().all(|&v| v == 0.0));
        assert_eq!(&up[27..39], &sh[12..24]);
        assert_eq!(relayout_sh(&up, 9, 4), sh);
    }
}
