//! The ops of a frozen VGG feature network used as a loss (LPIPS, [`crate::lpips`]) beyond convolution:
//! the 2×2 max-pool and its backward, the ReLU backward, unit normalisation over channels and the LPIPS
//! distance of one tap with its gradient. All take NCHW f32 tensors on the CPU; the GPU twins are in
//! `gpu/vgg.rs` (one kernel each). [`VggStorage`] declares them at the device seam, an extension of the
//! core [`Storage`] that only LPIPS uses.
//!
//! The loss only needs the gradient with respect to the image, never the weights', so these are plain
//! functions (no candle autograd): the network keeps its activations and calls the backward ops itself.

use candle_core::{Result, Tensor};
use rayon::prelude::*;

use super::device::{seam_ops, DeviceTensor, Storage};
use super::gpu::ops;

seam_ops! {
    /// The VGG feature-loss ops of LPIPS ([`crate::lpips`]) on each backend: an extension of the core
    /// [`Storage`], declared beside their CPU bodies (their kernels are in `kernels/gpu/vgg.rs`).
    pub(crate) trait VggStorage: Storage {
        /// 2×2 max-pool, stride 2, floor mode, of NCHW maps ([`max_pool2x2`]).
        unary fn max_pool2x2(&self) => cpu max_pool2x2(self), gpu ops::max_pool2x2(self);
        /// The input gradient of [`DeviceTensor::max_pool2x2`] ([`max_pool2x2_backward`]); `self` is
        /// the pool's input.
        binary fn max_pool2x2_backward(&self, grad: &Self)
            => cpu max_pool2x2_backward(self, grad), gpu ops::max_pool2x2_backward(self, grad);
        /// A ReLU's input gradient ([`relu_backward`]); `self` is the ReLU's output.
        binary fn relu_backward(&self, grad: &Self)
            => cpu relu_backward(self, grad), gpu ops::relu_backward(self, grad);
        /// `f / (‖f‖ + eps)` over the channels of each pixel ([`normalize_channels`]).
        unary fn normalize_channels(&self, eps: f32)
            => cpu normalize_channels(self, eps), gpu ops::normalize_channels(self, eps);
        /// [`lpips_distance`]; `self` holds the features, `lin` the tap's channel weights.
        special fn lpips_distance(
            &self,
            target: &Self,
            lin: &Tensor,
            eps: f32,
            with_grad: bool,
        ) -> Result<(Self, Option<Self>)>
            => cpu lpips_distance(self, target, lin, eps, with_grad),
               gpu ops::lpips_distance(self, target, &self.constant(lin)?, eps, with_grad);
    }
}

impl DeviceTensor {
    /// The LPIPS distance of one tap per pixel, [N, 1, H, W], and with `with_grad` the gradient of its
    /// spatial mean with respect to `self` ([`lpips_distance`]).
    pub fn lpips_distance(
        &self,
        target: &DeviceTensor,
        lin: &Tensor,
        eps: f32,
        with_grad: bool,
    ) -> Result<(DeviceTensor, Option<DeviceTensor>)> {
        Ok(match (self, target) {
            (DeviceTensor::Cpu(f), DeviceTensor::Cpu(t)) => {
                let (map, grad) = VggStorage::lpips_distance(f, t, lin, eps, with_grad)?;
                (DeviceTensor::Cpu(map), grad.map(DeviceTensor::Cpu))
            }
            (DeviceTensor::Gpu(f), DeviceTensor::Gpu(t)) => {
                let (map, grad) = VggStorage::lpips_distance(f, t, lin, eps, with_grad)?;
                (DeviceTensor::Gpu(map), grad.map(DeviceTensor::Gpu))
            }
            _ => candle_core::bail!("lpips_distance: operands on different devices"),
        })
    }
}

/// The contiguous values of an f32 CPU tensor (a copy; the tests' reader).
#[cfg(test)]
fn values(x: &Tensor) -> Result<Vec<f32>> {
    x.flatten_all()?.to_vec1::<f32>()
}

/// `f` on the values of an f32 CPU tensor, read in place (these ops run over every activation of the
/// network, so a copy per operand would cost a pass over memory each).
fn with_values<R>(x: &Tensor, op: &str, f: impl FnOnce(&[f32]) -> Result<R>) -> Result<R> {
    let x = x.contiguous()?;
    let (storage, layout) = x.storage_and_layout();
    match &*storage {
        candle_core::Storage::Cpu(cpu) => f(super::f32_slice(cpu, layout, op)?),
        _ => candle_core::bail!("{op}: expects CPU tensors"),
    }
}

fn dims4(x: &Tensor, op: &str) -> Result<(usize, usize, usize, usize)> {
    match x.dims() {
        &[n, c, h, w] => Ok((n, c, h, w)),
        other => candle_core::bail!("{op}: expected an NCHW tensor, got {other:?}"),
    }
}

