//! Photometric losses with their gradients: L1, SSIM (11-tap Gaussian window) and the 3DGS training loss
//! `(1 − λ)·L1 + λ·(1 − SSIM)`.
//!
//! All images are row-major, channel-interleaved (`H*W*C`) and every loss is a mean over all values, as in
//! the INRIA trainer; the returned gradient has the layout of the prediction. Mean reduction matters beyond
//! the loss value: the densification thresholds (`grow_grad2d = 0.0002`) assume gradients of a mean loss.
//!
//! SSIM follows the INRIA trainer's `utils/loss_utils.py`: a normalised 11-tap Gaussian (σ = 1.5) applied
//! separably per channel, 'same' output with zero padding (conv2d with padding 5), C1 = 0.01², C2 = 0.03²,
//! averaged over every pixel and channel.

use crate::render::cpu::{dispatch, Kernel};
use crate::render::real::{c, Real};
use rayon::prelude::*;

/// Taps of the SSIM window.
pub const SSIM_WINDOW: usize = 11;
/// Standard deviation of the SSIM window in pixels.
pub const SSIM_SIGMA: f64 = 1.5;
/// SSIM's stabilising constants for data in [0, 1]: (0.01·L)², (0.03·L)².
pub const SSIM_C1: f64 = 0.01 * 0.01;
pub const SSIM_C2: f64 = 0.03 * 0.03;
/// The INRIA trainer's weight of the D-SSIM term (`lambda_dssim`).
pub const DEFAULT_SSIM_WEIGHT: f32 = 0.2;

/// A scalar loss and its gradient with respect to the prediction (same layout as the prediction).
#[derive(Clone, Debug, PartialEq)]
pub struct Loss {
    pub value: f32,
    pub grad: Vec<f32>,
}

/// Mean absolute error. The gradient at equal values is 0 (torch's `sign(0)`).
///
/// # Panics
/// When the slices differ in length (a programming error).
pub fn l1(pred: &[f32], target: &[f32]) -> Loss {
    let (value, grad) = l1_generic(pred, target);
    Loss {
        value: value as f32,
        grad,
    }
}

fn l1_generic<R: Real>(pred: &[R], target: &[R]) -> (f64, Vec<R>) {
    assert_eq!(pred.len(), target.len(), "l1: prediction and target sizes");
    if pred.is_empty() {
        return (0.0, Vec::new());
    }
    let inv_n = 1.0 / pred.len() as f64;
    let step = c::<R>(inv_n);
    let mut sum = 0.0f64;
    let grad = pred
        .iter()
        .zip(target)
        .map(|(&p, &t)| {
            let d = p - t;
            sum += d.to_f64().abs();
            if d > R::ZERO {
                step
            } else if d < R::ZERO {
                -step
            } else {
                R::ZERO
            }
        })
        .collect();
    (sum * inv_n, grad)
}

/// Mean squared error.
pub fn mse(pred: &[f32], target: &[f32]) -> f64 {
    assert_eq!(pred.len(), target.len(), "mse: prediction and target sizes");
    if pred.is_empty() {
        return 0.0;
    }
    let sum: f64 = pred
        .iter()
        .zip(target)
        .map(|(&p, &t)| {
            let d = (p - t) as f64;
            d * d
        })
        .sum();
    sum / pred.len() as f64
}

/// PSNR in dB for images in [0, 1] (the prediction is clamped to [0, 1] first, as saved images are).
/// Identical images give +∞.
pub fn psnr(pred: &[f32], target: &[f32]) -> f64 {
    let clamped: Vec<f32> = pred.iter().map(|v| v.clamp(0.0, 1.0)).collect();
    psnr_from_mse(mse(&clamped, target))
}

/// PSNR in dB of a mean squared error on [0, 1] data (+∞ for 0).
pub fn psnr_from_mse(mse: f64) -> f64 {
    -10.0 * mse.log10()
}

