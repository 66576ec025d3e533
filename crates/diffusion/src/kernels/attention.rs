//! Scaled dot-product attention `softmax(q kᵀ · scale) v`.

use candle_core::{CpuStorage, Layout, Result, Shape, Tensor, D};
use rayon::prelude::*;

use super::approx;
use super::bf16::{self, Output, PackedPairs, MR, NR};
use super::softmax::{softmax_in_place, softmax_last_dim};
use super::{cpu_f32, f32_slices, needs_grad};

/// Score elements one query chunk of the unfused path may hold (~128 MB of f32).
const MAX_SCORE_ELEMENTS: usize = 1 << 25;

/// Score-block size of the fused kernel in f32 elements (~1 MB, so a block stays in L2 between the two
/// GEMMs and the softmax).
const FUSED_BLOCK_ELEMENTS: usize = 1 << 18;

/// Scaled dot-product attention `softmax(q kᵀ · scale) v` for q [.., q_len, d], k [.., k_len, d],
/// v [.., k_len, dv].
///
/// Inference on CPU/f32 runs a fused kernel: per (batch·head, block of queries) one GEMM for the scores,
/// an in-place softmax and one GEMM for the output, in parallel, never materialising the full
/// q_len × k_len map (1 GB per head batch at 64×64 latents). When the CPU's products run in bf16
/// ([`super::bf16`]) both GEMMs take bf16 operands with f32 sums, as PyTorch's bf16 attention does; the
/// softmax stays f32. Other dtypes/devices split the work into
/// query chunks of at most ~128 MB of scores; the differentiable path runs the whole product through
/// [`softmax_last_dim`] (which has a backward pass).
pub fn attention(q: &Tensor, k: &Tensor, v: &Tensor, scale: f64) -> Result<Tensor> {
    let training = needs_grad(&[q, k, v]);
    if !training && cpu_f32(&[q, k, v]) && q.rank() >= 3 {
        let (q, k, v) = (q.contiguous()?, k.contiguous()?, v.contiguous()?);
        return q.apply_op3_no_bwd(
            &k,
            &v,
            &FusedAttention {
                scale: scale as f32,
            },
        );
    }
    if training {
        let scores = (q.matmul(&k.t()?)? * scale)?;
        return softmax_last_dim(&scores)?.matmul(v);
    }
    chunked(q, k, v, scale, MAX_SCORE_ELEMENTS)
}

