//! Host side of the GPU kernels: one function per op on [`GpuTensor`]s, the same semantics (shapes,
//! broadcasting, layouts) as the CPU op it mirrors. Launches are asynchronous; errors surface when a result
//! is read back ([`GpuTensor::to_cpu`]).

use std::sync::OnceLock;

use candle_core::Result;
use cubecl::prelude::*;
use cubecl::server::Handle;

use super::cube::{
    self, binary_op, unary_op, ATTENTION_QUERIES, ELEMENTWISE_UNITS, GROUP_NORM_CHUNK, MATMUL_TILE,
    MATMUL_UNITS, REDUCE_UNITS,
};
use super::GpuTensor;

mod conv;
mod tiling;
pub use conv::{conv2d, forced_conv_path, tuned_conv_paths, with_conv_path, ConvPath};
#[cfg(test)]
use conv::{conv2d_blocked, im2col, im2col_on_grid, ConvWindow};
pub use tiling::Tiling;

/// Largest head width the flash kernel is compiled for (its rows live in registers); wider heads go
/// through the explicit-probabilities path.
const FLASH_MAX_HEAD_DIM: usize = 256;

/// A 2D launch of `cubes` cubes (the X count is capped at 65535; kernels bound-check the excess).
fn grid(cubes: usize) -> CubeCount {
    let cubes = cubes.max(1) as u32;
    let x = cubes.min(GRID_LIMIT);
    CubeCount::Static(x, cubes.div_ceil(x), 1)
}

/// Cubes of `units` units covering `n` elements.
fn grid_for(n: usize, units: u32) -> CubeCount {
    grid(n.div_ceil(units as usize))
}

fn to_u32(v: usize, what: &str) -> Result<u32> {
    u32::try_from(v).map_err(|_| candle_core::Error::msg(format!("gpu: {what} {v} exceeds u32")))
}

/// Uploads a small u32 parameter block.
struct Meta(Handle, usize);

impl Meta {
    fn new(x: &GpuTensor, values: &[usize]) -> Result<Meta> {
        let values = values
            .iter()
            .map(|&v| to_u32(v, "shape value"))
            .collect::<Result<Vec<u32>>>()?;
        Ok(Meta(
            x.client().create_from_slice(u32::as_bytes(&values)),
            values.len(),
        ))
    }

    fn arg(&self) -> BufferArg {
        // SAFETY: the handle holds exactly `self.1` u32 values.
        unsafe { BufferArg::from_raw_parts(self.0.clone(), self.1) }
    }
}

fn contiguous_strides(shape: &[usize]) -> Vec<usize> {
    let mut strides = vec![1; shape.len()];
    for d in (0..shape.len().saturating_sub(1)).rev() {
        strides[d] = strides[d + 1] * shape[d + 1];
    }
    strides
}

/// Merges the dimensions of `shape` that every stride set walks as one: size-1 dimensions go, and a
/// dimension joins the next where each set's stride is the next one's times the next size (broadcast
/// zeros included). The elementwise kernels then decompose an index into fewer coordinates, each a
/// division (a bias over [batch, channels, h, w] becomes [batch·channels, h·w]; equal shapes become
/// one dimension and no division). Returns the merged shape, at least one dimension.
fn coalesce<const S: usize>(
    shape: &[usize],
    strides: [&[usize]; S],
) -> (Vec<usize>, [Vec<usize>; S]) {
    let mut merged: Vec<usize> = Vec::with_capacity(shape.len());
    let mut out: [Vec<usize>; S] = std::array::from_fn(|_| Vec::with_capacity(shape.len()));
    for (d, &size) in shape.iter().enumerate() {
        if size == 1 {
            continue;
        }
        let joins = merged.last().is_some_and(|_| {
            strides
                .iter()
                .zip(&out)
                .all(|(s, o)| o.last() == Some(&(s[d] * size)))
        });
        if joins {
            *merged.last_mut().expect("checked") *= size;
            for (o, s) in out.iter_mut().zip(&strides) {
                *o.last_mut().expect("checked") = s[d];
            }
        } else {
            merged.push(size);
            for (o, s) in out.iter_mut().zip(&strides) {
                o.push(s[d]);
            }
        }
    }
    if merged.is_empty() {
        merged.push(1);
        for o in &mut out {
            o.push(0);
        }
    }
    (merged, out)
}

// ------------------------------------------------------------------------------------------ elementwise

fn unary(x: &GpuTensor, op: u32, a: f32, b: f32) -> GpuTensor {
    let out = x.empty_like_device(x.dims().to_vec());
    // SAFETY: out and x have the same element count; the kernel bound-checks against out.
    unsafe {
        cube::unary::launch_unchecked(
            x.client(),
            grid_for(x.elem_count(), ELEMENTWISE_UNITS),
            CubeDim::new_1d(ELEMENTWISE_UNITS),
            x.arg(),
            out.arg(),
            a,
            b,
            op,
        )
    };
    out
}

/// `x·mul + add`.
pub fn affine(x: &GpuTensor, mul: f32, add: f32) -> GpuTensor {
    unary(x, unary_op::AFFINE, mul, add)
}
pub fn relu(x: &GpuTensor) -> GpuTensor {
    unary(x, unary_op::RELU, 0.0, 0.0)
}
pub fn silu(x: &GpuTensor) -> GpuTensor {
    unary(x, unary_op::SILU, 0.0, 0.0)
}
/// GELU, exact (erf) form.
pub fn gelu(x: &GpuTensor) -> GpuTensor {
    unary(x, unary_op::GELU_ERF, 0.0, 0.0)
}
pub fn tanh(x: &GpuTensor) -> GpuTensor {
    unary(x, unary_op::TANH, 0.0, 0.0)
}
/// `tanh(x·inner)·outer`.
pub fn scaled_tanh(x: &GpuTensor, inner: f32, outer: f32) -> GpuTensor {
    unary(x, unary_op::SCALED_TANH, inner, outer)
}
pub fn exp(x: &GpuTensor) -> GpuTensor {
    unary(x, unary_op::EXP, 0.0, 0.0)
}
pub fn mish(x: &GpuTensor) -> GpuTensor {
    unary(x, unary_op::MISH, 0.0, 0.0)
}
/// A tensor of `shape` filled with `value`, on `like`'s device.
pub fn full(like: &GpuTensor, shape: Vec<usize>, value: f32) -> GpuTensor {
    let out = like.empty_like_device(shape);
    // The kernel does not read its input; a separate one-element buffer avoids binding `out` twice.
    let unused = GpuTensor::from_slice(like.device(), &[0.0], vec![1]);
    // SAFETY: the kernel writes out only, bound-checked.
    unsafe {
        cube::unary::launch_unchecked(
            like.client(),
            grid_for(out.elem_count(), ELEMENTWISE_UNITS),
            CubeDim::new_1d(ELEMENTWISE_UNITS),
            unused.arg(),
            out.arg(),
            value,
            0.0,
            unary_op::FILL,
        )
    };
    out
}

/// Zero padding of the last two dimensions: `bottom` rows and `right` columns appended.
pub fn pad_bottom_right(x: &GpuTensor, bottom: usize, right: usize) -> Result<GpuTensor> {
    let rank = x.dims().len();
    if rank < 2 {
        candle_core::bail!("gpu pad: rank {rank} < 2");
    }
    let mut shape = x.dims().to_vec();
    shape[rank - 2] += bottom;
    shape[rank - 1] += right;
    let out = full(x, shape.clone(), 0.0);
    copy_strided(
        x,
        &out,
        x.dims(),
        &contiguous_strides(x.dims()),
        0,
        &contiguous_strides(&shape),
        0,
    )?;
    Ok(out)
}

/// `x·σ(1.702x)`.
pub fn quick_gelu(x: &GpuTensor) -> GpuTensor {
    unary(x, unary_op::QUICK_GELU, 0.0, 0.0)
}
/// GELU, tanh approximation (candle `gelu`).
pub fn gelu_tanh(x: &GpuTensor) -> GpuTensor {
    unary(x, unary_op::GELU_TANH, 0.0, 0.0)
}

/// The broadcast shape of two shapes (numpy/candle rules, aligned on the right).
fn broadcast_shape(a: &[usize], b: &[usize]) -> Result<Vec<usize>> {
    let rank = a.len().max(b.len());
    let dim = |s: &[usize], d: usize| {
        if d + s.len() < rank {
            1
        } else {
            s[d + s.len() - rank]
        }
    };
    (0..rank)
        .map(|d| match (dim(a, d), dim(b, d)) {
            (x, y) if x == y || y == 1 => Ok(x),
            (1, y) => Ok(y),
            _ => candle_core::bail!("gpu: shapes {a:?} and {b:?} do not broadcast"),
        })
        .collect()
}

/// Strides of `shape` read as `out_shape` (0 on broadcast dimensions).
fn broadcast_strides(shape: &[usize], out_shape: &[usize]) -> Vec<usize> {
    let strides = contiguous_strides(shape);
    let pad = out_shape.len() - shape.len();
    (0..out_shape.len())
        .map(|d| {
            if d < pad || shape[d - pad] == 1 {
                0
            } else {
                strides[d - pad]
            }
        })
        .collect()
}

