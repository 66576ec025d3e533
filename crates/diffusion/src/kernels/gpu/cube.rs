//! CubeCL kernels of the GPU path (f32 activations, f32 or packed-f16 weights, f32 accumulation). Every tensor is a contiguous row-major
//! buffer; shapes and strides travel in a small `meta` buffer of u32 so one compiled kernel serves every
//! shape. Launch sizes are 2D (`CUBE_COUNT_X` ≤ 65535), read back as one linear position by [`linear_pos`].
//!
//! Kept simple and bounds-checked first: they are tested on Mesa lavapipe, where barriers are expensive,
//! and tuned on real GPUs later.

use cubecl::prelude::*;
use gpu::reduce::{cube_max, cube_sum};

/// Units per cube of the elementwise kernels.
pub const ELEMENTWISE_UNITS: u32 = 256;
/// Units per cube of the row reductions (norms, softmax): one cube per row or group.
pub const REDUCE_UNITS: u32 = 128;
/// Units per side of a [`matmul`] cube (`MATMUL_UNITS²` units).
pub const MATMUL_UNITS: u32 = 16;
/// Side of the block of outputs each [`matmul`] unit computes in registers.
pub const MATMUL_REG: u32 = 4;
/// Side of the square output tile of one [`matmul`] cube.
pub const MATMUL_TILE: u32 = MATMUL_UNITS * MATMUL_REG;
/// Depth (along k) of the shared-memory slices of A and B in [`matmul`].
pub const MATMUL_DEPTH: u32 = 16;
/// Query rows per cube and keys per shared-memory tile of [`flash_attention`].
pub const ATTENTION_QUERIES: u32 = 32;
pub const ATTENTION_KEYS: u32 = 16;

/// The linear index of this unit over a 2D launch of 1D cubes.
#[cube]
fn linear_pos() -> u32 {
    (CUBE_POS_Y * CUBE_COUNT_X + CUBE_POS_X) * CUBE_DIM_X + UNIT_POS_X
}

/// The linear index of this cube over a 2D launch.
#[cube]
fn cube_index() -> u32 {
    CUBE_POS_Y * CUBE_COUNT_X + CUBE_POS_X
}

/// Elementwise op codes of [`unary`].
pub mod unary_op {
    pub const AFFINE: u32 = 0;
    pub const RELU: u32 = 1;
    pub const SILU: u32 = 2;
    pub const GELU_ERF: u32 = 3;
    pub const TANH: u32 = 4;
    /// `tanh(x·a)·b` (the TAESD decoder's soft clamp).
    pub const SCALED_TANH: u32 = 5;
    pub const EXP: u32 = 6;
    /// `x·tanh(softplus(x))`.
    pub const MISH: u32 = 7;
    /// `x·σ(1.702x)` (OpenAI CLIP).
    pub const QUICK_GELU: u32 = 8;
    /// GELU, tanh approximation.
    pub const GELU_TANH: u32 = 9;
    /// The constant `a` (x is not read).
    pub const FILL: u32 = 10;
}

/// Binary op codes of [`binary`].
pub mod binary_op {
    pub const ADD: u32 = 0;
    pub const SUB: u32 = 1;
    pub const MUL: u32 = 2;
    pub const DIV: u32 = 3;
    /// `a` where `b > 0`, else 0 (a ReLU's backward: `a` the gradient, `b` the ReLU's output).
    pub const MASK_POSITIVE: u32 = 4;
}

#[cube]
fn gelu_erf(x: f32) -> f32 {
    0.5f32 * x * (1.0f32 + Erf::erf(x * 0.70710677f32))
}

#[cube]
fn apply_unary(x: f32, a: f32, b: f32, #[comptime] op: u32) -> f32 {
    if comptime!(op == unary_op::AFFINE) {
        x * a + b
    } else if comptime!(op == unary_op::RELU) {
        f32::max(x, 0.0f32)
    } else if comptime!(op == unary_op::SILU) {
        x / (1.0f32 + f32::exp(-x))
    } else if comptime!(op == unary_op::GELU_ERF) {
        gelu_erf(x)
    } else if comptime!(op == unary_op::TANH) {
        f32::tanh(x)
    } else if comptime!(op == unary_op::SCALED_TANH) {
        f32::tanh(x * a) * b
    } else if comptime!(op == unary_op::EXP) {
        f32::exp(x)
    } else if comptime!(op == unary_op::QUICK_GELU) {
        x / (1.0f32 + f32::exp(-1.702f32 * x))
    } else if comptime!(op == unary_op::GELU_TANH) {
        // 0.5·x·(1 + tanh(√(2/π)·(x + 0.044715·x³)))
        0.5f32 * x * (1.0f32 + f32::tanh(0.7978846f32 * (x + 0.044715f32 * x * x * x)))
    } else {
        // softplus = ln(1 + eˣ), computed as max(x, 0) + ln(1 + e^-|x|) so large x does not overflow.
        let softplus = f32::max(x, 0.0f32) + f32::ln(1.0f32 + f32::exp(-f32::abs(x)));
        x * f32::tanh(softplus)
    }
}

