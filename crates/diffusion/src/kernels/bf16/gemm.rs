//! The bf16 product itself: rounding, packing into bf16 pairs, and the AVX512-BF16 microkernel with
//! its cache tiling (no candle types, so it can be tested and timed on its own).

use rayon::prelude::*;

/// Rows of one output micro-tile: lines of the broadcast operand (A).
pub const MR: usize = 12;
/// Columns of one output micro-tile: lines of the vector operand (B), two 16-lane registers.
pub const NR: usize = 32;
/// k pairs per cache block: a B micro-panel (KC·NR·4 B = 24 KB) stays in L1 while the A panels of a
/// row block (8·KC·MR·4 B = 72 KB) stream from L2.
const KC: usize = 192;
/// A panels (of MR rows) per parallel task.
const ROW_PANELS_PER_TASK: usize = 8;
/// B panels (of NR columns) per parallel task.
const COL_PANELS_PER_TASK: usize = 4;

/// Whether this CPU runs the bf16 microkernel (AVX-512 F/BW/VL and AVX512-BF16).
pub fn bf16_products_available() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::is_x86_feature_detected!("avx512f")
            && std::is_x86_feature_detected!("avx512bw")
            && std::is_x86_feature_detected!("avx512vl")
            && std::is_x86_feature_detected!("avx512bf16")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// `x` rounded to bf16 (nearest, ties to even; NaN stays NaN), as its 16 bits.
#[inline(always)]
pub fn to_bf16_bits(x: f32) -> u16 {
    let bits = x.to_bits();
    if x.is_nan() {
        return ((bits >> 16) | 0x40) as u16;
    }
    let round = 0x7fff + ((bits >> 16) & 1);
    (bits.wrapping_add(round) >> 16) as u16
}

/// The f32 value of bf16 bits.
#[inline(always)]
pub fn from_bf16_bits(b: u16) -> f32 {
    f32::from_bits((b as u32) << 16)
}

/// Two adjacent k values of one line as a bf16 pair (the lower k in the low half).
#[inline(always)]
pub(super) fn pair(lo: f32, hi: f32) -> u32 {
    to_bf16_bits(lo) as u32 | ((to_bf16_bits(hi) as u32) << 16)
}

/// A matrix of `lines` lines by `k` summed values, rounded to bf16 and packed for [`gemm`]: panel `p`
/// holds lines `p·width ..` as `[k_pairs][width]` u32 pairs; missing lines and an odd k's last value are
/// zero.
#[derive(Debug, Clone)]
pub struct PackedPairs {
    data: Vec<u32>,
    lines: usize,
    k: usize,
    width: usize,
}

impl PackedPairs {
    /// Packs `src`, where element (line l, k index j) is `src[l·line_stride + j·k_stride]`, in panels of
    /// `width` lines ([`MR`] for the left operand, [`NR`] for the right one).
    pub fn pack(
        src: &[f32],
        lines: usize,
        k: usize,
        line_stride: usize,
        k_stride: usize,
        width: usize,
    ) -> Self {
        assert!(width == MR || width == NR, "panel width {width}");
        if lines > 0 && k > 0 {
            assert!(
                (lines - 1) * line_stride + (k - 1) * k_stride < src.len(),
                "pack: source too short"
            );
        }
        let kp = k.div_ceil(2);
        let panels = lines.div_ceil(width);
        let mut data = vec![0u32; panels * kp * width];
        if kp > 0 {
            data.par_chunks_mut(kp * width)
                .enumerate()
                .for_each(|(p, panel)| {
                    pack_panel(
                        src,
                        panel,
                        p * width,
                        lines,
                        k,
                        line_stride,
                        k_stride,
                        width,
                    )
                });
        }
        Self {
            data,
            lines,
            k,
            width,
        }
    }

    /// Pairs along the summed dimension (k rounded up to even, halved).
    pub(super) fn k_pairs(&self) -> usize {
        self.k.div_ceil(2)
    }

    /// Lines (rows of the left operand, columns of the right one).
    pub(super) fn lines(&self) -> usize {
        self.lines
    }

    /// Panel `p`: `[k_pairs][width]` words.
    pub(super) fn panel(&self, p: usize) -> &[u32] {
        let len = self.k_pairs() * self.width;
        &self.data[p * len..(p + 1) * len]
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.data.len() * 4
    }

