//! 2-D convolution with a faster CPU inference path than candle's.
//!
//! candle 0.11's CPU conv2d transposes the input to NHWC on one thread and gathers im2col tiles with scattered
//! writes; on the VAE/TAESD shapes that made it 2–5× slower than PyTorch. Here, when nothing needs gradients
//! (f32, CPU), the input stays NCHW: each im2col row (input channel × kernel tap) is a run of contiguous
//! copies, built in parallel for a band of output rows, and a single GEMM per band writes straight into the
//! NCHW output, whose rows were pre-filled with the bias. The weight [out, in, kh, kw] is already the GEMM's
//! left operand [out, in·kh·kw], so nothing is re-laid out. With gradients (training) the fused kernel of
//! [`crate::train_ops::conv2d`] runs (it has a backward pass), or candle's own op where that does not apply.

use candle_core::{CpuStorage, CustomOp2, DType, Layout, Module, Result, Shape, Tensor, WithDType};
use candle_nn::VarBuilder;
use rayon::prelude::*;

/// im2col band size in f32 elements (~32 MB): large enough for efficient GEMMs, small enough that a
/// 512×512 SD-VAE layer does not need a >1 GB scratch matrix.
const BAND_ELEMS: usize = 8 << 20;

/// A square-kernel `nn.Conv2d` (no dilation, no groups) with keys `weight` and optional `bias`.
#[derive(Debug, Clone)]
pub struct Conv2d {
    weight: Tensor,
    bias: Option<Tensor>,
    stride: usize,
    padding: usize,
}

impl Conv2d {
    /// `weight` [out, in, k, k], `bias` [out].
    pub fn new(weight: Tensor, bias: Option<Tensor>, stride: usize, padding: usize) -> Self {
        Self {
            weight,
            bias,
            stride,
            padding,
        }
    }

    /// Loads `weight` (and `bias` when `bias` is true) under `vb`.
    pub fn load(
        in_channels: usize,
        out_channels: usize,
        kernel: usize,
        stride: usize,
        padding: usize,
        bias: bool,
        vb: VarBuilder,
    ) -> Result<Self> {
        let weight = vb.get_with_hints(
            (out_channels, in_channels, kernel, kernel),
            "weight",
            candle_nn::init::DEFAULT_KAIMING_NORMAL,
        )?;
        let bias = if bias {
            let bound = 1.0 / ((in_channels * kernel * kernel) as f64).sqrt();
            Some(vb.get_with_hints(
                out_channels,
                "bias",
                candle_nn::Init::Uniform {
                    lo: -bound,
                    up: bound,
                },
            )?)
        } else {
            None
        };
        Ok(Self::new(weight, bias, stride, padding))
    }

    pub fn weight(&self) -> &Tensor {
        &self.weight
    }

    pub fn bias(&self) -> Option<&Tensor> {
        self.bias.as_ref()
    }

    /// The reference path: candle's differentiable conv2d plus a broadcast bias.
    fn forward_candle(&self, x: &Tensor) -> Result<Tensor> {
        let y = x.conv2d(&self.weight, self.padding, self.stride, 1, 1)?;
        match &self.bias {
            Some(b) => y.broadcast_add(&b.reshape((1, (), 1, 1))?),
            None => Ok(y),
        }
    }
}

impl Module for Conv2d {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let mut operands = vec![x, &self.weight];
        operands.extend(self.bias.as_ref());
        let fast = x.device().is_cpu()
            && operands
                .iter()
                .all(|t| t.dtype() == DType::F32 && !t.track_op())
            && x.rank() == 4;
        if !fast {
            // Training: the fused kernel with its own backward pass when it applies (f32, CPU, bias).
            if let Some(bias) = &self.bias {
                if x.rank() == 4 && crate::train_ops::supported(&[x, &self.weight, bias]) {
                    return crate::train_ops::conv2d(
                        x,
                        &self.weight,
                        bias,
                        self.stride,
                        self.padding,
                    );
                }
            }
            return self.forward_candle(x);
        }
        let bias = match &self.bias {
            Some(b) => Some(b.to_vec1::<f32>()?),
            None => None,
        };
        let op = Im2ColGemm {
            stride: self.stride,
            padding: self.padding,
            bias,
        };
        x.contiguous()?
            .apply_op2_no_bwd(&self.weight.contiguous()?, &op)
    }
}

struct Im2ColGemm {
    stride: usize,
    padding: usize,
    bias: Option<Vec<f32>>,
}