/// `out[i] = op(x[i])`, with scalar parameters `a`, `b` (see [`unary_op`]).
#[cube(launch_unchecked)]
pub fn unary(x: &[f32], out: &mut [f32], a: f32, b: f32, #[comptime] op: u32) {
    let i = linear_pos() as usize;
    if i < out.len() {
        if comptime!(op == unary_op::FILL) {
            out[i] = a;
        } else {
            out[i] = apply_unary(x[i], a, b, op);
        }
    }
}

/// The offsets into two operands of the element at linear index `i` of a contiguous `shape`, each
/// operand read at its own strides: `meta = [shape; rank][first strides; rank][second strides; rank]`. The host merges dimensions first (`ops::coalesce`), so `rank` is
/// usually 1–3; the outermost coordinate is what is left of `i`, so a rank-1 walk divides nothing
/// (integer division is the dearest instruction of these kernels: tens of cycles on a GPU, and
/// scalarised on a SIMD CPU).
#[cube]
fn strided_offsets(i: u32, meta: &[u32], #[comptime] rank: u32) -> (u32, u32) {
    let first = rank;
    let second = 2 * rank;
    let mut rest = i;
    let mut o1 = 0u32;
    let mut o2 = 0u32;
    #[unroll]
    for d in 0..rank - 1 {
        let axis = rank - 1 - d;
        let size = meta[axis as usize];
        let coord = rest % size;
        rest /= size;
        o1 += coord * meta[(first + axis) as usize];
        o2 += coord * meta[(second + axis) as usize];
    }
    o1 += rest * meta[first as usize];
    o2 += rest * meta[second as usize];
    (o1, o2)
}

/// `out = a op b` with broadcasting: `meta = [shape; rank][a strides; rank][b strides; rank]`
/// (stride 0 on a broadcast dimension); `out` is contiguous in `shape`.
#[cube(launch_unchecked)]
pub fn binary(
    a: &[f32],
    b: &[f32],
    out: &mut [f32],
    meta: &[u32],
    #[comptime] rank: u32,
    #[comptime] op: u32,
) {
    let i = linear_pos();
    if (i as usize) < out.len() {
        let (ia, ib) = strided_offsets(i, meta, rank);
        let x = a[ia as usize];
        let y = b[ib as usize];
        let v = if comptime!(op == binary_op::ADD) {
            x + y
        } else if comptime!(op == binary_op::SUB) {
            x - y
        } else if comptime!(op == binary_op::MUL) {
            x * y
        } else if comptime!(op == binary_op::DIV) {
            x / y
        } else {
            select(y > 0.0f32, x, 0.0f32)
        };
        out[i as usize] = v;
    }
}

/// Bias modes of [`product_epilogue`].
pub mod epilogue_bias {
    pub const NONE: u32 = 0;
    /// One value per output column (a linear layer's bias): `bias[i % cols]`.
    pub const PER_COLUMN: u32 = 1;
    /// One value per output row (a convolution's bias over [batch, rows, cols]): `bias[(i / cols) %
    /// bias_rows]`, `bias_rows` the rows of one matrix, or of the whole batch when the bias varies per
    /// image (a time embedding folded in).
    pub const PER_ROW: u32 = 2;
}

/// The finishing pass of a library product, in place: `values[i] = values[i]·alpha + bias + residual[i]`
/// (the library computes the plain product; its scale, bias and a layer's residual add cost one pass
/// over the result together instead of one each).
#[cube(launch_unchecked)]
pub fn product_epilogue(
    values: &mut [f32],
    bias: &[f32],
    residual: &[f32],
    alpha: f32,
    cols: u32,
    bias_rows: u32,
    #[comptime] bias_mode: u32,
    #[comptime] with_residual: bool,
) {
    let i = linear_pos();
    if (i as usize) < values.len() {
        let mut v = values[i as usize] * alpha;
        if comptime!(bias_mode == epilogue_bias::PER_COLUMN) {
            v += bias[(i % cols) as usize];
        } else if comptime!(bias_mode == epilogue_bias::PER_ROW) {
            v += bias[((i / cols) % bias_rows) as usize];
        }
        if comptime!(with_residual) {
            v += residual[i as usize];
        }
        values[i as usize] = v;
    }
}

/// Strided copy over `shape`: `out[out_offset + Σ cᵢ·out_strideᵢ] = x[in_offset + Σ cᵢ·in_strideᵢ]`;
/// `meta = [shape; rank][in strides; rank][out strides; rank][in_offset, out_offset, count]`.
/// Serves permutes, narrows, broadcasts and concatenation (one copy per part).
#[cube(launch_unchecked)]
pub fn strided_copy(x: &[f32], out: &mut [f32], meta: &[u32], #[comptime] rank: u32) {
    let i = linear_pos();
    if i < meta[(3 * rank + 2) as usize] {
        let (ix, io) = strided_offsets(i, meta, rank);
        let ix = ix + meta[(3 * rank) as usize];
        let io = io + meta[(3 * rank + 1) as usize];
        out[io as usize] = x[ix as usize];
    }
}

