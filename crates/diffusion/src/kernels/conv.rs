//! 2-D convolution (square kernel, no dilation or groups) with an optional bias, as im2col + GEMM.
//!
//! Two CPU kernels, tuned for the two regimes:
//! - [`BandedConv2d`] (inference): candle 0.11's CPU conv2d transposes the input to NHWC on one thread and
//!   gathers im2col tiles with scattered writes; on the VAE/TAESD shapes that made it 2–5× slower than
//!   PyTorch. Here the input stays NCHW: each im2col row (input channel × kernel tap) is a run of contiguous
//!   copies, built in parallel for a band of output rows, and a single parallel GEMM per band writes straight
//!   into the NCHW output, whose rows were pre-filled with the bias. The weight [out, in, kh, kw] is already
//!   the GEMM's left operand [out, in·kh·kw], so nothing is re-laid out. Under bf16 products it makes no
//!   im2col matrix at all: [`bf16::direct_conv`] packs the input once and reads it at each tap's shift.
//! - [`BatchedConv2d`] (training, with a backward pass): one image per rayon task with single-threaded
//!   GEMMs, which suits training batches of small images far better than one parallel GEMM per image.

use candle_core::{CpuStorage, CustomOp1, CustomOp2, CustomOp3, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

use super::bf16::{self, PackedPairs, WeightLayout};
use super::ProductWeight;
use super::{cpu_f32, f32_slices, needs_grad, split_grads, Addend, Grads3, Unary};

/// im2col band size in f32 elements (~32 MB): large enough for efficient GEMMs, small enough that a
/// 512×512 SD-VAE layer does not need a >1 GB scratch matrix.
const BAND_ELEMS: usize = 8 << 20;

/// `conv2d(x, weight) + bias` for x [batch, in, h, w], weight [out, in, k, k], bias [out].
///
/// The training kernel needs a bias; a differentiated conv without one runs candle's own op, as do other
/// dtypes and devices.
///
/// The weight is an f32 tensor (`tensor.into()`) or bf16 pairs only (a model loaded for bf16 products),
/// which run without ever making the f32 weight unless the products are f32 now.
pub fn conv2d(
    x: &Tensor,
    weight: &ProductWeight,
    bias: Option<&Tensor>,
    stride: usize,
    padding: usize,
) -> Result<Tensor> {
    conv2d_add_act(x, weight, bias, stride, padding, Addend::None, None)
}

/// [`conv2d`] plus `addend`, then the activation `act`. Under bf16 products the addend is written into
/// the output with the bias before the products accumulate onto it, and a ReLU is applied as the
/// finished sums are stored (TAESD's convolutions are each followed by one): no pass of their own. The
/// f32 path adds and activates afterwards, as it always has, so its results stay bit for bit.
pub fn conv2d_add_act(
    x: &Tensor,
    weight: &ProductWeight,
    bias: Option<&Tensor>,
    stride: usize,
    padding: usize,
    addend: Addend<'_, Tensor>,
    act: Option<Unary>,
) -> Result<Tensor> {
    let mut operands = vec![x];
    operands.extend(bias);
    operands.extend(addend.term());
    if x.rank() == 4 && weight.dims().len() == 4 && cpu_f32(&operands) && !needs_grad(&operands) {
        // bf16 products use the weight packed once (kept packed, or packed on first use and cached).
        if let Some(pairs) = weight.packed(WeightLayout::Conv)? {
            let (n, c_out) = (x.dim(0)?, weight.dims()[0]);
            let mut per_channel = match bias {
                Some(b) => b.to_vec1::<f32>()?.repeat(n),
                None => Vec::new(),
            };
            if let Addend::PerChannel(t) = addend {
                let t = t.reshape(n * c_out)?.to_vec1::<f32>()?;
                per_channel.resize(n * c_out, 0.0);
                per_channel.iter_mut().zip(t).for_each(|(b, t)| *b += t);
            }
            if !per_channel.is_empty() && per_channel.len() != n * c_out {
                candle_core::bail!(
                    "conv2d: {} biases for {c_out} outputs",
                    per_channel.len() / n.max(1)
                );
            }
            let relu = act == Some(Unary::Relu);
            let op = Bf16Conv2d {
                stride,
                padding,
                per_channel,
                pairs,
                weight_shape: Shape::from(weight.dims()),
                relu,
            };
            let x = x.contiguous()?;
            let y = match addend {
                Addend::Residual(r) => x.apply_op2_no_bwd(&r.contiguous()?, &op)?,
                _ => x.apply_op1_no_bwd(&op)?,
            };
            return match act {
                Some(act) if !relu => super::cpu::unary(&y, act),
                _ => Ok(y),
            };
        }
    }
    let y = conv2d_f32(x, weight, bias, stride, padding)?;
    let y = match addend {
        Addend::None => y,
        Addend::Residual(r) => (y + r)?,
        Addend::PerChannel(t) => {
            let (n, c, _, _) = y.dims4()?;
            y.broadcast_add(&t.reshape((n, c, 1, 1))?)?
        }
    };
    match act {
        Some(act) => super::cpu::unary(&y, act),
        None => Ok(y),
    }
}

/// [`conv2d`] with f32 products (the weight's f32 values, unpacked once where only pairs are kept).
fn conv2d_f32(
    x: &Tensor,
    weight: &ProductWeight,
    bias: Option<&Tensor>,
    stride: usize,
    padding: usize,
) -> Result<Tensor> {
    let mut operands = vec![x];
    operands.extend(bias);
    let weight = weight.tensor()?;
    operands.push(&weight);
    if x.rank() == 4 && cpu_f32(&operands) {
        if !needs_grad(&operands) {
            let op = BandedConv2d {
                stride,
                padding,
                bias: bias.map(|b| b.to_vec1::<f32>()).transpose()?,
            };
            return x.contiguous()?.apply_op2_no_bwd(&weight.contiguous()?, &op);
        }
        if let Some(bias) = bias {
            return x.contiguous()?.apply_op3(
                &weight.contiguous()?,
                &bias.contiguous()?,
                BatchedConv2d { stride, padding },
            );
        }
    }
    let y = x.conv2d(&weight, padding, stride, 1, 1)?;
    match bias {
        Some(b) => y.broadcast_add(&b.reshape((1, (), 1, 1))?),
        None => Ok(y),
    }
}

// conv2d

/// Geometry of one convolution.
#[derive(Clone, Copy, Debug)]
struct ConvGeometry {
    c_in: usize,
    h: usize,
    w: usize,
    c_out: usize,
    kernel: usize,
    stride: usize,
    padding: usize,
    out_h: usize,
    out_w: usize,
}

impl ConvGeometry {
    fn new(x: &Shape, weight: &Shape, stride: usize, padding: usize) -> Result<Self> {
        let (_, c_in, h, w) = x.dims4()?;
        let (c_out, wc_in, kh, kw) = weight.dims4()?;
        if wc_in != c_in || kh != kw || stride == 0 {
            candle_core::bail!(
                "conv2d: input {x:?} does not fit weight {weight:?} (stride {stride})"
            );
        }
        if h + 2 * padding < kh || w + 2 * padding < kh {
            candle_core::bail!(
                "conv2d: input {h}x{w} too small for kernel {kh} with padding {padding}"
            );
        }
        Ok(Self {
            c_in,
            h,
            w,
            c_out,
            kernel: kh,
            stride,
            padding,
            out_h: (h + 2 * padding - kh) / stride + 1,
            out_w: (w + 2 * padding - kh) / stride + 1,
        })
    }

    /// Rows of the im2col matrix (input channel × kernel tap).
    fn k_rows(&self) -> usize {
        self.c_in * self.kernel * self.kernel
    }

    fn out_plane(&self) -> usize {
        self.out_h * self.out_w
    }

    fn in_image(&self) -> usize {
        self.c_in * self.h * self.w
    }

    /// A 1×1, stride-1, unpadded conv: the image itself is the im2col matrix.
    fn pointwise(&self) -> bool {
        self.kernel == 1 && self.stride == 1 && self.padding == 0
    }

    /// Output columns `[lo, hi)` whose input column `ox·stride + kj − padding` lies inside the image.
    fn valid_columns(&self, kj: usize) -> (usize, usize) {
        let lo = self
            .padding
            .saturating_sub(kj)
            .div_ceil(self.stride)
            .min(self.out_w);
        let hi = if self.w + self.padding > kj {
            ((self.w + self.padding - kj - 1) / self.stride + 1).min(self.out_w)
        } else {
            0
        };
        (lo, hi.max(lo))
    }

    /// Fills `dst` with row `r` (input channel × kernel tap) of the im2col matrix of one image
    /// [c_in, h, w], for the output rows from `oy0` on (`dst` holds whole output rows).
    fn im2col_row(&self, image: &[f32], r: usize, dst: &mut [f32], oy0: usize) {
        let k = self.kernel;
        let (c, ki, kj) = (r / (k * k), (r / k) % k, r % k);
        let plane = &image[c * self.h * self.w..(c + 1) * self.h * self.w];
        let (lo, hi) = self.valid_columns(kj);
        for (row, out) in dst.chunks_mut(self.out_w).enumerate() {
            let iy = ((oy0 + row) * self.stride + ki) as isize - self.padding as isize;
            if iy < 0 || iy >= self.h as isize {
                out.fill(0.0);
                continue;
            }
            let src = &plane[iy as usize * self.w..(iy as usize + 1) * self.w];
            out[..lo].fill(0.0);
            out[hi..].fill(0.0);
            let ix0 = lo * self.stride + kj - self.padding;
            if self.stride == 1 {
                out[lo..hi].copy_from_slice(&src[ix0..ix0 + (hi - lo)]);
            } else {
                for (o, v) in out[lo..hi].iter_mut().enumerate() {
                    *v = src[ix0 + o * self.stride];
                }
            }
        }
    }

    /// Fills `col` [k_rows, out_h·out_w] with the patches of one image [c_in, h, w].
    fn im2col(&self, image: &[f32], col: &mut [f32]) {
        for (r, dst) in col.chunks_mut(self.out_plane()).enumerate() {
            self.im2col_row(image, r, dst, 0);
        }
    }

    /// Fills `rows` [out_h·out_w, k_rows] with the patches of one image [c_in, h, w], one output position
    /// per row (the transpose of [`Self::im2col`]).
    fn im2row(&self, image: &[f32], rows: &mut [f32]) {
        let (k, k_rows) = (self.kernel, self.k_rows());
        for (pos, row) in rows.chunks_mut(k_rows).enumerate() {
            let (oy, ox) = (pos / self.out_w, pos % self.out_w);
            let y0 = (oy * self.stride) as isize - self.padding as isize;
            let x0 = (ox * self.stride) as isize - self.padding as isize;
            for (c, taps) in row.chunks_mut(k * k).enumerate() {
                let plane = &image[c * self.h * self.w..(c + 1) * self.h * self.w];
                for ki in 0..k {
                    let iy = y0 + ki as isize;
                    let dst = &mut taps[ki * k..(ki + 1) * k];
                    if iy < 0 || iy >= self.h as isize {
                        dst.fill(0.0);
                        continue;
                    }
                    let src = &plane[iy as usize * self.w..(iy as usize + 1) * self.w];
                    for (kj, d) in dst.iter_mut().enumerate() {
                        let ix = x0 + kj as isize;
                        *d = if ix >= 0 && ix < self.w as isize {
                            src[ix as usize]
                        } else {
                            0.0
                        };
                    }
                }
            }
        }
    }

    /// Adds the columns `col` [k_rows, out_h·out_w] back onto the image gradient [c_in, h, w].
    fn col2im(&self, col: &[f32], image: &mut [f32]) {
        let (k, plane) = (self.kernel, self.out_plane());
        for (r, src) in col.chunks(plane).enumerate() {
            let (c, ki, kj) = (r / (k * k), (r / k) % k, r % k);
            let dst_plane = &mut image[c * self.h * self.w..(c + 1) * self.h * self.w];
            let (lo, hi) = self.valid_columns(kj);
            for (oy, row) in src.chunks(self.out_w).enumerate() {
                let iy = (oy * self.stride + ki) as isize - self.padding as isize;
                if iy < 0 || iy >= self.h as isize {
                    continue;
                }
                let dst = &mut dst_plane[iy as usize * self.w..(iy as usize + 1) * self.w];
                let ix0 = lo * self.stride + kj - self.padding;
                for (o, v) in row[lo..hi].iter().enumerate() {
                    dst[ix0 + o * self.stride] += v;
                }
            }
        }
    }
}

/// `dst[m, n] (+)= lhs[m, k] · rhs[k, n]` on one thread, with explicit (column, row) strides.
fn gemm_serial(
    (m, n, k): (usize, usize, usize),
    dst: &mut [f32],
    dst_strides: (isize, isize),
    accumulate: bool,
    lhs: &[f32],
    lhs_strides: (isize, isize),
    rhs: &[f32],
    rhs_strides: (isize, isize),
) {
    // SAFETY: callers pass slices that hold every element the strides address (checked by the debug
    // asserts below for the row-major layouts used here).
    debug_assert!(dst.len() >= m * n && lhs.len() >= m * k && rhs.len() >= k * n);
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst.as_mut_ptr(),
            dst_strides.0,
            dst_strides.1,
            accumulate,
            lhs.as_ptr(),
            lhs_strides.0,
            lhs_strides.1,
            rhs.as_ptr(),
            rhs_strides.0,
            rhs_strides.1,
            1.0,
            1.0,
            false,
            false,
            false,
            gemm::Parallelism::None,
        );
    }
}