    /// Lines of panels `width` wide ([`MR`] or [`NR`]).
    pub fn width(&self) -> usize {
        self.width
    }

    /// The matrix back in f32, `[lines, k]` row-major: the bf16 values exactly (for an f32 product over
    /// weights that are kept only packed).
    pub fn unpack(&self) -> Vec<f32> {
        let (k, width) = (self.k, self.width);
        let mut out = vec![0f32; self.lines * k];
        out.par_chunks_mut(k.max(1))
            .enumerate()
            .for_each(|(line, row)| {
                let panel = self.panel(line / width);
                let lane = line % width;
                for (j, v) in row.iter_mut().enumerate() {
                    let word = panel[(j / 2) * width + lane];
                    *v = from_bf16_bits((word >> (16 * (j % 2))) as u16);
                }
            });
        out
    }
}

/// Fills one panel (lines `first ..`) of a [`PackedPairs`].
#[allow(clippy::too_many_arguments)]
fn pack_panel(
    src: &[f32],
    panel: &mut [u32],
    first: usize,
    lines: usize,
    k: usize,
    line_stride: usize,
    k_stride: usize,
    width: usize,
) {
    let count = width.min(lines - first);
    let (full_pairs, odd) = (k / 2, k % 2 == 1);
    if line_stride == 1 {
        // Lines are contiguous (an im2col band): each k pair is two contiguous runs.
        for q in 0..full_pairs {
            let row0 = &src[2 * q * k_stride + first..][..count];
            let row1 = &src[(2 * q + 1) * k_stride + first..][..count];
            interleave_rows(row0, row1, &mut panel[q * width..q * width + count]);
        }
        if odd {
            let row0 = &src[2 * full_pairs * k_stride + first..][..count];
            let dst = &mut panel[full_pairs * width..full_pairs * width + count];
            for (d, &a) in dst.iter_mut().zip(row0) {
                *d = pair(a, 0.0);
            }
        }
    } else if k_stride == 1 && full_pairs >= 16 && bf16_products_available() {
        // Each line's k values are contiguous (a row-major left operand, attention probabilities).
        let lines: Vec<&[f32]> = (0..count)
            .map(|i| &src[(first + i) * line_stride..][..k])
            .collect();
        // SAFETY: the CPU has the instructions (checked just above).
        #[cfg(target_arch = "x86_64")]
        unsafe {
            pack_lines_avx512(&lines, panel, width)
        };
    } else {
        for i in 0..count {
            let line = &src[(first + i) * line_stride..];
            for q in 0..full_pairs {
                panel[q * width + i] = pair(line[2 * q * k_stride], line[(2 * q + 1) * k_stride]);
            }
            if odd {
                panel[full_pairs * width + i] = pair(line[2 * full_pairs * k_stride], 0.0);
            }
        }
    }
}

/// Up to `width` contiguous lines of k values as one panel's pairs, `panel[q·width + i] =
/// pair(lines[i][2q], lines[i][2q + 1])`: 32 values of each line converted at a time by the hardware
/// (the same rounding as [`pair`]) and written pair row by pair row, so the stores run through the
/// panel in order; the tails in scalar code.
///
/// # Safety
/// The CPU has AVX512-F/BW/VL/BF16.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw,avx512vl,avx512bf16")]
unsafe fn pack_lines_avx512(lines: &[&[f32]], panel: &mut [u32], width: usize) {
    use std::arch::x86_64::*;
    let Some(k) = lines.first().map(|l| l.len()) else {
        return;
    };
    let full_pairs = k / 2;
    let chunks = full_pairs / 16;
    let mut words = [[0u32; 16]; NR];
    for c in 0..chunks {
        for (line, words) in lines.iter().zip(words.iter_mut()) {
            // SAFETY: the 32 values from 32·c lie inside the line (c < full_pairs / 16).
            unsafe {
                let lo = _mm512_loadu_ps(line.as_ptr().add(32 * c));
                let hi = _mm512_loadu_ps(line.as_ptr().add(32 * c + 16));
                let pairs: __m512i =
                    std::mem::transmute::<__m512bh, __m512i>(_mm512_cvtne2ps_pbh(hi, lo));
                _mm512_storeu_si512(words.as_mut_ptr() as *mut _, pairs);
            }
        }
        for j in 0..16 {
            let row = &mut panel[(16 * c + j) * width..][..lines.len()];
            for (dst, words) in row.iter_mut().zip(&words) {
                *dst = words[j];
            }
        }
    }
    for (i, line) in lines.iter().enumerate() {
        for q in 16 * chunks..full_pairs {
            panel[q * width + i] = pair(line[2 * q], line[2 * q + 1]);
        }
        if k % 2 == 1 {
            panel[full_pairs * width + i] = pair(line[2 * full_pairs], 0.0);
        }
    }
}