/// Gather along one axis of a tensor seen as `[outer, len, inner]`: `out[o, j, i] = x[o, idx[j], i]`;
/// `meta = [len_in, len_out, inner, count, idx; len_out]`.
#[cube(launch_unchecked)]
pub fn index_select(x: &[f32], out: &mut [f32], meta: &[u32]) {
    let p = linear_pos();
    if p < meta[3] {
        let inner = meta[2];
        let len_out = meta[1];
        let i = p % inner;
        let j = (p / inner) % len_out;
        let o = p / (inner * len_out);
        let src = (o * meta[0] + meta[(4 + j) as usize]) * inner + i;
        out[p as usize] = x[src as usize];
    }
}

/// Nearest-neighbour resize of [planes, h, w] to [planes, oh, ow] through source-index tables:
/// `meta = [h, w, oh, ow, source row of each output row; oh, source column of each output column; ow]`.
#[cube(launch_unchecked)]
pub fn upsample_nearest(x: &[f32], out: &mut [f32], meta: &[u32]) {
    let i = linear_pos();
    if (i as usize) < out.len() {
        let h = meta[0];
        let w = meta[1];
        let oh = meta[2];
        let ow = meta[3];
        let ox = i % ow;
        let oy = (i / ow) % oh;
        let plane = i / (ow * oh);
        let sy = meta[(4 + oy) as usize];
        let sx = meta[(4 + oh + ox) as usize];
        out[i as usize] = x[((plane * h + sy) * w + sx) as usize];
    }
}

/// `out[i]` = element `i` of packed f16 `words` as f32 (a weight widened for the matrix-product library).
#[cube(launch_unchecked)]
pub fn widen_f16(words: &[u32], out: &mut [f32]) {
    let i = linear_pos();
    if (i as usize) < out.len() {
        out[i as usize] = load_operand(words, i, true);
    }
}

/// `out[i]` = `x[i]` rounded to f16: an activation narrowed into an operand of the tensor-core products.
/// Only launched where the device has native f16 (the SPIR-V path).
#[cube(launch_unchecked)]
pub fn narrow_f16(x: &[f32], out: &mut [half::f16]) {
    let i = linear_pos();
    if (i as usize) < x.len() {
        out[i as usize] = half::f16::cast_from(x[i as usize]);
    }
}

/// Element `index` of a matrix operand held as f32 words, or as f16 halves packed two per word (see
/// `precision::pack_f16`), as f32.
#[cube]
fn load_operand(buf: &[u32], index: u32, #[comptime] half: bool) -> f32 {
    if comptime!(half) {
        let word = buf[(index / 2) as usize];
        f16_bits_to_f32((word >> ((index % 2) * 16)) & 0xFFFFu32)
    } else {
        f32::reinterpret(buf[index as usize])
    }
}

/// The f32 value of f16 `bits` with bit operations only (no `shader-f16` needed). Weights are finite,
/// so infinities and NaNs are not decoded.
#[cube]
fn f16_bits_to_f32(bits: u32) -> f32 {
    let sign = (bits & 0x8000u32) << 16u32;
    let exponent = (bits >> 10u32) & 0x1Fu32;
    let mantissa = bits & 0x3FFu32;
    // Normal numbers: the exponent rebiased from 15 to 127, the mantissa widened.
    let normal = f32::reinterpret(sign | ((exponent + 112u32) << 23u32) | (mantissa << 13u32));
    // Zero and subnormals: mantissa · 2⁻²⁴, exact in f32 without relying on f32 subnormals.
    let magnitude = f32::cast_from(mantissa) * 5.9604645e-8f32;
    let small = if sign != 0u32 { -magnitude } else { magnitude };
    if exponent == 0u32 {
        small
    } else {
        normal
    }
}

