//! Copies that change a tensor's layout: permutes, narrows, concatenation, padding, gathers along an
//! axis and nearest-neighbour upsampling.

use candle_core::Result;

use super::elementwise::full;
use super::launch::{coalesce, contiguous_strides, launch_per_element, Meta};
use super::GpuTensor;

/// The kernels of this family (their host launchers follow the module).
mod kernel {
    use cubecl::prelude::*;

    use super::super::launch::{linear_pos, strided_offsets};

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
        launch_per_element!(
            kernel::strided_copy,
            src.client(),
            count,
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
        launch_per_element!(
            kernel::index_select,
            x.client(),
            count,
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
        launch_per_element!(
            kernel::upsample_nearest,
            x.client(),
            out.elem_count(),
            x.arg(),
            out.arg(),
            meta.arg(),
        )
    };
    Ok(out)
}

#[cfg(test)]
mod tests {
    //! The copies against their CPU twins.

    use super::*;
    use crate::kernels::gpu::testing::*;

    #[test]
    fn copies_match_cpu() {
        let Some(dev) = device_or_skip() else {
            return;
        };
        let x = randn(&[2, 3, 4, 5]);
        let g = up(&dev, &x);
        check(
            "permute",
            &permute(&g, &[0, 2, 3, 1]).unwrap(),
            &x.permute((0, 2, 3, 1)).unwrap().contiguous().unwrap(),
        );
        check(
            "transpose",
            &transpose(&g, 1, 2).unwrap(),
            &x.transpose(1, 2).unwrap().contiguous().unwrap(),
        );
        check(
            "narrow",
            &narrow(&g, 1, 1, 2).unwrap(),
            &x.narrow(1, 1, 2).unwrap().contiguous().unwrap(),
        );
        check(
            "narrow_permute",
            &narrow_permute(&g, 1, 1, 2, &[0, 2, 3, 1]).unwrap(),
            &x.narrow(1, 1, 2)
                .unwrap()
                .permute((0, 2, 3, 1))
                .unwrap()
                .contiguous()
                .unwrap(),
        );
        let y = randn(&[2, 6, 4, 5]);
        check(
            "cat",
            &cat(&[&g, &up(&dev, &y)], 1).unwrap(),
            &Tensor::cat(&[&x, &y], 1).unwrap(),
        );
        check(
            "reshape",
            &g.reshape(&[6, 20]).unwrap(),
            &x.reshape((6, 20)).unwrap(),
        );
        check(
            "upsample",
            &upsample_nearest2d(&g, 8, 15).unwrap(),
            &x.upsample_nearest2d(8, 15).unwrap(),
        );
        let padded = x
            .pad_with_zeros(3, 0, 1)
            .unwrap()
            .pad_with_zeros(2, 0, 1)
            .unwrap();
        check("pad", &pad_bottom_right(&g, 1, 1).unwrap(), &padded);
        for (dim, idx) in [(0, vec![1u32, 0, 1]), (3, vec![4, 0, 0, 2]), (1, vec![2])] {
            let cpu_idx = Tensor::new(idx.as_slice(), &Device::Cpu).unwrap();
            check(
                "index_select",
                &index_select(&g, &idx, dim).unwrap(),
                &x.index_select(&cpu_idx, dim).unwrap(),
            );
        }
        assert_eq!(index_select(&g, &[], 1).unwrap().dims(), &[2, 0, 4, 5]);
        assert!(index_select(&g, &[5], 3).is_err());
        assert!(permute(&g, &[0, 0, 1, 2]).is_err());
    }
}
