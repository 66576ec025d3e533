//! The fits' loss on the device: `(1 − λ)·L1 + λ·(1 − SSIM)` and its gradient, as
//! [`crate::loss::l1_dssim`] computes them (11-tap Gaussian window, σ 1.5, zero padding, per channel).
//!
//! Maps are planar on the device (plane `q` = pixels `q·H·W ..`). Kernels: `ssim_inputs` (x, y, x², y²,
//! xy per channel), a separable blur (`blur_rows`, `blur_columns`), `ssim_terms` (the SSIM map and the
//! partial derivatives with respect to the blurred maps), blurred again (the window is its own adjoint),
//! and `l1_dssim_grad` (the gradient in the image's interleaved layout, plus |pred − target|).

use super::{arg, GpuContext, GpuError};
use crate::loss::{ssim_window, SSIM_C1, SSIM_C2, SSIM_WINDOW};
use ::gpu::cubecl;
use ::gpu::cubecl::prelude::*;
use ::gpu::cubecl::server::Handle;
use ::gpu::gpu_call;
use ::gpu::prims::{empty32, grid, read_f32, upload_f32};

#[cube(launch)]
fn ssim_inputs(pred: &[f32], target: &[f32], npix: u32, channels: u32, planes: &mut [f32]) {
    let i = ABSOLUTE_POS;
    let total = (npix * channels) as usize;
    if i < total {
        let p = i / channels as usize;
        let ch = i % channels as usize;
        let n = npix as usize;
        let x = pred[i];
        let y = target[i];
        let base = ch * 5 * n;
        planes[base + p] = x;
        planes[base + n + p] = y;
        planes[base + 2 * n + p] = x * x;
        planes[base + 3 * n + p] = y * y;
        planes[base + 4 * n + p] = x * y;
    }
}

/// Horizontal pass of the zero-padded blur over `planes` planes of `width x height`.
#[cube(launch)]
fn blur_rows(src: &[f32], taps: &[f32], width: u32, height: u32, planes: u32, out: &mut [f32]) {
    let i = ABSOLUTE_POS as u32;
    if i < width * height * planes {
        let x = i % width;
        let row = i - x;
        let r = (SSIM_WINDOW / 2) as u32;
        let lo = select(x >= r, x - r, 0u32);
        let hi = u32::min(x + r, width - 1);
        let mut acc = 0.0f32;
        for xi in lo..hi + 1 {
            acc += taps[(xi + r - x) as usize] * src[(row + xi) as usize];
        }
        out[i as usize] = acc;
    }
}

/// Vertical pass of the zero-padded blur.
#[cube(launch)]
fn blur_columns(src: &[f32], taps: &[f32], width: u32, height: u32, planes: u32, out: &mut [f32]) {
    let i = ABSOLUTE_POS as u32;
    let plane_len = width * height;
    if i < plane_len * planes {
        let q = i / plane_len;
        let y = (i % plane_len) / width;
        let x = i % width;
        let r = (SSIM_WINDOW / 2) as u32;
        let lo = select(y >= r, y - r, 0u32);
        let hi = u32::min(y + r, height - 1);
        let mut acc = 0.0f32;
        for yi in lo..hi + 1 {
            acc += taps[(yi + r - y) as usize] * src[(q * plane_len + yi * width + x) as usize];
        }
        out[i as usize] = acc;
    }
}

/// From the blurred maps (5 planes per channel: μx, μy, E[x²], E[y²], E[xy]) the SSIM map and the
/// scaled partial derivatives with respect to μx, E[x²], E[xy] (3 planes per channel).
#[cube(launch)]
fn ssim_terms(
    blurred: &[f32],
    npix: u32,
    channels: u32,
    scale: f32,
    ssim_map: &mut [f32],
    partials: &mut [f32],
) {
    let i = ABSOLUTE_POS;
    let n = npix as usize;
    if i < n * channels as usize {
        let ch = i / n;
        let p = i % n;
        let b = ch * 5 * n;
        let mx = blurred[b + p];
        let my = blurred[b + n + p];
        let sxx = blurred[b + 2 * n + p] - mx * mx;
        let syy = blurred[b + 3 * n + p] - my * my;
        let sxy = blurred[b + 4 * n + p] - mx * my;
        let c1 = SSIM_C1 as f32;
        let c2 = SSIM_C2 as f32;
        let a = 2.0f32 * mx * my + c1;
        let bb = 2.0f32 * sxy + c2;
        let cc = mx * mx + my * my + c1;
        let d = sxx + syy + c2;
        let cd = cc * d;
        let s = a * bb / cd;
        ssim_map[i] = s;
        let o = ch * 3 * n;
        partials[o + p] = scale * (2.0f32 * my * (bb - a) / cd - 2.0f32 * mx * s * (d - cc) / cd);
        partials[o + n + p] = -scale * s / d;
        partials[o + 2 * n + p] = scale * 2.0f32 * a / cd;
    }
}