fn same_dims(a: &Tensor, b: &Tensor, op: &str) -> Result<()> {
    if a.dims() != b.dims() {
        candle_core::bail!("{op}: shapes {:?} and {:?} differ", a.dims(), b.dims());
    }
    Ok(())
}

/// Index (0..4, row-major in the 2×2 window) of the first maximum, as torch's `max_pool2d` picks it.
pub(crate) fn window_argmax(values: [f32; 4]) -> usize {
    let mut best = 0;
    for i in 1..4 {
        if values[i] > values[best] {
            best = i;
        }
    }
    best
}

/// 2×2 max-pool with stride 2 in floor mode (an odd last row or column is dropped, as in torch).
pub fn max_pool2x2(x: &Tensor) -> Result<Tensor> {
    let (n, c, h, w) = dims4(x, "max_pool2x2")?;
    let (oh, ow) = (h / 2, w / 2);
    let mut out = vec![0.0f32; n * c * oh * ow];
    if oh * ow > 0 {
        with_values(x, "max_pool2x2", |src| {
            out.par_chunks_mut(oh * ow)
                .zip(src.par_chunks(h * w))
                .for_each(|(dst, plane)| {
                    for y in 0..oh {
                        let (r0, r1) = (&plane[2 * y * w..], &plane[(2 * y + 1) * w..]);
                        for x in 0..ow {
                            dst[y * ow + x] = r0[2 * x]
                                .max(r0[2 * x + 1])
                                .max(r1[2 * x])
                                .max(r1[2 * x + 1]);
                        }
                    }
                });
            Ok(())
        })?;
    }
    Tensor::from_vec(out, (n, c, oh, ow), x.device())
}

/// The gradient of [`max_pool2x2`] with respect to its input `x`, given the gradient `grad` of its
/// output: each pooled gradient goes to its window's (first) maximum, everything else gets zero.
pub fn max_pool2x2_backward(x: &Tensor, grad: &Tensor) -> Result<Tensor> {
    let (n, c, h, w) = dims4(x, "max_pool2x2_backward")?;
    let (oh, ow) = (h / 2, w / 2);
    if grad.dims() != [n, c, oh, ow] {
        candle_core::bail!(
            "max_pool2x2_backward: gradient {:?} for input {:?}",
            grad.dims(),
            x.dims()
        );
    }
    let mut out = vec![0.0f32; n * c * h * w];
    if oh * ow > 0 {
        with_values(x, "max_pool2x2_backward", |src| {
            with_values(grad, "max_pool2x2_backward", |g| {
                out.par_chunks_mut(h * w)
                    .zip(src.par_chunks(h * w))
                    .zip(g.par_chunks(oh * ow))
                    .for_each(|((dst, plane), g)| {
                        for y in 0..oh {
                            for x in 0..ow {
                                let at = [
                                    2 * y * w + 2 * x,
                                    2 * y * w + 2 * x + 1,
                                    (2 * y + 1) * w + 2 * x,
                                    (2 * y + 1) * w + 2 * x + 1,
                                ];
                                let best = window_argmax(at.map(|i| plane[i]));
                                dst[at[best]] = g[y * ow + x];
                            }
                        }
                    });
                Ok(())
            })
        })?;
    }
    Tensor::from_vec(out, x.dims(), x.device())
}

/// The gradient of a ReLU with respect to its input, from its output `out` and the gradient `grad` of
/// that output: `grad` where `out > 0`, else zero.
pub fn relu_backward(out: &Tensor, grad: &Tensor) -> Result<Tensor> {
    same_dims(out, grad, "relu_backward")?;
    let masked = with_values(out, "relu_backward", |o| {
        with_values(grad, "relu_backward", |g| {
            let mut masked = vec![0.0f32; g.len()];
            masked
                .par_chunks_mut(PIXEL_CHUNK * 16)
                .zip(g.par_chunks(PIXEL_CHUNK * 16))
                .zip(o.par_chunks(PIXEL_CHUNK * 16))
                .for_each(|((m, g), o)| {
                    for ((m, &g), &o) in m.iter_mut().zip(g).zip(o) {
                        *m = if o > 0.0 { g } else { 0.0 };
                    }
                });
            Ok(masked)
        })
    })?;
    Tensor::from_vec(masked, out.dims(), out.device())
}

/// Pixels per rayon task of the per-pixel reductions over channels.
const PIXEL_CHUNK: usize = 1024;

