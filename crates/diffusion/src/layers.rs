//! Building blocks shared by the UNet and the VAE, loaded by diffusers key names.
//!
//! Every layer has two execution paths chosen per call:
//! - **inference** (no operand tracks gradients): fused CPU kernels (group norm + SiLU, softmax, layer norm)
//!   that avoid intermediate tensors;
//! - **training** (an input or a weight is a `Var` or depends on one): kernels with backward passes
//!   ([`crate::train_ops`]: conv, group norm (+ SiLU), layer norm, softmax, GEGLU for f32 on the CPU) and composite
//!   candle ops elsewhere, so `Tensor::backward` works through the whole network.
//!
//! The choice is automatic (see [`needs_grad`]), so the same model code serves both.

use candle_core::{CpuStorage, CustomOp1, DType, Device, Layout, Module, Result, Shape, Tensor, D};
use candle_nn::{Linear, VarBuilder};
use rayon::prelude::*;

use crate::conv::Conv2d;

/// True when the computation must stay differentiable: any of the given tensors is a variable or was
/// computed from one. Fused kernels have no backward pass, so they are used only when this is false.
pub fn needs_grad(tensors: &[&Tensor]) -> bool {
    tensors.iter().any(|t| t.track_op())
}

/// Makes glibc's allocator keep large blocks in the heap instead of `mmap`ing and unmapping them per
/// allocation. UNet activations at batch 6 are 30–250 MB each; with glibc's defaults every one is a fresh
/// mapping that the kernel must fault in and zero (about 13% of a batch-6 SD 1.5 forward). After this
/// call freed memory is reused instead (the process keeps its peak heap until exit, which suits a CLI).
/// Process-wide; a no-op on other platforms. Call once at startup, before heavy work.
pub fn tune_allocator_for_inference() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        extern "C" {
            fn mallopt(param: i32, value: i32) -> i32;
        }
        const M_TRIM_THRESHOLD: i32 = -1;
        const M_TOP_PAD: i32 = -2;
        const M_MMAP_MAX: i32 = -4;
        // SAFETY: mallopt only changes allocator tuning parameters; these values are valid for glibc.
        unsafe {
            mallopt(M_MMAP_MAX, 0);
            mallopt(M_TRIM_THRESHOLD, i32::MAX);
            mallopt(M_TOP_PAD, 256 << 20);
        }
    }
}

/// Loads a `nn.Linear` (`weight` [out, in], optional `bias` [out]) under `vb`.
pub fn linear(in_dim: usize, out_dim: usize, bias: bool, vb: VarBuilder) -> Result<Linear> {
    if bias {
        candle_nn::linear(in_dim, out_dim, vb)
    } else {
        candle_nn::linear_no_bias(in_dim, out_dim, vb)
    }
}

/// Loads a square `nn.Conv2d` with bias (`weight` [out, in, k, k], `bias` [out]) under `vb`.
pub fn conv2d(
    in_channels: usize,
    out_channels: usize,
    kernel: usize,
    stride: usize,
    padding: usize,
    vb: VarBuilder,
) -> Result<Conv2d> {
    // crate::conv::Conv2d: candle's conv when differentiating, a faster im2col+GEMM kernel otherwise.
    Conv2d::load(in_channels, out_channels, kernel, stride, padding, true, vb)
}

/// Applies SiLU, `x * sigmoid(x)` (candle's unary op has a backward pass).
pub fn silu(x: &Tensor) -> Result<Tensor> {
    x.silu()
}

/// Softmax over the last dimension: fused kernel for inference; when differentiating, the fused training
/// kernel (f32 CPU) or composite ops.
pub fn softmax_last_dim(x: &Tensor) -> Result<Tensor> {
    if needs_grad(&[x]) && crate::train_ops::supported(&[x]) {
        crate::train_ops::softmax_last_dim(x)
    } else if needs_grad(&[x]) || !x.device().is_cpu() {
        candle_nn::ops::softmax(x, D::Minus1)
    } else {
        candle_nn::ops::softmax_last_dim(x)
    }
}

/// `nn.LayerNorm` over the last dimension with weight and bias (keys `weight`, `bias`).
#[derive(Debug, Clone)]
pub struct LayerNorm {
    weight: Tensor,
    bias: Tensor,
    eps: f64,
}

impl LayerNorm {
    pub fn load(dim: usize, eps: f64, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            // The hints only matter when training from scratch (a VarMap): identity affine map.
            weight: vb.get_with_hints(dim, "weight", candle_nn::Init::Const(1.0))?,
            bias: vb.get_with_hints(dim, "bias", candle_nn::Init::Const(0.0))?,
            eps,
        })
    }

    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        if !needs_grad(&[x, &self.weight, &self.bias]) && x.device().is_cpu() {
            let x = x.contiguous()?;
            return candle_nn::ops::layer_norm(&x, &self.weight, &self.bias, self.eps as f32);
        }
        if crate::train_ops::supported(&[x, &self.weight, &self.bias]) {
            return crate::train_ops::layer_norm(x, &self.weight, &self.bias, self.eps);
        }
        let dim = x.dim(D::Minus1)? as f64;
        let mean = (x.sum_keepdim(D::Minus1)? / dim)?;
        let centred = x.broadcast_sub(&mean)?;
        let var = (centred.sqr()?.sum_keepdim(D::Minus1)? / dim)?;
        let normed = centred.broadcast_div(&(var + self.eps)?.sqrt()?)?;
        normed
            .broadcast_mul(&self.weight)?
            .broadcast_add(&self.bias)
    }
}