/// Mean SSIM between `pred` and `target` (`width*height*channels` each) and its gradient with respect to
/// `pred`.
///
/// # Panics
/// When the slices are not `width*height*channels` long (a programming error).
pub fn ssim(pred: &[f32], target: &[f32], width: usize, height: usize, channels: usize) -> Loss {
    ssim_to(pred, &SsimTarget::new(target, width, height, channels))
}

/// [`ssim`] against a target whose statistics are already computed: the same value and gradient, bit for
/// bit, without blurring the target again (a fit compares hundreds of renders with each target).
///
/// # Panics
/// When `pred` is not the target's `width*height*channels` long (a programming error).
pub fn ssim_to(pred: &[f32], target: &SsimTarget) -> Loss {
    let (value, grad) = ssim_generic_to(pred, target);
    Loss {
        value: value as f32,
        grad,
    }
}

/// The target's side of SSIM for one image: per channel its plane, the plane's local means (μy) and the
/// local means of its square (`E[y²]`). They depend on the target alone, so a fit computes them once per
/// target image instead of at every step.
#[derive(Clone, Debug)]
pub struct SsimTarget<R = f32> {
    width: usize,
    height: usize,
    channels: usize,
    /// Per channel: y, μy and `E[y²]`, each `width*height`.
    planes: Vec<[Vec<R>; 3]>,
}

impl<R: Real> SsimTarget<R> {
    /// The statistics of `target` (`width*height*channels`, channels interleaved).
    ///
    /// # Panics
    /// When `target` is not `width*height*channels` long (a programming error).
    pub fn new(target: &[R], width: usize, height: usize, channels: usize) -> Self {
        let n = width * height;
        assert_eq!(target.len(), n * channels, "ssim: target size");
        let taps = gaussian_taps::<R>();
        let planes = (0..channels)
            .into_par_iter()
            .map(|ch| {
                let y: Vec<R> = target.iter().skip(ch).step_by(channels).copied().collect();
                let yy: Vec<R> = y.iter().map(|&v| v * v).collect();
                let mut tmp = vec![R::ZERO; n];
                let mut mu = vec![R::ZERO; n];
                let mut e_yy = vec![R::ZERO; n];
                dispatch(Blur {
                    src: &y,
                    width,
                    height,
                    taps: &taps,
                    tmp: &mut tmp,
                    out: &mut mu,
                });
                dispatch(Blur {
                    src: &yy,
                    width,
                    height,
                    taps: &taps,
                    tmp: &mut tmp,
                    out: &mut e_yy,
                });
                [y, mu, e_yy]
            })
            .collect();
        Self {
            width,
            height,
            channels,
            planes,
        }
    }
}

impl SsimTarget<f32> {
    /// Bytes the statistics of one `width x height` image with `channels` channels take.
    pub fn bytes_for(width: usize, height: usize, channels: usize) -> usize {
        3 * width * height * channels * std::mem::size_of::<f32>()
    }

    /// The image's width, height and channels.
    pub fn shape(&self) -> (usize, usize, usize) {
        (self.width, self.height, self.channels)
    }
}

/// The 3DGS training loss `(1 − λ)·L1 + λ·(1 − SSIM)` with λ = `ssim_weight` and its gradient.
pub fn l1_dssim(
    pred: &[f32],
    target: &[f32],
    width: usize,
    height: usize,
    channels: usize,
    ssim_weight: f32,
) -> Loss {
    let l = l1(pred, target);
    if ssim_weight == 0.0 {
        return l;
    }
    let s = ssim(pred, target, width, height, channels);
    let w_l1 = 1.0 - ssim_weight;
    let grad = l
        .grad
        .iter()
        .zip(&s.grad)
        .map(|(&gl, &gs)| w_l1 * gl - ssim_weight * gs)
        .collect();
    Loss {
        value: w_l1 * l.value + ssim_weight * (1.0 - s.value),
        grad,
    }
}

/// The SSIM window's normalised 1D Gaussian taps; the 2D window is their outer product.
pub fn ssim_window() -> [f64; SSIM_WINDOW] {
    gaussian_taps()
}