/// Batched `out[b] = alpha · A[b] B[b] (+ bias)`, out contiguous [batch, m, n]; A and B are read through
/// strides, so transposes and broadcast operands need no copy.
/// `meta = [batch, m, n, k, a_batch, a_row, a_col, b_batch, b_row, b_col]` (strides in elements).
/// `bias_mode`: 0 none, 1 one bias per column (linear layers), 2 one per row (convolutions).
/// `a_half`/`b_half`: the operand is f16 packed two per word (weights), else f32 bits; sums are f32.
/// `b_k_contiguous`: B's elements are adjacent along k (a transposed weight), which sets how the units
/// share the loads of a B slice so that neighbouring units read neighbouring addresses.
///
/// Register-blocked and tiled: a cube of `MATMUL_UNITS²` units computes a `MATMUL_TILE²` output tile,
/// each unit a `MATMUL_REG²` block of it (rows `UNIT_POS_Y + i·MATMUL_UNITS`, columns likewise, so the
/// units of a row write adjacent columns). Slices of A and B `MATMUL_DEPTH` deep are staged in shared
/// memory; per depth step a unit reads `2·MATMUL_REG` values for `MATMUL_REG²` multiply-adds (a naive
/// tiled kernel reads 2 per multiply-add). Each output sums over k in order, as the CPU does.
#[cube(launch_unchecked)]
pub fn matmul(
    a: &[u32],
    b: &[u32],
    bias: &[f32],
    out: &mut [f32],
    meta: &[u32],
    alpha: f32,
    #[comptime] bias_mode: u32,
    #[comptime] a_half: bool,
    #[comptime] b_half: bool,
    #[comptime] b_k_contiguous: bool,
) {
    let units = comptime!(MATMUL_UNITS);
    let reg = comptime!(MATMUL_REG);
    let depth = comptime!(MATMUL_DEPTH);
    let tile = comptime!(MATMUL_TILE);
    let cube_units = comptime!(MATMUL_UNITS * MATMUL_UNITS);
    // Elements of one slice each unit loads.
    let loads = comptime!(MATMUL_TILE * MATMUL_DEPTH / (MATMUL_UNITS * MATMUL_UNITS));
    let m = meta[1];
    let n = meta[2];
    let k = meta[3];
    let batch = CUBE_POS_Z;
    let row0 = CUBE_POS_Y * tile;
    let col0 = CUBE_POS_X * tile;
    let a_base = batch * meta[4];
    let b_base = batch * meta[7];
    let a_row = meta[5];
    let a_col = meta[6];
    let b_row = meta[8];
    let b_col = meta[9];
    let unit = UNIT_POS_Y * units + UNIT_POS_X;
    // Both slices are stored depth-major: [depth][tile].
    let mut sa = Shared::<[f32]>::new_slice(comptime!((MATMUL_DEPTH * MATMUL_TILE) as usize));
    let mut sb = Shared::<[f32]>::new_slice(comptime!((MATMUL_DEPTH * MATMUL_TILE) as usize));
    let mut acc = Array::<f32>::new(comptime!((MATMUL_REG * MATMUL_REG) as usize));
    #[unroll]
    for i in 0..reg * reg {
        acc[i as usize] = 0.0f32;
    }
    let mut ar = Array::<f32>::new(comptime!(MATMUL_REG as usize));
    let mut br = Array::<f32>::new(comptime!(MATMUL_REG as usize));
    // Spelt out: `div_ceil` is not part of CubeCL's kernel language.
    #[allow(clippy::manual_div_ceil)]
    let slices = (k + depth - 1) / depth;
    for t in 0..slices {
        let k0 = t * depth;
        // A rows are contiguous along k in every caller: neighbouring units take neighbouring k.
        #[unroll]
        for l in 0..loads {
            let e = unit + l * cube_units;
            let r = e / depth;
            let kk = e % depth;
            let row = row0 + r;
            let ka = k0 + kk;
            sa[(kk * tile + r) as usize] = if row < m && ka < k {
                load_operand(a, a_base + row * a_row + ka * a_col, a_half)
            } else {
                0.0f32
            };
        }
        #[unroll]
        for l in 0..loads {
            let e = unit + l * cube_units;
            let mut c = e % tile;
            let mut kk = e / tile;
            if comptime!(b_k_contiguous) {
                c = e / depth;
                kk = e % depth;
            }
            let col = col0 + c;
            let kb = k0 + kk;
            sb[(kk * tile + c) as usize] = if col < n && kb < k {
                load_operand(b, b_base + kb * b_row + col * b_col, b_half)
            } else {
                0.0f32
            };
        }
        sync_cube();
        #[unroll]
        for kk in 0..depth {
            #[unroll]
            for i in 0..reg {
                ar[i as usize] = sa[(kk * tile + UNIT_POS_Y + i * units) as usize];
                br[i as usize] = sb[(kk * tile + UNIT_POS_X + i * units) as usize];
            }
            #[unroll]
            for i in 0..reg {
                #[unroll]
                for j in 0..reg {
                    acc[(i * reg + j) as usize] += ar[i as usize] * br[j as usize];
                }
            }
        }
        sync_cube();
    }
    #[unroll]
    for i in 0..reg {
        let row = row0 + UNIT_POS_Y + i * units;
        #[unroll]
        for j in 0..reg {
            let col = col0 + UNIT_POS_X + j * units;
            if row < m && col < n {
                let mut v = acc[(i * reg + j) as usize] * alpha;
                if comptime!(bias_mode == 1) {
                    v += bias[col as usize];
                } else if comptime!(bias_mode == 2) {
                    v += bias[row as usize];
                }
                out[((batch * m + row) * n + col) as usize] = v;
            }
        }
    }
}