/// Fills `col` ([k_rows, rows·out_w], row-major) with the input patches of output rows `oy0..oy0+rows`.
#[allow(clippy::too_many_arguments)]
fn fill_band(
    col: &mut [f32],
    input: &[f32],
    (h, w): (usize, usize),
    (kernel, stride, padding): (usize, usize, usize),
    out_w: usize,
    oy0: usize,
    rows: usize,
) {
    let band = rows * out_w;
    col.par_chunks_mut(band).enumerate().for_each(|(r, dst)| {
        let c = r / (kernel * kernel);
        let ki = (r / kernel) % kernel;
        let kj = r % kernel;
        let plane = &input[c * h * w..(c + 1) * h * w];
        // Output columns whose input column kj + ox·stride − padding lies inside [0, w).
        let ox_lo = padding.saturating_sub(kj).div_ceil(stride).min(out_w);
        let ox_hi = if w + padding > kj {
            ((w + padding - kj - 1) / stride + 1).min(out_w)
        } else {
            0
        }
        .max(ox_lo);
        for (row, out) in dst.chunks_mut(out_w).enumerate() {
            let iy = ((oy0 + row) * stride + ki) as isize - padding as isize;
            if iy < 0 || iy >= h as isize {
                out.fill(0.0);
                continue;
            }
            let src = &plane[iy as usize * w..(iy as usize + 1) * w];
            out[..ox_lo].fill(0.0);
            out[ox_hi..].fill(0.0);
            let ix0 = ox_lo * stride + kj - padding;
            if stride == 1 {
                out[ox_lo..ox_hi].copy_from_slice(&src[ix0..ix0 + (ox_hi - ox_lo)]);
            } else {
                for (o, v) in out[ox_lo..ox_hi].iter_mut().enumerate() {
                    *v = src[ix0 + o * stride];
                }
            }
        }
    });
}

impl CustomOp2 for Im2ColGemm {
    fn name(&self) -> &'static str {
        "im2col-gemm-conv2d"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (CpuStorage::F32(xs), CpuStorage::F32(ws)) = (s1, s2) else {
            candle_core::bail!("conv2d fast path expects f32 input and weight");
        };
        let (Some((x0, x1)), Some((w0, w1))) = (l1.contiguous_offsets(), l2.contiguous_offsets())
        else {
            candle_core::bail!("conv2d fast path expects contiguous operands");
        };
        let (xs, ws) = (&xs[x0..x1], &ws[w0..w1]);
        let (b, c_in, h, w) = l1.shape().dims4()?;
        let (c_out, wc_in, kh, kw) = l2.shape().dims4()?;
        if wc_in != c_in || kh != kw {
            candle_core::bail!(
                "conv2d: input {:?} does not fit weight {:?}",
                l1.shape(),
                l2.shape()
            );
        }
        let (kernel, stride, padding) = (kh, self.stride, self.padding);
        if stride == 0 || h + 2 * padding < kernel || w + 2 * padding < kernel {
            candle_core::bail!(
                "conv2d: input {h}x{w} too small for kernel {kernel} with padding {padding}"
            );
        }
        let out_h = (h + 2 * padding - kernel) / stride + 1;
        let out_w = (w + 2 * padding - kernel) / stride + 1;
        let k_rows = c_in * kernel * kernel;
        let out_plane = out_h * out_w;