/// `dst[i] = pair(row0[i], row1[i])`: 16 at a time with the hardware conversion (the same rounding).
pub(super) fn interleave_rows(row0: &[f32], row1: &[f32], dst: &mut [u32]) {
    #[cfg(target_arch = "x86_64")]
    if bf16_products_available() {
        // SAFETY: the CPU has the instructions (checked just above).
        unsafe { interleave_rows_avx512(row0, row1, dst) };
        return;
    }
    for ((d, &a), &b) in dst.iter_mut().zip(row0).zip(row1) {
        *d = pair(a, b);
    }
}

/// [`interleave_rows`] with AVX512-BF16: two rows converted to bf16, widened and merged 16 pairs at a
/// time; the tail in scalar code.
///
/// # Safety
/// The CPU has AVX512-F/BW/VL/BF16.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw,avx512vl,avx512bf16")]
unsafe fn interleave_rows_avx512(row0: &[f32], row1: &[f32], dst: &mut [u32]) {
    use std::arch::x86_64::*;
    let n = dst.len().min(row0.len()).min(row1.len());
    let full = n / 16 * 16;
    for i in (0..full).step_by(16) {
        // SAFETY: i + 16 ≤ n, inside all three slices.
        unsafe {
            let lo: __m256i = std::mem::transmute::<__m256bh, __m256i>(_mm512_cvtneps_pbh(
                _mm512_loadu_ps(row0.as_ptr().add(i)),
            ));
            let hi: __m256i = std::mem::transmute::<__m256bh, __m256i>(_mm512_cvtneps_pbh(
                _mm512_loadu_ps(row1.as_ptr().add(i)),
            ));
            let pairs = _mm512_or_si512(
                _mm512_cvtepu16_epi32(lo),
                _mm512_slli_epi32::<16>(_mm512_cvtepu16_epi32(hi)),
            );
            _mm512_storeu_si512(dst.as_mut_ptr().add(i) as *mut _, pairs);
        }
    }
    for i in full..n {
        dst[i] = pair(row0[i], row1[i]);
    }
}

/// The output of a product: `c[row·row_stride + col]` for `rows × cols`.
pub struct Output<'a> {
    pub data: &'a mut [f32],
    pub rows: usize,
    pub cols: usize,
    pub row_stride: usize,
}