/// im2col of one convolution over a block of its output: images `n0..n0 + images` of x [batch, cin, h, w]
/// and output rows `oy0..oy0 + oh` → cols [images, cin·kh·kw, oh·ow] (zero padding).
/// `meta = [cin, h, w, kh, kw, stride, padding, oh, ow, oy0, n0, images]`. `F`: f32, or f16 where the
/// product that reads the columns takes f16 operands (written at once, so no narrowing pass follows).
///
/// The launch is 3D: cubes along x walk the output pixels, y the input channels, z the images, each
/// striding by its grid's size, so any size fits the grid limits. A unit takes one output pixel of one
/// channel and writes its kh·kw taps (column rows `c·kh·kw..`), so it divides once (the pixel's row and
/// column) for all of them, where decomposing each column element's linear index took eight divisions:
/// on the H200 those had made im2col 13 % of the SD 1.5 UNet's kernel time.
#[cube(launch_unchecked)]
pub fn im2col<F: Float>(x: &[f32], cols: &mut [F], meta: &[u32]) {
    let cin = meta[0];
    let h = meta[1];
    let w = meta[2];
    let kh = meta[3];
    let kw = meta[4];
    let stride = meta[5];
    let pad = meta[6];
    let oh = meta[7];
    let ow = meta[8];
    let oy0 = meta[9];
    let n0 = meta[10];
    let images = meta[11];
    let pixels = oh * ow;
    let taps = kh * kw;
    let pixel_step = CUBE_COUNT_X * CUBE_DIM_X;
    let mut image = CUBE_POS_Z;
    while image < images {
        let mut c = CUBE_POS_Y;
        while c < cin {
            let plane = ((image + n0) * cin + c) * h * w;
            let first_row = (image * cin + c) * taps * pixels;
            let mut p = CUBE_POS_X * CUBE_DIM_X + UNIT_POS_X;
            while p < pixels {
                let oy = p / ow;
                let ox = p - oy * ow;
                // Padded coordinates stay unsigned: compare against [pad, pad + size).
                let y0 = (oy + oy0) * stride;
                let x0 = ox * stride;
                let mut at = first_row + p;
                for ky in 0..kh {
                    let py = y0 + ky;
                    let row_inside = py >= pad && py < pad + h;
                    for kx in 0..kw {
                        let px = x0 + kx;
                        let mut v = 0.0f32;
                        if row_inside && px >= pad && px < pad + w {
                            v = x[(plane + (py - pad) * w + px - pad) as usize];
                        }
                        cols[at as usize] = F::cast_from(v);
                        at += pixels;
                    }
                }
                p += pixel_step;
            }
            c += CUBE_COUNT_Y;
        }
        image += CUBE_COUNT_Z;
    }
}

/// Mean of `x[base..base + len]`, computed by the whole cube.
#[cube]
fn segment_mean(x: &[f32], base: u32, len: u32, #[comptime] units: u32) -> f32 {
    let mut sum = 0.0f32;
    let mut i = UNIT_POS;
    while i < len {
        sum += x[(base + i) as usize];
        i += units;
    }
    cube_sum::<f32>(sum, units) / f32::cast_from(len)
}

/// `1/√(variance + eps)` of `x[base..base + len]` around `mean` (a second pass, for accuracy).
#[cube]
fn segment_inv_std(
    x: &[f32],
    base: u32,
    len: u32,
    mean: f32,
    eps: f32,
    #[comptime] units: u32,
) -> f32 {
    let mut sq = 0.0f32;
    let mut i = UNIT_POS;
    while i < len {
        let d = x[(base + i) as usize] - mean;
        sq += d * d;
        i += units;
    }
    1.0f32 / f32::sqrt(cube_sum::<f32>(sq, units) / f32::cast_from(len) + eps)
}

/// A channel's normalisation: `(x − mean)·scale + shift`.
#[derive(CubeType, Clone, Copy)]
struct Affine {
    mean: f32,
    scale: f32,
    shift: f32,
}

/// `out[start + i] = affine(x[start + i])` (then SiLU) for `i < len`, the cube's units striding; nothing
/// is written unless `write` (a cube past the last group only takes part in the reductions).
#[cube]
#[allow(clippy::too_many_arguments)]
fn normalise_span(
    x: &[f32],
    out: &mut [f32],
    start: u32,
    len: u32,
    affine: Affine,
    write: bool,
    #[comptime] silu: bool,
    #[comptime] units: u32,
) {
    let mut i = UNIT_POS;
    while i < len {
        let mut v = (x[(start + i) as usize] - affine.mean) * affine.scale + affine.shift;
        if comptime!(silu) {
            v = apply_unary(v, 0.0f32, 0.0f32, unary_op::SILU);
        }
        if write {
            out[(start + i) as usize] = v;
        }
        i += units;
    }
}

/// Group norm (+ optional SiLU) of x [batch, channels, spatial]: one cube of `units` units (a power of
/// two) per (batch, group), two passes (mean, then the mean squared deviation) for accuracy.
/// `meta = [channels, spatial, groups, cubes]`.
#[cube(launch_unchecked)]
#[allow(clippy::too_many_arguments)]
pub fn group_norm(
    x: &[f32],
    weight: &[f32],
    bias: &[f32],
    out: &mut [f32],
    meta: &[u32],
    eps: f32,
    #[comptime] silu: bool,
    #[comptime] units: u32,
) {
    let channels = meta[0];
    let spatial = meta[1];
    let groups = meta[2];
    // Cubes past the last group (the 2D launch rounds up) redo the last one without writing.
    let valid = cube_index() < meta[3];
    let cube = u32::min(cube_index(), meta[3] - 1);
    let per_group = channels / groups;
    let len = per_group * spatial;
    let group = cube % groups;
    let base = cube * len;
    let mean = segment_mean(x, base, len, units);
    let inv = segment_inv_std(x, base, len, mean, eps, units);
    // Channel by channel, so that no element divides to find its channel, and each channel's scale
    // and shift are read once per unit.
    for local in 0..per_group {
        let c = group * per_group + local;
        let scale = inv * weight[c as usize];
        let shift = bias[c as usize];
        let affine = Affine { mean, scale, shift };
        normalise_span(
            x,
            out,
            base + local * spatial,
            spatial,
            affine,
            valid,
            silu,
            units,
        );
    }
}

