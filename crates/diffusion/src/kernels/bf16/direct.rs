//! bf16 convolutions without an im2col matrix.
//!
//! An im2col matrix repeats every input value k² times (9 for a 3×3 kernel) and, in bf16, has to be
//! rounded and packed at every call: on the codecs' wide, shallow layers (TAESD's 64 channels at 512²)
//! making it cost as much as the product. Here the input is rounded and packed once, in its own size, and
//! each kernel tap reads it at a shift:
//!
//! - **Weights** are packed tap-major ([`pack_conv_weight`]): summed index `(ky, kx, c)` with the input
//!   channels `c` paired (an odd count padded with a zero channel), in the [`MR`]-row panels of
//!   [`PackedPairs`]. A model loaded for bf16 products keeps its convolutions' weights in this order only.
//! - **Input** ([`PackedInput`]): one image, zero-padded, split into `stride²` phase planes (plane
//!   `(py, px)` holds the padded pixels `(s·y + py, s·x + px)`), each plane as bf16 pairs of adjacent
//!   channels, `ConvDims::plane_words` pairs per channel pair.
//! - **Output positions** are counted row-major over a plane's width `Wq` instead of the output's width
//!   (`o = oy·Wq + ox`): then for every tap `(ky, kx)` the inputs of NR consecutive positions are NR
//!   consecutive pairs of plane `(ky mod s, kx mod s)` at offset `o + (ky div s)·Wq + kx div s`, one vector
//!   load per channel pair. The positions with `ox ≥ out_w` (1–2 per row) are computed and dropped when the
//!   tile is stored; the register tile is [`super::gemm`]'s, [`MR`]×[`NR`], B read at each pair's offset
//!   instead of from a packed panel.

use rayon::prelude::*;

use super::gemm::{interleave_rows, pair, PackedPairs, SharedOut, MR, NR};

/// k pairs per cache block: a tile's B vectors (up to three cache lines per pair) stay in L1 while the
/// A panels of a row block stream from L2.
const KC: usize = 128;
/// A panels (of MR output channels) per parallel task.
const ROW_PANELS_PER_TASK: usize = 8;
/// Output tiles (of NR positions) per parallel task.
const TILES_PER_TASK: usize = 4;

/// The geometry of one convolution (square kernel, no dilation or groups) over one image.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ConvDims {
    pub c_in: usize,
    pub h: usize,
    pub w: usize,
    pub c_out: usize,
    pub kernel: usize,
    pub stride: usize,
    pub padding: usize,
    pub out_h: usize,
    pub out_w: usize,
}

impl ConvDims {
    /// Pairs of input channels (an odd channel count gets a zero channel).
    fn channel_pairs(&self) -> usize {
        self.c_in.div_ceil(2)
    }

    /// Summed pairs of one output: taps × channel pairs.
    fn k_pairs(&self) -> usize {
        self.kernel * self.kernel * self.channel_pairs()
    }

    /// A phase plane's height and width (padded image rows/columns of one phase, rounded up).
    fn plane_hw(&self) -> (usize, usize) {
        (
            (self.h + 2 * self.padding).div_ceil(self.stride),
            (self.w + 2 * self.padding).div_ceil(self.stride),
        )
    }

    /// Output tiles of NR positions over the `out_h × Wq` positions.
    fn tiles(&self) -> usize {
        (self.out_h * self.plane_hw().1).div_ceil(NR)
    }

    /// Where tap `(ky, kx)` reads: its phase plane and the offset of position 0 within that plane.
    fn tap(&self, ky: usize, kx: usize) -> (usize, usize) {
        let s = self.stride;
        let wq = self.plane_hw().1;
        ((ky % s) * s + kx % s, (ky / s) * wq + kx / s)
    }

    /// Words per channel-pair plane: every position a tile reads (the last tile's NR positions at the
    /// largest tap offset) lies inside, rounded to an odd number of cache lines so that the planes a
    /// tile reads one after another do not share cache sets.
    fn plane_words(&self) -> usize {
        let (hq, wq) = self.plane_hw();
        let k = self.kernel - 1;
        let reach = self.tiles() * NR + (k / self.stride) * wq + k / self.stride;
        let lines = (hq * wq).max(reach).div_ceil(16);
        (lines | 1) * 16
    }
}