/// `nn.GroupNorm` with affine weight/bias (keys `weight`, `bias`) over [batch, channels, ...].
#[derive(Debug, Clone)]
pub struct GroupNorm {
    weight: Tensor,
    bias: Tensor,
    num_groups: usize,
    eps: f64,
}

impl GroupNorm {
    pub fn load(num_groups: usize, channels: usize, eps: f64, vb: VarBuilder) -> Result<Self> {
        if num_groups == 0 || !channels.is_multiple_of(num_groups) {
            candle_core::bail!(
                "group norm {}: {channels} channels are not divisible into {num_groups} groups",
                vb.prefix()
            );
        }
        Ok(Self {
            // The hints only matter when training from scratch (a VarMap): identity affine map.
            weight: vb.get_with_hints(channels, "weight", candle_nn::Init::Const(1.0))?,
            bias: vb.get_with_hints(channels, "bias", candle_nn::Init::Const(0.0))?,
            num_groups,
            eps,
        })
    }

    /// Group norm alone.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        self.run(x, false)
    }

    /// Group norm followed by SiLU (the pairing used throughout ResNet blocks), fused on the fast path.
    pub fn forward_silu(&self, x: &Tensor) -> Result<Tensor> {
        self.run(x, true)
    }

    fn run(&self, x: &Tensor, with_silu: bool) -> Result<Tensor> {
        let dims = x.dims().to_vec();
        if dims.len() < 3 {
            candle_core::bail!("group norm expects [batch, channels, ...], got {:?}", dims);
        }
        let fast = x.dtype() == DType::F32
            && x.device().is_cpu()
            && !needs_grad(&[x, &self.weight, &self.bias]);
        if fast {
            let op = GroupNormOp {
                weight: self.weight.to_vec1::<f32>()?,
                bias: self.bias.to_vec1::<f32>()?,
                num_groups: self.num_groups,
                eps: self.eps as f32,
                with_silu,
                channels: dims[1],
            };
            return x.apply_op1_no_bwd(&op);
        }
        if crate::train_ops::supported(&[x, &self.weight, &self.bias]) {
            return crate::train_ops::group_norm(
                x,
                &self.weight,
                &self.bias,
                self.num_groups,
                self.eps,
                with_silu,
            );
        }
        let (batch, channels) = (dims[0], dims[1]);
        // Half-precision inputs are normalised in f32; f32/f64 stay as they are.
        let internal = match x.dtype() {
            DType::F16 | DType::BF16 => DType::F32,
            other => other,
        };
        let grouped = x
            .to_dtype(internal)?
            .reshape((batch, self.num_groups, ()))?;
        let n = grouped.dim(2)? as f64;
        let mean = (grouped.sum_keepdim(2)? / n)?;
        let centred = grouped.broadcast_sub(&mean)?;
        let var = (centred.sqr()?.sum_keepdim(2)? / n)?;
        let normed = centred.broadcast_div(&(var + self.eps)?.sqrt()?)?;
        let mut wshape = vec![1usize; dims.len()];
        wshape[1] = channels;
        let out = normed
            .reshape(dims.as_slice())?
            .broadcast_mul(&self.weight.to_dtype(internal)?.reshape(wshape.as_slice())?)?
            .broadcast_add(&self.bias.to_dtype(internal)?.reshape(wshape.as_slice())?)?;
        let out = if with_silu { out.silu()? } else { out };
        out.to_dtype(x.dtype())
    }
}

/// Fused CPU group norm (+ optional SiLU) for f32; one rayon task per (sample, group).
struct GroupNormOp {
    weight: Vec<f32>,
    bias: Vec<f32>,
    num_groups: usize,
    eps: f32,
    with_silu: bool,
    channels: usize,
}

impl CustomOp1 for GroupNormOp {
    fn name(&self) -> &'static str {
        "group-norm"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> Result<(CpuStorage, Shape)> {
        let src = match storage {
            CpuStorage::F32(v) => v,
            _ => candle_core::bail!("group-norm fast path expects f32"),
        };
        let src = match layout.contiguous_offsets() {
            Some((start, end)) => &src[start..end],
            None => candle_core::bail!("group-norm fast path expects a contiguous input"),
        };
        let shape = layout.shape().clone();
        let per_channel: usize = shape.dims()[2..].iter().product();
        let per_group = per_channel * (self.channels / self.num_groups);
        let mut dst = vec![0f32; src.len()];
        if per_group == 0 {
            return Ok((CpuStorage::F32(dst), shape));
        }
        let group_channels = self.channels / self.num_groups;
        dst.par_chunks_mut(per_group)
            .zip(src.par_chunks(per_group))
            .enumerate()
            .for_each(|(index, (out, inp))| {
                let group = index % self.num_groups;
                // Two-pass statistics in f64: cheap next to the data pass and robust for large groups.
                let mean = inp.iter().map(|&v| v as f64).sum::<f64>() / per_group as f64;
                let var = inp
                    .iter()
                    .map(|&v| {
                        let d = v as f64 - mean;
                        d * d
                    })
                    .sum::<f64>()
                    / per_group as f64;
                let inv_std = (1.0 / (var + self.eps as f64).sqrt()) as f32;
                let mean = mean as f32;
                for c in 0..group_channels {
                    let channel = group * group_channels + c;
                    let scale = self.weight[channel] * inv_std;
                    let shift = self.bias[channel] - mean * scale;
                    let range = c * per_channel..(c + 1) * per_channel;
                    let (o, i) = (&mut out[range.clone()], &inp[range]);
                    affine_silu(o, i, scale, shift, self.with_silu);
                }
            });
        Ok((CpuStorage::F32(dst), shape))
    }
}