fn binary(a: &GpuTensor, b: &GpuTensor, op: u32) -> Result<GpuTensor> {
    let shape = broadcast_shape(a.dims(), b.dims())?;
    let a_strides = broadcast_strides(a.dims(), &shape);
    let b_strides = broadcast_strides(b.dims(), &shape);
    let (walk, [a_strides, b_strides]) = coalesce(&shape, [&a_strides, &b_strides]);
    let mut meta = walk.clone();
    meta.extend(a_strides);
    meta.extend(b_strides);
    let meta = Meta::new(a, &meta)?;
    let rank = walk.len() as u32;
    let out = a.empty_like_device(shape);
    // SAFETY: the strides address within a and b for every coordinate of the broadcast shape.
    unsafe {
        cube::binary::launch_unchecked(
            a.client(),
            grid_for(out.elem_count(), ELEMENTWISE_UNITS),
            CubeDim::new_1d(ELEMENTWISE_UNITS),
            a.arg(),
            b.arg(),
            out.arg(),
            meta.arg(),
            rank,
            op,
        )
    };
    Ok(out)
}

pub fn add(a: &GpuTensor, b: &GpuTensor) -> Result<GpuTensor> {
    binary(a, b, binary_op::ADD)
}
pub fn sub(a: &GpuTensor, b: &GpuTensor) -> Result<GpuTensor> {
    binary(a, b, binary_op::SUB)
}
pub fn mul(a: &GpuTensor, b: &GpuTensor) -> Result<GpuTensor> {
    binary(a, b, binary_op::MUL)
}
pub fn div(a: &GpuTensor, b: &GpuTensor) -> Result<GpuTensor> {
    binary(a, b, binary_op::DIV)
}
/// A ReLU's input gradient: `grad` where the ReLU's output `out` is positive, else 0.
pub fn relu_backward(out: &GpuTensor, grad: &GpuTensor) -> Result<GpuTensor> {
    if out.dims() != grad.dims() {
        candle_core::bail!(
            "gpu relu_backward: shapes {:?} and {:?} differ",
            out.dims(),
            grad.dims()
        );
    }
    binary(grad, out, binary_op::MASK_POSITIVE)
}

// ---------------------------------------------------------------------------------------------- copies

/// Copies `shape` elements read at `src_strides`/`src_offset` of `src` into `dst` at
/// `dst_strides`/`dst_offset`.
fn copy_strided(
    src: &GpuTensor,
    dst: &GpuTensor,
    shape: &[usize],
    src_strides: &[usize],
    src_offset: usize,
    dst_strides: &[usize],
    dst_offset: usize,
) -> Result<()> {
    let count: usize = shape.iter().product();
    if count == 0 {
        return Ok(());
    }
    let (walk, [src_strides, dst_strides]) = coalesce(shape, [src_strides, dst_strides]);
    let rank = walk.len() as u32;
    let mut meta = walk;
    meta.extend(src_strides);
    meta.extend(dst_strides);
    meta.extend([src_offset, dst_offset, count]);
    let meta = Meta::new(src, &meta)?;
    // SAFETY: the caller's strides and offsets address within both buffers.
    unsafe {
        cube::strided_copy::launch_unchecked(
            src.client(),
            grid_for(count, ELEMENTWISE_UNITS),
            CubeDim::new_1d(ELEMENTWISE_UNITS),
            src.arg(),
            dst.arg(),
            meta.arg(),
            rank,
        )
    };
    Ok(())
}

/// `x.permute(dims)` materialised (contiguous).
pub fn permute(x: &GpuTensor, dims: &[usize]) -> Result<GpuTensor> {
    let len = x.dims().first().copied().unwrap_or(0);
    narrow_permute(x, 0, 0, len, dims)
}

/// `x.transpose(d0, d1)` materialised.
pub fn transpose(x: &GpuTensor, d0: usize, d1: usize) -> Result<GpuTensor> {
    let mut dims: Vec<usize> = (0..x.dims().len()).collect();
    dims.swap(d0, d1);
    permute(x, &dims)
}

/// `x.narrow(dim, start, len)` materialised.
pub fn narrow(x: &GpuTensor, dim: usize, start: usize, len: usize) -> Result<GpuTensor> {
    let dims: Vec<usize> = (0..x.dims().len()).collect();
    narrow_permute(x, dim, start, len, &dims)
}

/// `x.narrow(dim, start, len).permute(dims)` materialised in one copy (attention takes its heads out
/// of a fused projection this way).
pub fn narrow_permute(
    x: &GpuTensor,
    dim: usize,
    start: usize,
    len: usize,
    dims: &[usize],
) -> Result<GpuTensor> {
    let rank = x.dims().len();
    let mut seen = vec![false; rank];
    if dims.len() != rank
        || dims
            .iter()
            .any(|&d| d >= rank || std::mem::replace(&mut seen[d], true))
    {
        candle_core::bail!("gpu permute: {dims:?} is not a permutation of rank {rank}");
    }
    if rank > 0 && (dim >= rank || start + len > x.dims()[dim]) {
        candle_core::bail!("gpu narrow: {start}+{len} on dim {dim} of {:?}", x.dims());
    }
    let strides = contiguous_strides(x.dims());
    let mut narrowed = x.dims().to_vec();
    if rank > 0 {
        narrowed[dim] = len;
    }
    let shape: Vec<usize> = dims.iter().map(|&d| narrowed[d]).collect();
    let src_strides: Vec<usize> = dims.iter().map(|&d| strides[d]).collect();
    let out = x.empty_like_device(shape.clone());
    let offset = if rank > 0 { start * strides[dim] } else { 0 };
    copy_strided(
        x,
        &out,
        &shape,
        &src_strides,
        offset,
        &contiguous_strides(&shape),
        0,
    )?;
    Ok(out)
}

/// Concatenation along `dim` (e.g. channels of NCHW tensors for the UNet's skip connections).
pub fn cat(parts: &[&GpuTensor], dim: usize) -> Result<GpuTensor> {
    let Some(first) = parts.first() else {
        candle_core::bail!("gpu cat: no tensors");
    };
    let rank = first.dims().len();
    let mut shape = first.dims().to_vec();
    if dim >= rank {
        candle_core::bail!("gpu cat: dim {dim} out of range for rank {rank}");
    }
    shape[dim] = 0;
    for p in parts {
        let ok =
            p.dims().len() == rank && (0..rank).all(|d| d == dim || p.dims()[d] == first.dims()[d]);
        if !ok {
            candle_core::bail!(
                "gpu cat: {:?} does not match {:?} off dim {dim}",
                p.dims(),
                first.dims()
            );
        }
        shape[dim] += p.dims()[dim];
    }
    let out = first.empty_like_device(shape.clone());
    let out_strides = contiguous_strides(&shape);
    let mut offset = 0;
    for p in parts {
        copy_strided(
            p,
            &out,
            p.dims(),
            &contiguous_strides(p.dims()),
            0,
            &out_strides,
            offset * out_strides[dim],
        )?;
        offset += p.dims()[dim];
    }
    Ok(out)
}

/// `x.index_select(indices, dim)`: the slices of `dim` at `indices`, in that order (repeats allowed).
pub fn index_select(x: &GpuTensor, indices: &[u32], dim: usize) -> Result<GpuTensor> {
    let dims = x.dims();
    if dim >= dims.len() {
        candle_core::bail!("gpu index_select: dim {dim} out of range for {dims:?}");
    }
    if let Some(&bad) = indices.iter().find(|&&i| i as usize >= dims[dim]) {
        candle_core::bail!("gpu index_select: index {bad} out of range for dim {dim} of {dims:?}");
    }
    let mut shape = dims.to_vec();
    shape[dim] = indices.len();
    let inner: usize = dims[dim + 1..].iter().product();
    let out = x.empty_like_device(shape);
    let count = out.elem_count();
    if count == 0 {
        return Ok(out);
    }
    let mut meta = vec![dims[dim], indices.len(), inner, count];
    meta.extend(indices.iter().map(|&i| i as usize));
    let meta = Meta::new(x, &meta)?;
    // SAFETY: every index is below `dims[dim]`, so each source offset lies within x.
    unsafe {
        cube::index_select::launch_unchecked(
            x.client(),
            grid_for(count, ELEMENTWISE_UNITS),
            CubeDim::new_1d(ELEMENTWISE_UNITS),
            x.arg(),
            out.arg(),
            meta.arg(),
        )
    };
    Ok(out)
}

/// Nearest-neighbour resize of [.., h, w] to [.., out_h, out_w], choosing source pixels exactly as
/// candle's CPU `upsample_nearest2d` does (`floor(i · in / out)` in f64), so odd sizes agree too.
pub fn upsample_nearest2d(x: &GpuTensor, out_h: usize, out_w: usize) -> Result<GpuTensor> {
    let rank = x.dims().len();
    if rank < 2 {
        candle_core::bail!("gpu upsample: rank {rank} < 2");
    }
    let (h, w) = (x.dims()[rank - 2], x.dims()[rank - 1]);
    if h == 0 || w == 0 || out_h == 0 || out_w == 0 {
        candle_core::bail!("gpu upsample: {h}x{w} to {out_h}x{out_w}");
    }
    let source = |len: usize, out: usize| {
        let scale = len as f64 / out as f64;
        (0..out).map(move |i| ((i as f64 * scale) as usize).min(len - 1))
    };
    let mut meta = vec![h, w, out_h, out_w];
    meta.extend(source(h, out_h));
    meta.extend(source(w, out_w));
    let meta = Meta::new(x, &meta)?;
    let mut shape = x.dims().to_vec();
    shape[rank - 2] = out_h;
    shape[rank - 1] = out_w;
    let out = x.empty_like_device(shape);
    // SAFETY: the kernel bound-checks against out; the index tables stay inside the source planes.
    unsafe {
        cube::upsample_nearest::launch_unchecked(
            x.client(),
            grid_for(out.elem_count(), ELEMENTWISE_UNITS),
            CubeDim::new_1d(ELEMENTWISE_UNITS),
            x.arg(),
            out.arg(),
            meta.arg(),
        )
    };
    Ok(out)
}

