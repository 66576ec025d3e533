//! The fits' loss on the device: `(1 − λ)·L1 + λ·(1 − SSIM)` and its gradient, as
//! [`crate::train::loss::l1_dssim`] computes them (11-tap Gaussian window, σ 1.5, zero padding, per channel),
//! or with free weights `a·L1 + b·(1 − SSIM)` ([`l1_dssim_weighted`], the editing fit's 10 : 2.5).
//!
//! Maps are planar on the device (plane `q` = pixels `q·H·W ..`). The separable blur's two passes are
//! fused into their neighbours (four kernels, each sum in the order of the unfused passes):
//! `ssim_rows` (row pass of x, y, x², y², xy per channel, read from the images), `ssim_terms` (column
//! pass, then the SSIM map and the partial derivatives with respect to the blurred maps), `blur_rows`
//! of the partials (the window is its own adjoint) and `l1_dssim_grad` (their column pass, then the
//! gradient in the image's interleaved layout, plus |pred − target|).

use crate::train::loss::{ssim_window, SSIM_C1, SSIM_C2, SSIM_WINDOW};
use ::gpu::cubecl;
use ::gpu::cubecl::prelude::*;
use ::gpu::cubecl::server::Handle;
use ::gpu::gpu_call;
use ::gpu::prims::arg;
use ::gpu::prims::{empty32, grid, read_f32, upload_f32};
use ::gpu::{GpuContext, GpuError};

/// The horizontal blur pass of the five SSIM inputs (x, y, x², y², xy per channel), read straight
/// from the interleaved images: 5 planes per channel into `out` (plane `5·ch + k`).
///
/// Over `images` images (1, or 2 for a pair of fits): image 1's `pred` and planes follow image 0's, its
/// target is `target_b`.
#[cube(launch)]
fn ssim_rows(
    pred: &[f32],
    target: &[f32],
    target_b: &[f32],
    taps: &[f32],
    width: u32,
    height: u32,
    channels: u32,
    images: u32,
    out: &mut [f32],
) {
    let all = ABSOLUTE_POS as u32;
    let n = width * height;
    let total = n * channels;
    if all < total * images {
        let img = all / total;
        let i = all % total;
        let ch = i / n;
        let p = i % n;
        let x = p % width;
        let row = p - x;
        let r = (SSIM_WINDOW / 2) as u32;
        let lo = select(x >= r, x - r, 0u32);
        let hi = u32::min(x + r, width - 1);
        let mut sx = 0.0f32;
        let mut sy = 0.0f32;
        let mut sxx = 0.0f32;
        let mut syy = 0.0f32;
        let mut sxy = 0.0f32;
        for xi in lo..hi + 1 {
            let tap = taps[(xi + r - x) as usize];
            let e = ((row + xi) * channels + ch) as usize;
            let a = pred[(img * total) as usize + e];
            let b = target_of(target, target_b, img, e);
            sx += tap * a;
            sy += tap * b;
            sxx += tap * (a * a);
            syy += tap * (b * b);
            sxy += tap * (a * b);
        }
        let base = (img * 5 * total + ch * 5 * n + p) as usize;
        let nu = n as usize;
        out[base] = sx;
        out[base + nu] = sy;
        out[base + 2 * nu] = sxx;
        out[base + 3 * nu] = syy;
        out[base + 4 * nu] = sxy;
    }
}

/// Element `e` of image `img`'s target: `target`'s, or `target_b`'s for image 1 of a pair.
#[cube]
fn target_of(target: &[f32], target_b: &[f32], img: u32, e: usize) -> f32 {
    select(img != 0, target_b[e], target[e])
}