/// The training kernel: one image per rayon task; the backward pass is [`BatchedConv2dBackward`].
struct BatchedConv2d {
    stride: usize,
    padding: usize,
}

impl CustomOp3 for BatchedConv2d {
    fn name(&self) -> &'static str {
        "batched-conv2d"
    }

    fn cpu_fwd(
        &self,
        xs: &CpuStorage,
        xl: &Layout,
        ws: &CpuStorage,
        wl: &Layout,
        bs: &CpuStorage,
        bl: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let name = self.name();
        let [x, weight, bias] = f32_slices([(xs, xl), (ws, wl), (bs, bl)], name)?;
        let g = ConvGeometry::new(xl.shape(), wl.shape(), self.stride, self.padding)?;
        let batch = xl.shape().dims()[0];
        if bias.len() != g.c_out {
            candle_core::bail!(
                "conv2d: bias has {} entries for {} outputs",
                bias.len(),
                g.c_out
            );
        }
        let (k_rows, plane) = (g.k_rows(), g.out_plane());
        let mut out = vec![0f32; batch * g.c_out * plane];
        out.par_chunks_mut(g.c_out * plane)
            .enumerate()
            .for_each_init(Vec::new, |col, (n, dst)| {
                for (o, p) in dst.chunks_mut(plane).enumerate() {
                    p.fill(bias[o]);
                }
                let image = &x[n * g.in_image()..(n + 1) * g.in_image()];
                let rhs = if g.pointwise() {
                    image
                } else {
                    col.resize(k_rows * plane, 0.0);
                    g.im2col(image, col);
                    col.as_slice()
                };
                gemm_serial(
                    (g.c_out, plane, k_rows),
                    dst,
                    (1, plane as isize),
                    true,
                    weight,
                    (1, k_rows as isize),
                    rhs,
                    (1, plane as isize),
                );
            });
        Ok((
            CpuStorage::F32(out),
            Shape::from((batch, g.c_out, g.out_h, g.out_w)),
        ))
    }

    fn bwd(
        &self,
        x: &Tensor,
        weight: &Tensor,
        bias: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<Grads3> {
        let grad = grad.contiguous()?;
        let packed = x.apply_op3_no_bwd(
            weight,
            &grad,
            &BatchedConv2dBackward {
                stride: self.stride,
                padding: self.padding,
            },
        )?;
        split_grads(&packed, x, weight, bias)
    }
}