// ---------------------------------------------------------------------------------------------- matmul

/// One batched product's geometry: `out[b] = alpha · A[b] B[b] (+ bias)`, strides in elements.
struct Gemm {
    batch: usize,
    m: usize,
    n: usize,
    k: usize,
    /// (batch, row, column) strides of A and B.
    a_strides: [usize; 3],
    b_strides: [usize; 3],
    alpha: f32,
}

/// Bias of a product: none, one per output column (linear), one per output row (convolution), one per
/// output row of each matrix of the batch ([batch·m]: a convolution's bias with a time embedding folded in).
#[derive(Clone, Copy)]
enum GemmBias<'a> {
    None,
    PerColumn(&'a GpuTensor),
    PerRow(&'a GpuTensor),
    PerBatchRow(&'a GpuTensor),
}

/// `alpha·A[b]B[b] + bias (+ residual)`, `residual` of the output's shape (a layer's skip connection).
fn gemm(
    a: &GpuTensor,
    b: &GpuTensor,
    bias: GemmBias,
    residual: Option<&GpuTensor>,
    g: &Gemm,
    out_shape: Vec<usize>,
) -> Result<GpuTensor> {
    if let Some(r) = residual {
        if r.dims() != out_shape.as_slice() {
            candle_core::bail!(
                "gpu product: residual {:?} for an output {out_shape:?}",
                r.dims()
            );
        }
    }
    let library = library_gemm(a, b, g, &out_shape);
    LAST_ROUTE.set(library.as_ref().map_or("own", |(_, route)| *route));
    if let Some((product, _)) = library {
        return finish_product(product, bias, residual, g);
    }
    // Our kernel adds a bias shared by the batch itself; a per-image bias and the residual follow.
    let (bias, late_bias) = match bias {
        GemmBias::PerBatchRow(t) => (GemmBias::None, Some(t)),
        other => (other, None),
    };
    let out = a.empty_like_device(out_shape.clone());
    let mut meta = vec![g.batch, g.m, g.n, g.k];
    meta.extend(g.a_strides);
    meta.extend(g.b_strides);
    let meta = Meta::new(a, &meta)?;
    let (bias_arg, mode) = match bias {
        // Not read: any buffer will do.
        GemmBias::None | GemmBias::PerBatchRow(_) => (out.arg(), 0u32),
        GemmBias::PerColumn(t) => (t.arg(), 1),
        GemmBias::PerRow(t) => (t.arg(), 2),
    };
    let tiles = |v: usize| to_u32(v.div_ceil(MATMUL_TILE as usize), "matmul tiles");
    // B adjacent along k and not along n: a transposed weight (linear layers, `q kᵀ`).
    let b_k_contiguous = g.b_strides[1] == 1 && g.b_strides[2] != 1;
    // SAFETY: the strides describe in-bounds views of a and b; the kernel bound-checks rows/columns.
    unsafe {
        cube::matmul::launch_unchecked(
            a.client(),
            CubeCount::Static(tiles(g.n)?, tiles(g.m)?, to_u32(g.batch, "batch")?),
            CubeDim::new_2d(MATMUL_UNITS, MATMUL_UNITS),
            a.word_arg(),
            b.word_arg(),
            bias_arg,
            out.arg(),
            meta.arg(),
            g.alpha,
            mode,
            a.is_f16(),
            b.is_f16(),
            b_k_contiguous,
        )
    };
    let out = match late_bias {
        Some(t) => add(
            &out.reshape(&[g.batch * g.m, g.n])?,
            &t.reshape(&[g.batch * g.m, 1])?,
        )?
        .reshape(&out_shape)?,
        None => out,
    };
    match residual {
        Some(r) => add(&out, r),
        None => Ok(out),
    }
}

/// The library product's scale, bias and residual in one pass over it, in place (nothing else holds the
/// fresh product), or none when there is nothing to add.
fn finish_product(
    product: GpuTensor,
    bias: GemmBias,
    residual: Option<&GpuTensor>,
    g: &Gemm,
) -> Result<GpuTensor> {
    use cube::epilogue_bias;
    let (bias, mode, bias_rows) = match bias {
        GemmBias::None => (None, epilogue_bias::NONE, 1),
        GemmBias::PerColumn(t) => (Some(t), epilogue_bias::PER_COLUMN, 1),
        GemmBias::PerRow(t) => (Some(t), epilogue_bias::PER_ROW, g.m),
        GemmBias::PerBatchRow(t) => (Some(t), epilogue_bias::PER_ROW, g.batch * g.m),
    };
    // An operand the kernel does not read is bound to one it does (never to the written product).
    let Some(bound) = bias.or(residual) else {
        return Ok(if g.alpha == 1.0 {
            product
        } else {
            affine(&product, g.alpha, 0.0)
        });
    };
    if let Some(t) = bias {
        let expected = if mode == epilogue_bias::PER_COLUMN {
            g.n
        } else {
            bias_rows
        };
        if t.elem_count() != expected {
            candle_core::bail!(
                "gpu product: bias {:?} for {} rows × {} columns",
                t.dims(),
                g.batch * g.m,
                g.n
            );
        }
    }
    // SAFETY: the bias holds every index the mode reads (checked above), the residual has the product's
    // shape (checked by `gemm`); the kernel bound-checks against the product.
    unsafe {
        cube::product_epilogue::launch_unchecked(
            product.client(),
            grid_for(product.elem_count(), ELEMENTWISE_UNITS),
            CubeDim::new_1d(ELEMENTWISE_UNITS),
            product.arg(),
            bias.unwrap_or(bound).arg(),
            residual.unwrap_or(bound).arg(),
            g.alpha,
            to_u32(g.n, "product columns")?,
            to_u32(bias_rows, "bias rows")?,
            mode,
            residual.is_some(),
        )
    };
    Ok(product)
}

/// The path an A/B environment variable `var` forces, read once per process (`once`): `parse` of its
/// trimmed, lower-case value; `None` (the default path) where it is unset or names no path.
fn forced_by_env<T: Copy>(
    once: &OnceLock<Option<T>>,
    var: &str,
    parse: impl FnOnce(&str) -> Option<T>,
) -> Option<T> {
    *once.get_or_init(|| {
        parse(
            std::env::var(var)
                .unwrap_or_default()
                .trim()
                .to_ascii_lowercase()
                .as_str(),
        )
    })
}

/// How a product runs: our own kernel, or the matrix-product library (cubek) on f32 or f16 operands.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum MatmulPath {
    /// Our register-blocked kernel (f32 sums; f16 weights unpacked as they are read).
    Own,
    /// The library's unit routine on f32 operands (f16 weights widened into a transient copy).
    Unit,
    /// The library's unit routine on f16 operands: the tensor-core path's operands without tensor
    /// cores, so it can be tested where there are none (lavapipe).
    UnitF16,
    /// Cooperative matrices (tensor cores): f16 operands, f32 sums.
    TensorCores,
}

impl std::fmt::Display for MatmulPath {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Own => "own",
            Self::Unit => "unit",
            Self::UnitF16 => "unit-f16",
            Self::TensorCores => "tensor-cores",
        })
    }
}

thread_local! {
    /// Set by tests to pick a path on their thread (the environment is shared by test threads).
    static PATH_OVERRIDE: std::cell::Cell<Option<MatmulPath>> = const { std::cell::Cell::new(None) };
}

/// Runs `f` with the products of this thread on `path` (tests).
#[cfg(test)]
pub(crate) fn with_matmul_path<T>(path: MatmulPath, f: impl FnOnce() -> T) -> T {
    PATH_OVERRIDE.set(Some(path));
    let result = f();
    PATH_OVERRIDE.set(None);
    result
}

/// Runs `f` with our own matrix-product kernel instead of the library's, on this thread (tests).
#[cfg(test)]
pub(crate) fn with_own_matmul<T>(f: impl FnOnce() -> T) -> T {
    with_matmul_path(MatmulPath::Own, f)
}