/// One `width x height` plane blurred with the SSIM window ('same' size, zero padding): the local means
/// SSIM is built from, for callers that weight or mask the statistics themselves.
pub fn ssim_blur(plane: &[f64], width: usize, height: usize) -> Vec<f64> {
    assert_eq!(plane.len(), width * height, "ssim_blur: plane size");
    let mut tmp = vec![0.0; plane.len()];
    let mut out = vec![0.0; plane.len()];
    blur(plane, width, height, &gaussian_taps(), &mut tmp, &mut out);
    out
}

/// The normalised 1D Gaussian window; the 2D window is its outer product.
fn gaussian_taps<R: Real>() -> [R; SSIM_WINDOW] {
    let half = (SSIM_WINDOW / 2) as f64;
    let raw: [f64; SSIM_WINDOW] = std::array::from_fn(|i| {
        (-(i as f64 - half).powi(2) / (2.0 * SSIM_SIGMA * SSIM_SIGMA)).exp()
    });
    let sum: f64 = raw.iter().sum();
    raw.map(|v| c(v / sum))
}

/// 'Same'-size separable blur with zero padding: `out = g ⊛ g ⊛ src` for one `width x height` plane.
/// The window is symmetric, so this is also its own adjoint (used by the backward pass).
#[inline(always)]
fn blur<R: Real>(
    src: &[R],
    width: usize,
    height: usize,
    taps: &[R; SSIM_WINDOW],
    tmp: &mut [R],
    out: &mut [R],
) {
    let r = SSIM_WINDOW / 2;
    // Horizontal pass into tmp.
    let w = *taps;
    for y in 0..height {
        let row = &src[y * width..(y + 1) * width];
        let dst = &mut tmp[y * width..(y + 1) * width];
        let edge = |x: usize| {
            let lo = x.saturating_sub(r);
            let hi = (x + r).min(width - 1);
            let mut acc = R::ZERO;
            for (xi, &v) in row.iter().enumerate().take(hi + 1).skip(lo) {
                acc += w[xi + r - x] * v;
            }
            acc
        };
        if width > 2 * r {
            for (x, d) in dst.iter_mut().enumerate().take(r) {
                *d = edge(x);
            }
            // The interior runs the full window. Tap by tap over the whole row, so each output adds its
            // taps in the same order as a per-pixel loop would (the same bits) while the loop over
            // pixels vectorises.
            let m = width - 2 * r;
            let mid = &mut dst[r..width - r];
            mid.fill(R::ZERO);
            for (k, &wk) in w.iter().enumerate() {
                for (d, &v) in mid.iter_mut().zip(&row[k..k + m]) {
                    *d += wk * v;
                }
            }
            for (x, d) in dst.iter_mut().enumerate().skip(width - r) {
                *d = edge(x);
            }
        } else {
            for (x, d) in dst.iter_mut().enumerate() {
                *d = edge(x);
            }
        }
    }
    // Vertical pass: accumulate whole rows so the inner loop runs over contiguous memory.
    out.iter_mut().for_each(|v| *v = R::ZERO);
    for y in 0..height {
        let lo = y.saturating_sub(r);
        let hi = (y + r).min(height - 1);
        let dst = &mut out[y * width..(y + 1) * width];
        for yi in lo..=hi {
            let wgt = taps[yi + r - y];
            let srow = &tmp[yi * width..(yi + 1) * width];
            for (d, &s) in dst.iter_mut().zip(srow) {
                *d += wgt * s;
            }
        }
    }
}

/// [`blur`] compiled for AVX2 as well (plain multiplies and adds: the same bits either way).
struct Blur<'a, R> {
    src: &'a [R],
    width: usize,
    height: usize,
    taps: &'a [R; SSIM_WINDOW],
    tmp: &'a mut [R],
    out: &'a mut [R],
}

impl<R: Real> Kernel for Blur<'_, R> {
    type Output = ();

    #[inline(always)]
    fn run<const SIMD: bool>(self) {
        blur(
            self.src,
            self.width,
            self.height,
            self.taps,
            self.tmp,
            self.out,
        )
    }
}