/// The order of a convolution weight's summed values in its bf16 pairs.
///
/// `[out, in, k, k]` f32 → [`MR`] panels over summed index `(ky, kx, c)`, `c` running over the input
/// channels rounded up to even (the extra channel zero).
pub fn pack_conv_weight(values: &[f32], c_out: usize, c_in: usize, kernel: usize) -> PackedPairs {
    let (taps, c_even) = (kernel * kernel, c_in.div_ceil(2) * 2);
    assert_eq!(values.len(), c_out * c_in * taps, "conv weight shape");
    let mut reordered = vec![0f32; c_out * taps * c_even];
    reordered
        .par_chunks_mut((taps * c_even).max(1))
        .enumerate()
        .for_each(|(o, dst)| {
            for c in 0..c_in {
                for t in 0..taps {
                    dst[t * c_even + c] = values[(o * c_in + c) * taps + t];
                }
            }
        });
    PackedPairs::pack(&reordered, c_out, taps * c_even, taps * c_even, 1, MR)
}

/// The f32 weight `[out, in, k, k]` of pairs made by [`pack_conv_weight`] (the bf16 values exactly).
pub fn unpack_conv_weight(
    pairs: &PackedPairs,
    c_out: usize,
    c_in: usize,
    kernel: usize,
) -> Vec<f32> {
    let (taps, c_even) = (kernel * kernel, c_in.div_ceil(2) * 2);
    let reordered = pairs.unpack();
    assert_eq!(reordered.len(), c_out * taps * c_even, "conv weight shape");
    let mut values = vec![0f32; c_out * c_in * taps];
    values
        .par_chunks_mut((c_in * taps).max(1))
        .enumerate()
        .for_each(|(o, dst)| {
            for c in 0..c_in {
                for t in 0..taps {
                    dst[c * taps + t] = reordered[(o * taps + t) * c_even + c];
                }
            }
        });
    values
}

/// One image zero-padded, split into phase planes and rounded to bf16 channel pairs: word
/// `[(phase·channel_pairs + q)·plane_words + y·Wq + x]` holds channels `2q, 2q+1` of padded pixel
/// `(s·y + py, s·x + px)`.
pub struct PackedInput {
    data: Vec<u32>,
}

impl PackedInput {
    /// Packs `image` [c_in, h, w].
    pub fn new(dims: &ConvDims, image: &[f32]) -> Self {
        let (c_in, h, w, s, p) = (dims.c_in, dims.h, dims.w, dims.stride, dims.padding);
        assert_eq!(image.len(), c_in * h * w, "conv input shape");
        let (hq, wq) = dims.plane_hw();
        let plane_words = dims.plane_words();
        let pairs = dims.channel_pairs();
        let mut data = vec![0u32; s * s * pairs * plane_words];
        let zeros = vec![0f32; w];
        data.par_chunks_mut(plane_words)
            .enumerate()
            .for_each(|(plane, dst)| {
                let (phase, q) = (plane / pairs, plane % pairs);
                let (py, px) = (phase / s, phase % s);
                let channel = |c: usize| -> &[f32] {
                    if c < c_in {
                        &image[c * h * w..(c + 1) * h * w]
                    } else {
                        &[]
                    }
                };
                let (lo, hi) = (channel(2 * q), channel(2 * q + 1));
                // Plane columns whose padded column s·x + px lies inside the image: x in [x0, x1).
                let x0 = p.saturating_sub(px).div_ceil(s);
                let x1 = (w + p).saturating_sub(px).div_ceil(s).min(wq);
                for y in 0..hq {
                    let Some(iy) = (s * y + py).checked_sub(p).filter(|&iy| iy < h) else {
                        continue;
                    };
                    let row0 = &lo[iy * w..(iy + 1) * w];
                    let row1 = if hi.is_empty() {
                        &zeros[..]
                    } else {
                        &hi[iy * w..(iy + 1) * w]
                    };
                    let out = &mut dst[y * wq..(y + 1) * wq];
                    if x0 >= x1 {
                        continue;
                    }
                    let ix0 = s * x0 + px - p;
                    if s == 1 {
                        interleave_rows(&row0[ix0..], &row1[ix0..], &mut out[x0..x1]);
                    } else {
                        for (x, o) in (x0..x1).zip(&mut out[x0..x1]) {
                            let ix = s * x + px - p;
                            *o = pair(row0[ix], row1[ix]);
                        }
                    }
                }
            });
        Self { data }
    }
}