/// The path of a product on `device`. By default: tensor cores where the device has them and the
/// weights are f16 (the precision says how much rounding the user accepts; f32 keeps f32 operands), the
/// library's unit routine elsewhere (lavapipe: 13.6 GFLOP/s against our kernel's 2.1 on SD 1.5's
/// 4096×320×1280 product). `VCEDIT_GPU_MATMUL=own|unit|unit-f16` forces one (A/B switch for
/// benchmarks); a path the device cannot take falls back to the default.
pub fn matmul_path(device: &super::GpuDevice) -> MatmulPath {
    static FORCED: OnceLock<Option<MatmulPath>> = OnceLock::new();
    let forced =
        PATH_OVERRIDE.get().or(forced_by_env(
            &FORCED,
            "VCEDIT_GPU_MATMUL",
            |name| match name {
                "own" => Some(MatmulPath::Own),
                "unit" => Some(MatmulPath::Unit),
                "unit-f16" => Some(MatmulPath::UnitF16),
                _ => None,
            },
        ));
    let half_weights = device.precision() == super::Precision::F16;
    let native_f16 = device
        .client()
        .properties()
        .supports_type(cubecl::ir::ElemType::Float(cubecl::ir::FloatKind::F16));
    match forced {
        Some(MatmulPath::Own) => MatmulPath::Own,
        Some(MatmulPath::Unit) => MatmulPath::Unit,
        Some(MatmulPath::UnitF16) if native_f16 => MatmulPath::UnitF16,
        Some(MatmulPath::TensorCores) | None | Some(MatmulPath::UnitF16)
            if half_weights && device.context().tensor_cores =>
        {
            MatmulPath::TensorCores
        }
        _ => MatmulPath::Unit,
    }
}

/// Whether products on `device` take f16 operands (tensor cores, or the unit routine on f16): then an
/// op whose output only feeds a product writes it as f16 at once instead of leaving a narrowing pass
/// to the product.
fn half_operands(device: &super::GpuDevice) -> bool {
    matches!(
        matmul_path(device),
        MatmulPath::TensorCores | MatmulPath::UnitF16
    )
}

/// An f32 copy of a packed f16 tensor; an f32 tensor as it is (shared buffer).
fn widen_f16(x: &GpuTensor) -> GpuTensor {
    if !x.is_f16() {
        return x.clone();
    }
    let out = x.empty_like_device(x.dims().to_vec());
    // SAFETY: the kernel bound-checks against out, and out's element count is x's.
    unsafe {
        cube::widen_f16::launch_unchecked(
            x.client(),
            grid_for(out.elem_count(), ELEMENTWISE_UNITS),
            CubeDim::new_1d(ELEMENTWISE_UNITS),
            x.word_arg(),
            out.arg(),
        )
    };
    out
}

/// An f16 copy of an f32 tensor (rounded to nearest); a packed f16 tensor as it is.
fn narrow_f16(x: &GpuTensor) -> GpuTensor {
    if x.is_f16() {
        return x.clone();
    }
    let out = x.empty_half_like(x.dims().to_vec());
    // SAFETY: the kernel bound-checks against x, and out holds x's element count of halves.
    unsafe {
        cube::narrow_f16::launch_unchecked(
            x.client(),
            grid_for(x.elem_count(), ELEMENTWISE_UNITS),
            CubeDim::new_1d(ELEMENTWISE_UNITS),
            x.arg(),
            out.half_arg(),
        )
    };
    out
}

/// The product `A[b] B[b]` (no scale, no bias) by CubeCL's matrix-product library, or `None` where it
/// does not apply (our own kernel chosen, a shared B under a strided A, an empty product) or declines
/// the problem; the caller then runs our own kernel. A tensor-core product the library declines is
/// retried on the unit routine.
fn library_gemm(
    a: &GpuTensor,
    b: &GpuTensor,
    g: &Gemm,
    out_shape: &[usize],
) -> Option<(GpuTensor, &'static str)> {
    if g.m == 0 || g.n == 0 || g.k == 0 {
        return None;
    }
    let unit = || library_gemm_on(a, b, g, out_shape, MatmulPath::Unit).map(|p| (p, "unit"));
    match matmul_path(a.device()) {
        MatmulPath::Own => None,
        MatmulPath::Unit => unit(),
        MatmulPath::UnitF16 => library_gemm_on(a, b, g, out_shape, MatmulPath::UnitF16)
            .map(|p| (p, "unit-f16"))
            .or_else(unit),
        MatmulPath::TensorCores => {
            let routine = tensor_core_routine();
            library_gemm_on(a, b, g, out_shape, MatmulPath::TensorCores)
                .map(|p| (p, routine))
                .or_else(unit)
        }
    }
}

/// The library's tensor-core routines a product may take on a card with cooperative matrices (`cmma`:
/// the portable cooperative-matrix instructions; `mma`: manual fragments). Which is fastest differs
/// between cards and shapes: `vcedit bench matmul --routines` times each, tools/gpu-check runs it.
/// `_multi_rows`: the library's other tiling for the simple routines (8×32×16 tiles, four partitions of
/// rows per plane); `_specialized`: double buffering with planes specialised into loaders and computers.
/// On an H200 (2026-11-27) the seven routines without a suffix reached 5–14 TFLOP/s at 4096×320×1280
/// against cuBLAS's 155, so the tilings are the next thing to measure ([`Tiling`]). `tiled_cmma` is the
/// library's other kernel family (written on its tile DSL: double-buffered stages sized to the shared
/// memory, a swizzled cube order); it takes row-major operands whose shape its stage divides, so a
/// linear layer's transposed weight goes to the unit routine, and only activation × activation products
/// (attention, `vcedit bench matmul`'s `matmul`) measure it.
pub const TENSOR_CORE_ROUTINES: [&str; 14] = [
    "simple_cyclic_cmma",
    "simple_cyclic_cmma_multi_rows",
    "simple_strided_cmma",
    "simple_strided_cmma_multi_rows",
    "simple_tilewise_cmma",
    "double_cyclic_cmma",
    "double_cyclic_cmma_specialized",
    "double_tilewise_cmma",
    "double_hybrid_cmma",
    "ordered_double_cmma",
    "specialized_cyclic_cmma",
    "simple_cyclic_mma",
    "double_cyclic_mma",
    "tiled_cmma",
];

/// The routine products take on tensor cores unless told otherwise (the library's own first choice).
pub const DEFAULT_TENSOR_CORE_ROUTINE: &str = "simple_cyclic_cmma";

thread_local! {
    /// Set by benches to time one tensor-core routine on their thread.
    static ROUTINE_OVERRIDE: std::cell::Cell<Option<&'static str>> = const { std::cell::Cell::new(None) };
    /// How the last product of this thread ran: a routine name, `unit`, `unit-f16` or `own`.
    static LAST_ROUTE: std::cell::Cell<&'static str> = const { std::cell::Cell::new("own") };
    /// Set by benches to run this thread's tensor-core products on one tiling.
    static TILING_OVERRIDE: std::cell::Cell<Option<Tiling>> = const { std::cell::Cell::new(None) };
    /// Whether the last library product of this thread ran on the asked tiling.
    static LAST_TILED: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

/// Runs `f` with this thread's tensor-core products on `tiling` where it applies (the simple routines;
/// a shape it does not fit keeps the routine's own tiling).
pub fn with_matmul_tiling<T>(tiling: Tiling, f: impl FnOnce() -> T) -> T {
    /// Puts the thread's previous tiling back, also when `f` panics (a bench that catches the panic of
    /// one tiling goes on with the next).
    struct Restore(Option<Tiling>);
    impl Drop for Restore {
        fn drop(&mut self) {
            TILING_OVERRIDE.set(self.0);
        }
    }
    let _restore = Restore(TILING_OVERRIDE.replace(Some(tiling)));
    f()
}

/// Whether the last library product of this thread ran on the tiling asked for (not on the routine's
/// own, and not on the unit routine).
pub fn last_product_tiled() -> bool {
    LAST_TILED.get()
}

/// The tiling of this thread's tensor-core products: a bench's choice, else `VCEDIT_GPU_MATMUL_TILING`
/// (see [`Tiling::parse`]; one that does not parse is said once on stderr and not used), else the
/// library's own.
fn matmul_tiling() -> Tiling {
    static FROM_ENV: std::sync::OnceLock<Tiling> = std::sync::OnceLock::new();
    TILING_OVERRIDE.get().unwrap_or_else(|| {
        *FROM_ENV.get_or_init(|| {
            let spec = std::env::var("VCEDIT_GPU_MATMUL_TILING").unwrap_or_default();
            Tiling::parse(&spec).unwrap_or_else(|e| {
                eprintln!("VCEDIT_GPU_MATMUL_TILING ignored: {e}");
                Tiling::default()
            })
        })
    })
}

/// Runs `f` with this thread's tensor-core products on routine `name` (one of [`TENSOR_CORE_ROUTINES`];
/// an unknown name is an error).
pub fn with_tensor_core_routine<T>(name: &str, f: impl FnOnce() -> T) -> Result<T> {
    let Some(&known) = TENSOR_CORE_ROUTINES.iter().find(|r| **r == name) else {
        candle_core::bail!(
            "unknown tensor-core routine '{name}' (expected one of {})",
            TENSOR_CORE_ROUTINES.join(", ")
        );
    };
    /// Puts the thread's previous routine back, also when `f` panics.
    struct Restore(Option<&'static str>);
    impl Drop for Restore {
        fn drop(&mut self) {
            ROUTINE_OVERRIDE.set(self.0);
        }
    }
    let _restore = Restore(ROUTINE_OVERRIDE.replace(Some(known)));
    Ok(f())
}

/// How the last product of this thread ran: the tensor-core routine's name, `unit` (also where tensor
/// cores declined the product), `unit-f16`, or `own` (our kernel).
pub fn last_product_route() -> &'static str {
    LAST_ROUTE.get()
}

/// The tensor-core routine of this thread's products: a bench's choice, else `VCEDIT_GPU_MATMUL_ROUTINE`,
/// else [`DEFAULT_TENSOR_CORE_ROUTINE`].
fn tensor_core_routine() -> &'static str {
    static FROM_ENV: std::sync::OnceLock<Option<&'static str>> = std::sync::OnceLock::new();
    ROUTINE_OVERRIDE
        .get()
        .or(*FROM_ENV.get_or_init(|| {
            let name = std::env::var("VCEDIT_GPU_MATMUL_ROUTINE").unwrap_or_default();
            TENSOR_CORE_ROUTINES
                .iter()
                .copied()
                .find(|r| *r == name.trim())
        }))
        .unwrap_or(DEFAULT_TENSOR_CORE_ROUTINE)
}