/// How many query rows one attention chunk may hold so the score matrix stays near `MAX_SCORE_ELEMENTS`.
const MAX_SCORE_ELEMENTS: usize = 1 << 25;

/// Score-block size of the fused kernel in f32 elements (~1 MB, so a block stays in L2 between the two
/// GEMMs and the softmax).
const FUSED_BLOCK_ELEMENTS: usize = 1 << 18;

/// Scaled dot-product attention `softmax(q kᵀ · scale) v` for q [.., q_len, d], k [.., k_len, d],
/// v [.., k_len, dv].
///
/// Inference on CPU/f32 runs a fused kernel: per (batch·head, block of queries) one GEMM for the scores,
/// an in-place softmax and one GEMM for the output, in parallel, never materialising the full
/// q_len × k_len map (1 GB per head batch at 64×64 latents). Other dtypes/devices split the work into
/// query chunks of at most ~128 MB of scores; the differentiable path uses plain composite ops.
pub fn scaled_dot_product_attention(
    q: &Tensor,
    k: &Tensor,
    v: &Tensor,
    scale: f64,
) -> Result<Tensor> {
    let training = needs_grad(&[q, k, v]);
    let fused_ok = [q, k, v]
        .iter()
        .all(|t| t.dtype() == DType::F32 && t.device().is_cpu());
    if !training && fused_ok && q.rank() >= 3 {
        let (q, k, v) = (q.contiguous()?, k.contiguous()?, v.contiguous()?);
        return q.apply_op3_no_bwd(
            &k,
            &v,
            &FusedAttention {
                scale: scale as f32,
            },
        );
    }
    let q_len = q.dim(D::Minus2)?;
    let k_len = k.dim(D::Minus2)?;
    let leading: usize = q.dims()[..q.rank() - 2].iter().product();
    let kt = k.transpose(D::Minus1, D::Minus2)?;
    let rows = (MAX_SCORE_ELEMENTS / (leading * k_len).max(1)).max(1);
    if training || rows >= q_len {
        let scores = (q.matmul(&kt)? * scale)?;
        return softmax_last_dim(&scores)?.matmul(v);
    }
    let kt = kt.contiguous()?;
    let mut outs = Vec::with_capacity(q_len.div_ceil(rows));
    let mut start = 0;
    while start < q_len {
        let len = rows.min(q_len - start);
        let qc = q.narrow(D::Minus2, start, len)?;
        let scores = (qc.matmul(&kt)? * scale)?;
        outs.push(softmax_last_dim(&scores)?.matmul(v)?);
        start += len;
    }
    Tensor::cat(&outs, D::Minus2)
}

/// The fused CPU attention kernel behind [`scaled_dot_product_attention`] (inputs contiguous f32).
struct FusedAttention {
    scale: f32,
}

fn f32_slice<'a>(storage: &'a CpuStorage, layout: &Layout, what: &str) -> Result<&'a [f32]> {
    let data = match storage {
        CpuStorage::F32(v) => v.as_slice(),
        _ => candle_core::bail!("fused attention: {what} must be f32"),
    };
    match layout.contiguous_offsets() {
        Some((start, end)) => Ok(&data[start..end]),
        None => candle_core::bail!("fused attention: {what} must be contiguous"),
    }
}

impl candle_core::CustomOp3 for FusedAttention {
    fn name(&self) -> &'static str {
        "fused-attention"
    }

    fn cpu_fwd(
        &self,
        qs: &CpuStorage,
        ql: &Layout,
        ks: &CpuStorage,
        kl: &Layout,
        vs: &CpuStorage,
        vl: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (q, k, v) = (
            f32_slice(qs, ql, "q")?,
            f32_slice(ks, kl, "k")?,
            f32_slice(vs, vl, "v")?,
        );
        let (qd, kd, vd) = (ql.shape().dims(), kl.shape().dims(), vl.shape().dims());
        let r = qd.len();
        let (q_len, d) = (qd[r - 2], qd[r - 1]);
        let (k_len, dv) = (kd[r - 2], vd[r - 1]);
        let leading: usize = qd[..r - 2].iter().product();
        if kd.len() != r
            || vd.len() != r
            || kd[..r - 2] != qd[..r - 2]
            || vd[..r - 2] != qd[..r - 2]
            || kd[r - 1] != d
            || vd[r - 2] != k_len
        {
            candle_core::bail!("fused attention: incompatible shapes q {qd:?} k {kd:?} v {vd:?}");
        }
        let mut out_dims = qd.to_vec();
        out_dims[r - 1] = dv;
        let mut out = vec![0f32; leading * q_len * dv];
        if out.is_empty() || k_len == 0 {
            return Ok((CpuStorage::F32(out), Shape::from(out_dims)));
        }
        let block = (FUSED_BLOCK_ELEMENTS / k_len).clamp(8, q_len.max(8));
        let scale = self.scale;
        out.par_chunks_mut(q_len * dv)
            .enumerate()
            .for_each(|(head, out_head)| {
                let qh = &q[head * q_len * d..(head + 1) * q_len * d];
                let kh = &k[head * k_len * d..(head + 1) * k_len * d];
                let vh = &v[head * k_len * dv..(head + 1) * k_len * dv];
                out_head
                    .par_chunks_mut(block * dv)
                    .enumerate()
                    .for_each(|(bi, out_block)| {
                        let rows = out_block.len() / dv;
                        let q_block = &qh[bi * block * d..(bi * block + rows) * d];
                        SCORES.with(|cell| {
                            let mut scores = cell.borrow_mut();
                            scores.resize(rows * k_len, 0.0);
                            attention_block(
                                q_block,
                                kh,
                                vh,
                                &mut scores,
                                out_block,
                                rows,
                                k_len,
                                d,
                                dv,
                                scale,
                            );
                        });
                    });
            });
        Ok((CpuStorage::F32(out), Shape::from(out_dims)))
    }
}