/// `C (+)= A·Bᵀ`-in-pairs: `c[i, j] (+)= Σ_k a[i, k]·b[j, k]` for A packed with [`MR`]-line panels (its
/// lines are C's rows) and B with [`NR`]-line panels (C's columns); f32 sums. `accumulate` adds onto C's
/// values (a bias or residual pre-filled there), otherwise C is overwritten.
///
/// Panics when the CPU lacks the instructions (callers check [`bf16_products_available`] through
/// [`cpu_precision`]) or the shapes disagree.
pub fn gemm(a: &PackedPairs, b: &PackedPairs, c: Output<'_>, accumulate: bool) {
    assert_eq!(a.width, MR, "gemm: A must be packed in MR panels");
    assert_eq!(b.width, NR, "gemm: B must be packed in NR panels");
    assert_eq!(a.k, b.k, "gemm: A and B sum over different lengths");
    assert!(c.rows == a.lines && c.cols == b.lines, "gemm: output shape");
    assert!(c.cols <= c.row_stride || c.rows <= 1, "gemm: output stride");
    if c.rows == 0 || c.cols == 0 {
        return;
    }
    assert!(
        (c.rows - 1) * c.row_stride + c.cols <= c.data.len(),
        "gemm: output too short"
    );
    assert!(
        bf16_products_available(),
        "gemm: no AVX512-BF16 on this CPU"
    );
    let kp = a.k_pairs();
    if kp == 0 {
        if !accumulate {
            for r in 0..c.rows {
                c.data[r * c.row_stride..][..c.cols].fill(0.0);
            }
        }
        return;
    }
    let (row_panels, col_panels) = (c.rows.div_ceil(MR), c.cols.div_ceil(NR));
    let row_blocks = row_panels.div_ceil(ROW_PANELS_PER_TASK);
    let col_blocks = col_panels.div_ceil(COL_PANELS_PER_TASK);
    let out = SharedOut(c.data.as_mut_ptr());
    let (rows, cols, row_stride) = (c.rows, c.cols, c.row_stride);
    (0..row_blocks * col_blocks)
        .into_par_iter()
        .for_each(|task| {
            let (rb, cb) = (task / col_blocks, task % col_blocks);
            let panels_r =
                rb * ROW_PANELS_PER_TASK..((rb + 1) * ROW_PANELS_PER_TASK).min(row_panels);
            let panels_c =
                cb * COL_PANELS_PER_TASK..((cb + 1) * COL_PANELS_PER_TASK).min(col_panels);
            let mut k0 = 0;
            while k0 < kp {
                let len = KC.min(kp - k0);
                for pc in panels_c.clone() {
                    let b_panel = &b.panel(pc)[k0 * NR..(k0 + len) * NR];
                    let (col0, ncols) = (pc * NR, NR.min(cols - pc * NR));
                    for pr in panels_r.clone() {
                        let a_panel = &a.panel(pr)[k0 * MR..(k0 + len) * MR];
                        let (row0, nrows) = (pr * MR, MR.min(rows - pr * MR));
                        // SAFETY: the tiles of different tasks are disjoint, and each lies inside `c.data`
                        // (checked above: (rows-1)·row_stride + cols ≤ len); the CPU has the instructions.
                        unsafe {
                            micro_tile(
                                len,
                                a_panel,
                                b_panel,
                                out.at(row0 * row_stride + col0),
                                row_stride,
                                nrows,
                                ncols,
                                accumulate || k0 > 0,
                            );
                        }
                    }
                }
                k0 += len;
            }
        });
}

/// The output pointer, shared by the tasks that write disjoint tiles of it.
#[derive(Clone, Copy)]
pub(super) struct SharedOut(pub(super) *mut f32);
// SAFETY: tasks write disjoint tiles only (see `gemm`).
unsafe impl Send for SharedOut {}
unsafe impl Sync for SharedOut {}

impl SharedOut {
    /// The element `offset` floats in (a method, so closures capture the whole `Send` wrapper).
    ///
    /// # Safety
    /// `offset` lies inside the output.
    pub(super) unsafe fn at(self, offset: usize) -> *mut f32 {
        // SAFETY: the caller's contract.
        unsafe { self.0.add(offset) }
    }
}