/// The library strategy of a routine of [`TENSOR_CORE_ROUTINES`].
fn tensor_core_strategy(name: &str) -> cubek_matmul::strategy::Strategy {
    use cubek_matmul::multi_level::routines::batch::{double_buffering, simple};
    use cubek_matmul::multi_level::Strategy as R;
    use cubek_matmul::routine::BlueprintStrategy::Inferred;
    if name == "tiled_cmma" {
        let tiled = cubek_matmul::tiled::Strategy::Cmma(Default::default());
        return cubek_matmul::strategy::Strategy::Tiled(tiled);
    }
    let multi_rows = simple::SimpleArgs {
        multi_rows: true,
        ..Default::default()
    };
    let specialized = double_buffering::DoubleBufferingArgs {
        specialized: true,
        ..Default::default()
    };
    let routine = match name {
        "simple_cyclic_cmma_multi_rows" => R::SimpleCyclicCmma(Inferred(multi_rows)),
        "simple_strided_cmma_multi_rows" => R::SimpleStridedCmma(Inferred(multi_rows)),
        "double_cyclic_cmma_specialized" => R::DoubleCyclicCmma(Inferred(specialized)),
        "simple_strided_cmma" => R::SimpleStridedCmma(Default::default()),
        "simple_tilewise_cmma" => R::SimpleTilewiseCmma(Default::default()),
        "double_cyclic_cmma" => R::DoubleCyclicCmma(Default::default()),
        "double_tilewise_cmma" => R::DoubleTilewiseCmma(Default::default()),
        "double_hybrid_cmma" => R::DoubleHybridCmma(Default::default()),
        "ordered_double_cmma" => R::OrderedDoubleCmma(Default::default()),
        "specialized_cyclic_cmma" => R::SpecializedCyclicCmma(Default::default()),
        "simple_cyclic_mma" => R::SimpleCyclicMma(Default::default()),
        "double_cyclic_mma" => R::DoubleCyclicMma(Default::default()),
        _ => R::SimpleCyclicCmma(Default::default()),
    };
    cubek_matmul::strategy::Strategy::MultiLevel(routine)
}

fn library_gemm_on(
    a: &GpuTensor,
    b: &GpuTensor,
    g: &Gemm,
    out_shape: &[usize],
    path: MatmulPath,
) -> Option<GpuTensor> {
    use cubecl::ir::{ElemType, FloatKind};
    use cubek_matmul::definition::{MatmulElems, MatmulGlobalElems};
    use cubek_matmul::strategy::Strategy;
    use cubek_std::InputBinding;
    let half = path != MatmulPath::Unit;
    // f32 operands: packed f16 weights are widened into a transient f32 copy (one pass over the
    // weight, small beside the product). f16 operands: weights are read as stored and activations
    // narrowed (one pass over them); the sums stay f32 either way.
    let (a, b) = if half {
        (&narrow_f16(a), &narrow_f16(b))
    } else {
        (&widen_f16(a), &widen_f16(b))
    };
    let (mut batch, mut m, mut a_strides) = (g.batch, g.m, g.a_strides);
    let mut b_strides = g.b_strides;
    if b_strides[0] == 0 && batch > 1 {
        // One B for every batch: fold the batches into A's rows when they are contiguous.
        if a_strides != [g.m * g.k, g.k, 1] {
            return None;
        }
        (m, batch, a_strides) = (batch * g.m, 1, [batch * g.m * g.k, g.k, 1]);
    }
    if batch == 1 {
        // A size-1 batch's stride is never stepped; give it the whole matrix so layouts classify.
        a_strides[0] = m * g.k;
        b_strides[0] = g.k * g.n;
    }
    let out = a.empty_like_device(out_shape.to_vec());
    let f32_type = ElemType::Float(FloatKind::F32);
    let operand = if half {
        ElemType::Float(FloatKind::F16)
    } else {
        f32_type
    };
    let mut dtypes = MatmulElems::from_globals(&MatmulGlobalElems {
        lhs: operand,
        rhs: operand,
        out: f32_type,
    });
    let lhs = || InputBinding::new(a.binding(&[batch, m, g.k], &a_strides), operand);
    let rhs = || InputBinding::new(b.binding(&[batch, g.k, g.n], &b_strides), operand);
    let dst = || out.binding(&[batch, m, g.n], &[m * g.n, g.n, 1]);
    let launch = |strategy: Strategy, dtypes: &mut MatmulElems| {
        cubek_matmul::launch::launch_ref(&strategy, a.client(), lhs(), rhs(), dst(), dtypes).is_ok()
    };
    LAST_TILED.set(false);
    if path == MatmulPath::TensorCores {
        let name = tensor_core_routine();
        let tiling = matmul_tiling();
        if !tiling.is_default() {
            // A tiling the inference or the launch declines for this shape leaves the routine's own.
            let mut tiled_dtypes = dtypes.clone();
            let forced = tiling::forced_routine(
                name,
                &tiling,
                a.client(),
                &lhs(),
                &rhs(),
                &dst(),
                &tiled_dtypes,
            );
            if forced
                .is_some_and(|routine| launch(Strategy::MultiLevel(routine), &mut tiled_dtypes))
            {
                LAST_TILED.set(true);
                return Some(out);
            }
        }
        return launch(tensor_core_strategy(name), &mut dtypes).then_some(out);
    }
    launch(Strategy::MultiLevel(unit_routine()), &mut dtypes).then_some(out)
}

/// The library's routine for products without tensor cores: `VCEDIT_GPU_UNIT_ROUTINE` = `simple_max`
/// (the default: one stage, the largest unit tile the shape allows), `simple_min`, `double_max` or
/// `double_min` (double-buffered stages) — the four burn's autotune chooses among.
fn unit_routine() -> cubek_matmul::multi_level::Strategy {
    use cubek_matmul::multi_level::routines::batch::{double_unit, simple_unit};
    use cubek_matmul::multi_level::routines::TileSizeSelection as T;
    use cubek_matmul::multi_level::Strategy as R;
    use cubek_matmul::routine::BlueprintStrategy::Inferred;
    const NAMES: [&str; 4] = ["simple_max", "simple_min", "double_max", "double_min"];
    static FROM_ENV: std::sync::OnceLock<&str> = std::sync::OnceLock::new();
    // An unknown name is said once on stderr (as `VCEDIT_GPU_MATMUL_TILING` does) and not used.
    let name = FROM_ENV.get_or_init(|| {
        let asked = std::env::var("VCEDIT_GPU_UNIT_ROUTINE").unwrap_or_default();
        let asked = asked.trim();
        NAMES.into_iter().find(|n| *n == asked).unwrap_or_else(|| {
            if !asked.is_empty() {
                eprintln!(
                    "VCEDIT_GPU_UNIT_ROUTINE ignored: unknown routine '{asked}' (expected one of {})",
                    NAMES.join(", ")
                );
            }
            NAMES[0]
        })
    });
    let tile_size = if name.ends_with("_min") {
        T::MinTileSize
    } else {
        T::MaxTileSize
    };
    if name.starts_with("double") {
        R::DoubleUnit(Inferred(double_unit::DoubleUnitSelectionArgs { tile_size }))
    } else {
        R::SimpleUnit(Inferred(simple_unit::SimpleUnitSelectionArgs { tile_size }))
    }
}

/// Batched matrix product a [.., m, k] × b [.., k, n] → [.., m, n]; a rank-2 `b` is shared by every batch.
pub fn matmul(a: &GpuTensor, b: &GpuTensor) -> Result<GpuTensor> {
    matmul_scaled(a, b, false, 1.0)
}