thread_local! {
    /// Per-thread score buffer of the fused attention kernel (reused across calls).
    static SCORES: std::cell::RefCell<Vec<f32>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// One query block: scores = scale · q kᵀ, row softmax in place, out = scores v.
#[allow(clippy::too_many_arguments)]
fn attention_block(
    q: &[f32],
    k: &[f32],
    v: &[f32],
    scores: &mut [f32],
    out: &mut [f32],
    rows: usize,
    k_len: usize,
    d: usize,
    dv: usize,
    scale: f32,
) {
    // SAFETY: every matrix is a row-major slice of exactly the stated size (checked by the caller's
    // shape logic); kᵀ is read through swapped strides.
    unsafe {
        gemm::gemm(
            rows,
            k_len,
            d,
            scores.as_mut_ptr(),
            1,
            k_len as isize,
            false,
            q.as_ptr(),
            1,
            d as isize,
            k.as_ptr(),
            d as isize,
            1,
            0.0,
            scale,
            false,
            false,
            false,
            gemm::Parallelism::None,
        );
    }
    for row in scores.chunks_exact_mut(k_len) {
        softmax_in_place(row);
    }
    // SAFETY: as above; `out` is the [rows, dv] block of the output.
    unsafe {
        gemm::gemm(
            rows,
            dv,
            k_len,
            out.as_mut_ptr(),
            1,
            dv as isize,
            false,
            scores.as_ptr(),
            1,
            k_len as isize,
            v.as_ptr(),
            1,
            dv as isize,
            0.0,
            1.0,
            false,
            false,
            false,
            gemm::Parallelism::None,
        );
    }
}

/// Runs `$kernel($args)` compiled for AVX-512 or AVX2+FMA when the CPU has them (the kernels are
/// `#[inline(always)]` loops, so each instantiation is vectorised for its instruction set).
macro_rules! simd_dispatch {
    (fn $name:ident($($arg:ident: $ty:ty),*) => $kernel:ident) => {
        fn $name($($arg: $ty),*) {
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx512f")]
                unsafe fn avx512($($arg: $ty),*) {
                    $kernel($($arg),*)
                }
                #[target_feature(enable = "avx2,fma")]
                unsafe fn avx2($($arg: $ty),*) {
                    $kernel($($arg),*)
                }
                if std::is_x86_feature_detected!("avx512f") {
                    // SAFETY: the CPU supports the enabled features (checked just above).
                    return unsafe { avx512($($arg),*) };
                }
                if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
                    // SAFETY: as above.
                    return unsafe { avx2($($arg),*) };
                }
            }
            $kernel($($arg),*)
        }
    };
}

#[inline(always)]
fn affine_silu_kernel(out: &mut [f32], inp: &[f32], scale: f32, shift: f32, with_silu: bool) {
    if with_silu {
        for (o, &i) in out.iter_mut().zip(inp) {
            let y = i * scale + shift;
            *o = y / (1.0 + exp_fast(-y));
        }
    } else {
        for (o, &i) in out.iter_mut().zip(inp) {
            *o = i * scale + shift;
        }
    }
}

simd_dispatch!(fn affine_silu(out: &mut [f32], inp: &[f32], scale: f32, shift: f32, with_silu: bool) => affine_silu_kernel);

/// `erfc(x)` with relative error below 1.2e-7 (Numerical Recipes' Chebyshev-fitted `erfcc`), branch-free
/// so it vectorises.
#[inline(always)]
#[allow(clippy::excessive_precision)] // the published coefficients, kept verbatim
fn erfc_fast(x: f32) -> f32 {
    let z = x.abs();
    let t = 1.0 / (1.0 + 0.5 * z);
    let mut p = 0.170_872_77f32;
    p = p * t - 0.822_152_23;
    p = p * t + 1.488_515_87;
    p = p * t - 1.135_203_98;
    p = p * t + 0.278_868_07;
    p = p * t - 0.186_288_06;
    p = p * t + 0.096_784_18;
    p = p * t + 0.374_091_96;
    p = p * t + 1.000_023_68;
    p = p * t - 1.265_512_23;
    let ans = t * exp_fast(-z * z + p);
    if x >= 0.0 {
        ans
    } else {
        2.0 - ans
    }
}