/// SSIM of one channel plane `x` against its target's plane `t` ([`SsimTarget`]: y, μy, `E[y²]`): the sum
/// of the SSIM map, with d(sum)/d(x) · `scale` written into `grad` (compiled for AVX2 as well; no fused
/// multiply-adds, so the bits are the same either way).
struct SsimPlane<'a, R> {
    x: &'a [R],
    t: &'a [Vec<R>; 3],
    width: usize,
    height: usize,
    scale: R,
    grad: &'a mut [R],
}

impl<R: Real> Kernel for SsimPlane<'_, R> {
    type Output = f64;

    #[inline(always)]
    fn run<const SIMD: bool>(self) -> f64 {
        ssim_plane(
            self.x,
            self.t,
            self.width,
            self.height,
            self.scale,
            self.grad,
        )
    }
}

#[inline(always)]
fn ssim_plane<R: Real>(
    x: &[R],
    t: &[Vec<R>; 3],
    width: usize,
    height: usize,
    scale: R,
    grad: &mut [R],
) -> f64 {
    let n = width * height;
    let [y, mu_y, e_yy] = t;
    let taps = gaussian_taps::<R>();
    let mut tmp = vec![R::ZERO; n];
    let mut blurred = |src: &[R]| {
        let mut out = vec![R::ZERO; n];
        blur(src, width, height, &taps, &mut tmp, &mut out);
        out
    };
    let mu_x = blurred(x);
    let xx: Vec<R> = x.iter().map(|&v| v * v).collect();
    let xy: Vec<R> = x.iter().zip(y).map(|(&a, &b)| a * b).collect();
    let e_xx = blurred(&xx);
    let e_xy = blurred(&xy);

    let (c1, c2) = (c::<R>(SSIM_C1), c::<R>(SSIM_C2));
    let two = c::<R>(2.0);
    // s = A·B / (C·D) with A = 2μxμy + C1, B = 2σxy + C2, C = μx² + μy² + C1, D = σx² + σy² + C2, where
    // σx² = E[x²] − μx², σxy = E[xy] − μxμy. Partial derivatives with respect to the blurred maps μx, E[x²]
    // and E[xy] (written without dividing by A or B, which may vanish).
    let mut map = vec![R::ZERO; n];
    let mut g_mu = vec![R::ZERO; n];
    let mut g_xx = vec![R::ZERO; n];
    let mut g_xy = vec![R::ZERO; n];
    for i in 0..n {
        let (mx, my) = (mu_x[i], mu_y[i]);
        let sxx = e_xx[i] - mx * mx;
        let syy = e_yy[i] - my * my;
        let sxy = e_xy[i] - mx * my;
        let a = two * mx * my + c1;
        let b = two * sxy + c2;
        let cc = mx * mx + my * my + c1;
        let d = sxx + syy + c2;
        let cd = cc * d;
        let s = a * b / cd;
        map[i] = s;
        g_mu[i] = scale * (two * my * (b - a) / cd - two * mx * s * (d - cc) / cd);
        g_xx[i] = -scale * s / d;
        g_xy[i] = scale * two * a / cd;
    }
    // Summed in pixel order in f64 (apart from the loop above, which then vectorises).
    let mut sum = 0.0f64;
    for s in &map {
        sum += s.to_f64();
    }
    let b_mu = blurred(&g_mu);
    let b_xx = blurred(&g_xx);
    let b_xy = blurred(&g_xy);
    for i in 0..n {
        grad[i] = b_mu[i] + two * x[i] * b_xx[i] + y[i] * b_xy[i];
    }
    sum
}

/// [`ssim_generic_to`] with the target's statistics made here (the tests' entry, in f64 too).
#[cfg(test)]
fn ssim_generic<R: Real>(
    pred: &[R],
    target: &[R],
    width: usize,
    height: usize,
    channels: usize,
) -> (f64, Vec<R>) {
    assert_eq!(
        pred.len(),
        width * height * channels,
        "ssim: prediction size"
    );
    ssim_generic_to(pred, &SsimTarget::new(target, width, height, channels))
}