#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn l1_dssim_grad(
    pred: &[f32],
    target: &[f32],
    blurred_partials: &[f32],
    npix: u32,
    channels: u32,
    w_l1: f32,
    w_ssim: f32,
    grad: &mut [f32],
    abs_diff: &mut [f32],
) {
    let i = ABSOLUTE_POS;
    let n = npix as usize;
    let total = n * channels as usize;
    if i < total {
        let p = i / channels as usize;
        let ch = i % channels as usize;
        let x = pred[i];
        let d = x - target[i];
        let step = 1.0f32 / total as f32;
        let g_l1 = select(d > 0.0, step, select(d < 0.0, -step, 0.0f32));
        let o = ch * 3 * n;
        let g_ssim = blurred_partials[o + p]
            + 2.0f32 * x * blurred_partials[o + n + p]
            + target[i] * blurred_partials[o + 2 * n + p];
        grad[i] = w_l1 * g_l1 - w_ssim * g_ssim;
        abs_diff[i] = f32::abs(d);
    }
}

/// The loss on the device: the gradient (interleaved like `pred`) stays there; the value needs a read.
pub struct GpuLoss {
    pub grad: Handle,
    abs_diff: Handle,
    ssim_map: Handle,
    len: usize,
    ssim_weight: f32,
}

impl GpuLoss {
    /// Reads the two maps back and sums them: the loss value.
    pub fn value(&self, ctx: &GpuContext) -> Result<f32, GpuError> {
        let c = &ctx.client;
        if self.len == 0 {
            return Ok(0.0);
        }
        let l1 = read_f32(c, &self.abs_diff, self.len)?
            .iter()
            .map(|&v| v as f64)
            .sum::<f64>()
            / self.len as f64;
        let ssim = read_f32(c, &self.ssim_map, self.len)?
            .iter()
            .map(|&v| v as f64)
            .sum::<f64>()
            / self.len as f64;
        let w = self.ssim_weight as f64;
        Ok(((1.0 - w) * l1 + w * (1.0 - ssim)) as f32)
    }
}

/// `(1 − λ)·L1 + λ·D-SSIM` of `pred` against `target` (both H*W*C interleaved, on the device).
pub fn l1_dssim(
    ctx: &GpuContext,
    pred: &Handle,
    target: &Handle,
    width: usize,
    height: usize,
    channels: usize,
    ssim_weight: f32,
) -> Result<GpuLoss, GpuError> {
    let c = &ctx.client;
    let npix = width * height;
    let total = npix * channels;
    gpu_call(|| {
        let taps = upload_f32(c, &ssim_window().map(|v| v as f32));
        let blur = |src: &Handle, planes: usize| {
            let len = planes * npix;
            let tmp = empty32(c, len);
            let out = empty32(c, len);
            let (count, dim) = grid(len);
            let dims = (width as u32, height as u32, planes as u32);
            blur_rows::launch(
                c,
                count.clone(),
                dim,
                arg(src, len),
                arg(&taps, SSIM_WINDOW),
                dims.0,
                dims.1,
                dims.2,
                arg(&tmp, len),
            );
            blur_columns::launch(
                c,
                count,
                dim,
                arg(&tmp, len),
                arg(&taps, SSIM_WINDOW),
                dims.0,
                dims.1,
                dims.2,
                arg(&out, len),
            );
            out
        };
        let grad = empty32(c, total);
        let abs_diff = empty32(c, total);
        let ssim_map = empty32(c, total);
        if total > 0 {
            let (count, dim) = grid(total);
            let inputs = empty32(c, 5 * total);
            ssim_inputs::launch(
                c,
                count.clone(),
                dim,
                arg(pred, total),
                arg(target, total),
                npix as u32,
                channels as u32,
                arg(&inputs, 5 * total),
            );
            let blurred = blur(&inputs, 5 * channels);
            let partials = empty32(c, 3 * total);
            ssim_terms::launch(
                c,
                count.clone(),
                dim,
                arg(&blurred, 5 * total),
                npix as u32,
                channels as u32,
                1.0 / total as f32,
                arg(&ssim_map, total),
                arg(&partials, 3 * total),
            );
            let blurred_partials = blur(&partials, 3 * channels);
            l1_dssim_grad::launch(
                c,
                count,
                dim,
                arg(pred, total),
                arg(target, total),
                arg(&blurred_partials, 3 * total),
                npix as u32,
                channels as u32,
                1.0 - ssim_weight,
                ssim_weight,
                arg(&grad, total),
                arg(&abs_diff, total),
            );
        }
        Ok(GpuLoss {
            grad,
            abs_diff,
            ssim_map,
            len: total,
            ssim_weight,
        })
    })
}