/// `alpha · a × b`, or `alpha · a × bᵀ` when `transpose_b` (b then [.., n, k]), without copying b.
pub fn matmul_scaled(
    a: &GpuTensor,
    b: &GpuTensor,
    transpose_b: bool,
    alpha: f32,
) -> Result<GpuTensor> {
    let (ra, rb) = (a.dims().len(), b.dims().len());
    if ra < 2 || rb < 2 {
        candle_core::bail!("gpu matmul: ranks {ra} and {rb} (need >= 2)");
    }
    let (m, k) = (a.dims()[ra - 2], a.dims()[ra - 1]);
    let (kb, n) = if transpose_b {
        (b.dims()[rb - 1], b.dims()[rb - 2])
    } else {
        (b.dims()[rb - 2], b.dims()[rb - 1])
    };
    let batch: usize = a.dims()[..ra - 2].iter().product();
    let b_batch: usize = b.dims()[..rb - 2].iter().product();
    if k != kb || (rb > 2 && (b_batch != batch || b.dims()[..rb - 2] != a.dims()[..ra - 2])) {
        candle_core::bail!(
            "gpu matmul: shapes {:?} x {:?}{}",
            a.dims(),
            b.dims(),
            if transpose_b { "ᵀ" } else { "" }
        );
    }
    let b_batch_stride = if rb > 2 {
        b.dims()[rb - 2] * b.dims()[rb - 1]
    } else {
        0
    };
    let b_strides = if transpose_b {
        [b_batch_stride, 1, k]
    } else {
        [b_batch_stride, n, 1]
    };
    let mut out_shape = a.dims()[..ra - 2].to_vec();
    out_shape.extend([m, n]);
    let g = Gemm {
        batch,
        m,
        n,
        k,
        a_strides: [m * k, k, 1],
        b_strides,
        alpha,
    };
    gemm(a, b, GemmBias::None, None, &g, out_shape)
}

/// A linear layer: x [.., in] × weightᵀ (weight `[out, in]`) + bias `[out]` (+ `residual`, of the output's
/// shape, in the same pass as the bias).
pub fn linear(
    x: &GpuTensor,
    weight: &GpuTensor,
    bias: Option<&GpuTensor>,
    residual: Option<&GpuTensor>,
) -> Result<GpuTensor> {
    let rank = x.dims().len();
    let (out_dim, in_dim) = match weight.dims() {
        [o, i] => (*o, *i),
        other => candle_core::bail!("gpu linear: weight shape {other:?}"),
    };
    if rank == 0 || x.dims()[rank - 1] != in_dim {
        candle_core::bail!(
            "gpu linear: input {:?} for weight {:?}",
            x.dims(),
            weight.dims()
        );
    }
    let rows = x.elem_count() / in_dim;
    let mut out_shape = x.dims().to_vec();
    out_shape[rank - 1] = out_dim;
    let g = Gemm {
        batch: 1,
        m: rows,
        n: out_dim,
        k: in_dim,
        a_strides: [0, in_dim, 1],
        b_strides: [0, 1, in_dim],
        alpha: 1.0,
    };
    let bias = bias.map_or(GemmBias::None, GemmBias::PerColumn);
    gemm(x, weight, bias, residual, &g, out_shape)
}

/// The most cubes along one dimension of a launch (Vulkan guarantees 65535).
const GRID_LIMIT: u32 = 65535;

/// Largest transient buffer one block of a blocked op may take (a convolution's im2col buffer, a chunk of
/// attention scores): the device's largest buffer, at most [`TRANSIENT_CAP_BYTES`] (beyond that a larger
/// block saves nothing: each product is already long).
fn transient_cap(x: &GpuTensor) -> usize {
    let most = TRANSIENT_CAP_BYTES as u64;
    let limit = x.device().context().limits.max_buffer_bytes;
    let limit = if limit == 0 { most } else { limit.min(most) };
    usize::try_from(limit).unwrap_or(usize::MAX)
}

/// The most bytes [`transient_cap`] allows on any device (the memory estimate counts it).
pub const TRANSIENT_CAP_BYTES: usize = 256 << 20;

// ------------------------------------------------------------------------------------------ reductions

/// Group norm of x [batch, channels, ..] with per-channel weight and bias, optionally followed by SiLU.
pub fn group_norm(
    x: &GpuTensor,
    weight: &GpuTensor,
    bias: &GpuTensor,
    groups: usize,
    eps: f64,
    silu: bool,
) -> Result<GpuTensor> {
    // A software adapter (lavapipe) runs a few cubes at a time, and its barriers are dear: there one
    // cube per group is faster (SD 1.5's [6, 320, 64, 64] with SiLU: 186 against 251 ms, Mesa 25).
    let split = !x.device().context().software;
    group_norm_on(x, weight, bias, groups, eps, silu, split)
}

/// [`group_norm`], large groups split over several cubes where `split`.
fn group_norm_on(
    x: &GpuTensor,
    weight: &GpuTensor,
    bias: &GpuTensor,
    groups: usize,
    eps: f64,
    silu: bool,
    split: bool,
) -> Result<GpuTensor> {
    let dims = x.dims();
    if dims.len() < 2
        || groups == 0
        || !dims[1].is_multiple_of(groups)
        || weight.elem_count() != dims[1]
        || bias.elem_count() != dims[1]
    {
        candle_core::bail!(
            "gpu group_norm: input {dims:?}, {groups} groups, weight {:?}, bias {:?}",
            weight.dims(),
            bias.dims()
        );
    }
    let channels = dims[1];
    let spatial: usize = dims[2..].iter().product();
    let out = x.empty_like_device(dims.to_vec());
    let chunk = GROUP_NORM_CHUNK as usize;
    let split_chunks = (channels / groups) * spatial.div_ceil(chunk);
    let fits_grid = dims[0] * groups <= GRID_LIMIT as usize && split_chunks <= GRID_LIMIT as usize;
    if split && (channels / groups) * spatial >= GROUP_NORM_SPLIT && fits_grid {
        // Large groups: one cube per chunk of a channel (SD 1.5's 64² layers at batch 6: 1,920 cubes of
        // 4,096 elements instead of 192 of 40,960), statistics combined in a second pass.
        let (parts, chunks) = (spatial.div_ceil(chunk), split_chunks);
        let count = CubeCount::Static(
            to_u32(chunks, "group norm chunks")?,
            to_u32(dims[0] * groups, "groups")?,
            1,
        );
        let meta = Meta::new(x, &[channels, spatial, groups, parts])?;
        let partials = x.empty_like_device(vec![dims[0] * groups * chunks * 2]);
        // SAFETY: cube (chunk, group) reads its chunk of x and writes its two partials, then reads its
        // group's partials and writes its chunk of out; chunks tile each channel (the last one shorter).
        unsafe {
            cube::group_norm_partials::launch_unchecked(
                x.client(),
                count.clone(),
                CubeDim::new_1d(REDUCE_UNITS),
                x.arg(),
                partials.arg(),
                meta.arg(),
            );
            cube::group_norm_apply::launch_unchecked(
                x.client(),
                count,
                CubeDim::new_1d(REDUCE_UNITS),
                x.arg(),
                partials.arg(),
                weight.arg(),
                bias.arg(),
                out.arg(),
                meta.arg(),
                eps as f32,
                silu,
            )
        };
        return Ok(out);
    }
    let cubes = dims[0] * groups;
    let meta = Meta::new(x, &[channels, spatial, groups, cubes])?;
    let units = row_units((channels / groups) * spatial);
    // SAFETY: one cube per (batch, group) reads/writes that group's channels only.
    unsafe {
        cube::group_norm::launch_unchecked(
            x.client(),
            grid(cubes),
            CubeDim::new_1d(units),
            x.arg(),
            weight.arg(),
            bias.arg(),
            out.arg(),
            meta.arg(),
            eps as f32,
            silu,
            units,
        )
    };
    Ok(out)
}

/// Elements of a group from which the group norm splits it over several cubes: smaller groups are few
/// cubes' work anyway, and a second launch would cost more than it spreads.
const GROUP_NORM_SPLIT: usize = 2 * GROUP_NORM_CHUNK as usize;

/// Layer norm over the last dimension.
pub fn layer_norm(
    x: &GpuTensor,
    weight: &GpuTensor,
    bias: &GpuTensor,
    eps: f64,
) -> Result<GpuTensor> {
    let width = *x.dims().last().unwrap_or(&0);
    if width == 0 || weight.elem_count() != width || bias.elem_count() != width {
        candle_core::bail!(
            "gpu layer_norm: input {:?}, weight {:?}",
            x.dims(),
            weight.dims()
        );
    }
    let rows = x.elem_count() / width;
    let meta = Meta::new(x, &[width, rows])?;
    let out = x.empty_like_device(x.dims().to_vec());
    let units = row_units(width);
    // SAFETY: one cube per row.
    unsafe {
        cube::layer_norm::launch_unchecked(
            x.client(),
            grid(rows),
            CubeDim::new_1d(units),
            x.arg(),
            weight.arg(),
            bias.arg(),
            out.arg(),
            meta.arg(),
            eps as f32,
            units,
        )
    };
    Ok(out)
}

/// Units of a cube that reduces one row (or group) `width` elements wide: at least four elements each,
/// from 32 (a warp) to [`REDUCE_UNITS`]. Narrow rows on 128 units left most of them idle through every
/// level of the reduction tree: the small UNet's LayerNorms (rows 64–256 wide) took 4–6 ms a launch on
/// lavapipe.
fn row_units(width: usize) -> u32 {
    (width.next_power_of_two() / 4).clamp(32, REDUCE_UNITS as usize) as u32
}

/// Softmax over the last dimension.
pub fn softmax_last_dim(x: &GpuTensor) -> Result<GpuTensor> {
    softmax_scaled(x, 1.0, false)
}