fn ssim_generic_to<R: Real>(pred: &[R], target: &SsimTarget<R>) -> (f64, Vec<R>) {
    let (width, height, channels) = (target.width, target.height, target.channels);
    let n = width * height;
    assert_eq!(pred.len(), n * channels, "ssim: prediction size");
    if pred.is_empty() {
        return (1.0, Vec::new());
    }
    let total = (n * channels) as f64;
    let scale = c::<R>(1.0 / total);
    let planes: Vec<(f64, Vec<R>)> = target
        .planes
        .par_iter()
        .enumerate()
        .map(|(ch, t)| {
            let x: Vec<R> = pred.iter().skip(ch).step_by(channels).copied().collect();
            let mut g = vec![R::ZERO; n];
            let s = dispatch(SsimPlane {
                x: &x,
                t,
                width,
                height,
                scale,
                grad: &mut g,
            });
            (s, g)
        })
        .collect();
    let mut grad = vec![R::ZERO; n * channels];
    let mut sum = 0.0;
    for (ch, (s, g)) in planes.into_iter().enumerate() {
        sum += s;
        for (i, v) in g.into_iter().enumerate() {
            grad[i * channels + ch] = v;
        }
    }
    (sum / total, grad)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A deterministic, non-smooth test image built from integers so Python can rebuild it exactly.
    fn pattern(len: usize, a: usize, b: usize, m: usize) -> Vec<f64> {
        (0..len)
            .map(|i| ((i * a + b) % m) as f64 / (m - 1) as f64)
            .collect()
    }

    /// SSIM by the definition: explicit 2D window sums with zero padding, no separability.
    fn naive_ssim(x: &[f64], y: &[f64], w: usize, h: usize, ch: usize) -> f64 {
        let taps = gaussian_taps::<f64>();
        let r = (SSIM_WINDOW / 2) as isize;
        let mut total = 0.0;
        for c0 in 0..ch {
            for py in 0..h as isize {
                for px in 0..w as isize {
                    let (mut mx, mut my, mut xx, mut yy, mut xy) = (0.0, 0.0, 0.0, 0.0, 0.0);
                    for dy in -r..=r {
                        for dx in -r..=r {
                            let (qx, qy) = (px + dx, py + dy);
                            if qx < 0 || qy < 0 || qx >= w as isize || qy >= h as isize {
                                continue;
                            }
                            let wgt = taps[(dx + r) as usize] * taps[(dy + r) as usize];
                            let i = (qy as usize * w + qx as usize) * ch + c0;
                            mx += wgt * x[i];
                            my += wgt * y[i];
                            xx += wgt * x[i] * x[i];
                            yy += wgt * y[i] * y[i];
                            xy += wgt * x[i] * y[i];
                        }
                    }
                    let (sxx, syy, sxy) = (xx - mx * mx, yy - my * my, xy - mx * my);
                    total += ((2.0 * mx * my + SSIM_C1) * (2.0 * sxy + SSIM_C2))
                        / ((mx * mx + my * my + SSIM_C1) * (sxx + syy + SSIM_C2));
                }
            }
        }
        total / (w * h * ch) as f64
    }

    #[test]
    fn window_is_normalised_and_symmetric() {
        let t = gaussian_taps::<f64>();
        assert!((t.iter().sum::<f64>() - 1.0).abs() < 1e-12);
        for i in 0..SSIM_WINDOW {
            assert_eq!(t[i], t[SSIM_WINDOW - 1 - i]);
        }
        assert!(t[5] > t[4] && t[4] > t[0]);
    }

    #[test]
    fn ssim_matches_naive_definition() {
        let (w, h, ch) = (13, 9, 3);
        let x = pattern(w * h * ch, 37, 11, 101);
        let y = pattern(w * h * ch, 53, 7, 97);
        let (s, _) = ssim_generic(&x, &y, w, h, ch);
        let want = naive_ssim(&x, &y, w, h, ch);
        assert!((s - want).abs() < 1e-12, "{s} vs {want}");
        // Narrower than the window (no interior), taller than it.
        let (w, h, ch) = (7, 15, 2);
        let x = pattern(w * h * ch, 41, 5, 103);
        let y = pattern(w * h * ch, 23, 9, 91);
        let (s, _) = ssim_generic(&x, &y, w, h, ch);
        assert!((s - naive_ssim(&x, &y, w, h, ch)).abs() < 1e-12);
        // Images larger than the window in one direction only, and a single channel.
        let (w, h, ch) = (23, 4, 1);
        let x = pattern(w * h * ch, 29, 3, 89);
        let y: Vec<f64> = x.iter().map(|v| 0.8 * v + 0.1).collect();
        let (s, _) = ssim_generic(&x, &y, w, h, ch);
        assert!((s - naive_ssim(&x, &y, w, h, ch)).abs() < 1e-12);
    }

    /// Value computed with the INRIA trainer's `ssim()` (utils/loss_utils.py logic: conv2d with the
    /// 11x11 Gaussian window, padding 5, groups = 3) in torch 2.15 float64 on the same two patterns:
    /// `x[i] = ((37 i + 11) % 101) / 100`, `y[i] = ((53 i + 7) % 97) / 96`, i over the H=9, W=13, C=3
    /// interleaved array, permuted to NCHW. Script: tools/ssim_reference.py.
    #[test]
    fn ssim_matches_torch_reference() {
        let (w, h, ch) = (13, 9, 3);
        let x = pattern(w * h * ch, 37, 11, 101);
        let y = pattern(w * h * ch, 53, 7, 97);
        let (s, _) = ssim_generic(&x, &y, w, h, ch);
        const TORCH_SSIM: f64 = 0.36568127755423896;
        assert!((s - TORCH_SSIM).abs() < 1e-10, "{s} vs torch {TORCH_SSIM}");
    }

    #[test]
    fn identical_images_have_ssim_one_and_zero_gradient() {
        let (w, h, ch) = (16, 12, 3);
        let x: Vec<f32> = pattern(w * h * ch, 37, 11, 101)
            .into_iter()
            .map(|v| v as f32)
            .collect();
        let s = ssim(&x, &x, w, h, ch);
        assert!((s.value - 1.0).abs() < 1e-5, "{}", s.value);
        assert!(s.grad.iter().all(|g| g.abs() < 1e-5));
        let d = l1_dssim(&x, &x, w, h, ch, 0.2);
        assert!(d.value.abs() < 1e-5);
    }

    fn check_gradient(f: impl Fn(&[f64]) -> (f64, Vec<f64>), x: &[f64], what: &str) {
        let (_, g) = f(x);
        let eps = 1e-6;
        let mut worst = 0.0f64;
        let scale = g.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        for i in 0..x.len() {
            let mut xp = x.to_vec();
            xp[i] += eps;
            let mut xm = x.to_vec();
            xm[i] -= eps;
            let fd = (f(&xp).0 - f(&xm).0) / (2.0 * eps);
            // Entries far below the largest one are compared on the largest one's scale: the round-off of
            // the differenced sums (~1e-10 here) is not relative to tiny entries.
            let err = (fd - g[i]).abs() / (fd.abs().max(g[i].abs()).max(1e-2 * scale));
            worst = worst.max(err);
        }
        assert!(
            worst < 2e-4,
            "{what}: worst relative gradient error {worst:e}"
        );
    }

    #[test]
    fn ssim_gradient_matches_finite_differences() {
        let (w, h, ch) = (14, 12, 2);
        let x = pattern(w * h * ch, 37, 11, 101);
        let y = pattern(w * h * ch, 53, 7, 97);
        check_gradient(|p| ssim_generic(p, &y, w, h, ch), &x, "ssim");
        // Near-identical images: the regime training ends in.
        let close: Vec<f64> = y
            .iter()
            .zip(&x)
            .map(|(a, b)| a + 0.01 * (b - 0.5))
            .collect();
        check_gradient(
            |p| ssim_generic(p, &y, w, h, ch),
            &close,
            "ssim near target",
        );
    }

    #[test]
    fn l1_gradient_matches_finite_differences() {
        let x = pattern(60, 37, 11, 101);
        let y = pattern(60, 53, 7, 97);
        // Keep away from the kink at p == t.
        let x: Vec<f64> = x
            .iter()
            .zip(&y)
            .map(|(a, b)| if (a - b).abs() < 1e-3 { a + 0.01 } else { *a })
            .collect();
        check_gradient(|p| l1_generic(p, &y), &x, "l1");
    }

    #[test]
    fn combined_loss_is_weighted_sum_in_f32() {
        let (w, h, ch) = (20, 17, 3);
        let x: Vec<f32> = pattern(w * h * ch, 37, 11, 101)
            .into_iter()
            .map(|v| v as f32)
            .collect();
        let y: Vec<f32> = pattern(w * h * ch, 53, 7, 97)
            .into_iter()
            .map(|v| v as f32)
            .collect();
        let l = l1(&x, &y);
        let s = ssim(&x, &y, w, h, ch);
        let d = l1_dssim(&x, &y, w, h, ch, 0.2);
        assert!((d.value - (0.8 * l.value + 0.2 * (1.0 - s.value))).abs() < 1e-6);
        for i in 0..x.len() {
            assert!((d.grad[i] - (0.8 * l.grad[i] - 0.2 * s.grad[i])).abs() < 1e-9);
        }
        // f32 and f64 paths agree.
        let x64: Vec<f64> = x.iter().map(|&v| v as f64).collect();
        let y64: Vec<f64> = y.iter().map(|&v| v as f64).collect();
        let (s64, g64) = ssim_generic(&x64, &y64, w, h, ch);
        assert!((s.value as f64 - s64).abs() < 1e-5);
        let gmax = g64.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        for (a, b) in s.grad.iter().zip(&g64) {
            assert!((*a as f64 - b).abs() < 1e-3 * gmax);
        }
    }

    /// The kept target statistics give the loss of [`ssim`] bit for bit, and the AVX2 build of the blur and
    /// the SSIM map the portable one's (plain multiplies and adds, the taps in the same order).
    #[test]
    fn kept_target_and_vector_paths_match_bit_for_bit() {
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        // Wider than the window, narrower than it, and one the width of the demo's views.
        for (w, h) in [(37, 21), (9, 14), (128, 16)] {
            let x: Vec<f32> = pattern(w * h * 3, 37, 11, 101)
                .into_iter()
                .map(|v| v as f32)
                .collect();
            let y: Vec<f32> = pattern(w * h * 3, 53, 7, 97)
                .into_iter()
                .map(|v| v as f32)
                .collect();
            let fresh = ssim(&x, &y, w, h, 3);
            let target = SsimTarget::new(&y, w, h, 3);
            assert_eq!(target.shape(), (w, h, 3));
            for _ in 0..2 {
                let kept = ssim_to(&x, &target);
                assert_eq!(kept.value.to_bits(), fresh.value.to_bits(), "{w}x{h}");
                assert_eq!(bits(&kept.grad), bits(&fresh.grad), "{w}x{h}");
            }
            crate::render::cpu::force_portable(true);
            let portable = ssim(&x, &y, w, h, 3);
            crate::render::cpu::force_portable(false);
            assert_eq!(portable.value.to_bits(), fresh.value.to_bits(), "{w}x{h}");
            assert_eq!(bits(&portable.grad), bits(&fresh.grad), "{w}x{h}");
        }
    }

    #[test]
    fn psnr_and_mse() {
        let a = [0.0f32, 0.5, 1.0, 0.25];
        let b = [0.1f32, 0.5, 0.9, 0.25];
        let m = mse(&a, &b);
        assert!((m - 0.005).abs() < 1e-8);
        assert!((psnr(&a, &b) - (-10.0 * 0.005f64.log10())).abs() < 1e-4);
        assert!(psnr(&a, &a).is_infinite());
    }
}