/// The vertical pass of the zero-padded blur at (x, y) of the plane starting at `base`.
#[cube]
fn column_blur(
    src: &[f32],
    taps: &[f32],
    base: u32,
    x: u32,
    y: u32,
    width: u32,
    height: u32,
) -> f32 {
    let r = (SSIM_WINDOW / 2) as u32;
    let lo = select(y >= r, y - r, 0u32);
    let hi = u32::min(y + r, height - 1);
    let mut acc = 0.0f32;
    for yi in lo..hi + 1 {
        acc += taps[(yi + r - y) as usize] * src[(base + yi * width + x) as usize];
    }
    acc
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

/// The vertical blur pass of the row-blurred SSIM inputs (5 planes per channel) finishes the local
/// statistics μx, μy, `E[x²]`, `E[y²]`, `E[xy]`; from them the SSIM map and the scaled partial derivatives
/// with respect to μx, `E[x²]`, `E[xy]` (3 planes per channel).
/// Over `images` images as [`ssim_rows`].
#[cube(launch)]
fn ssim_terms(
    rows: &[f32],
    taps: &[f32],
    width: u32,
    height: u32,
    channels: u32,
    images: u32,
    scale: f32,
    ssim_map: &mut [f32],
    partials: &mut [f32],
) {
    let all = ABSOLUTE_POS;
    let n = (width * height) as usize;
    let total = n * channels as usize;
    if all < total * images as usize {
        let img = all / total;
        let i = all % total;
        let ch = i / n;
        let p = i % n;
        let x = p as u32 % width;
        let y = p as u32 / width;
        let b = (img * 5 * total + ch * 5 * n) as u32;
        let nu = n as u32;
        let mx = column_blur(rows, taps, b, x, y, width, height);
        let my = column_blur(rows, taps, b + nu, x, y, width, height);
        let sxx = column_blur(rows, taps, b + 2 * nu, x, y, width, height) - mx * mx;
        let syy = column_blur(rows, taps, b + 3 * nu, x, y, width, height) - my * my;
        let sxy = column_blur(rows, taps, b + 4 * nu, x, y, width, height) - mx * my;
        let c1 = SSIM_C1 as f32;
        let c2 = SSIM_C2 as f32;
        let a = 2.0f32 * mx * my + c1;
        let bb = 2.0f32 * sxy + c2;
        let cc = mx * mx + my * my + c1;
        let d = sxx + syy + c2;
        let cd = cc * d;
        let s = a * bb / cd;
        ssim_map[all] = s;
        let o = img * 3 * total + ch * 3 * n;
        partials[o + p] = scale * (2.0f32 * my * (bb - a) / cd - 2.0f32 * mx * s * (d - cc) / cd);
        partials[o + n + p] = -scale * s / d;
        partials[o + 2 * n + p] = scale * 2.0f32 * a / cd;
    }
}

/// Over `images` images as [`ssim_rows`].
#[cube(launch)]
fn l1_dssim_grad(
    pred: &[f32],
    target: &[f32],
    target_b: &[f32],
    partial_rows: &[f32],
    taps: &[f32],
    width: u32,
    height: u32,
    channels: u32,
    images: u32,
    w_l1: f32,
    w_ssim: f32,
    grad: &mut [f32],
    abs_diff: &mut [f32],
) {
    let all = ABSOLUTE_POS;
    let n = (width * height) as usize;
    let total = n * channels as usize;
    if all < total * images as usize {
        let img = all / total;
        let i = all % total;
        let p = i / channels as usize;
        let ch = i % channels as usize;
        let px = p as u32 % width;
        let py = p as u32 / width;
        let x = pred[all];
        let y = target_of(target, target_b, img as u32, i);
        let d = x - y;
        let step = 1.0f32 / total as f32;
        let g_l1 = select(d > 0.0, step, select(d < 0.0, -step, 0.0f32));
        // The vertical pass of the partials' blur (the window is its own adjoint).
        let o = (img * 3 * total + ch * 3 * n) as u32;
        let nu = n as u32;
        let b0 = column_blur(partial_rows, taps, o, px, py, width, height);
        let b1 = column_blur(partial_rows, taps, o + nu, px, py, width, height);
        let b2 = column_blur(partial_rows, taps, o + 2 * nu, px, py, width, height);
        let g_ssim = b0 + 2.0f32 * x * b1 + y * b2;
        grad[all] = w_l1 * g_l1 - w_ssim * g_ssim;
        abs_diff[all] = f32::abs(d);
    }
}

/// The weights of `l1·L1 + dssim·(1 − SSIM)`. Kept in f64 so that the value of the blended form
/// `(1 − λ)·L1 + λ·D-SSIM` is computed exactly as before the weights were split.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct L1DssimWeights {
    pub l1: f64,
    pub dssim: f64,
}