/// Gradients of [`BatchedConv2d`] from (input, weight, output gradient), packed as [dx, dweight, dbias].
struct BatchedConv2dBackward {
    stride: usize,
    padding: usize,
}

impl CustomOp3 for BatchedConv2dBackward {
    fn name(&self) -> &'static str {
        "batched-conv2d-backward"
    }

    fn cpu_fwd(
        &self,
        xs: &CpuStorage,
        xl: &Layout,
        ws: &CpuStorage,
        wl: &Layout,
        gs: &CpuStorage,
        gl: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let name = self.name();
        let [x, weight, grad] = f32_slices([(xs, xl), (ws, wl), (gs, gl)], name)?;
        let g = ConvGeometry::new(xl.shape(), wl.shape(), self.stride, self.padding)?;
        let batch = xl.shape().dims()[0];
        let (k_rows, plane, c_out) = (g.k_rows(), g.out_plane(), g.c_out);
        if grad.len() != batch * c_out * plane {
            candle_core::bail!("{name}: gradient shape {:?} does not fit", gl.shape());
        }
        let mut dx = vec![0f32; x.len()];
        let zeros = || {
            (
                vec![0f32; c_out * k_rows],
                vec![0f32; c_out],
                Vec::new(),
                Vec::new(),
            )
        };
        let (dw, db, _, _) = dx
            .par_chunks_mut(g.in_image())
            .enumerate()
            .fold(zeros, |(mut dw, mut db, mut col, mut dcol), (n, dx_n)| {
                let image = &x[n * g.in_image()..(n + 1) * g.in_image()];
                let g_n = &grad[n * c_out * plane..(n + 1) * c_out * plane];
                for (o, row) in g_n.chunks(plane).enumerate() {
                    db[o] += row.iter().sum::<f32>();
                }
                // dW [c_out, k_rows] += g_n [c_out, plane] · rows [plane, k_rows]. The patches are laid out
                // one output position per row so both GEMM operands are row-major (packing a transposed
                // im2col matrix cost more than the product itself).
                col.resize(k_rows * plane, 0.0);
                g.im2row(image, &mut col);
                gemm_serial(
                    (c_out, k_rows, plane),
                    &mut dw,
                    (1, k_rows as isize),
                    true,
                    g_n,
                    (1, plane as isize),
                    &col,
                    (1, k_rows as isize),
                );
                // dcols [k_rows, plane] = Wᵀ [k_rows, c_out] · g_n [c_out, plane]
                let target: &mut [f32] = if g.pointwise() {
                    dx_n
                } else {
                    dcol.resize(k_rows * plane, 0.0);
                    &mut dcol
                };
                gemm_serial(
                    (k_rows, plane, c_out),
                    target,
                    (1, plane as isize),
                    false,
                    weight,
                    (k_rows as isize, 1),
                    g_n,
                    (1, plane as isize),
                );
                if !g.pointwise() {
                    g.col2im(&dcol, dx_n);
                }
                (dw, db, col, dcol)
            })
            .reduce(zeros, |(mut dw, mut db, c, d), (dw2, db2, _, _)| {
                dw.iter_mut().zip(&dw2).for_each(|(a, b)| *a += b);
                db.iter_mut().zip(&db2).for_each(|(a, b)| *a += b);
                (dw, db, c, d)
            });
        let n = dx.len() + dw.len() + db.len();
        let mut packed = dx;
        packed.extend_from_slice(&dw);
        packed.extend_from_slice(&db);
        Ok((CpuStorage::F32(packed), Shape::from(n)))
    }
}