/// Softmax of `scale · x` over the last dimension (attention's scaled scores, without a pass to scale
/// them), written as f16 when `half` (probabilities that only feed an f16-operand product).
fn softmax_scaled(x: &GpuTensor, scale: f32, half: bool) -> Result<GpuTensor> {
    let width = *x.dims().last().unwrap_or(&0);
    if width == 0 {
        candle_core::bail!("gpu softmax: empty last dimension in {:?}", x.dims());
    }
    let rows = x.elem_count() / width;
    let meta = Meta::new(x, &[width, rows])?;
    let units = row_units(width);
    let (count, dim) = (grid(rows), CubeDim::new_1d(units));
    let shape = x.dims().to_vec();
    // SAFETY: one cube per row.
    let out = unsafe {
        if half {
            let out = x.empty_half_like(shape);
            cube::softmax_rows::launch_unchecked::<half::f16>(
                x.client(),
                count,
                dim,
                x.arg(),
                out.half_arg(),
                meta.arg(),
                scale,
                units,
            );
            out
        } else {
            let out = x.empty_like_device(shape);
            cube::softmax_rows::launch_unchecked::<f32>(
                x.client(),
                count,
                dim,
                x.arg(),
                out.arg(),
                meta.arg(),
                scale,
                units,
            );
            out
        }
    };
    Ok(out)
}

/// GEGLU over the last dimension: [.., 2·inner] → hidden · gelu(gate), [.., inner].
pub fn geglu(x: &GpuTensor) -> Result<GpuTensor> {
    let width = *x.dims().last().unwrap_or(&0);
    if width == 0 || !width.is_multiple_of(2) {
        candle_core::bail!("geglu: last dimension {width} is not a positive even number");
    }
    let mut shape = x.dims().to_vec();
    *shape.last_mut().expect("rank >= 1") = width / 2;
    let out = x.empty_like_device(shape);
    // SAFETY: the kernel bound-checks against out.
    unsafe {
        cube::geglu::launch_unchecked(
            x.client(),
            grid_for(out.elem_count(), ELEMENTWISE_UNITS),
            CubeDim::new_1d(ELEMENTWISE_UNITS),
            x.arg(),
            out.arg(),
            to_u32(width / 2, "geglu width")?,
        )
    };
    Ok(out)
}

// ------------------------------------------------------------------------------------------- attention

/// Checks q [.., q_len, d], k [.., k_len, d], v [.., k_len, dv]; returns (batch, q_len, k_len, d, dv).
fn attention_dims(
    q: &GpuTensor,
    k: &GpuTensor,
    v: &GpuTensor,
) -> Result<(usize, usize, usize, usize, usize)> {
    let r = q.dims().len();
    let ok = r >= 2
        && k.dims().len() == r
        && v.dims().len() == r
        && q.dims()[..r - 2] == k.dims()[..r - 2]
        && k.dims()[..r - 2] == v.dims()[..r - 2]
        && q.dims()[r - 1] == k.dims()[r - 1]
        && k.dims()[r - 2] == v.dims()[r - 2];
    if !ok {
        candle_core::bail!(
            "gpu attention: q {:?}, k {:?}, v {:?}",
            q.dims(),
            k.dims(),
            v.dims()
        );
    }
    let batch = q.dims()[..r - 2].iter().product();
    Ok((
        batch,
        q.dims()[r - 2],
        k.dims()[r - 2],
        q.dims()[r - 1],
        v.dims()[r - 1],
    ))
}

/// How attention runs on the GPU.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AttentionPath {
    /// Our flash kernel: one unit per query row, online softmax, no score matrix (scalar f32 arithmetic).
    Flash,
    /// Two products through the matrix-product path (tensor cores where the device has them) around a
    /// row softmax, the scores held in chunks of whole heads of at most [`transient_cap`] bytes.
    Products,
    /// The library's flash attention (`cubek-attention`, what burn runs): its unit routine (one query
    /// row per unit, tiles of the widest vector) without tensor cores, cooperative-matrix tiles with
    /// them. Where it declines a problem (f16 activations, a scale other than 1/√d, a head width its
    /// tiles do not divide) the attention takes the flash kernel or the products as by default.
    Library,
}

impl std::fmt::Display for AttentionPath {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Flash => "flash",
            Self::Products => "products",
            Self::Library => "library",
        })
    }
}

thread_local! {
    /// Set by tests to pick an attention path on their thread.
    static ATTENTION_OVERRIDE: std::cell::Cell<Option<AttentionPath>> = const { std::cell::Cell::new(None) };
}

/// Runs `f` with the attention of this thread on `path` (tests, benches).
pub fn with_attention_path<T>(path: AttentionPath, f: impl FnOnce() -> T) -> T {
    let before = ATTENTION_OVERRIDE.replace(Some(path));
    let result = f();
    ATTENTION_OVERRIDE.set(before);
    result
}

/// Heads at most this wide take the flash kernel where the library's attention declines them: a score
/// costs the kernel `d` multiply-adds, against a fixed write, softmax and read of it as products.
/// `vcedit bench attention` on lavapipe, 2026-11-26, 8 heads of 1024 queries and keys: d = 8 flash
/// 171 ms / products 359 ms; d = 16 698 / 394; d = 32 1365 / 440. At SD 1.5's d = 40: 16 heads of
/// 1024², 3.4 s / 0.96 s; 8 heads of 4096², 18.8 s / 3.6 s.
const FLASH_DEFAULT_MAX_HEAD_DIM: usize = 8;

/// The attention path of heads `d` wide (values `dv`) on `device`, where none is forced: the library's
/// flash attention, except for heads wider than [`FLASH_DEFAULT_MAX_HEAD_DIM`] on tensor cores, where
/// the products run on them (until `tools/gpu-check` has timed the library's cooperative-matrix tiles
/// against them: `attention`, `unet-library`), and on software adapters (below). Measured on lavapipe
/// (Mesa 25.0.7, WGSL, 2026-11-29, `vcedit bench attention`, 48 entries, the small UNet's shapes):
/// the library took 14.6 ms at 256 queries × 256 keys × d 8 against the flash kernel's 82.6 and the
/// products' 245; 2.2 ms at 64² × 16 against 18.0 / 31.7; 2.0 ms at 16² × 32 against 12.7 / 14.0. Its kernel is compiled per shape, and
/// slowly by lavapipe as heads widen (first call 11 s at d 8, 37 s at d 16, 169 s at d 32; Mesa's
/// shader cache keeps them, but CI machines start cold: the demo model's 16- and 32-wide heads took
/// `vcedit demo --device gpu` in tools/gpu-check's local run from 71 s to 118 s), so software adapters,
/// which only tests and CI use, keep the products for wider heads.
/// `VCEDIT_GPU_ATTENTION=flash|products|library` forces one (A/B switch for benches; `vcedit bench
/// attention` times all three); heads wider than the flash kernel can take run as products instead.
pub fn attention_path(device: &super::GpuDevice, d: usize, dv: usize) -> AttentionPath {
    static FORCED: OnceLock<Option<AttentionPath>> = OnceLock::new();
    let forced = ATTENTION_OVERRIDE.get().or(forced_by_env(
        &FORCED,
        "VCEDIT_GPU_ATTENTION",
        |name| match name {
            "flash" => Some(AttentionPath::Flash),
            "products" => Some(AttentionPath::Products),
            "library" => Some(AttentionPath::Library),
            _ => None,
        },
    ));
    let widest = d.max(dv);
    match forced {
        Some(AttentionPath::Flash) if widest > FLASH_MAX_HEAD_DIM => AttentionPath::Products,
        Some(path) => path,
        None if widest > FLASH_DEFAULT_MAX_HEAD_DIM
            && (matmul_path(device) == MatmulPath::TensorCores || device.context().software) =>
        {
            AttentionPath::Products
        }
        None => AttentionPath::Library,
    }
}

/// Where the library declines a problem: the flash kernel for narrow heads, else products.
fn fallback_attention_path(widest: usize) -> AttentionPath {
    if widest <= FLASH_DEFAULT_MAX_HEAD_DIM {
        AttentionPath::Flash
    } else {
        AttentionPath::Products
    }
}

/// The library's flash attention of q [.., q_len, d], k [.., k_len, d], v [.., k_len, dv] (f32, the
/// scale 1/√d, which the library applies itself), or `None` where it declines the problem.
fn library_attention(q: &GpuTensor, k: &GpuTensor, v: &GpuTensor, scale: f64) -> Option<GpuTensor> {
    use cubecl::ir::{ElemType, FloatKind};
    use cubek_attention::forward::definition::{
        AccumulatorPrecision, AttentionGlobalTypes, AttentionOptions,
    };
    use cubek_attention::forward::launch::{launch_ref, BlueprintStrategy, Strategy};
    use cubek_attention::forward::routines::blackbox_accelerated::BlackboxAcceleratedStrategy;
    let (batch, q_len, k_len, d, dv) = attention_dims(q, k, v).ok()?;
    let library_scale = 1.0 / (d as f64).sqrt();
    if q.is_f16() || k.is_f16() || v.is_f16() || q_len == 0 || k_len == 0 {
        return None;
    }
    if (scale - library_scale).abs() > 1e-6 * library_scale {
        return None;
    }
    let f32_type = ElemType::Float(FloatKind::F32);
    let dtypes = AttentionGlobalTypes::from_single_float_dtype(
        f32_type,
        AttentionGlobalTypes::mask_dtype(q.client()),
    );
    let options = AttentionOptions {
        causal: false,
        accumulator_precision: AccumulatorPrecision::Strict(f32_type),
    };
    // The library's layout is [batch, heads, seq, dim]: every (batch, head) entry as one batch.
    let bind = |t: &GpuTensor, rows: usize, width: usize| {
        t.binding(
            &[batch, 1, rows, width],
            &[rows * width, rows * width, width, 1],
        )
    };
    let mut shape = q.dims().to_vec();
    *shape.last_mut().expect("rank >= 2") = dv;
    let out = q.empty_like_device(shape);
    let launch = |strategy: Strategy| {
        launch_ref(
            strategy,
            q.client(),
            bind(q, q_len, d),
            bind(k, k_len, d),
            bind(v, k_len, dv),
            None,
            bind(&out, q_len, dv),
            &dtypes,
            options.clone(),
        )
        .is_ok()
    };
    // On tensor cores the cooperative-matrix tiles (burn's middle candidate: four planes, one tile of
    // queries and keys each), else or where those decline, the unit routine.
    let tensor_cores = matmul_path(q.device()) == MatmulPath::TensorCores
        && launch(Strategy::BlackboxAccelerated(BlueprintStrategy::Inferred(
            BlackboxAcceleratedStrategy {
                num_planes: 4,
                seq_q: 1,
                seq_kv: 1,
            },
        )));
    (tensor_cores || launch(Strategy::Unit(BlueprintStrategy::Inferred(())))).then_some(out)
}