/// `out[o, oy, ox] (+)= Σ weight · input` over the taps and channels: `weight` from
/// [`pack_conv_weight`], `image` one image [c_in, h, w], `out` [c_out, out_h, out_w]. `accumulate` adds
/// onto `out` (a bias or residual pre-filled there), otherwise it is overwritten; `relu` clamps the
/// finished sums at 0 as they are stored (a ReLU after the convolution, without a pass of its own).
///
/// Panics when the CPU lacks AVX512-BF16 or the shapes disagree.
pub fn conv(
    dims: &ConvDims,
    weight: &PackedPairs,
    images: &[f32],
    out: &mut [f32],
    accumulate: bool,
    relu: bool,
) {
    assert!(
        super::bf16_products_available(),
        "conv: no AVX512-BF16 on this CPU"
    );
    assert_eq!(
        weight.width(),
        MR,
        "conv: weight must be packed in MR panels"
    );
    assert_eq!(
        (weight.lines(), weight.k_pairs()),
        (dims.c_out, dims.k_pairs()),
        "conv: weight does not fit {dims:?}"
    );
    let (in_image, out_plane) = (dims.c_in * dims.h * dims.w, dims.out_h * dims.out_w);
    let out_image = dims.c_out * out_plane;
    let batch = images.len() / in_image.max(1);
    assert_eq!(images.len(), batch * in_image, "conv: input shape");
    assert_eq!(out.len(), batch * out_image, "conv: output shape");
    if out.is_empty() {
        return;
    }
    let inputs: Vec<PackedInput> = images
        .chunks(in_image)
        .map(|image| PackedInput::new(dims, image))
        .collect();
    let plane_words = dims.plane_words();
    let pairs = dims.channel_pairs();
    let (_, wq) = dims.plane_hw();
    // Each k block's B offsets, one per pair: where its NR words start, from a tile's first position.
    let kp = dims.k_pairs();
    let k_blocks = kp.div_ceil(KC);
    let block_len = kp.div_ceil(k_blocks);
    let offsets: Vec<usize> = (0..kp)
        .map(|q| {
            let (tap, c) = (q / pairs, q % pairs);
            let (phase, offset) = dims.tap(tap / dims.kernel, tap % dims.kernel);
            (phase * pairs + c) * plane_words + offset
        })
        .collect();
    let blocks: Vec<&[usize]> = offsets.chunks(block_len).collect();
    let (row_panels, tiles) = (dims.c_out.div_ceil(MR), dims.tiles());
    let row_blocks = row_panels.div_ceil(ROW_PANELS_PER_TASK);
    // Small images (a batch of 16² latents) get tasks of fewer tiles, so that both threads have work.
    let threads = rayon::current_num_threads().max(1);
    let tiles_per_task = (batch * row_blocks * tiles / (8 * threads)).clamp(1, TILES_PER_TASK);
    let col_blocks = tiles.div_ceil(tiles_per_task);
    let dst = SharedOut(out.as_mut_ptr());
    (0..batch * row_blocks * col_blocks)
        .into_par_iter()
        .for_each(|task| {
            let (n, task) = (
                task / (row_blocks * col_blocks),
                task % (row_blocks * col_blocks),
            );
            let (rb, cb) = (task / col_blocks, task % col_blocks);
            let input = &inputs[n];
            let panels = rb * ROW_PANELS_PER_TASK..((rb + 1) * ROW_PANELS_PER_TASK).min(row_panels);
            let task_tiles = cb * tiles_per_task..((cb + 1) * tiles_per_task).min(tiles);
            let segments: Vec<Vec<Segment>> = task_tiles
                .clone()
                .map(|t| tile_segments(t * NR, wq, dims.out_w, dims.out_h))
                .collect();
            let mut tile = [[0f32; NR]; MR];
            for (b, block) in blocks.iter().enumerate() {
                let q0 = b * block_len;
                for (t, segments) in task_tiles.clone().zip(&segments) {
                    // SAFETY: every run reads NR words from t·NR + its offset, inside its plane
                    // (`ConvDims::plane_words`), for its count of planes.
                    let b_tile = unsafe { input.data.as_ptr().add(t * NR) };
                    for pr in panels.clone() {
                        let a = &weight.panel(pr)[q0 * MR..];
                        let rows = MR.min(dims.c_out - pr * MR);
                        // SAFETY: the CPU has the instructions (asserted above); `a` holds the block's
                        // pairs; the B reads stay inside the input (see above).
                        unsafe {
                            match rows {
                                1..=4 => tap_tile::<4>(a, b_tile, block, &mut tile),
                                5..=8 => tap_tile::<8>(a, b_tile, block, &mut tile),
                                _ => tap_tile::<MR>(a, b_tile, block, &mut tile),
                            }
                        }
                        let add = accumulate || b > 0;
                        let clamp = relu && b + 1 == blocks.len();
                        for (r, values) in tile.iter().enumerate().take(rows) {
                            let channel = n * out_image + (pr * MR + r) * out_plane;
                            for seg in segments {
                                // SAFETY: the segment lies inside output channel `pr·MR + r`, and the
                                // tasks' (channel, position) tiles are disjoint.
                                unsafe {
                                    let o = std::slice::from_raw_parts_mut(
                                        dst.at(channel + seg.out),
                                        seg.len,
                                    );
                                    let v = &values[seg.lane..seg.lane + seg.len];
                                    match (add, clamp) {
                                        (true, false) => {
                                            o.iter_mut().zip(v).for_each(|(o, v)| *o += v)
                                        }
                                        (false, false) => o.copy_from_slice(v),
                                        (true, true) => o
                                            .iter_mut()
                                            .zip(v)
                                            .for_each(|(o, v)| *o = (*o + v).max(0.0)),
                                        (false, true) => {
                                            o.iter_mut().zip(v).for_each(|(o, v)| *o = v.max(0.0))
                                        }
                                    }
                                }
                            }
                        }
                    }
                }
            }
        });
}