/// The inference kernel: per image, bands of output rows, each one parallel im2col fill and one parallel
/// GEMM (see the module docs).
struct BandedConv2d {
    stride: usize,
    padding: usize,
    bias: Option<Vec<f32>>,
}

impl BandedConv2d {
    /// `dst[c_out, cols] (+)= weight · rhs`, `rhs` [k_rows, cols] (row stride `cols`), `dst` rows
    /// `out_plane` apart, as an f32 GEMM on `parallelism`.
    #[allow(clippy::too_many_arguments)]
    fn product(
        &self,
        g: &ConvGeometry,
        weight: &[f32],
        rhs: &[f32],
        cols: usize,
        dst: &mut [f32],
        parallelism: gemm::Parallelism,
    ) {
        let (c_out, k_rows, out_plane) = (g.c_out, g.k_rows(), g.out_plane());
        // SAFETY: all pointers/strides describe in-bounds row-major matrices of the stated sizes: `rhs`
        // [k_rows, cols], weights [c_out, k_rows], `dst` c_out rows of `cols` at stride out_plane.
        debug_assert!(dst.len() >= c_out.saturating_sub(1) * out_plane + cols);
        unsafe {
            gemm::gemm(
                c_out,
                cols,
                k_rows,
                dst.as_mut_ptr(),
                1,
                out_plane as isize,
                self.bias.is_some(),
                weight.as_ptr(),
                1,
                k_rows as isize,
                rhs.as_ptr(),
                1,
                cols as isize,
                1.0,
                1.0,
                false,
                false,
                false,
                parallelism,
            );
        }
    }
}