/// GEGLU on one row `[hidden | gate]` → `hidden · gelu(gate)` with the exact (erf) GELU.
#[inline(always)]
fn geglu_kernel(out: &mut [f32], hidden: &[f32], gate: &[f32]) {
    for ((o, &h), &g) in out.iter_mut().zip(hidden).zip(gate) {
        *o = h * 0.5 * g * erfc_fast(-g * std::f32::consts::FRAC_1_SQRT_2);
    }
}

simd_dispatch!(fn geglu_row(out: &mut [f32], hidden: &[f32], gate: &[f32]) => geglu_kernel);

/// `hidden * gelu_erf(gate)` where `x` = [..., 2·inner] holds `[hidden | gate]` (diffusers `GEGLU`);
/// fused on the inference path, composite (differentiable) otherwise.
pub fn geglu(x: &Tensor) -> Result<Tensor> {
    let width = x.dim(D::Minus1)?;
    if width % 2 != 0 {
        candle_core::bail!("geglu: last dimension {width} is odd");
    }
    let inner = width / 2;
    if needs_grad(&[x]) && crate::train_ops::supported(&[x]) {
        return crate::train_ops::geglu(x);
    }
    if needs_grad(&[x]) || x.dtype() != DType::F32 || !x.device().is_cpu() {
        let hidden = x.narrow(D::Minus1, 0, inner)?;
        let gate = x.narrow(D::Minus1, inner, inner)?;
        return hidden * gate.gelu_erf()?;
    }
    x.contiguous()?.apply_op1_no_bwd(&GegluOp)
}

struct GegluOp;

impl CustomOp1 for GegluOp {
    fn name(&self) -> &'static str {
        "geglu"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> Result<(CpuStorage, Shape)> {
        let src = f32_slice(storage, layout, "geglu input")?;
        let mut dims = layout.shape().dims().to_vec();
        let width = dims[dims.len() - 1];
        let inner = width / 2;
        *dims.last_mut().unwrap() = inner;
        let mut dst = vec![0f32; src.len() / 2];
        if inner > 0 {
            dst.par_chunks_mut(inner)
                .zip(src.par_chunks(width))
                .for_each(|(o, row)| geglu_row(o, &row[..inner], &row[inner..]));
        }
        Ok((CpuStorage::F32(dst), Shape::from(dims)))
    }
}

/// `exp(x)` for x ≤ 0.. moderate positive values, written so loops over it vectorise: Cody–Waite range
/// reduction to r ∈ [-ln2/2, ln2/2] and a degree-6 polynomial (Cephes `expf` coefficients, ~1 ulp);
/// inputs below -87 flush to ~1e-38 instead of 0, harmless for softmax/SiLU.
#[inline(always)]
#[allow(clippy::excessive_precision)] // the published coefficients, kept verbatim
pub(crate) fn exp_fast(x: f32) -> f32 {
    let x = x.clamp(-87.0, 88.0);
    let n = (x * std::f32::consts::LOG2_E).round_ties_even();
    let r = x - n * 0.693_359_4 + n * 2.121_944_4e-4;
    let mut p = 1.987_569_1e-4f32;
    p = p * r + 1.398_199_9e-3;
    p = p * r + 8.333_452e-3;
    p = p * r + 4.166_579_6e-2;
    p = p * r + 1.666_666_5e-1;
    p = p * r + 5.000_000_1e-1;
    let e = p * r * r + r + 1.0;
    // 2^n without a float→int conversion (`as` saturates lane by lane and blocks vectorisation): adding
    // 1.5·2^23 puts n in the low mantissa bits.
    let n_bits = (n + 12_582_912.0).to_bits().wrapping_sub(0x4B40_0000);
    e * f32::from_bits(n_bits.wrapping_add(127) << 23)
}

#[inline(always)]
fn softmax_row(row: &mut [f32]) {
    const LANES: usize = 16;
    let mut maxes = [f32::NEG_INFINITY; LANES];
    let mut chunks = row.chunks_exact(LANES);
    for c in &mut chunks {
        for (m, &x) in maxes.iter_mut().zip(c) {
            *m = if x > *m { x } else { *m };
        }
    }
    let mut max = chunks
        .remainder()
        .iter()
        .fold(f32::NEG_INFINITY, |a, &b| a.max(b));
    for m in maxes {
        max = max.max(m);
    }
    let mut sums = [0f32; LANES];
    let mut chunks = row.chunks_exact_mut(LANES);
    for c in &mut chunks {
        for (s, x) in sums.iter_mut().zip(c.iter_mut()) {
            *x = exp_fast(*x - max);
            *s += *x;
        }
    }
    let mut sum: f32 = 0.0;
    for x in chunks.into_remainder() {
        *x = exp_fast(*x - max);
        sum += *x;
    }
    sum += sums.iter().sum::<f32>();
    let inv = 1.0 / sum;
    for x in row.iter_mut() {
        *x *= inv;
    }
}

// Numerically stable softmax of one row, vectorised for the CPU it runs on.
simd_dispatch!(fn softmax_in_place(row: &mut [f32]) => softmax_row);