impl L1DssimWeights {
    /// The fits' blend `(1 − λ)·L1 + λ·D-SSIM`.
    pub fn blend(ssim_weight: f32) -> Self {
        Self {
            l1: 1.0 - ssim_weight as f64,
            dssim: ssim_weight as f64,
        }
    }

    /// Free weights `l1·L1 + dssim·D-SSIM` (the editing fit: 10 and 2.5).
    pub fn new(l1: f32, dssim: f32) -> Self {
        Self {
            l1: l1 as f64,
            dssim: dssim as f64,
        }
    }
}

/// Units summing the two loss maps in [`GpuLoss::value`]: each adds every `LOSS_SUM_UNITS`-th element of
/// both maps (adjacent units read adjacent elements), so the host reads 2 × 256 partial sums instead of
/// two image-sized maps.
const LOSS_SUM_UNITS: u32 = 256;

/// Partial sums of `abs_diff` and `ssim_map` (both `len` long): unit `u` writes the sum of elements
/// `u, u + units, u + 2·units, …` of each to `partials[u]` and `partials[units + u]`. No shared memory, so
/// it runs wherever the other loss kernels do (Mesa 25's SPIR-V path included).
#[cube(launch)]
fn loss_partials(abs_diff: &[f32], ssim_map: &[f32], len: u32, partials: &mut [f32]) {
    let u = ABSOLUTE_POS as u32;
    let units = comptime!(LOSS_SUM_UNITS);
    if u < units {
        let mut l1 = 0.0f32;
        let mut ssim = 0.0f32;
        let mut i = u;
        while i < len {
            l1 += abs_diff[i as usize];
            ssim += ssim_map[i as usize];
            i += units;
        }
        partials[u as usize] = l1;
        partials[(units + u) as usize] = ssim;
    }
}

/// The loss on the device: the gradient (interleaved like `pred`) stays there; the value needs a read.
pub struct GpuLoss {
    pub grad: Handle,
    abs_diff: Handle,
    ssim_map: Handle,
    len: usize,
    weights: L1DssimWeights,
}

impl GpuLoss {
    /// The loss value: the two maps summed on the device into 2 × [`LOSS_SUM_UNITS`] partial sums, read
    /// back (one wait for the device, 2 KiB) and added in f64.
    pub fn value(&self, ctx: &GpuContext) -> Result<f32, GpuError> {
        let c = &ctx.client;
        if self.len == 0 {
            return Ok(0.0);
        }
        let units = LOSS_SUM_UNITS as usize;
        let partials = empty32(c, 2 * units);
        gpu_call(|| {
            let (count, dim) = grid(units);
            loss_partials::launch(
                c,
                count,
                dim,
                arg(&self.abs_diff, self.len),
                arg(&self.ssim_map, self.len),
                self.len as u32,
                arg(&partials, 2 * units),
            );
            Ok(())
        })?;
        let sums = read_f32(c, &partials, 2 * units)?;
        let mean = |part: &[f32]| part.iter().map(|&v| v as f64).sum::<f64>() / self.len as f64;
        let (l1, ssim) = (mean(&sums[..units]), mean(&sums[units..]));
        let w = self.weights;
        Ok((w.l1 * l1 + w.dssim * (1.0 - ssim)) as f32)
    }
}