/// Largest number of a channel's elements one cube of the split group norm takes.
pub const GROUP_NORM_CHUNK: u32 = 4096;

/// Where a cube of the split group norm works: its chunk is part `part` of channel `local` of group
/// `bg` (batch · groups + group); `meta = [channels, spatial, groups, parts]`. Returns (bg, local, first
/// element, length).
#[cube]
fn group_norm_chunk(meta: &[u32]) -> (u32, u32, u32, u32) {
    let channels = meta[0];
    let spatial = meta[1];
    let groups = meta[2];
    let parts = meta[3];
    let bg = CUBE_POS_Y;
    let local = CUBE_POS_X / parts;
    let part = CUBE_POS_X % parts;
    let start = part * comptime!(GROUP_NORM_CHUNK);
    let len = u32::min(comptime!(GROUP_NORM_CHUNK), spatial - start);
    let base = (bg * (channels / groups) + local) * spatial + start;
    (bg, local, base, len)
}

/// Elements of chunk `k` of a group (part `k % parts` of a channel of `spatial` elements).
#[cube]
fn chunk_count(k: u32, parts: u32, spatial: u32) -> f32 {
    let start = (k % parts) * comptime!(GROUP_NORM_CHUNK);
    f32::cast_from(u32::min(comptime!(GROUP_NORM_CHUNK), spatial - start))
}

/// First pass of the split group norm (large groups, where one cube per group would leave most of a
/// card idle): each cube writes its chunk's mean and sum of squared deviations (two passes over a chunk
/// that stays in cache) to `partials[2·(bg·chunks + chunk)]`. Grid: (chunks of a group, batch · groups).
#[cube(launch_unchecked)]
pub fn group_norm_partials(x: &[f32], partials: &mut [f32], meta: &[u32]) {
    let units = comptime!(REDUCE_UNITS);
    let (bg, _, base, len) = group_norm_chunk(meta);
    let mean = segment_mean(x, base, len, units);
    let mut sq = 0.0f32;
    let mut i = UNIT_POS;
    while i < len {
        let d = x[(base + i) as usize] - mean;
        sq += d * d;
        i += units;
    }
    let m2 = cube_sum::<f32>(sq, units);
    if UNIT_POS == 0 {
        let at = 2 * (bg * CUBE_COUNT_X + CUBE_POS_X);
        partials[at as usize] = mean;
        partials[(at + 1) as usize] = m2;
    }
}

/// Second pass of the split group norm: each cube combines its group's chunk statistics (the mean of
/// the means weighted by their counts, then the deviations' sums plus each chunk's count times its
/// squared offset from that mean: exact, and as stable as the two-pass form) and normalises its own
/// chunk (+ optional SiLU). Same grid and `meta` as [`group_norm_partials`].
#[cube(launch_unchecked)]
pub fn group_norm_apply(
    x: &[f32],
    partials: &[f32],
    weight: &[f32],
    bias: &[f32],
    out: &mut [f32],
    meta: &[u32],
    eps: f32,
    #[comptime] silu: bool,
) {
    let units = comptime!(REDUCE_UNITS);
    let (bg, local, base, len) = group_norm_chunk(meta);
    let spatial = meta[1];
    let groups = meta[2];
    let parts = meta[3];
    let chunks = CUBE_COUNT_X;
    let per_group = meta[0] / groups;
    let total = f32::cast_from(per_group * spatial);
    let first = bg * chunks;
    let mut weighted = 0.0f32;
    let mut k = UNIT_POS;
    while k < chunks {
        weighted += chunk_count(k, parts, spatial) * partials[(2 * (first + k)) as usize];
        k += units;
    }
    let mean = cube_sum::<f32>(weighted, units) / total;
    let mut sq = 0.0f32;
    k = UNIT_POS;
    while k < chunks {
        let d = partials[(2 * (first + k)) as usize] - mean;
        sq += partials[(2 * (first + k) + 1) as usize] + chunk_count(k, parts, spatial) * d * d;
        k += units;
    }
    let inv = 1.0f32 / f32::sqrt(cube_sum::<f32>(sq, units) / total + eps);
    let c = (bg % groups) * per_group + local;
    let scale = inv * weight[c as usize];
    let shift = bias[c as usize];
    let affine = Affine { mean, scale, shift };
    normalise_span(x, out, base, len, affine, true, silu, units);
}