/// Per-pixel `‖f‖` over the channels of one image (`f` is its C×HW planes), accumulated in f64.
fn channel_norms(f: &[f32], c: usize, hw: usize) -> Vec<f32> {
    let mut norms = vec![0.0f32; hw];
    norms
        .par_chunks_mut(PIXEL_CHUNK)
        .enumerate()
        .for_each(|(k, dst)| {
            let start = k * PIXEL_CHUNK;
            let mut sums = vec![0.0f64; dst.len()];
            for ch in 0..c {
                let plane = &f[ch * hw + start..ch * hw + start + dst.len()];
                for (s, &v) in sums.iter_mut().zip(plane) {
                    *s += f64::from(v) * f64::from(v);
                }
            }
            for (d, s) in dst.iter_mut().zip(sums) {
                *d = s.sqrt() as f32;
            }
        });
    norms
}

/// Unit normalisation over channels, `f / (‖f‖ + eps)` per pixel (`lpips.normalize_tensor`).
pub fn normalize_channels(x: &Tensor, eps: f32) -> Result<Tensor> {
    let (n, c, h, w) = dims4(x, "normalize_channels")?;
    let hw = h * w;
    let mut f = with_values(x, "normalize_channels", |v| Ok(v.to_vec()))?;
    for image in f.chunks_mut(c * hw.max(1)).take(n) {
        let norms = channel_norms(image, c, hw);
        image.par_chunks_mut(hw.max(1)).for_each(|plane| {
            for (v, norm) in plane.iter_mut().zip(&norms) {
                *v /= norm + eps;
            }
        });
    }
    Tensor::from_vec(f, x.dims(), x.device())
}

/// The LPIPS distance at one tap, per pixel: `Σ_c lin_c (f_c / (‖f‖ + eps) − t_c)²` for the features `f`
/// (ReLU outputs, NCHW) against the normalised target features `t` (same shape), as an [N, 1, H, W] map.
/// With `with_grad`, also the gradient of the map's spatial mean per image with respect to `f`.
pub fn lpips_distance(
    f: &Tensor,
    target: &Tensor,
    lin: &Tensor,
    eps: f32,
    with_grad: bool,
) -> Result<(Tensor, Option<Tensor>)> {
    let (n, c, h, w) = dims4(f, "lpips_distance")?;
    same_dims(f, target, "lpips_distance")?;
    if lin.elem_count() != c {
        candle_core::bail!(
            "lpips_distance: {} lin weights for {c} channels",
            lin.elem_count()
        );
    }
    let hw = h * w;
    let lin = with_values(lin, "lpips_distance", |v| Ok(v.to_vec()))?;
    let (map, grad) = with_values(f, "lpips_distance", |fv| {
        with_values(target, "lpips_distance", |tv| {
            Ok(distance_planes(fv, tv, &lin, n, c, hw, eps, with_grad))
        })
    })?;
    let map = Tensor::from_vec(map, (n, 1, h, w), f.device())?;
    let grad = with_grad
        .then(|| Tensor::from_vec(grad, (n, c, h, w), f.device()))
        .transpose()?;
    Ok((map, grad))
}

/// [`lpips_distance`] on the values: the per-pixel map and (empty without `with_grad`) the gradient.
fn distance_planes(
    fv: &[f32],
    tv: &[f32],
    lin: &[f32],
    n: usize,
    c: usize,
    hw: usize,
    eps: f32,
    with_grad: bool,
) -> (Vec<f32>, Vec<f32>) {
    let mut map = vec![0.0f32; n * hw];
    let mut grad = if with_grad {
        vec![0.0f32; n * c * hw]
    } else {
        Vec::new()
    };
    let inv_area = 1.0 / hw.max(1) as f32;
    for i in 0..n {
        let (f, t) = (
            &fv[i * c * hw..(i + 1) * c * hw],
            &tv[i * c * hw..(i + 1) * c * hw],
        );
        let norms = channel_norms(f, c, hw);
        // Per pixel: the distance and, for the gradient, the radial term `(g·f) / (‖f‖ (‖f‖+eps)²)` with
        // `g = ∂mean/∂n = 2 lin (n − t) / area` (the derivative through `n = f / (‖f‖ + eps)`).
        let mut radial = vec![0.0f32; hw];
        map[i * hw..(i + 1) * hw]
            .par_chunks_mut(PIXEL_CHUNK)
            .zip(radial.par_chunks_mut(PIXEL_CHUNK))
            .enumerate()
            .for_each(|(k, (dist, radial))| {
                let start = k * PIXEL_CHUNK;
                let len = dist.len();
                let mut value = vec![0.0f64; len];
                let mut g_dot_f = vec![0.0f64; len];
                for ch in 0..c {
                    let at = ch * hw + start;
                    for p in 0..len {
                        let v = f[at + p];
                        let d = v / (norms[start + p] + eps) - t[at + p];
                        value[p] += f64::from(lin[ch] * d * d);
                        g_dot_f[p] += f64::from(2.0 * lin[ch] * d * inv_area) * f64::from(v);
                    }
                }
                for p in 0..len {
                    dist[p] = value[p] as f32;
                    let norm = f64::from(norms[start + p]);
                    let denom = norm + f64::from(eps);
                    // An all-zero feature vector has a zero ReLU mask anyway; skipping it avoids 0/0.
                    radial[p] = if norm > 0.0 {
                        (g_dot_f[p] / (norm * denom * denom)) as f32
                    } else {
                        0.0
                    };
                }
            });
        if with_grad {
            grad[i * c * hw..(i + 1) * c * hw]
                .par_chunks_mut(hw.max(1))
                .enumerate()
                .for_each(|(ch, plane)| {
                    for (p, g) in plane.iter_mut().enumerate() {
                        let v = f[ch * hw + p];
                        let denom = norms[p] + eps;
                        let g_n = 2.0 * lin[ch] * (v / denom - t[ch * hw + p]) * inv_area;
                        *g = g_n / denom - v * radial[p];
                    }
                });
        }
    }
    (map, grad)
}