/// `(1 − λ)·L1 + λ·D-SSIM` of `pred` against `target` (both H*W*C interleaved, on the device).
#[cfg(test)]
pub fn l1_dssim(
    ctx: &GpuContext,
    pred: &Handle,
    target: &Handle,
    width: usize,
    height: usize,
    channels: usize,
    ssim_weight: f32,
) -> Result<GpuLoss, GpuError> {
    l1_dssim_weighted(
        ctx,
        pred,
        target,
        width,
        height,
        channels,
        L1DssimWeights::blend(ssim_weight),
    )
}

/// `l1·L1 + dssim·D-SSIM` of `pred` against `target` (both H*W*C interleaved, on the device); value and
/// gradient as the host's weighted sum of [`crate::train::loss::l1`] and [`crate::train::loss::ssim`].
pub fn l1_dssim_weighted(
    ctx: &GpuContext,
    pred: &Handle,
    target: &Handle,
    width: usize,
    height: usize,
    channels: usize,
    weights: L1DssimWeights,
) -> Result<GpuLoss, GpuError> {
    l1_dssim_images(ctx, pred, &[target], width, height, channels, weights)
}

/// [`l1_dssim_weighted`] of one image or of two in one launch per kernel (a pair of fits): `pred`
/// holds the images one after the other, `targets` one target each. The gradient holds each image's
/// own (as [`l1_dssim_weighted`] of that image alone gives, bit for bit), and the value is the mean of
/// the images' losses.
pub fn l1_dssim_images(
    ctx: &GpuContext,
    pred: &Handle,
    targets: &[&Handle],
    width: usize,
    height: usize,
    channels: usize,
    weights: L1DssimWeights,
) -> Result<GpuLoss, GpuError> {
    assert!(
        matches!(targets.len(), 1 | 2),
        "one image or a pair of images"
    );
    let c = &ctx.client;
    let npix = width * height;
    let total = npix * channels;
    let images = targets.len();
    let all = images * total;
    let (target, target_b) = (targets[0], targets[images - 1]);
    gpu_call(|| {
        let taps = upload_f32(c, &ssim_window().map(|v| v as f32));
        let grad = empty32(c, all);
        let abs_diff = empty32(c, all);
        let ssim_map = empty32(c, all);
        if total > 0 {
            let (count, dim) = grid(all);
            let (w, h) = (width as u32, height as u32);
            let rows = empty32(c, 5 * all);
            ssim_rows::launch(
                c,
                count.clone(),
                dim,
                arg(pred, all),
                arg(target, total),
                arg(target_b, total),
                arg(&taps, SSIM_WINDOW),
                w,
                h,
                channels as u32,
                images as u32,
                arg(&rows, 5 * all),
            );
            let partials = empty32(c, 3 * all);
            ssim_terms::launch(
                c,
                count.clone(),
                dim,
                arg(&rows, 5 * all),
                arg(&taps, SSIM_WINDOW),
                w,
                h,
                channels as u32,
                images as u32,
                1.0 / total as f32,
                arg(&ssim_map, all),
                arg(&partials, 3 * all),
            );
            let partial_rows = empty32(c, 3 * all);
            let (count3, dim3) = grid(3 * all);
            blur_rows::launch(
                c,
                count3,
                dim3,
                arg(&partials, 3 * all),
                arg(&taps, SSIM_WINDOW),
                w,
                h,
                (3 * channels * images) as u32,
                arg(&partial_rows, 3 * all),
            );
            l1_dssim_grad::launch(
                c,
                count,
                dim,
                arg(pred, all),
                arg(target, total),
                arg(target_b, total),
                arg(&partial_rows, 3 * all),
                arg(&taps, SSIM_WINDOW),
                w,
                h,
                channels as u32,
                images as u32,
                weights.l1 as f32,
                weights.dssim as f32,
                arg(&grad, all),
                arg(&abs_diff, all),
            );
        }
        Ok(GpuLoss {
            grad,
            abs_diff,
            ssim_map,
            len: all,
            weights,
        })
    })
}