/// Configuration of a [`ResnetBlock2D`] (diffusers `ResnetBlock2D` arguments that SD 1.x uses).
#[derive(Debug, Clone)]
pub struct ResnetConfig {
    pub in_channels: usize,
    pub out_channels: usize,
    /// Width of the time embedding; `None` for blocks without `time_emb_proj` (VAE).
    pub temb_channels: Option<usize>,
    pub groups: usize,
    /// Groups of `norm2`; defaults to `groups`.
    pub groups_out: Option<usize>,
    pub eps: f64,
    /// The sum `shortcut + residual` is divided by this (UNet mid block: `mid_block_scale_factor`).
    pub output_scale_factor: f64,
    /// `"default"` adds the projected embedding; `"scale_shift"` applies it as FiLM after `norm2`.
    pub time_embedding_norm: TimeEmbeddingNorm,
}

impl ResnetConfig {
    /// The common case: `groups` groups, eps, scale factor 1, additive time embedding.
    pub fn new(
        in_channels: usize,
        out_channels: usize,
        temb_channels: Option<usize>,
        groups: usize,
        eps: f64,
    ) -> Self {
        Self {
            in_channels,
            out_channels,
            temb_channels,
            groups,
            groups_out: None,
            eps,
            output_scale_factor: 1.0,
            time_embedding_norm: TimeEmbeddingNorm::Default,
        }
    }
}

/// How a ResNet block injects the time embedding (`resnet_time_scale_shift` in UNet configs).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TimeEmbeddingNorm {
    Default,
    ScaleShift,
}

/// diffusers `ResnetBlock2D`: keys `norm1`, `conv1`, `time_emb_proj`, `norm2`, `conv2`, `conv_shortcut`.
#[derive(Debug, Clone)]
pub struct ResnetBlock2D {
    norm1: GroupNorm,
    conv1: Conv2d,
    time_emb_proj: Option<Linear>,
    norm2: GroupNorm,
    conv2: Conv2d,
    conv_shortcut: Option<Conv2d>,
    output_scale_factor: f64,
    time_embedding_norm: TimeEmbeddingNorm,
}

impl ResnetBlock2D {
    pub fn load(cfg: &ResnetConfig, vb: VarBuilder) -> Result<Self> {
        let (cin, cout) = (cfg.in_channels, cfg.out_channels);
        let time_emb_proj = match cfg.temb_channels {
            Some(t) => {
                let width = match cfg.time_embedding_norm {
                    TimeEmbeddingNorm::Default => cout,
                    TimeEmbeddingNorm::ScaleShift => 2 * cout,
                };
                Some(linear(t, width, true, vb.pp("time_emb_proj"))?)
            }
            None => None,
        };
        // diffusers adds the 1x1 shortcut exactly when the channel count changes.
        let conv_shortcut = if cin != cout {
            Some(conv2d(cin, cout, 1, 1, 0, vb.pp("conv_shortcut"))?)
        } else {
            None
        };
        Ok(Self {
            norm1: GroupNorm::load(cfg.groups, cin, cfg.eps, vb.pp("norm1"))?,
            conv1: conv2d(cin, cout, 3, 1, 1, vb.pp("conv1"))?,
            time_emb_proj,
            norm2: GroupNorm::load(
                cfg.groups_out.unwrap_or(cfg.groups),
                cout,
                cfg.eps,
                vb.pp("norm2"),
            )?,
            conv2: conv2d(cout, cout, 3, 1, 1, vb.pp("conv2"))?,
            conv_shortcut,
            output_scale_factor: cfg.output_scale_factor,
            time_embedding_norm: cfg.time_embedding_norm,
        })
    }

    /// `x` [batch, in, h, w]; `temb` [batch, temb_channels] (ignored by blocks loaded without one).
    pub fn forward(&self, x: &Tensor, temb: Option<&Tensor>) -> Result<Tensor> {
        let h = self.conv1.forward(&self.norm1.forward_silu(x)?)?;
        let emb = match (&self.time_emb_proj, temb) {
            (Some(proj), Some(t)) => Some(proj.forward(&t.silu()?)?.unsqueeze(2)?.unsqueeze(3)?),
            _ => None,
        };
        let h = match (self.time_embedding_norm, emb) {
            (TimeEmbeddingNorm::ScaleShift, Some(emb)) => {
                let chunks = emb.chunk(2, 1)?;
                let normed = self.norm2.forward(&h)?;
                normed
                    .broadcast_mul(&(&chunks[0] + 1.0)?)?
                    .broadcast_add(&chunks[1])?
                    .silu()?
            }
            (_, Some(emb)) => self.norm2.forward_silu(&h.broadcast_add(&emb)?)?,
            (_, None) => self.norm2.forward_silu(&h)?,
        };
        let h = self.conv2.forward(&h)?;
        let shortcut = match &self.conv_shortcut {
            Some(conv) => conv.forward(x)?,
            None => x.clone(),
        };
        let out = (shortcut + h)?;
        if self.output_scale_factor == 1.0 {
            Ok(out)
        } else {
            out / self.output_scale_factor
        }
    }
}

/// diffusers `Downsample2D` with a convolution (key `conv`): 3x3, stride 2. With `padding == 0` the input is
/// padded by one zero row/column at the bottom/right first, as diffusers does.
#[derive(Debug, Clone)]
pub struct Downsample2D {
    conv: Conv2d,
    padding: usize,
}

impl Downsample2D {
    pub fn load(
        in_channels: usize,
        out_channels: usize,
        padding: usize,
        vb: VarBuilder,
    ) -> Result<Self> {
        Ok(Self {
            conv: conv2d(in_channels, out_channels, 3, 2, padding, vb.pp("conv"))?,
            padding,
        })
    }

    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        if self.padding == 0 {
            let x = x
                .pad_with_zeros(D::Minus1, 0, 1)?
                .pad_with_zeros(D::Minus2, 0, 1)?;
            self.conv.forward(&x)
        } else {
            self.conv.forward(x)
        }
    }
}