/// The inference kernel under bf16 products: image by image the direct convolution over the packed
/// input ([`bf16::direct_conv`]: no im2col matrix), accumulated onto the output pre-filled with the
/// bias, the per-channel addend and the residual (the op's second operand), whichever there are.
struct Bf16Conv2d {
    stride: usize,
    padding: usize,
    /// Bias plus per-channel addend, [batch, out] (empty: none).
    per_channel: Vec<f32>,
    pairs: std::sync::Arc<PackedPairs>,
    weight_shape: Shape,
    /// A ReLU applied as the sums are stored.
    relu: bool,
}

impl Bf16Conv2d {
    fn forward(
        &self,
        xs: &[f32],
        x_shape: &Shape,
        residual: Option<&[f32]>,
    ) -> Result<(CpuStorage, Shape)> {
        let g = ConvGeometry::new(x_shape, &self.weight_shape, self.stride, self.padding)?;
        let batch = x_shape.dims()[0];
        let (c_out, plane) = (g.c_out, g.out_plane());
        let shape = Shape::from((batch, c_out, g.out_h, g.out_w));
        if residual.is_some_and(|r| r.len() != shape.elem_count()) {
            candle_core::bail!("conv2d: residual does not fit the output {shape:?}");
        }
        // One pass writes each plane's residual plus its bias (or just one of them).
        let mut out = vec![0f32; shape.elem_count()];
        if residual.is_some() || !self.per_channel.is_empty() {
            out.par_chunks_mut(plane.max(1))
                .enumerate()
                .for_each(|(i, p)| {
                    let b = self.per_channel.get(i).copied().unwrap_or(0.0);
                    match residual {
                        Some(r) => p
                            .iter_mut()
                            .zip(&r[i * plane..])
                            .for_each(|(o, r)| *o = r + b),
                        None => p.fill(b),
                    }
                });
        }
        let accumulate = residual.is_some() || !self.per_channel.is_empty();
        let dims = bf16::ConvDims {
            c_in: g.c_in,
            h: g.h,
            w: g.w,
            c_out,
            kernel: g.kernel,
            stride: g.stride,
            padding: g.padding,
            out_h: g.out_h,
            out_w: g.out_w,
        };
        bf16::direct_conv(&dims, &self.pairs, xs, &mut out, accumulate, self.relu);
        Ok((CpuStorage::F32(out), shape))
    }
}

