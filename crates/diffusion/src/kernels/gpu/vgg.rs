//! The VGG feature-loss ops of LPIPS beyond convolution (`kernels::vgg` has their CPU twins): the 2×2
//! max-pool and its backward, unit normalisation over channels and the LPIPS distance of one tap. (The
//! ReLU backward is a binary op: `elementwise::relu_backward`.)

use candle_core::Result;

use super::launch::{launch_per_element, u32_args};
use super::GpuTensor;

/// The kernels of this family (their host launchers follow the module).
mod kernel {
    use cubecl::prelude::*;

    use super::super::launch::linear_pos;

    /// 2×2 max-pool, stride 2, floor mode, over NCHW planes `h`×`w` into `h/2`×`w/2`; one unit per output
    /// value.
    #[cube(launch_unchecked)]
    pub fn max_pool2x2(x: &[f32], out: &mut [f32], h: u32, w: u32) {
        let (oh, ow) = (h / 2, w / 2);
        let i = linear_pos();
        if (i as usize) < out.len() {
            let plane = i / (oh * ow);
            let rest = i % (oh * ow);
            let base = plane * h * w + 2 * (rest / ow) * w + 2 * (rest % ow);
            let top = f32::max(x[base as usize], x[(base + 1) as usize]);
            let bottom = f32::max(x[(base + w) as usize], x[(base + w + 1) as usize]);
            out[i as usize] = f32::max(top, bottom);
        }
    }

    /// The input gradient of [`max_pool2x2`] (same sizes): one unit per input value, which receives its
    /// window's pooled gradient when it is the window's first maximum (row-major order, as torch), else 0.
    #[cube(launch_unchecked)]
    pub fn max_pool2x2_backward(x: &[f32], grad: &[f32], out: &mut [f32], h: u32, w: u32) {
        let (oh, ow) = (h / 2, w / 2);
        let i = linear_pos();
        if (i as usize) < out.len() {
            let plane = i / (h * w);
            let rest = i % (h * w);
            let y = rest / w;
            let col = rest % w;
            let py = y / 2;
            let px = col / 2;
            let mut v = 0.0f32;
            if py < oh && px < ow {
                let base = plane * h * w + 2 * py * w + 2 * px;
                let mut best = 0u32;
                let mut most = x[base as usize];
                let b = x[(base + 1) as usize];
                if b > most {
                    best = 1u32;
                    most = b;
                }
                let c = x[(base + w) as usize];
                if c > most {
                    best = 2u32;
                    most = c;
                }
                if x[(base + w + 1) as usize] > most {
                    best = 3u32;
                }
                if (y - 2 * py) * 2 + (col - 2 * px) == best {
                    v = grad[(plane * oh * ow + py * ow + px) as usize];
                }
            }
            out[i as usize] = v;
        }
    }

    /// `‖f‖` over the `channels` planes (`hw` apart) of the pixel at `base`.
    #[cube]
    fn channel_norm(f: &[f32], base: u32, channels: u32, hw: u32) -> f32 {
        let mut sum = 0.0f32;
        for ch in 0..channels {
            let v = f[(base + ch * hw) as usize];
            sum += v * v;
        }
        f32::sqrt(sum)
    }

    /// `f / (‖f‖ + eps)` over the `channels` of each of the `pixels` pixels of NCHW maps (`hw` = h·w);
    /// one unit per pixel (neighbouring units read neighbouring values of each channel plane).
    #[cube(launch_unchecked)]
    pub fn normalize_channels(
        x: &[f32],
        out: &mut [f32],
        channels: u32,
        hw: u32,
        pixels: u32,
        eps: f32,
    ) {
        let i = linear_pos();
        if i < pixels {
            let base = (i / hw) * channels * hw + i % hw;
            let denom = channel_norm(x, base, channels, hw) + eps;
            for ch in 0..channels {
                let at = (base + ch * hw) as usize;
                out[at] = x[at] / denom;
            }
        }
    }