/// Layer norm over the last dimension, one cube of `units` units (a power of two) per row;
/// `meta = [width, rows]`.
#[cube(launch_unchecked)]
pub fn layer_norm(
    x: &[f32],
    weight: &[f32],
    bias: &[f32],
    out: &mut [f32],
    meta: &[u32],
    eps: f32,
    #[comptime] units: u32,
) {
    let width = meta[0];
    let valid = cube_index() < meta[1];
    let base = u32::min(cube_index(), meta[1] - 1) * width;
    let mean = segment_mean(x, base, width, units);
    let inv = segment_inv_std(x, base, width, mean, eps, units);
    let mut i = UNIT_POS;
    while i < width {
        if valid {
            out[(base + i) as usize] =
                (x[(base + i) as usize] - mean) * inv * weight[i as usize] + bias[i as usize];
        }
        i += units;
    }
}

/// Softmax of `scale · x` over the last dimension, one cube of `units` units (a power of two) per row;
/// `meta = [width, rows]`. The scale is applied here so attention's scores need no pass of their own to
/// be scaled. `F`: f32, or f16 where the probabilities only feed an f16-operand product (attention's
/// `P V`): the narrowing pass before that product was a fifth of an SD 1.5 UNet's kernel time on an H200
/// (docs/gpu-results.md, 2026-11-27).
#[cube(launch_unchecked)]
pub fn softmax_rows<F: Float>(
    x: &[f32],
    out: &mut [F],
    meta: &[u32],
    scale: f32,
    #[comptime] units: u32,
) {
    let width = meta[0];
    let valid = cube_index() < meta[1];
    let base = u32::min(cube_index(), meta[1] - 1) * width;
    // −∞ stand-in: finite for WGSL; exp(it − any score) = 0. Built at run time so it is a runtime value.
    let mut floor = 0.0f32;
    floor -= 3.0e38f32;
    // One pass for the statistics (online: each unit's running max and its sum rescaled as the max
    // grows), then one for the output: the row is read twice, not three times (the scores are the
    // largest tensor attention touches).
    let mut unit_max = floor;
    let mut unit_sum = 0.0f32;
    let mut i = UNIT_POS;
    while i < width {
        let v = x[(base + i) as usize] * scale;
        let grown = f32::max(unit_max, v);
        unit_sum = unit_sum * f32::exp(unit_max - grown) + f32::exp(v - grown);
        unit_max = grown;
        i += units;
    }
    let m = cube_max::<f32>(unit_max, units);
    // A unit that saw no element keeps the floor and a zero sum: its share is 0 · exp(floor − m) = 0.
    let inv = 1.0f32 / cube_sum::<f32>(unit_sum * f32::exp(unit_max - m), units);
    i = UNIT_POS;
    while i < width {
        if valid {
            out[(base + i) as usize] =
                F::cast_from(f32::exp(x[(base + i) as usize] * scale - m) * inv);
        }
        i += units;
    }
}

/// GEGLU: x [rows, 2·inner] → out [rows, inner] = hidden · gelu(gate).
#[cube(launch_unchecked)]
pub fn geglu(x: &[f32], out: &mut [f32], inner: u32) {
    let i = linear_pos();
    if (i as usize) < out.len() {
        let row = i / inner;
        let j = i % inner;
        let hidden = x[(row * 2 * inner + j) as usize];
        let gate = x[(row * 2 * inner + inner + j) as usize];
        out[i as usize] = hidden * gelu_erf(gate);
    }
}