/// A run of a tile's lanes that are real output positions: lanes `lane..lane + len` go to output
/// positions `out..out + len` of each channel.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Segment {
    lane: usize,
    out: usize,
    len: usize,
}

/// The segments of the tile whose first position is `first` (positions `oy·wq + ox`).
fn tile_segments(first: usize, wq: usize, out_w: usize, out_h: usize) -> Vec<Segment> {
    let mut segments = Vec::new();
    let mut lane = 0;
    while lane < NR {
        let o = first + lane;
        let (oy, ox) = (o / wq, o % wq);
        if oy >= out_h {
            break;
        }
        if ox >= out_w {
            lane += wq - ox;
            continue;
        }
        let len = (out_w - ox).min(NR - lane);
        segments.push(Segment {
            lane,
            out: oy * out_w + ox,
            len,
        });
        lane += len;
    }
    segments
}

/// One tile of `R` output channels × NR positions over one k block: `tile[r] = Σ a·b`, the A pairs
/// `a` [pairs][MR] (rows ≥ R ignored), the i-th pair's B words read from `b + offsets[i]`. One flat loop
/// over the pairs (as in the product's microkernel), so the accumulators stay in registers.
///
/// # Safety
/// The CPU has AVX512-F/BW/VL/BF16; `a` holds `offsets.len()` pairs; every B read of NR words lies
/// inside the allocation `b` points into.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw,avx512vl,avx512bf16")]
unsafe fn tap_tile<const R: usize>(
    a: &[u32],
    b: *const u32,
    offsets: &[usize],
    tile: &mut [[f32; NR]; MR],
) {
    use std::arch::x86_64::*;
    debug_assert!(a.len() >= offsets.len() * MR);
    let mut acc = [[_mm512_setzero_ps(); 2]; R];
    let ap = a.as_ptr();
    for (i, &offset) in offsets.iter().enumerate() {
        // SAFETY: the caller's contract (B reads inside, A holds every pair).
        let (b0, b1) = unsafe {
            let bp = b.add(offset);
            (
                std::mem::transmute::<__m512i, __m512bh>(_mm512_loadu_si512(bp as *const _)),
                std::mem::transmute::<__m512i, __m512bh>(
                    _mm512_loadu_si512(bp.add(16) as *const _),
                ),
            )
        };
        for (r, acc) in acc.iter_mut().enumerate() {
            // SAFETY: as above.
            let a = unsafe { *ap.add(i * MR + r) };
            let a = std::mem::transmute::<__m512i, __m512bh>(_mm512_set1_epi32(a as i32));
            acc[0] = _mm512_dpbf16_ps(acc[0], a, b0);
            acc[1] = _mm512_dpbf16_ps(acc[1], a, b1);
        }
    }
    for (row, acc) in tile.iter_mut().zip(&acc) {
        // SAFETY: each row holds NR = 32 floats.
        unsafe {
            _mm512_storeu_ps(row.as_mut_ptr(), acc[0]);
            _mm512_storeu_ps(row.as_mut_ptr().add(16), acc[1]);
        }
    }
}