    /// The LPIPS distance of one tap per pixel, `Σ_c lin_c (f_c/(‖f‖+eps) − t_c)²`, into `map`, and with
    /// `with_grad` the gradient of its spatial mean (`inv_area` = 1/(h·w)) with respect to `f` into `grad`
    /// (see `kernels::vgg::lpips_distance`), over `channels`, `hw` = h·w and `pixels` = n·h·w; one unit
    /// per pixel.
    #[cube(launch_unchecked)]
    pub fn lpips_distance(
        f: &[f32],
        t: &[f32],
        lin: &[f32],
        map: &mut [f32],
        grad: &mut [f32],
        channels: u32,
        hw: u32,
        pixels: u32,
        eps: f32,
        inv_area: f32,
        #[comptime] with_grad: bool,
    ) {
        let i = linear_pos();
        if i < pixels {
            let base = (i / hw) * channels * hw + i % hw;
            let norm = channel_norm(f, base, channels, hw);
            let denom = norm + eps;
            let mut value = 0.0f32;
            let mut g_dot_f = 0.0f32;
            for ch in 0..channels {
                let at = (base + ch * hw) as usize;
                let v = f[at];
                let d = v / denom - t[at];
                let l = lin[ch as usize];
                value += l * d * d;
                g_dot_f += 2.0f32 * l * d * inv_area * v;
            }
            map[i as usize] = value;
            if comptime!(with_grad) {
                // An all-zero feature vector has a zero ReLU mask anyway; skipping it avoids 0/0.
                let mut radial = 0.0f32;
                if norm > 0.0f32 {
                    radial = g_dot_f / (norm * denom * denom);
                }
                for ch in 0..channels {
                    let at = (base + ch * hw) as usize;
                    let v = f[at];
                    let g_n = 2.0f32 * lin[ch as usize] * (v / denom - t[at]) * inv_area;
                    grad[at] = g_n / denom - v * radial;
                }
            }
        }
    }
}

fn nchw(x: &GpuTensor, op: &str) -> Result<(usize, usize, usize, usize)> {
    match x.dims() {
        &[n, c, h, w] => Ok((n, c, h, w)),
        other => candle_core::bail!("gpu {op}: expected an NCHW tensor, got {other:?}"),
    }
}

/// 2×2 max-pool, stride 2, floor mode (`kernels::vgg::max_pool2x2`).
pub fn max_pool2x2(x: &GpuTensor) -> Result<GpuTensor> {
    let (n, c, h, w) = nchw(x, "max_pool2x2")?;
    let sizes = u32_args([h, w])?;
    let out = x.empty_like_device(vec![n, c, h / 2, w / 2]);
    // SAFETY: every output window lies inside its input plane (floor mode); bound-checked against out.
    unsafe {
        launch_per_element!(
            kernel::max_pool2x2,
            x.client(),
            out.elem_count(),
            x.arg(),
            out.arg(),
            sizes[0],
            sizes[1],
        )
    };
    Ok(out)
}

/// The input gradient of [`max_pool2x2`] (`kernels::vgg::max_pool2x2_backward`): `x` is the pool's input.
pub fn max_pool2x2_backward(x: &GpuTensor, grad: &GpuTensor) -> Result<GpuTensor> {
    let (n, c, h, w) = nchw(x, "max_pool2x2_backward")?;
    if grad.dims() != [n, c, h / 2, w / 2] {
        candle_core::bail!(
            "gpu max_pool2x2_backward: gradient {:?} for input {:?}",
            grad.dims(),
            x.dims()
        );
    }
    let sizes = u32_args([h, w])?;
    let out = x.empty_like_device(x.dims().to_vec());
    // SAFETY: one unit per input value; windows and pooled indices are inside x and grad.
    unsafe {
        launch_per_element!(
            kernel::max_pool2x2_backward,
            x.client(),
            out.elem_count(),
            x.arg(),
            grad.arg(),
            out.arg(),
            sizes[0],
            sizes[1],
        )
    };
    Ok(out)
}