/// Memory-efficient attention `softmax(q kᵀ · scale) v` that never stores the probabilities: q [batch,
/// q_len, d], k [batch, k_len, d], v [batch, k_len, dv]. A cube handles `ATTENTION_QUERIES` query rows of
/// one batch entry (one unit per row); key/value tiles of `ATTENTION_KEYS` rows go through shared memory
/// and each unit keeps a running max, running sum and output accumulator (online softmax).
/// `meta = [q_len, k_len]`.
#[cube(launch_unchecked)]
pub fn flash_attention(
    q: &[f32],
    k: &[f32],
    v: &[f32],
    out: &mut [f32],
    meta: &[u32],
    scale: f32,
    #[comptime] d: u32,
    #[comptime] dv: u32,
) {
    let tile = comptime!(ATTENTION_KEYS);
    let queries = comptime!(ATTENTION_QUERIES);
    let q_len = meta[0];
    let k_len = meta[1];
    let batch = CUBE_POS_Y;
    let row = CUBE_POS_X * queries + UNIT_POS_X;
    let valid = row < q_len;
    let mut qr = Array::<f32>::new(comptime!(d as usize));
    #[unroll]
    for c in 0..d {
        qr[c as usize] = if valid {
            q[((batch * q_len + row) * d + c) as usize] * scale
        } else {
            0.0f32
        };
    }
    let mut acc = Array::<f32>::new(comptime!(dv as usize));
    #[unroll]
    for c in 0..dv {
        acc[c as usize] = 0.0f32;
    }
    // −∞ stand-in: finite for WGSL; exp(it − any score) = 0. Built at run time so it is a runtime value.
    let mut floor = 0.0f32;
    floor -= 3.0e38f32;
    let mut run_max = floor;
    let mut run_sum = 0.0f32;
    let mut sk = Shared::<[f32]>::new_slice(comptime!((ATTENTION_KEYS * d) as usize));
    let mut sv = Shared::<[f32]>::new_slice(comptime!((ATTENTION_KEYS * dv) as usize));
    let mut scores = Array::<f32>::new(comptime!(ATTENTION_KEYS as usize));
    #[allow(clippy::manual_div_ceil)]
    let tiles = (k_len + tile - 1) / tile;
    for t in 0..tiles {
        let key0 = t * tile;
        // Cooperative loads of the key and value tiles (zeros past k_len).
        let mut e = UNIT_POS_X;
        while e < tile * d {
            let key = key0 + e / d;
            sk[e as usize] = if key < k_len {
                k[((batch * k_len + key0) * d + e) as usize]
            } else {
                0.0f32
            };
            e += queries;
        }
        e = UNIT_POS_X;
        while e < tile * dv {
            let key = key0 + e / dv;
            sv[e as usize] = if key < k_len {
                v[((batch * k_len + key0) * dv + e) as usize]
            } else {
                0.0f32
            };
            e += queries;
        }
        sync_cube();
        let mut tile_max = floor;
        #[unroll]
        for j in 0..tile {
            let mut s = 0.0f32;
            #[unroll]
            for c in 0..d {
                s += qr[c as usize] * sk[(j * d + c) as usize];
            }
            if key0 + j >= k_len {
                s = floor;
            }
            scores[j as usize] = s;
            tile_max = f32::max(tile_max, s);
        }
        let new_max = f32::max(run_max, tile_max);
        // exp(−3e38 − finite) = 0: nothing to rescale on the first tile.
        let correction = f32::exp(run_max - new_max);
        run_sum *= correction;
        #[unroll]
        for c in 0..dv {
            acc[c as usize] *= correction;
        }
        #[unroll]
        for j in 0..tile {
            let p = f32::exp(scores[j as usize] - new_max);
            run_sum += p;
            #[unroll]
            for c in 0..dv {
                acc[c as usize] += p * sv[(j * dv + c) as usize];
            }
        }
        run_max = new_max;
        sync_cube();
    }
    if valid {
        let inv = 1.0f32 / run_sum;
        #[unroll]
        for c in 0..dv {
            out[((batch * q_len + row) * dv + c) as usize] = acc[c as usize] * inv;
        }
    }
}

// ------------------------------------------------------------------------- VGG feature-loss ops

/// 2×2 max-pool, stride 2, floor mode, over NCHW planes: `meta = [h, w, out h, out w]`; one unit per
/// output value.
#[cube(launch_unchecked)]
pub fn max_pool2x2(x: &[f32], out: &mut [f32], meta: &[u32]) {
    let i = linear_pos();
    if (i as usize) < out.len() {
        let w = meta[1];
        let oh = meta[2];
        let ow = meta[3];
        let plane = i / (oh * ow);
        let rest = i % (oh * ow);
        let base = plane * meta[0] * w + 2 * (rest / ow) * w + 2 * (rest % ow);
        let top = f32::max(x[base as usize], x[(base + 1) as usize]);
        let bottom = f32::max(x[(base + w) as usize], x[(base + w + 1) as usize]);
        out[i as usize] = f32::max(top, bottom);
    }
}

/// The input gradient of [`max_pool2x2`] (same `meta`): one unit per input value, which receives its
/// window's pooled gradient when it is the window's first maximum (row-major order, as torch), else 0.
#[cube(launch_unchecked)]
pub fn max_pool2x2_backward(x: &[f32], grad: &[f32], out: &mut [f32], meta: &[u32]) {
    let i = linear_pos();
    if (i as usize) < out.len() {
        let h = meta[0];
        let w = meta[1];
        let oh = meta[2];
        let ow = meta[3];
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

/// `f / (‖f‖ + eps)` over the channels of each pixel of NCHW maps: `meta = [channels, h·w, n·h·w]`; one
/// unit per pixel (neighbouring units read neighbouring values of each channel plane).
#[cube(launch_unchecked)]
pub fn normalize_channels(x: &[f32], out: &mut [f32], meta: &[u32], eps: f32) {
    let i = linear_pos();
    let channels = meta[0];
    let hw = meta[1];
    if i < meta[2] {
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
/// (see `kernels::vgg::lpips_distance`). `meta = [channels, h·w, n·h·w]`; one unit per pixel.
#[cube(launch_unchecked)]
pub fn lpips_distance(
    f: &[f32],
    t: &[f32],
    lin: &[f32],
    map: &mut [f32],
    grad: &mut [f32],
    meta: &[u32],
    eps: f32,
    inv_area: f32,
    #[comptime] with_grad: bool,
) {
    let i = linear_pos();
    let channels = meta[0];
    let hw = meta[1];
    if i < meta[2] {
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