#[cfg(not(target_arch = "x86_64"))]
unsafe fn tap_tile<const R: usize>(_: &[u32], _: *const u32, _: &[usize], _: &mut [[f32; NR]; MR]) {
    unreachable!("bf16 products are only detected on x86_64")
}

#[cfg(test)]
mod tests {
    use super::super::gemm::tests::{round, values};
    use super::*;

    fn dims(
        c_in: usize,
        c_out: usize,
        h: usize,
        w: usize,
        k: usize,
        s: usize,
        p: usize,
    ) -> ConvDims {
        ConvDims {
            c_in,
            h,
            w,
            c_out,
            kernel: k,
            stride: s,
            padding: p,
            out_h: (h + 2 * p - k) / s + 1,
            out_w: (w + 2 * p - k) / s + 1,
        }
    }

    /// The convolution in f64 over the given values, [c_out, out_h, out_w].
    fn reference(d: &ConvDims, weight: &[f32], image: &[f32]) -> Vec<f64> {
        let k = d.kernel;
        let mut out = vec![0f64; d.c_out * d.out_h * d.out_w];
        for o in 0..d.c_out {
            for oy in 0..d.out_h {
                for ox in 0..d.out_w {
                    let mut sum = 0f64;
                    for c in 0..d.c_in {
                        for ky in 0..k {
                            for kx in 0..k {
                                let iy = (oy * d.stride + ky) as isize - d.padding as isize;
                                let ix = (ox * d.stride + kx) as isize - d.padding as isize;
                                if iy < 0 || ix < 0 || iy >= d.h as isize || ix >= d.w as isize {
                                    continue;
                                }
                                sum += weight[((o * d.c_in + c) * k + ky) * k + kx] as f64
                                    * image[(c * d.h + iy as usize) * d.w + ix as usize] as f64;
                            }
                        }
                    }
                    out[(o * d.out_h + oy) * d.out_w + ox] = sum;
                }
            }
        }
        out
    }

