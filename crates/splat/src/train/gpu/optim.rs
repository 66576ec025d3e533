//! Adam on the device: the update of `crate::train::optim::Adam::step` (torch's Adam with the trainer's eps),
//! with the moments kept beside a [`GpuScene`]. The CPU [`Adam`] still holds the learning rates and the
//! step count, so both paths share one schedule. A per-Gaussian trainable mask (u32 flags on the device)
//! skips frozen Gaussians as [`Adam::step`] does: parameters and moments untouched.

use crate::render::gpu::{GpuScene, GpuSceneGrads};
use crate::train::optim::{Adam, Group};
use ::gpu::cubecl;
use ::gpu::cubecl::prelude::*;
use ::gpu::cubecl::server::Handle;
use ::gpu::gpu_call;
use ::gpu::prims::arg;
#[cfg(test)]
use ::gpu::prims::zeros32;
use ::gpu::prims::{empty32, grid, read_f32, upload_f32};
use ::gpu::{GpuContext, GpuError};

/// One Adam update of an array of `width` values per Gaussian: the first `first` values of each block
/// use `lr_first`, the rest `lr_rest` (SH: DC and higher coefficients). With `use_mask` set, Gaussians
/// whose `mask` flag is 0 are skipped.
#[cube(launch)]
fn adam_update(
    params: &mut [f32],
    grads: &[f32],
    m: &mut [f32],
    v: &mut [f32],
    mask: &[u32],
    use_mask: u32,
    len: u32,
    width: u32,
    first: u32,
    lr_first: f32,
    lr_rest: f32,
    beta1: f32,
    beta2: f32,
    eps: f32,
    inv_bias1: f32,
    inv_sqrt_bias2: f32,
) {
    let i = ABSOLUTE_POS;
    let mut live = i < len as usize;
    // Nested so that the mask (a 1-element dummy when unused) is only read when it is there.
    if live && use_mask != 0 {
        live = mask[i / width as usize] != 0;
    }
    if live {
        let lr = select((i as u32 % width) < first, lr_first, lr_rest);
        let g = grads[i];
        let mi = beta1 * m[i] + (1.0f32 - beta1) * g;
        let vi = beta2 * v[i] + (1.0f32 - beta2) * g * g;
        m[i] = mi;
        v[i] = vi;
        let denom = vi.sqrt() * inv_sqrt_bias2 + eps;
        params[i] -= lr * inv_bias1 * mi / denom;
    }
}

/// First and second moments of every parameter array, on the device.
pub struct GpuAdam {
    /// (m, v) for means, log-scales, quaternions, opacity logits, SH.
    moments: [(Handle, Handle); 5],
}

impl GpuAdam {
    /// Zero moments for `scene`.
    #[cfg(test)]
    pub fn new(ctx: &GpuContext, scene: &GpuScene) -> Self {
        let c = &ctx.client;
        let n = scene.len;
        let k = crate::scene::sh_coeffs(scene.sh_degree);
        let pair = |len: usize| (zeros32(c, len), zeros32(c, len));
        Self {
            moments: [
                pair(3 * n),
                pair(3 * n),
                pair(4 * n),
                pair(n),
                pair(3 * k * n),
            ],
        }
    }

    /// The moments of a host optimiser, uploaded.
    pub fn from_host(ctx: &GpuContext, adam: &Adam) -> Self {
        let c = &ctx.client;
        let pair = |m: &crate::train::optim::Moments| (upload_f32(c, &m.m), upload_f32(c, &m.v));
        Self {
            moments: [
                pair(&adam.means),
                pair(&adam.log_scales),
                pair(&adam.quats),
                pair(&adam.opacity),
                pair(&adam.sh),
            ],
        }
    }

    /// Reads the moments back into `adam` (sized for the same scene).
    pub fn download_into(&self, ctx: &GpuContext, adam: &mut Adam) -> Result<(), GpuError> {
        let c = &ctx.client;
        for ((m, v), host) in self.moments.iter().zip([
            &mut adam.means,
            &mut adam.log_scales,
            &mut adam.quats,
            &mut adam.opacity,
            &mut adam.sh,
        ]) {
            let len = host.m.len();
            host.m = read_f32(c, m, len)?;
            host.v = read_f32(c, v, len)?;
        }
        Ok(())
    }

    /// One step of every parameter with `adam`'s rates and hyper-parameters; advances `adam`'s step count
    /// as [`Adam::step`] does. With a per-Gaussian `trainable` mask (u32 flags, N), as [`Adam::step`]
    /// with a mask: frozen Gaussians keep their parameters and moments in the groups the mask hooks,
    /// rotations included only when `adam.mask_rotation`.
    pub fn step_masked(
        &mut self,
        ctx: &GpuContext,
        adam: &mut Adam,
        scene: &GpuScene,
        grads: &GpuSceneGrads,
        trainable: Option<&Handle>,
    ) -> Result<(), GpuError> {
        let c = &ctx.client;
        let n = scene.len;
        let k = crate::scene::sh_coeffs(scene.sh_degree);
        adam.steps += 1;
        let t = adam.steps as i32;
        let p = adam.params;
        let bias1 = 1.0 - (p.beta1 as f64).powi(t);
        let bias2 = 1.0 - (p.beta2 as f64).powi(t);
        let (inv_bias1, inv_sqrt_bias2) = ((1.0 / bias1) as f32, (1.0 / bias2.sqrt()) as f32);
        // The mask of each array: rotations only when `mask_rotation` (as `Adam::step`).
        let rot_mask = if adam.mask_rotation { trainable } else { None };
        let arrays = [
            (
                &scene.means,
                &grads.means,
                3,
                3,
                adam.lr(Group::Means),
                0.0,
                trainable,
            ),
            (
                &scene.log_scales,
                &grads.log_scales,
                3,
                3,
                adam.lr(Group::LogScales),
                0.0,
                trainable,
            ),
            (
                &scene.quats,
                &grads.quats,
                4,
                4,
                adam.lr(Group::Quats),
                0.0,
                rot_mask,
            ),
            (
                &scene.opacity_logits,
                &grads.opacity_logits,
                1,
                1,
                adam.lr(Group::Opacity),
                0.0,
                trainable,
            ),
            (
                &scene.sh,
                &grads.sh,
                3 * k,
                3,
                adam.lr(Group::ShDc),
                adam.lr(Group::ShRest),
                trainable,
            ),
        ];
        gpu_call(|| {
            let dummy = empty32(c, 1);
            for ((param, grad, width, first, lr_first, lr_rest, mask), (m, v)) in
                arrays.into_iter().zip(&self.moments)
            {
                let len = width * n;
                if len == 0 {
                    continue;
                }
                let (count, dim) = grid(len);
                let (mask, mask_len, use_mask) = mask.map_or((&dummy, 1, 0u32), |h| (h, n, 1));
                adam_update::launch(
                    c,
                    count,
                    dim,
                    arg(param, len),
                    arg(grad, len),
                    arg(m, len),
                    arg(v, len),
                    arg(mask, mask_len),
                    use_mask,
                    len as u32,
                    width as u32,
                    first as u32,
                    lr_first,
                    lr_rest,
                    p.beta1,
                    p.beta2,
                    p.eps,
                    inv_bias1,
                    inv_sqrt_bias2,
                );
            }
            Ok(())
        })
    }
}