/// `f / (‖f‖ + eps)` over the channels of each pixel (`kernels::vgg::normalize_channels`).
pub fn normalize_channels(x: &GpuTensor, eps: f32) -> Result<GpuTensor> {
    let (n, c, h, w) = nchw(x, "normalize_channels")?;
    let pixels = n * h * w;
    let sizes = u32_args([c, h * w, pixels])?;
    let out = x.empty_like_device(x.dims().to_vec());
    // SAFETY: one unit per pixel, reading and writing that pixel's channels.
    unsafe {
        launch_per_element!(
            kernel::normalize_channels,
            x.client(),
            pixels,
            x.arg(),
            out.arg(),
            sizes[0],
            sizes[1],
            sizes[2],
            eps,
        )
    };
    Ok(out)
}

/// The LPIPS distance of one tap per pixel and, with `with_grad`, the gradient of its spatial mean
/// (`kernels::vgg::lpips_distance`).
pub fn lpips_distance(
    f: &GpuTensor,
    target: &GpuTensor,
    lin: &GpuTensor,
    eps: f32,
    with_grad: bool,
) -> Result<(GpuTensor, Option<GpuTensor>)> {
    let (n, c, h, w) = nchw(f, "lpips_distance")?;
    if target.dims() != f.dims() || lin.elem_count() != c {
        candle_core::bail!(
            "gpu lpips_distance: features {:?}, target {:?}, {} lin weights",
            f.dims(),
            target.dims(),
            lin.elem_count()
        );
    }
    let pixels = n * h * w;
    let sizes = u32_args([c, h * w, pixels])?;
    let map = f.empty_like_device(vec![n, 1, h, w]);
    // Without the gradient the kernel writes no `grad`; a one-value buffer stands in.
    let grad = f.empty_like_device(if with_grad {
        f.dims().to_vec()
    } else {
        vec![1]
    });
    // SAFETY: one unit per pixel, reading and writing that pixel's channels and map value.
    unsafe {
        launch_per_element!(
            kernel::lpips_distance,
            f.client(),
            pixels,
            f.arg(),
            target.arg(),
            lin.arg(),
            map.arg(),
            grad.arg(),
            sizes[0],
            sizes[1],
            sizes[2],
            eps,
            1.0 / (h * w).max(1) as f32,
            with_grad,
        )
    };
    Ok((map, with_grad.then_some(grad)))
}

#[cfg(test)]
mod tests {
    //! The VGG feature-loss ops against their CPU twins.

    use super::*;
    use crate::kernels::gpu::ops::*;
    use crate::kernels::gpu::testing::*;

    #[test]
    fn vgg_feature_loss_ops_match_cpu() {
        let Some(dev) = device_or_skip() else {
            return;
        };
        use crate::kernels::vgg;
        // Odd sides: the pool drops the last row and column.
        let x = randn(&[2, 3, 7, 9]);
        let gx = up(&dev, &x);
        let pooled = vgg::max_pool2x2(&x).unwrap();
        check("max_pool2x2", &max_pool2x2(&gx).unwrap(), &pooled);
        let g = randn(pooled.dims());
        check(
            "max_pool2x2_backward",
            &max_pool2x2_backward(&gx, &up(&dev, &g)).unwrap(),
            &vgg::max_pool2x2_backward(&x, &g).unwrap(),
        );
        let out = x.relu().unwrap();
        let gr = randn(x.dims());
        check(
            "relu_backward",
            &relu_backward(&up(&dev, &out), &up(&dev, &gr)).unwrap(),
            &vgg::relu_backward(&out, &gr).unwrap(),
        );
        check(
            "normalize_channels",
            &normalize_channels(&gx, 1e-10).unwrap(),
            &vgg::normalize_channels(&x, 1e-10).unwrap(),
        );
        let t = vgg::normalize_channels(&randn(x.dims()), 1e-10).unwrap();
        let lin = randn(&[3]).abs().unwrap();
        let lin_gpu = up(&dev, &lin);
        for with_grad in [false, true] {
            let (map, grad) =
                lpips_distance(&up(&dev, &out), &up(&dev, &t), &lin_gpu, 1e-10, with_grad).unwrap();
            let (want_map, want_grad) =
                vgg::lpips_distance(&out, &t, &lin, 1e-10, with_grad).unwrap();
            check("lpips_distance map", &map, &want_map);
            assert_eq!(grad.is_some(), with_grad);
            if let (Some(grad), Some(want)) = (grad, want_grad) {
                check("lpips_distance grad", &grad, &want);
            }
        }
    }
}