    /// Over batches of one and two images, odd channel counts, output channels that leave 4- and 8-row panels, images narrower than a
    /// tile, strides 1 and 2, paddings 0–2, 1×1 and 3×3 kernels and several k blocks: the direct
    /// convolution of bf16-rounded operands equals their exact convolution up to f32 summation;
    /// accumulating adds onto the output, and the fused ReLU clamps the sum of both.
    #[test]
    fn direct_conv_matches_the_rounded_operands_exactly() {
        if !super::super::bf16_products_available() {
            eprintln!("skipped: no AVX512-BF16 on this CPU");
            return;
        }
        let cases = [
            // (c_in, c_out, h, w, kernel, stride, padding)
            (3, 5, 9, 7, 3, 1, 1),
            (4, 16, 8, 8, 3, 2, 1),
            (7, 20, 9, 6, 3, 2, 0),
            (33, 12, 5, 5, 1, 1, 0),
            (5, 4, 7, 3, 1, 2, 0),
            (2, 3, 4, 5, 3, 1, 2),
            (64, 30, 11, 40, 3, 1, 1),
            (40, 13, 16, 16, 3, 2, 1),
            (1, 1, 1, 1, 1, 1, 0),
        ];
        for (seed, &(ci, co, h, w, k, s, p)) in cases.iter().enumerate() {
            let d = dims(ci, co, h, w, k, s, p);
            let batch = 1 + seed % 2;
            let weight = values(co * ci * k * k, 2 * seed as u64 + 1);
            let image = values(batch * ci * h * w, 2 * seed as u64 + 2);
            let packed = pack_conv_weight(&weight, co, ci, k);
            let plane = d.out_h * d.out_w;
            // The reference image by image.
            let per_image = |wt: &[f32], im: &[f32]| -> Vec<f64> {
                im.chunks(ci * h * w)
                    .flat_map(|one| reference(&d, wt, one))
                    .collect()
            };
            for (accumulate, relu) in [(false, false), (true, false), (true, true)] {
                let mut out = vec![if accumulate { 0.25 } else { f32::NAN }; batch * co * plane];
                conv(&d, &packed, &image, &mut out, accumulate, relu);
                let wr: Vec<f32> = weight.iter().map(|&x| round(x)).collect();
                let ir: Vec<f32> = image.iter().map(|&x| round(x)).collect();
                let exact = per_image(&wr, &ir);
                let wa: Vec<f32> = weight.iter().map(|x| x.abs()).collect();
                let ia: Vec<f32> = image.iter().map(|x| x.abs()).collect();
                let scale = per_image(&wa, &ia);
                let base = if accumulate { 0.25 } else { 0.0 };
                for (i, (&got, &want)) in out.iter().zip(&exact).enumerate() {
                    let want = if relu {
                        (want + base).max(0.0) - base
                    } else {
                        want
                    };
                    assert!(
                        (got as f64 - base - want).abs() <= 1e-5 * scale[i].max(1e-3),
                        "case {:?} at {i}: {got} vs {want}",
                        (ci, co, h, w, k, s, p)
                    );
                }
            }
        }
    }

    /// Packing a weight tap-major and unpacking it gives back each value rounded to bf16.
    #[test]
    fn conv_weights_unpack_to_the_rounded_values() {
        for (co, ci, k) in [(5, 3, 3), (13, 8, 1), (2, 7, 3)] {
            let w = values(co * ci * k * k, 11);
            let packed = pack_conv_weight(&w, co, ci, k);
            let back = unpack_conv_weight(&packed, co, ci, k);
            let rounded: Vec<f32> = w.iter().map(|&x| round(x)).collect();
            assert_eq!(back, rounded, "{:?}", (co, ci, k));
        }
    }

    /// A tile's segments skip the positions past each row's end and past the last row.
    #[test]
    fn segments_skip_the_padding_columns() {
        // Rows of 5 outputs in planes 7 wide: positions 0–4 real, 5–6 not.
        let segs = tile_segments(0, 7, 5, 3);
        let got: Vec<(usize, usize, usize)> = segs.iter().map(|s| (s.lane, s.out, s.len)).collect();
        assert_eq!(got, vec![(0, 0, 5), (7, 5, 5), (14, 10, 5)]);
        // A wide row: one segment up to the tile's end, then the next row's start.
        let got: Vec<(usize, usize, usize)> = tile_segments(32, 42, 40, 2)
            .iter()
            .map(|s| (s.lane, s.out, s.len))
            .collect();
        assert_eq!(got, vec![(0, 32, 8), (10, 40, 22)]);
    }
}