        // Pre-fill with the bias so the GEMM accumulates onto it.
        let mut out = vec![0f32; b * c_out * out_plane];
        if let Some(bias) = &self.bias {
            if bias.len() != c_out {
                candle_core::bail!(
                    "conv2d: bias has {} entries for {c_out} outputs",
                    bias.len()
                );
            }
            out.par_chunks_mut(out_plane)
                .enumerate()
                .for_each(|(i, plane)| plane.fill(bias[i % c_out]));
        }
        let parallelism = gemm::Parallelism::Rayon(rayon::current_num_threads().max(1));
        let pointwise = kernel == 1 && stride == 1 && padding == 0;
        let band_rows = (BAND_ELEMS / (k_rows * out_w).max(1)).clamp(1, out_h);
        let mut col = if pointwise {
            Vec::new()
        } else {
            vec![0f32; k_rows * band_rows * out_w]
        };
        for n in 0..b {
            let input = &xs[n * c_in * h * w..(n + 1) * c_in * h * w];
            let dst = &mut out[n * c_out * out_plane..(n + 1) * c_out * out_plane];
            if pointwise {
                // The input plane is already the [c_in, h·w] right operand.
                // SAFETY: all pointers/strides describe in-bounds row-major matrices of the stated sizes.
                unsafe {
                    gemm::gemm(
                        c_out,
                        out_plane,
                        c_in,
                        dst.as_mut_ptr(),
                        1,
                        out_plane as isize,
                        self.bias.is_some(),
                        ws.as_ptr(),
                        1,
                        c_in as isize,
                        input.as_ptr(),
                        1,
                        out_plane as isize,
                        1.0,
                        1.0,
                        false,
                        false,
                        false,
                        parallelism,
                    );
                }
                continue;
            }
            let mut oy0 = 0;
            while oy0 < out_h {
                let rows = band_rows.min(out_h - oy0);
                let band = rows * out_w;
                let col = &mut col[..k_rows * band];
                fill_band(
                    col,
                    input,
                    (h, w),
                    (kernel, stride, padding),
                    out_w,
                    oy0,
                    rows,
                );
                // dst[c_out, band] sits at column offset oy0·out_w of each output plane (row stride out_plane).
                // SAFETY: in-bounds as above; `col` is [k_rows, band], weights [c_out, k_rows].
                unsafe {
                    gemm::gemm(
                        c_out,
                        band,
                        k_rows,
                        dst.as_mut_ptr().add(oy0 * out_w),
                        1,
                        out_plane as isize,
                        self.bias.is_some(),
                        ws.as_ptr(),
                        1,
                        k_rows as isize,
                        col.as_ptr(),
                        1,
                        band as isize,
                        1.0,
                        1.0,
                        false,
                        false,
                        false,
                        parallelism,
                    );
                }
                oy0 += rows;
            }
        }
        Ok((
            f32::to_cpu_storage_owned(out),
            Shape::from((b, c_out, out_h, out_w)),
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, Var};

    fn max_diff(a: &Tensor, b: &Tensor) -> f32 {
        (a - b)
            .unwrap()
            .abs()
            .unwrap()
            .flatten_all()
            .unwrap()
            .max(0)
            .unwrap()
            .to_scalar()
            .unwrap()
    }

    /// The fast path against candle's conv over kernels, strides, paddings, odd sizes and batches.
    #[test]
    fn fast_path_matches_candle() {
        let dev = Device::Cpu;
        let cases = [
            // (batch, c_in, c_out, h, w, kernel, stride, padding, bias)
            (2, 3, 5, 9, 7, 3, 1, 1, true),
            (1, 4, 6, 8, 8, 3, 2, 1, false),
            (2, 4, 3, 9, 6, 3, 2, 0, true),
            (1, 6, 2, 5, 5, 1, 1, 0, true),
            (2, 5, 4, 7, 3, 1, 2, 0, false),
            (1, 2, 3, 4, 5, 3, 1, 2, true),
            (1, 3, 3, 3, 3, 3, 1, 0, true),
        ];
        for (b, ci, co, h, w, k, s, p, bias) in cases {
            let x = Tensor::randn(0f32, 1.0, (b, ci, h, w), &dev).unwrap();
            let wt = Tensor::randn(0f32, 1.0, (co, ci, k, k), &dev).unwrap();
            let bt = bias.then(|| Tensor::randn(0f32, 1.0, co, &dev).unwrap());
            let conv = Conv2d::new(wt, bt, s, p);
            let fast = conv.forward(&x).unwrap();
            let reference = conv.forward_candle(&x).unwrap();
            assert_eq!(fast.dims(), reference.dims());
            let d = max_diff(&fast, &reference);
            assert!(d < 1e-4, "case {:?}: {d}", (b, ci, co, h, w, k, s, p, bias));
        }
    }

    /// Band splitting (several GEMMs per image) gives the same result as one band.
    #[test]
    fn banded_output_is_seamless() {
        let dev = Device::Cpu;
        // k_rows·out_w = 288·4096 > BAND_ELEMS/… forces several bands for a tall image.
        let (ci, h, w) = (32, 600, 4096 / 8);
        let x = Tensor::randn(0f32, 1.0, (1, ci, h, w), &dev).unwrap();
        let wt = Tensor::randn(0f32, 0.1, (2, ci, 3, 3), &dev).unwrap();
        let conv = Conv2d::new(wt, None, 1, 1);
        assert!(ci * 9 * w * h > BAND_ELEMS);
        let d = max_diff(
            &conv.forward(&x).unwrap(),
            &conv.forward_candle(&x).unwrap(),
        );
        assert!(d < 1e-4, "{d}");
    }

    #[test]
    fn training_path_has_gradients() {
        let dev = Device::Cpu;
        let w = Var::randn(0f32, 1.0, (2, 3, 3, 3), &dev).unwrap();
        let conv = Conv2d::new(w.as_tensor().clone(), None, 1, 1);
        let x = Tensor::randn(0f32, 1.0, (1, 3, 5, 5), &dev).unwrap();
        let grads = conv
            .forward(&x)
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        assert!(grads.get(w.as_tensor()).is_some());
    }
}