/// Unfused attention over query chunks whose score matrices hold about `max_scores` elements.
fn chunked(q: &Tensor, k: &Tensor, v: &Tensor, scale: f64, max_scores: usize) -> Result<Tensor> {
    let q_len = q.dim(D::Minus2)?;
    let k_len = k.dim(D::Minus2)?;
    let leading: usize = q.dims()[..q.rank() - 2].iter().product();
    let kt = k.t()?;
    let rows = (max_scores / (leading * k_len).max(1)).max(1);
    if rows >= q_len {
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

/// The fused CPU attention kernel behind [`attention`] (inputs contiguous f32).
struct FusedAttention {
    scale: f32,
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
        let [q, k, v] = f32_slices([(qs, ql), (ks, kl), (vs, vl)], self.name())?;
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
        // Read on the calling thread: the precision may be set for this thread only.
        let bf16 = bf16::bf16_active();
        let mut block = (FUSED_BLOCK_ELEMENTS / k_len).clamp(8, q_len.max(8));
        if bf16 {
            // Whole NR-line panels of queries (a partial panel computes padding lines).
            block = (block / NR).max(1) * NR;
        }
        let scale = self.scale;
        out.par_chunks_mut(q_len * dv)
            .enumerate()
            .for_each(|(head, out_head)| {
                let qh = &q[head * q_len * d..(head + 1) * q_len * d];
                let kh = &k[head * k_len * d..(head + 1) * k_len * d];
                let vh = &v[head * k_len * dv..(head + 1) * k_len * dv];
                // With bf16 products a head's keys and values are rounded and packed once, for all its
                // query blocks, as the left operands of the transposed products (see
                // `attention_block_bf16`): keys by rows, values read down their columns.
                let packed = bf16.then(|| {
                    (
                        PackedPairs::pack(kh, k_len, d, d, 1, MR),
                        PackedPairs::pack(vh, dv, k_len, 1, dv, MR),
                    )
                });
                out_head
                    .par_chunks_mut(block * dv)
                    .enumerate()
                    .for_each(|(bi, out_block)| {
                        let rows = out_block.len() / dv;
                        let q_block = &qh[bi * block * d..(bi * block + rows) * d];
                        SCORES.with(|cell| {
                            let mut scores = cell.borrow_mut();
                            scores.resize(rows * k_len, 0.0);
                            let shape = BlockShape {
                                rows,
                                k_len,
                                d,
                                dv,
                                scale,
                            };
                            match &packed {
                                Some((k, v)) => attention_block_bf16(
                                    q_block,
                                    k,
                                    v,
                                    &mut scores,
                                    out_block,
                                    shape,
                                ),
                                None => {
                                    attention_block(q_block, kh, vh, &mut scores, out_block, shape)
                                }
                            }
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

/// The sizes of one query block: `rows` queries of length `d` against `k_len` keys, values of length
/// `dv`, scores scaled by `scale`.
#[derive(Clone, Copy)]
struct BlockShape {
    rows: usize,
    k_len: usize,
    d: usize,
    dv: usize,
    scale: f32,
}

/// One query block: scores = scale · q kᵀ, row softmax in place, out = scores v.
fn attention_block(
    q: &[f32],
    k: &[f32],
    v: &[f32],
    scores: &mut [f32],
    out: &mut [f32],
    shape: BlockShape,
) {
    let BlockShape {
        rows,
        k_len,
        d,
        dv,
        scale,
    } = shape;
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

/// [`attention_block`] with bf16 products (f32 sums), as PyTorch's bf16 attention: the block's queries
/// and its probabilities are rounded to bf16 for the products; the softmax runs in f32. `k` holds the
/// head's keys packed as [`MR`] panels, `v` its values transposed (dv lines of `k_len`), also [`MR`].
///
/// Both products are computed transposed — scoresᵀ = K·Qᵀ, then outᵀ = Vᵀ·Pᵀ — so that the probabilities
/// are the second product's right operand, whose pairs (two keys of one query) are two rows of
/// scoresᵀ: they pack with contiguous vector conversions, where packing them as a left operand would
/// scatter every pair (that packing cost as much as the products at SD's 40-wide heads). The softmax
/// then runs down scoresᵀ's columns, vectorised across the queries.
fn attention_block_bf16(
    q: &[f32],
    k: &PackedPairs,
    v: &PackedPairs,
    scores_t: &mut [f32],
    out: &mut [f32],
    shape: BlockShape,
) {
    let BlockShape { rows, k_len, .. } = shape;
    let (d, dv) = (shape.d, shape.dv);
    let q = PackedPairs::pack(q, rows, d, d, 1, NR);
    bf16::gemm(k, &q, whole_rows(scores_t, k_len, rows), false);
    softmax_columns(scores_t, rows, shape.scale);
    let probs = PackedPairs::pack(scores_t, rows, k_len, 1, rows, NR);
    OUT_T.with(|cell| {
        let mut out_t = cell.borrow_mut();
        out_t.resize(dv * rows, 0.0);
        bf16::gemm(v, &probs, whole_rows(&mut out_t, dv, rows), false);
        for (i, out_row) in out.chunks_exact_mut(dv).enumerate() {
            for (c, o) in out_row.iter_mut().enumerate() {
                *o = out_t[c * rows + i];
            }
        }
    });
}

thread_local! {
    /// Per-thread transposed output block of the bf16 attention (reused across calls).
    static OUT_T: std::cell::RefCell<Vec<f32>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// Softmax of `scale ·` each column of the row-major matrix `s` with `cols` columns (scores of one query
/// per column, one key per row).
fn softmax_columns(s: &mut [f32], cols: usize, scale: f32) {
    let mut max = vec![f32::NEG_INFINITY; cols];
    let mut sum = vec![0f32; cols];
    column_max(s, &mut max);
    exp_columns(s, &max, &mut sum, scale);
    for x in sum.iter_mut() {
        *x = 1.0 / *x;
    }
    scale_columns(s, &sum);
}

#[inline(always)]
fn column_max_kernel(s: &[f32], max: &mut [f32]) {
    for row in s.chunks_exact(max.len()) {
        for (m, &x) in max.iter_mut().zip(row) {
            *m = if x > *m { x } else { *m };
        }
    }
}

#[inline(always)]
fn exp_columns_kernel(s: &mut [f32], max: &[f32], sum: &mut [f32], scale: f32) {
    for row in s.chunks_exact_mut(max.len()) {
        for ((x, &m), t) in row.iter_mut().zip(max).zip(sum.iter_mut()) {
            *x = approx::exp(scale * (*x - m));
            *t += *x;
        }
    }
}

#[inline(always)]
fn scale_columns_kernel(s: &mut [f32], factor: &[f32]) {
    for row in s.chunks_exact_mut(factor.len()) {
        for (x, &f) in row.iter_mut().zip(factor) {
            *x *= f;
        }
    }
}

simd_dispatch!(
    /// Each column's largest value.
    fn column_max(s: &[f32], max: &mut [f32]) => column_max_kernel
);

simd_dispatch!(
    /// `exp(scale · (x − column max))` in place, summed per column.
    fn exp_columns(s: &mut [f32], max: &[f32], sum: &mut [f32], scale: f32) => exp_columns_kernel
);

simd_dispatch!(
    /// Each column times its factor.
    fn scale_columns(s: &mut [f32], factor: &[f32]) => scale_columns_kernel
);

/// `data` as a product's output of `rows` × `cols`, rows back to back.
fn whole_rows(data: &mut [f32], rows: usize, cols: usize) -> Output<'_> {
    Output {
        data,
        rows,
        cols,
        row_stride: cols,
    }
}

#[cfg(test)]
mod tests {
    use super::super::test_support::max_diff;
    use super::*;
    use candle_core::Device;

    fn reference(q: &Tensor, k: &Tensor, v: &Tensor, scale: f64) -> Tensor {
        let scores = (q.matmul(&k.t().unwrap()).unwrap() * scale).unwrap();
        candle_nn::ops::softmax(&scores, D::Minus1)
            .unwrap()
            .matmul(v)
            .unwrap()
    }

    #[test]
    fn chunked_attention_matches_unchunked() {
        let dev = Device::Cpu;
        let q = Tensor::randn(0f32, 1.0, (2, 3, 37, 4), &dev).unwrap();
        let k = Tensor::randn(0f32, 1.0, (2, 3, 50, 4), &dev).unwrap();
        let v = Tensor::randn(0f32, 1.0, (2, 3, 50, 5), &dev).unwrap();
        let want = reference(&q, &k, &v, 0.5);
        // 1, 2 and 12 query rows per chunk (the last chunk shorter), and one chunk.
        for max_scores in [1, 2 * 300 + 1, 12 * 300, 1 << 20] {
            let got = chunked(&q, &k, &v, 0.5, max_scores).unwrap();
            assert!(max_diff(&got, &want) < 1e-5, "{max_scores}");
        }
    }

    #[test]
    fn fused_attention_matches_composite_for_odd_shapes() {
        let dev = Device::Cpu;
        for (q_len, k_len, d, dv) in [(37, 77, 8, 8), (300, 1000, 5, 3), (1, 1, 4, 4)] {
            let q = Tensor::randn(0f32, 1.0, (2, 3, q_len, d), &dev).unwrap();
            let k = Tensor::randn(0f32, 1.0, (2, 3, k_len, d), &dev).unwrap();
            let v = Tensor::randn(0f32, 1.0, (2, 3, k_len, dv), &dev).unwrap();
            let got = attention(&q, &k, &v, 0.7).unwrap();
            let want = reference(&q, &k, &v, 0.7);
            assert!(max_diff(&got, &want) < 1e-5, "{q_len}x{k_len}x{d}x{dv}");
        }
    }

    /// With bf16 products the fused kernel stays within bf16 rounding of the f32 reference, for shapes
    /// that leave partial query panels, key panels and value panels (and SD's 40-wide heads).
    #[test]
    fn fused_attention_with_bf16_products_is_within_bf16_rounding() {
        use crate::kernels::{with_cpu_precision, CpuPrecision};
        let dev = Device::Cpu;
        for (q_len, k_len, d, dv) in [
            (37, 77, 8, 8),
            (300, 1000, 5, 3),
            (1, 1, 4, 4),
            (130, 64, 40, 40),
        ] {
            let q = Tensor::randn(0f32, 1.0, (2, 3, q_len, d), &dev).unwrap();
            let k = Tensor::randn(0f32, 1.0, (2, 3, k_len, d), &dev).unwrap();
            let v = Tensor::randn(0f32, 1.0, (2, 3, k_len, dv), &dev).unwrap();
            let Ok(got) = with_cpu_precision(CpuPrecision::Bf16, || attention(&q, &k, &v, 0.7))
            else {
                eprintln!("skipped: no AVX512-BF16 on this CPU");
                return;
            };
            let got = got.unwrap();
            let want = reference(&q, &k, &v, 0.7);
            let rel = testkit::diff::tensor_relative_l2(&got, &want);
            // bf16 keeps 8 bits of mantissa: ~0.4 % per rounded operand.
            assert!(
                rel > 0.0 && rel < 1e-2,
                "{q_len}x{k_len}x{d}x{dv}: relative L2 {rel}"
            );
            let f32_out = attention(&q, &k, &v, 0.7).unwrap();
            assert!(
                max_diff(&f32_out, &want) < 1e-5,
                "f32 stays f32 outside the precision scope"
            );
        }
    }

    #[test]
    fn training_path_has_gradients() {
        let dev = Device::Cpu;
        let q = candle_core::Var::randn(0f32, 1.0, (1, 2, 5, 4), &dev).unwrap();
        let k = Tensor::randn(0f32, 1.0, (1, 2, 6, 4), &dev).unwrap();
        let v = Tensor::randn(0f32, 1.0, (1, 2, 6, 3), &dev).unwrap();
        let out = attention(q.as_tensor(), &k, &v, 0.5).unwrap();
        assert!(max_diff(&out, &reference(q.as_tensor(), &k, &v, 0.5)) < 1e-5);
        let grads = out.sum_all().unwrap().backward().unwrap();
        assert!(grads.get(q.as_tensor()).is_some());
    }
}