#[cfg(test)]
mod tests {
    use candle_core::{Device, Tensor};

    use super::*;

    fn tensor(v: Vec<f32>, dims: &[usize]) -> Tensor {
        Tensor::from_vec(v, dims, &Device::Cpu).unwrap()
    }

    #[test]
    fn max_pool_drops_odd_edges_and_routes_the_gradient_to_the_first_maximum() {
        // One 3×5 plane: the last row and column are outside every window.
        let x = tensor(
            vec![
                1.0, 2.0, 7.0, 7.0, 9.0, //
                4.0, 3.0, 0.0, 5.0, 9.0, //
                9.0, 9.0, 9.0, 9.0, 9.0,
            ],
            &[1, 1, 3, 5],
        );
        let pooled = max_pool2x2(&x).unwrap();
        assert_eq!(pooled.dims(), [1, 1, 1, 2]);
        assert_eq!(values(&pooled).unwrap(), [4.0, 7.0]);
        let g = max_pool2x2_backward(&x, &tensor(vec![10.0, 20.0], &[1, 1, 1, 2])).unwrap();
        // Ties go to the first maximum in row-major window order, as torch picks it.
        assert_eq!(
            values(&g).unwrap(),
            [
                0.0, 0.0, 20.0, 0.0, 0.0, //
                10.0, 0.0, 0.0, 0.0, 0.0, //
                0.0, 0.0, 0.0, 0.0, 0.0
            ]
        );
    }

    #[test]
    fn relu_backward_keeps_the_gradient_where_the_output_is_positive() {
        let out = tensor(vec![0.0, 1.0, 0.5, 0.0], &[1, 1, 2, 2]);
        let g = relu_backward(&out, &tensor(vec![1.0, 2.0, 3.0, 4.0], &[1, 1, 2, 2])).unwrap();
        assert_eq!(values(&g).unwrap(), [0.0, 2.0, 3.0, 0.0]);
    }

    #[test]
    fn normalised_pixels_have_unit_norm() {
        let x = Tensor::randn(0f32, 1.0, (2, 5, 3, 4), &Device::Cpu).unwrap();
        let n = normalize_channels(&x, 1e-10).unwrap();
        let norms = n.sqr().unwrap().sum(1).unwrap().sqrt().unwrap();
        for v in values(&norms).unwrap() {
            assert!((v - 1.0).abs() < 1e-5, "{v}");
        }
    }

    #[test]
    fn the_distance_gradient_matches_finite_differences() {
        let dims = [1, 6, 3, 5];
        let f = Tensor::rand(0.05f32, 1.0, &dims[..], &Device::Cpu).unwrap();
        let t = normalize_channels(
            &Tensor::rand(0f32, 1.0, &dims[..], &Device::Cpu).unwrap(),
            1e-10,
        )
        .unwrap();
        let lin = Tensor::rand(0f32, 1.0, 6, &Device::Cpu).unwrap();
        let mean = |f: &Tensor| -> f64 {
            let (map, _) = lpips_distance(f, &t, &lin, 1e-10, false).unwrap();
            values(&map)
                .unwrap()
                .iter()
                .map(|&v| f64::from(v))
                .sum::<f64>()
                / 15.0
        };
        let (map, grad) = lpips_distance(&f, &t, &lin, 1e-10, true).unwrap();
        assert_eq!(map.dims(), [1, 1, 3, 5]);
        let grad = values(&grad.unwrap()).unwrap();
        let base = values(&f).unwrap();
        for i in [0, 7, 29, 44, 89] {
            let h = 1e-3;
            let at = |d: f32| {
                let mut v = base.clone();
                v[i] += d;
                mean(&tensor(v, &dims))
            };
            let numeric = (at(h) - at(-h)) / (2.0 * f64::from(h));
            assert!(
                (numeric - f64::from(grad[i])).abs() < 1e-3 * numeric.abs().max(1e-2),
                "component {i}: analytic {} numeric {numeric}",
                grad[i]
            );
        }
    }
}