/// diffusers `Upsample2D` with a convolution (key `conv`): nearest-neighbour resize then 3x3 conv.
#[derive(Debug, Clone)]
pub struct Upsample2D {
    conv: Conv2d,
}

impl Upsample2D {
    pub fn load(in_channels: usize, out_channels: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            conv: conv2d(in_channels, out_channels, 3, 1, 1, vb.pp("conv"))?,
        })
    }

    /// Doubles the spatial size, or resizes to `size` = (h, w) when given (the UNet passes the skip
    /// connection's size when the latent is not a multiple of the total downsampling factor).
    pub fn forward(&self, x: &Tensor, size: Option<(usize, usize)>) -> Result<Tensor> {
        let (_, _, h, w) = x.dims4()?;
        let (th, tw) = size.unwrap_or((2 * h, 2 * w));
        self.conv.forward(&x.upsample_nearest2d(th, tw)?)
    }
}

/// diffusers `Attention` as used by the VAE mid block: group norm over [B, C, H, W], single- or multi-head
/// self-attention over the H·W positions, output projection, residual added.
///
/// Keys: `group_norm`, `to_q`, `to_k`, `to_v`, `to_out.0` (older checkpoints: `query`, `key`, `value`,
/// `proj_attn`, which diffusers converts on load; accepted here too).
#[derive(Debug, Clone)]
pub struct SpatialSelfAttention {
    group_norm: GroupNorm,
    to_q: Linear,
    to_k: Linear,
    to_v: Linear,
    to_out: Linear,
    heads: usize,
    rescale_output_factor: f64,
}

impl SpatialSelfAttention {
    /// `head_dim` is diffusers' `attention_head_dim` (the VAE passes the channel count: one head).
    pub fn load(
        channels: usize,
        head_dim: usize,
        groups: usize,
        eps: f64,
        vb: VarBuilder,
    ) -> Result<Self> {
        if head_dim == 0 || !channels.is_multiple_of(head_dim) {
            candle_core::bail!(
                "attention {}: {channels} channels not divisible by head dim {head_dim}",
                vb.prefix()
            );
        }
        let legacy = !vb.contains_tensor("to_q.weight") && vb.contains_tensor("query.weight");
        let names = if legacy {
            ["query", "key", "value", "proj_attn"]
        } else {
            ["to_q", "to_k", "to_v", "to_out.0"]
        };
        Ok(Self {
            group_norm: GroupNorm::load(groups, channels, eps, vb.pp("group_norm"))?,
            to_q: linear(channels, channels, true, vb.pp(names[0]))?,
            to_k: linear(channels, channels, true, vb.pp(names[1]))?,
            to_v: linear(channels, channels, true, vb.pp(names[2]))?,
            to_out: linear(channels, channels, true, vb.pp(names[3]))?,
            heads: channels / head_dim,
            rescale_output_factor: 1.0,
        })
    }

    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let (b, c, h, w) = x.dims4()?;
        let normed = self.group_norm.forward(x)?;
        let tokens = normed
            .reshape((b, c, h * w))?
            .transpose(1, 2)?
            .contiguous()?;
        let head_dim = c / self.heads;
        let split = |t: Tensor| -> Result<Tensor> {
            t.reshape((b, h * w, self.heads, head_dim))?
                .transpose(1, 2)?
                .contiguous()
        };
        let q = split(self.to_q.forward(&tokens)?)?;
        let k = split(self.to_k.forward(&tokens)?)?;
        let v = split(self.to_v.forward(&tokens)?)?;
        let attn = scaled_dot_product_attention(&q, &k, &v, 1.0 / (head_dim as f64).sqrt())?;
        let attn = attn.transpose(1, 2)?.reshape((b, h * w, c))?;
        let out = self.to_out.forward(&attn)?;
        let out = out.transpose(1, 2)?.reshape((b, c, h, w))?;
        let out = (out + x)?;
        if self.rescale_output_factor == 1.0 {
            Ok(out)
        } else {
            out / self.rescale_output_factor
        }
    }
}