/// One MR×NR tile: `c (+)= a·b` over `kp` k pairs, `a` [kp][MR], `b` [kp][NR]; only `rows × cols` of the
/// tile are read and written.
///
/// # Safety
/// The CPU has AVX512-F/BW/VL/BF16; `c` addresses `rows` rows of `cols` floats at `row_stride`.
#[cfg(target_arch = "x86_64")]
#[allow(clippy::too_many_arguments)]
#[target_feature(enable = "avx512f,avx512bw,avx512vl,avx512bf16")]
unsafe fn micro_tile(
    kp: usize,
    a: &[u32],
    b: &[u32],
    c: *mut f32,
    row_stride: usize,
    rows: usize,
    cols: usize,
    accumulate: bool,
) {
    use std::arch::x86_64::*;
    debug_assert!(a.len() >= kp * MR && b.len() >= kp * NR);
    let mut acc = [[_mm512_setzero_ps(); 2]; MR];
    let (ap, bp) = (a.as_ptr(), b.as_ptr());
    for q in 0..kp {
        // SAFETY: q < kp, and the slices hold kp·MR / kp·NR words.
        let (b0, b1) = unsafe {
            (
                _mm512_loadu_si512(bp.add(q * NR) as *const _),
                _mm512_loadu_si512(bp.add(q * NR + 16) as *const _),
            )
        };
        let (b0, b1): (__m512bh, __m512bh) = (
            std::mem::transmute::<__m512i, __m512bh>(b0),
            std::mem::transmute::<__m512i, __m512bh>(b1),
        );
        for (r, acc) in acc.iter_mut().enumerate() {
            // SAFETY: as above.
            let a = unsafe { *ap.add(q * MR + r) };
            let a = std::mem::transmute::<__m512i, __m512bh>(_mm512_set1_epi32(a as i32));
            acc[0] = _mm512_dpbf16_ps(acc[0], a, b0);
            acc[1] = _mm512_dpbf16_ps(acc[1], a, b1);
        }
    }
    let lanes = |n: usize| -> __mmask16 {
        if n >= 16 {
            0xffff
        } else {
            ((1u32 << n) - 1) as __mmask16
        }
    };
    let (m0, m1) = (lanes(cols), lanes(cols.saturating_sub(16)));
    for (r, acc) in acc.iter().enumerate().take(rows) {
        // SAFETY: row r < rows and the masks keep to the first `cols` floats (caller's contract).
        unsafe {
            let row = c.add(r * row_stride);
            let (mut v0, mut v1) = (acc[0], acc[1]);
            if accumulate {
                v0 = _mm512_add_ps(v0, _mm512_maskz_loadu_ps(m0, row));
                if m1 != 0 {
                    v1 = _mm512_add_ps(v1, _mm512_maskz_loadu_ps(m1, row.add(16)));
                }
            }
            _mm512_mask_storeu_ps(row, m0, v0);
            if m1 != 0 {
                _mm512_mask_storeu_ps(row.add(16), m1, v1);
            }
        }
    }
}