impl CustomOp1 for Bf16Conv2d {
    fn name(&self) -> &'static str {
        "conv2d-bf16"
    }

    fn cpu_fwd(&self, xs: &CpuStorage, xl: &Layout) -> Result<(CpuStorage, Shape)> {
        let [xs] = f32_slices([(xs, xl)], CustomOp1::name(self))?;
        self.forward(xs, xl.shape(), None)
    }
}

impl CustomOp2 for Bf16Conv2d {
    fn name(&self) -> &'static str {
        "conv2d-bf16-residual"
    }

    fn cpu_fwd(
        &self,
        xs: &CpuStorage,
        xl: &Layout,
        rs: &CpuStorage,
        rl: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let [xs, rs] = f32_slices([(xs, xl), (rs, rl)], CustomOp2::name(self))?;
        self.forward(xs, xl.shape(), Some(rs))
    }
}

impl CustomOp2 for BandedConv2d {
    fn name(&self) -> &'static str {
        "banded-conv2d"
    }

    fn cpu_fwd(
        &self,
        xs: &CpuStorage,
        xl: &Layout,
        ws: &CpuStorage,
        wl: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let [xs, ws] = f32_slices([(xs, xl), (ws, wl)], CustomOp2::name(self))?;
        self.forward(xs, xl.shape(), wl.shape(), ws)
    }
}