/// A CPU `VarBuilder` over a safetensors file in f32 (weights in f16/bf16 are converted on load).
pub fn cpu_var_builder(path: &std::path::Path) -> Result<VarBuilder<'static>> {
    // SAFETY: the file is memory-mapped read-only; it must not be modified while the model is alive,
    // which is the usual contract for checkpoint files.
    unsafe { VarBuilder::from_mmaped_safetensors(&[path], DType::F32, &Device::Cpu) }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Var;

    fn composite_group_norm(x: &Tensor, groups: usize, w: &Tensor, b: &Tensor, eps: f64) -> Tensor {
        let dims = x.dims().to_vec();
        let g = x.reshape((dims[0], groups, ())).unwrap();
        let n = g.dim(2).unwrap() as f64;
        let mean = (g.sum_keepdim(2).unwrap() / n).unwrap();
        let c = g.broadcast_sub(&mean).unwrap();
        let var = (c.sqr().unwrap().sum_keepdim(2).unwrap() / n).unwrap();
        let y = c
            .broadcast_div(&(var + eps).unwrap().sqrt().unwrap())
            .unwrap();
        y.reshape(dims.as_slice())
            .unwrap()
            .broadcast_mul(&w.reshape((1, dims[1], 1, 1)).unwrap())
            .unwrap()
            .broadcast_add(&b.reshape((1, dims[1], 1, 1)).unwrap())
            .unwrap()
    }

    fn max_diff(a: &Tensor, b: &Tensor) -> f32 {
        (a - b)
            .unwrap()
            .abs()
            .unwrap()
            .flatten_all()
            .unwrap()
            .max(0)
            .unwrap()
            .to_scalar::<f32>()
            .unwrap()
    }

    #[test]
    fn fused_group_norm_matches_composite_and_training_path() {
        let dev = Device::Cpu;
        let x = Tensor::randn(0f32, 1.0, (2, 8, 5, 3), &dev)
            .unwrap()
            .affine(3.0, 1.5)
            .unwrap();
        let w = Tensor::randn(1f32, 0.2, 8, &dev).unwrap();
        let b = Tensor::randn(0f32, 0.2, 8, &dev).unwrap();
        let gn = GroupNorm {
            weight: w.clone(),
            bias: b.clone(),
            num_groups: 4,
            eps: 1e-5,
        };
        let want = composite_group_norm(&x, 4, &w, &b, 1e-5);
        assert!(max_diff(&gn.forward(&x).unwrap(), &want) < 1e-5);
        assert!(max_diff(&gn.forward_silu(&x).unwrap(), &want.silu().unwrap()) < 1e-5);
        // Through a Var the composite path runs and gradients flow.
        let xv = Var::from_tensor(&x).unwrap();
        let y = gn.forward_silu(xv.as_tensor()).unwrap();
        assert!(max_diff(&y, &want.silu().unwrap()) < 1e-5);
        let grads = y.sum_all().unwrap().backward().unwrap();
        assert!(grads.get(xv.as_tensor()).is_some());
    }

    #[test]
    fn chunked_attention_matches_unchunked() {
        let dev = Device::Cpu;
        // leading 1 × k_len 64 → rows = 2^25/64 which exceeds q_len; force chunking with a big k_len.
        let q = Tensor::randn(0f32, 1.0, (1, 1, 3000, 4), &dev).unwrap();
        let k = Tensor::randn(0f32, 1.0, (1, 1, 20000, 4), &dev).unwrap();
        let v = Tensor::randn(0f32, 1.0, (1, 1, 20000, 4), &dev).unwrap();
        let got = scaled_dot_product_attention(&q, &k, &v, 0.5).unwrap();
        let scores = (q.matmul(&k.t().unwrap()).unwrap() * 0.5).unwrap();
        let want = candle_nn::ops::softmax(&scores, D::Minus1)
            .unwrap()
            .matmul(&v)
            .unwrap();
        assert!(max_diff(&got, &want) < 1e-5);
    }

    #[test]
    fn fast_exp_is_accurate() {
        for i in 0..20000 {
            let x = -87.0 + i as f32 * 0.00525;
            let (got, want) = (exp_fast(x) as f64, (x as f64).exp());
            assert!(
                (got - want).abs() <= 4e-7 * want,
                "exp({x}): {got} vs {want}"
            );
        }
    }

    #[test]
    fn fused_attention_matches_composite_for_odd_shapes() {
        let dev = Device::Cpu;
        for (q_len, k_len, d, dv) in [(37, 77, 8, 8), (300, 1000, 5, 3), (1, 1, 4, 4)] {
            let q = Tensor::randn(0f32, 1.0, (2, 3, q_len, d), &dev).unwrap();
            let k = Tensor::randn(0f32, 1.0, (2, 3, k_len, d), &dev).unwrap();
            let v = Tensor::randn(0f32, 1.0, (2, 3, k_len, dv), &dev).unwrap();
            let got = scaled_dot_product_attention(&q, &k, &v, 0.7).unwrap();
            let scores = (q.matmul(&k.t().unwrap()).unwrap() * 0.7).unwrap();
            let want = candle_nn::ops::softmax(&scores, D::Minus1)
                .unwrap()
                .matmul(&v)
                .unwrap();
            assert!(max_diff(&got, &want) < 1e-5, "{q_len}x{k_len}x{d}x{dv}");
        }
    }

    #[test]
    fn fused_geglu_matches_exact_gelu() {
        let x = Tensor::randn(0f32, 3.0, (2, 5, 24), &Device::Cpu).unwrap();
        let want = (x.narrow(2, 0, 12).unwrap() * x.narrow(2, 12, 12).unwrap().gelu_erf().unwrap())
            .unwrap();
        assert!(max_diff(&geglu(&x).unwrap(), &want) < 1e-5);
    }

    #[test]
    fn layer_norm_paths_agree() {
        let dev = Device::Cpu;
        let x = Tensor::randn(0f32, 2.0, (2, 7, 16), &dev).unwrap();
        let ln = LayerNorm {
            weight: Tensor::randn(1f32, 0.1, 16, &dev).unwrap(),
            bias: Tensor::randn(0f32, 0.1, 16, &dev).unwrap(),
            eps: 1e-5,
        };
        let fast = ln.forward(&x).unwrap();
        let xv = Var::from_tensor(&x).unwrap();
        let slow = ln.forward(xv.as_tensor()).unwrap();
        assert!(max_diff(&fast, &slow) < 1e-5);
    }
}