#[cfg(not(target_arch = "x86_64"))]
#[allow(clippy::too_many_arguments)]
unsafe fn micro_tile(
    _: usize,
    _: &[u32],
    _: &[u32],
    _: *mut f32,
    _: usize,
    _: usize,
    _: usize,
    _: bool,
) {
    unreachable!("bf16 products are only detected on x86_64")
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;

    /// Deterministic values in [-1, 1).
    pub(in super::super) fn values(n: usize, seed: u64) -> Vec<f32> {
        let mut s = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
        (0..n)
            .map(|_| {
                s ^= s << 13;
                s ^= s >> 7;
                s ^= s << 17;
                (s >> 40) as f32 / (1u64 << 23) as f32 - 1.0
            })
            .collect()
    }

    /// `x` rounded to bf16 and back.
    pub(in super::super) fn round(x: f32) -> f32 {
        from_bf16_bits(to_bf16_bits(x))
    }

    #[test]
    fn rounding_is_nearest_even() {
        assert_eq!(round(1.0), 1.0);
        // 1 + 2^-8 lies halfway between bf16 neighbours 1 and 1 + 2^-7: ties go to the even one (1).
        assert_eq!(round(1.0 + 1.0 / 256.0), 1.0);
        assert_eq!(round(1.0 + 3.0 / 256.0), 1.0 + 4.0 / 256.0);
        assert_eq!(round(-2.5), -2.5);
        assert!(round(f32::NAN).is_nan());
        assert_eq!(round(f32::INFINITY), f32::INFINITY);
        assert_eq!(round(f32::MAX), f32::INFINITY);
        for x in values(1000, 3) {
            assert!((round(x) - x).abs() <= x.abs() / 256.0, "{x}");
        }
    }

    /// `c[i, j] = Σ a[i, k]·b[j, k]` in f64 over given (already rounded or not) operands.
    fn reference(a: &[f32], b: &[f32], m: usize, n: usize, k: usize) -> Vec<f64> {
        let mut c = vec![0f64; m * n];
        for i in 0..m {
            for j in 0..n {
                c[i * n + j] = (0..k)
                    .map(|t| a[i * k + t] as f64 * b[j * k + t] as f64)
                    .sum();
            }
        }
        c
    }

    /// The product of bf16-rounded operands equals their exact product up to f32 summation (1e-5 of
    /// the sums' scale), over edge sizes (partial tiles, odd k, several k blocks and tasks), both
    /// packing layouts and accumulation; against the unrounded f32 product it is within bf16's
    /// rounding (2·2^-9 relative per term, so ≤ 1 % of Σ|a||b| and ~0.3 % of typical sums).
    #[test]
    fn product_matches_the_rounded_operands_exactly_and_f32_within_bf16() {
        if !bf16_products_available() {
            eprintln!("skipped: no AVX512-BF16 on this CPU");
            return;
        }
        for &(m, n, k) in &[
            (1, 1, 1),
            (12, 32, 2),
            (13, 33, 7),
            (5, 70, 400),
            (100, 129, 3 * KC + 5),
            (200, 300, 64),
        ] {
            let (a, b) = (values(m * k, 1 + m as u64), values(n * k, 2 + n as u64));
            // A row-major (k contiguous), B as columns of a [k, n] matrix (lines contiguous).
            let bt: Vec<f32> = (0..k * n).map(|i| b[(i % n) * k + i / n]).collect();
            let pa = PackedPairs::pack(&a, m, k, k, 1, MR);
            let pb = PackedPairs::pack(&bt, n, k, 1, n, NR);
            let stride = n + 3;
            let mut c = vec![0.5f32; m * stride];
            gemm(
                &pa,
                &pb,
                Output {
                    data: &mut c,
                    rows: m,
                    cols: n,
                    row_stride: stride,
                },
                true,
            );
            let ar: Vec<f32> = a.iter().map(|&x| round(x)).collect();
            let br: Vec<f32> = b.iter().map(|&x| round(x)).collect();
            let exact = reference(&ar, &br, m, n, k);
            let unrounded = reference(&a, &b, m, n, k);
            let abs = {
                let (aa, ba): (Vec<f32>, Vec<f32>) = (
                    a.iter().map(|x| x.abs()).collect(),
                    b.iter().map(|x| x.abs()).collect(),
                );
                reference(&aa, &ba, m, n, k)
            };
            let (mut err2, mut ref2) = (0f64, 0f64);
            for i in 0..m {
                for j in 0..n {
                    let got = c[i * stride + j] as f64 - 0.5;
                    let scale = abs[i * n + j].max(1e-3);
                    assert!(
                        (got - exact[i * n + j]).abs() <= 1e-5 * scale,
                        "{m}x{n}x{k} at ({i},{j}): {got} vs {}",
                        exact[i * n + j]
                    );
                    assert!((got - unrounded[i * n + j]).abs() <= 1e-2 * scale);
                    err2 += (got - unrounded[i * n + j]).powi(2);
                    ref2 += unrounded[i * n + j].powi(2);
                }
                // The padding columns between rows are untouched.
                assert!(c[i * stride + n..(i + 1) * stride]
                    .iter()
                    .all(|&v| v == 0.5));
            }
            if k >= 64 {
                let rel = (err2 / ref2).sqrt();
                assert!(rel < 5e-3, "{m}x{n}x{k}: relative L2 {rel}");
            }
        }
    }

    /// Unpacking gives back each value rounded to bf16, for both panel widths, odd k and partial panels,
    /// with lines short enough for the scalar packing and long enough for the vector one (two chunks of
    /// 32 values, a scalar tail and an odd last value).
    #[test]
    fn unpacking_gives_the_rounded_matrix() {
        for (lines, k) in [(37, 11), (29, 75)] {
            let m = values(lines * k, 7);
            let rounded: Vec<f32> = m.iter().map(|&x| from_bf16_bits(to_bf16_bits(x))).collect();
            for width in [MR, NR] {
                let packed = PackedPairs::pack(&m, lines, k, k, 1, width);
                assert_eq!(packed.unpack(), rounded, "{lines}x{k}, width {width}");
            }
        }
    }

    #[test]
    fn overwrite_ignores_previous_output() {
        if !bf16_products_available() {
            return;
        }
        let (m, n, k) = (7, 40, 9);
        let (a, b) = (values(m * k, 5), values(n * k, 6));
        let pa = PackedPairs::pack(&a, m, k, k, 1, MR);
        let pb = PackedPairs::pack(&b, n, k, k, 1, NR);
        let mut fresh = vec![0f32; m * n];
        let mut dirty = vec![f32::NAN; m * n];
        for (out, acc) in [(&mut fresh, true), (&mut dirty, false)] {
            gemm(
                &pa,
                &pb,
                Output {
                    data: out,
                    rows: m,
                    cols: n,
                    row_stride: n,
                },
                acc,
            );
        }
        assert_eq!(fresh, dirty);
    }
}