impl BandedConv2d {
    /// The convolution of `xs` (contiguous, `x_shape`) by the f32 weight `ws` of `w_shape`.
    fn forward(
        &self,
        xs: &[f32],
        x_shape: &Shape,
        w_shape: &Shape,
        ws: &[f32],
    ) -> Result<(CpuStorage, Shape)> {
        let g = ConvGeometry::new(x_shape, w_shape, self.stride, self.padding)?;
        let batch = x_shape.dims()[0];
        let (c_out, k_rows, out_plane, out_w) = (g.c_out, g.k_rows(), g.out_plane(), g.out_w);

        // Pre-fill with the bias so the GEMM accumulates onto it.
        let mut out = vec![0f32; batch * c_out * out_plane];
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
        let band_rows = (BAND_ELEMS / (k_rows * out_w).max(1)).clamp(1, g.out_h);
        let mut col = if g.pointwise() {
            Vec::new()
        } else {
            vec![0f32; k_rows * band_rows * out_w]
        };
        for n in 0..batch {
            let input = &xs[n * g.in_image()..(n + 1) * g.in_image()];
            let dst = &mut out[n * c_out * out_plane..(n + 1) * c_out * out_plane];
            if g.pointwise() {
                // The input plane is already the [c_in, h·w] right operand.
                self.product(&g, ws, input, out_plane, dst, parallelism);
                continue;
            }
            let mut oy0 = 0;
            while oy0 < g.out_h {
                let rows = band_rows.min(g.out_h - oy0);
                let band = rows * out_w;
                let col = &mut col[..k_rows * band];
                col.par_chunks_mut(band)
                    .enumerate()
                    .for_each(|(r, dst)| g.im2col_row(input, r, dst, oy0));
                // dst[c_out, band] sits at column offset oy0·out_w of each output plane (row stride out_plane).
                self.product(&g, ws, col, band, &mut dst[oy0 * out_w..], parallelism);
                oy0 += rows;
            }
        }
        Ok((
            CpuStorage::F32(out),
            Shape::from((batch, c_out, g.out_h, out_w)),
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::super::test_support::{check_gradients, max_diff, var};
    use super::*;
    use candle_core::{Device, Var};

    /// candle's conv2d plus a broadcast bias.
    fn reference(
        x: &Tensor,
        w: &Tensor,
        b: Option<&Tensor>,
        stride: usize,
        padding: usize,
    ) -> Tensor {
        let y = x.conv2d(w, padding, stride, 1, 1).unwrap();
        match b {
            Some(b) => y.broadcast_add(&b.reshape((1, (), 1, 1)).unwrap()).unwrap(),
            None => y,
        }
    }

    /// The inference kernel against candle's conv over kernels, strides, paddings, odd sizes and batches.
    #[test]
    fn inference_matches_candle() {
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
            let fast = conv2d(&x, &wt.clone().into(), bt.as_ref(), s, p).unwrap();
            let want = reference(&x, &wt, bt.as_ref(), s, p);
            assert_eq!(fast.dims(), want.dims());
            let d = max_diff(&fast, &want);
            assert!(d < 1e-4, "case {:?}: {d}", (b, ci, co, h, w, k, s, p, bias));
        }
    }

    /// With bf16 products (where the CPU has them) the inference kernel stays within bf16's rounding of
    /// candle's f32 conv (relative L2 ≤ 5e-3; above 1e-5, so the bf16 path ran), and drops back to f32
    /// for a weight that tracks gradients.
    #[test]
    fn inference_with_bf16_products_is_within_bf16_rounding() {
        use super::super::bf16::{with_cpu_precision, CpuPrecision};
        let dev = Device::Cpu;
        let cases = [
            // (batch, c_in, c_out, h, w, kernel, stride, padding, bias)
            (2, 8, 13, 9, 7, 3, 1, 1, true),
            (1, 16, 40, 8, 8, 3, 2, 1, false),
            (2, 33, 5, 6, 6, 1, 1, 0, true),
            (1, 7, 3, 5, 4, 3, 1, 0, true),
        ];
        for (b, ci, co, h, w, k, s, p, bias) in cases {
            let x = Tensor::randn(0f32, 1.0, (b, ci, h, w), &dev).unwrap();
            let wt = Tensor::randn(0f32, 1.0, (co, ci, k, k), &dev).unwrap();
            let bt = bias.then(|| Tensor::randn(0f32, 1.0, co, &dev).unwrap());
            let Ok(fast) = with_cpu_precision(CpuPrecision::Bf16, || {
                conv2d(&x, &wt.clone().into(), bt.as_ref(), s, p).unwrap()
            }) else {
                eprintln!("skipped: no AVX512-BF16 on this CPU");
                return;
            };
            let want = reference(&x, &wt, bt.as_ref(), s, p);
            let diff = (&fast - &want).unwrap().sqr().unwrap().sum_all().unwrap();
            let norm = want.sqr().unwrap().sum_all().unwrap();
            let rel = (diff.to_scalar::<f32>().unwrap() / norm.to_scalar::<f32>().unwrap()).sqrt();
            let case = (b, ci, co, h, w, k, s, p, bias);
            assert!(
                rel <= 5e-3 && rel > 1e-5,
                "case {case:?}: relative L2 {rel}"
            );
        }
        let w = Var::randn(0f32, 1.0, (2, 3, 3, 3), &dev).unwrap();
        let x = Tensor::randn(0f32, 1.0, (1, 3, 5, 5), &dev).unwrap();
        let trained = with_cpu_precision(CpuPrecision::Bf16, || {
            conv2d(&x, &w.as_tensor().clone().into(), None, 1, 1).unwrap()
        });
        if let Ok(trained) = trained {
            assert!(max_diff(&trained, &reference(&x, w.as_tensor(), None, 1, 1)) < 1e-4);
        }
    }

    /// Band splitting (several GEMMs per image) gives the same result as one band.
    #[test]
    fn banded_output_is_seamless() {
        let dev = Device::Cpu;
        let (ci, h, w) = (32, 600, 4096 / 8);
        assert!(ci * 9 * w * h > BAND_ELEMS);
        let x = Tensor::randn(0f32, 1.0, (1, ci, h, w), &dev).unwrap();
        let wt = Tensor::randn(0f32, 0.1, (2, ci, 3, 3), &dev).unwrap();
        let d = max_diff(
            &conv2d(&x, &wt.clone().into(), None, 1, 1).unwrap(),
            &reference(&x, &wt, None, 1, 1),
        );
        assert!(d < 1e-4, "{d}");
    }

    #[test]
    fn training_matches_candle_with_gradients() {
        // (batch, c_in, c_out, h, w, kernel, stride, padding)
        let cases = [
            (2, 3, 5, 9, 7, 3, 1, 1),
            (3, 4, 6, 8, 8, 3, 2, 1),
            (2, 4, 3, 9, 6, 3, 2, 0),
            (2, 6, 2, 5, 5, 1, 1, 0),
            (1, 2, 3, 4, 5, 3, 1, 2),
            (2, 3, 4, 6, 6, 1, 2, 0),
        ];
        for (b, ci, co, h, w, k, s, p) in cases {
            let vars = [
                var(&[b, ci, h, w], 0.0, 1.0),
                var(&[co, ci, k, k], 0.0, 0.5),
                var(&[co], 0.0, 1.0),
            ];
            check_gradients(
                &vars,
                |t| conv2d(&t[0], &t[1].clone().into(), Some(&t[2]), s, p).unwrap(),
                |t| {
                    // candle's conv backward mis-sizes the input gradient when a strided conv leaves
                    // trailing rows/columns unused; the reference crops them away (their gradient is 0).
                    // (Only unpadded cases leave such a remainder here.)
                    let used = |n: usize| if p == 0 { (n - k) / s * s + k } else { n };
                    let x = t[0].narrow(2, 0, used(h)).unwrap();
                    let x = x.narrow(3, 0, used(w)).unwrap();
                    reference(&x, &t[1], Some(&t[2]), s, p)
                },
                &format!("conv {:?}", (b, ci, co, h, w, k, s, p)),
            );
        }
    }

    #[test]
    fn training_without_bias_has_gradients() {
        let dev = Device::Cpu;
        let w = Var::randn(0f32, 1.0, (2, 3, 3, 3), &dev).unwrap();
        let x = Tensor::randn(0f32, 1.0, (1, 3, 5, 5), &dev).unwrap();
        let grads = conv2d(&x, &w.as_tensor().clone().into(), None, 1, 1)
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        assert!(grads.get(w.as_tensor()).is_some());
    }
}