/// `softmax(q kᵀ · scale) v` without returning the probabilities, on the [`attention_path`].
pub fn attention(q: &GpuTensor, k: &GpuTensor, v: &GpuTensor, scale: f64) -> Result<GpuTensor> {
    let (batch, q_len, k_len, d, dv) = attention_dims(q, k, v)?;
    let mut path = attention_path(q.device(), d, dv);
    if path == AttentionPath::Library {
        if let Some(out) = library_attention(q, k, v, scale) {
            return Ok(out);
        }
        path = fallback_attention_path(d.max(dv));
    }
    if path == AttentionPath::Products || k_len == 0 {
        return attention_in_chunks(q, k, v, scale, transient_cap(q));
    }
    let mut shape = q.dims().to_vec();
    *shape.last_mut().expect("rank >= 2") = dv;
    let out = q.empty_like_device(shape);
    let meta = Meta::new(q, &[q_len, k_len])?;
    let blocks = q_len.div_ceil(ATTENTION_QUERIES as usize);
    // SAFETY: rows past q_len and keys past k_len are masked in the kernel.
    unsafe {
        cube::flash_attention::launch_unchecked(
            q.client(),
            CubeCount::Static(to_u32(blocks, "query blocks")?, to_u32(batch, "batch")?, 1),
            CubeDim::new_1d(ATTENTION_QUERIES),
            q.arg(),
            k.arg(),
            v.arg(),
            out.arg(),
            meta.arg(),
            scale as f32,
            d as u32,
            dv as u32,
        )
    };
    Ok(out)
}

/// Attention as products, the score matrix in chunks of whole (batch, head) entries of at most `cap`
/// bytes (at least one entry): at SD 1.5's 64² latents one head's scores are 64 MiB, a batch of six
/// branches' 48 heads 3 GiB. The chunks' inputs are copied out and their outputs concatenated: passes
/// over Q/K/V-sized tensors, small beside the score-sized ones.
fn attention_in_chunks(
    q: &GpuTensor,
    k: &GpuTensor,
    v: &GpuTensor,
    scale: f64,
    cap: usize,
) -> Result<GpuTensor> {
    let (batch, q_len, k_len, d, dv) = attention_dims(q, k, v)?;
    let per_entry = (q_len * k_len * std::mem::size_of::<f32>()).max(1);
    let entries = (cap / per_entry).max(1);
    if entries >= batch {
        return attention_products(q, k, v, scale);
    }
    let (q3, k3, v3) = (
        q.reshape(&[batch, q_len, d])?,
        k.reshape(&[batch, k_len, d])?,
        v.reshape(&[batch, k_len, dv])?,
    );
    let parts = (0..batch)
        .step_by(entries)
        .map(|b0| {
            let n = entries.min(batch - b0);
            attention_products(
                &narrow(&q3, 0, b0, n)?,
                &narrow(&k3, 0, b0, n)?,
                &narrow(&v3, 0, b0, n)?,
                scale,
            )
        })
        .collect::<Result<Vec<_>>>()?;
    let mut shape = q.dims().to_vec();
    *shape.last_mut().expect("rank >= 2") = dv;
    cat(&parts.iter().collect::<Vec<_>>(), 0)?.reshape(&shape)
}

/// Attention that also returns its probabilities [.., q_len, k_len] (for the attention hook of
/// cross-attention layers, whose maps the edit controller reads): two products and a row softmax that
/// applies the scale.
pub fn attention_with_probs(
    q: &GpuTensor,
    k: &GpuTensor,
    v: &GpuTensor,
    scale: f64,
) -> Result<(GpuTensor, GpuTensor)> {
    attention_dims(q, k, v)?;
    let scores = matmul_scaled(q, k, true, 1.0)?;
    let probs = softmax_scaled(&scores, scale as f32, false)?;
    let out = matmul(&probs, v)?;
    Ok((out, probs))
}

/// [`attention_with_probs`] without the probabilities: where the products take f16 operands, the
/// softmax writes them as f16 (the product would narrow them to f16 anyway, in a pass of its own).
fn attention_products(
    q: &GpuTensor,
    k: &GpuTensor,
    v: &GpuTensor,
    scale: f64,
) -> Result<GpuTensor> {
    attention_dims(q, k, v)?;
    let scores = matmul_scaled(q, k, true, 1.0)?;
    let probs = softmax_scaled(&scores, scale as f32, half_operands(q.device()))?;
    matmul(&probs, v)
}

// -------------------------------------------------------------------------- VGG feature-loss ops

fn nchw(x: &GpuTensor, op: &str) -> Result<(usize, usize, usize, usize)> {
    match x.dims() {
        &[n, c, h, w] => Ok((n, c, h, w)),
        other => candle_core::bail!("gpu {op}: expected an NCHW tensor, got {other:?}"),
    }
}

/// 2×2 max-pool, stride 2, floor mode (`kernels::vgg::max_pool2x2`).
pub fn max_pool2x2(x: &GpuTensor) -> Result<GpuTensor> {
    let (n, c, h, w) = nchw(x, "max_pool2x2")?;
    let meta = Meta::new(x, &[h, w, h / 2, w / 2])?;
    let out = x.empty_like_device(vec![n, c, h / 2, w / 2]);
    // SAFETY: every output window lies inside its input plane (floor mode); bound-checked against out.
    unsafe {
        cube::max_pool2x2::launch_unchecked(
            x.client(),
            grid_for(out.elem_count(), ELEMENTWISE_UNITS),
            CubeDim::new_1d(ELEMENTWISE_UNITS),
            x.arg(),
            out.arg(),
            meta.arg(),
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
    let meta = Meta::new(x, &[h, w, h / 2, w / 2])?;
    let out = x.empty_like_device(x.dims().to_vec());
    // SAFETY: one unit per input value; windows and pooled indices are inside x and grad.
    unsafe {
        cube::max_pool2x2_backward::launch_unchecked(
            x.client(),
            grid_for(out.elem_count(), ELEMENTWISE_UNITS),
            CubeDim::new_1d(ELEMENTWISE_UNITS),
            x.arg(),
            grad.arg(),
            out.arg(),
            meta.arg(),
        )
    };
    Ok(out)
}

/// `f / (‖f‖ + eps)` over the channels of each pixel (`kernels::vgg::normalize_channels`).
pub fn normalize_channels(x: &GpuTensor, eps: f32) -> Result<GpuTensor> {
    let (n, c, h, w) = nchw(x, "normalize_channels")?;
    let pixels = n * h * w;
    let meta = Meta::new(x, &[c, h * w, pixels])?;
    let out = x.empty_like_device(x.dims().to_vec());
    // SAFETY: one unit per pixel, reading and writing that pixel's channels.
    unsafe {
        cube::normalize_channels::launch_unchecked(
            x.client(),
            grid_for(pixels, ELEMENTWISE_UNITS),
            CubeDim::new_1d(ELEMENTWISE_UNITS),
            x.arg(),
            out.arg(),
            meta.arg(),
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
    let meta = Meta::new(f, &[c, h * w, pixels])?;
    let map = f.empty_like_device(vec![n, 1, h, w]);
    // Without the gradient the kernel writes no `grad`; a one-value buffer stands in.
    let grad = f.empty_like_device(if with_grad {
        f.dims().to_vec()
    } else {
        vec![1]
    });
    // SAFETY: one unit per pixel, reading and writing that pixel's channels and map value.
    unsafe {
        cube::lpips_distance::launch_unchecked(
            f.client(),
            grid_for(pixels, ELEMENTWISE_UNITS),
            CubeDim::new_1d(ELEMENTWISE_UNITS),
            f.arg(),
            target.arg(),
            lin.arg(),
            map.arg(),
            grad.arg(),
            meta.arg(),
            eps,
            1.0 / (h * w).max(1) as f32,
            with_grad,
        )
    };
    Ok((map, with_grad.then_some(grad)))
}

#[cfg(test)]
mod tests;
