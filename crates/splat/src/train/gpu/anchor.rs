//! The gradient of the HGS anchor loss on the device: what [`Anchor::loss`] adds into the gradients,
//! λ·2·w·(P − P̂)/denom per element, with the anchored parameters, the per-Gaussian weights and the
//! per-term factors uploaded once (they change only at a densification, after which the device trainer
//! is rebuilt). The loss value itself is not computed: the fits never read it.

use crate::render::gpu::{GpuScene, GpuSceneGrads};
use crate::train::anchor::Anchor;
use ::gpu::cubecl;
use ::gpu::cubecl::prelude::*;
use ::gpu::cubecl::server::Handle;
use ::gpu::gpu_call;
use ::gpu::prims::arg;
use ::gpu::prims::{grid, upload_f32};
use ::gpu::{GpuContext, GpuError};

/// Adds `coef·w·(params − anchor)` into `grads` for an array of `width` values per Gaussian; the first
/// `first` values of each block use `coef_first`, the rest `coef_rest` (SH: DC and higher coefficients,
/// two terms of the loss with their own denominators). `weights` is 0 for Gaussians outside the loss.
#[cube(launch)]
fn anchor_grad(
    params: &[f32],
    anchor: &[f32],
    weights: &[f32],
    grads: &mut [f32],
    len: u32,
    width: u32,
    first: u32,
    coef_first: f32,
    coef_rest: f32,
) {
    let i = ABSOLUTE_POS;
    if i < len as usize {
        let w = weights[i / width as usize];
        if w != 0.0 {
            let coef = select((i as u32 % width) < first, coef_first, coef_rest);
            let d = params[i] - anchor[i];
            grads[i] += coef * (w * d);
        }
    }
}

/// λ·2/denom of each term of [`Anchor::loss`] (0 when the term adds nothing).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
struct TermFactors {
    means: f32,
    quats: f32,
    sh_dc: f32,
    sh_rest: f32,
    opacity: f32,
    log_scales: f32,
}

/// An [`Anchor`] on the device, restricted to a mask as [`Anchor::loss`] is.
pub struct GpuAnchor {
    len: usize,
    sh_degree: u32,
    snapshot: GpuScene,
    /// w\[generation\] of each selected Gaussian, 0 for the others.
    weights: Handle,
    factors: TermFactors,
}

impl GpuAnchor {
    /// Uploads `anchor` for the Gaussians selected by `mask` (all when `None`).
    ///
    /// # Panics
    /// When the anchor and mask disagree in size (as [`Anchor::loss`]).
    pub fn upload(ctx: &GpuContext, anchor: &Anchor, mask: Option<&[bool]>) -> Self {
        let n = anchor.generations.len();
        assert_eq!(anchor.snapshot.len(), n, "anchor snapshot size");
        if let Some(m) = mask {
            assert_eq!(m.len(), n, "mask size");
        }
        let selected = |j: usize| mask.is_none_or(|m| m[j]);
        let weights: Vec<f32> = (0..n)
            .map(|j| {
                if selected(j) {
                    anchor.schedule[anchor.generations[j] as usize]
                } else {
                    0.0
                }
            })
            .collect();
        let count = (0..n).filter(|&j| selected(j)).count();
        let k = anchor.snapshot.sh_coeffs();
        let c = &anchor.config;
        // Each term is a mean over count·width elements (as in `Anchor::loss`).
        let factor = |lambda: f32, width: usize| -> f32 {
            if count == 0 || width == 0 {
                0.0
            } else {
                (lambda as f64 * 2.0 / (count * width) as f64) as f32
            }
        };
        Self {
            len: n,
            sh_degree: anchor.snapshot.sh_degree,
            snapshot: GpuScene::upload(ctx, &anchor.snapshot),
            weights: upload_f32(&ctx.client, &weights),
            factors: TermFactors {
                means: factor(c.lambda_geo, 3),
                quats: factor(c.lambda_geo, 4),
                sh_dc: factor(c.lambda_color, 3),
                sh_rest: factor(c.lambda_color, 3 * (k - 1)),
                opacity: factor(c.lambda_opacity, 1),
                log_scales: factor(c.lambda_scale, 3),
            },
        }
    }

    /// Adds the anchor loss's gradient at `scene` into `grads`.
    ///
    /// # Panics
    /// When `scene` is not the anchored scene's size or SH degree (programming errors).
    pub fn add_grad(
        &self,
        ctx: &GpuContext,
        scene: &GpuScene,
        grads: &GpuSceneGrads,
    ) -> Result<(), GpuError> {
        assert_eq!(scene.len, self.len, "anchor snapshot size");
        assert_eq!(scene.sh_degree, self.sh_degree, "anchor SH degree");
        let n = self.len;
        let k = crate::scene::sh_coeffs(self.sh_degree);
        let f = self.factors;
        let s = &self.snapshot;
        let terms = [
            (&scene.means, &s.means, &grads.means, 3, 3, f.means, f.means),
            (&scene.quats, &s.quats, &grads.quats, 4, 4, f.quats, f.quats),
            (&scene.sh, &s.sh, &grads.sh, 3 * k, 3, f.sh_dc, f.sh_rest),
            (
                &scene.opacity_logits,
                &s.opacity_logits,
                &grads.opacity_logits,
                1,
                1,
                f.opacity,
                f.opacity,
            ),
            (
                &scene.log_scales,
                &s.log_scales,
                &grads.log_scales,
                3,
                3,
                f.log_scales,
                f.log_scales,
            ),
        ];
        gpu_call(|| {
            for (param, anchored, grad, width, first, coef_first, coef_rest) in terms {
                let len = width * n;
                if len == 0 || (coef_first == 0.0 && coef_rest == 0.0) {
                    continue;
                }
                let (count, dim) = grid(len);
                anchor_grad::launch(
                    &ctx.client,
                    count,
                    dim,
                    arg(param, len),
                    arg(anchored, len),
                    arg(&self.weights, n),
                    arg(grad, len),
                    len as u32,
                    width as u32,
                    first as u32,
                    coef_first,
                    coef_rest,
                );
            }
            Ok(())
        })
    }
}
