//! Row reductions: group norm (one cube per group, or split over chunks for large groups), layer norm and
//! the row softmax, each a cube per row or group reducing through shared memory.

use candle_core::Result;
use cubecl::prelude::*;

use self::kernel::{GROUP_NORM_CHUNK, REDUCE_UNITS};
use super::launch::{grid, to_u32, u32_args, GRID_LIMIT};
use super::GpuTensor;

/// The kernels of this family (their host launchers follow the module).
mod kernel {
    use cubecl::prelude::*;
    use gpu::reduce::{cube_max, cube_sum};

    use super::super::elementwise::kernel::{apply_unary, unary_op};
    use super::super::launch::cube_index;

    /// Units per cube of the row reductions (norms, softmax): one cube per row or group.
    pub const REDUCE_UNITS: u32 = 128;

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
    /// two) per (batch, group) of the `cubes`, two passes (mean, then the mean squared deviation) for
    /// accuracy.
    #[cube(launch_unchecked)]
    #[allow(clippy::too_many_arguments)]
    pub fn group_norm(
        x: &[f32],
        weight: &[f32],
        bias: &[f32],
        out: &mut [f32],
        channels: u32,
        spatial: u32,
        groups: u32,
        cubes: u32,
        eps: f32,
        #[comptime] silu: bool,
        #[comptime] units: u32,
    ) {
        // Cubes past the last group (the 2D launch rounds up) redo the last one without writing.
        let valid = cube_index() < cubes;
        let cube = u32::min(cube_index(), cubes - 1);
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
    /// `bg` (batch · groups + group), each channel `spatial` elements in `parts` chunks. Returns (bg,
    /// local, first element, length).
    #[cube]
    fn group_norm_chunk(
        channels: u32,
        spatial: u32,
        groups: u32,
        parts: u32,
    ) -> (u32, u32, u32, u32) {
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
    pub fn group_norm_partials(
        x: &[f32],
        partials: &mut [f32],
        channels: u32,
        spatial: u32,
        groups: u32,
        parts: u32,
    ) {
        let units = comptime!(REDUCE_UNITS);
        let (bg, _, base, len) = group_norm_chunk(channels, spatial, groups, parts);
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
    /// chunk (+ optional SiLU). Same grid and sizes as [`group_norm_partials`].
    #[cube(launch_unchecked)]
    pub fn group_norm_apply(
        x: &[f32],
        partials: &[f32],
        weight: &[f32],
        bias: &[f32],
        out: &mut [f32],
        channels: u32,
        spatial: u32,
        groups: u32,
        parts: u32,
        eps: f32,
        #[comptime] silu: bool,
    ) {
        let units = comptime!(REDUCE_UNITS);
        let (bg, local, base, len) = group_norm_chunk(channels, spatial, groups, parts);
        let chunks = CUBE_COUNT_X;
        let per_group = channels / groups;
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

    /// Layer norm over the last dimension (`width`), one cube of `units` units (a power of two) per row of
    /// the `rows`.
    #[cube(launch_unchecked)]
    pub fn layer_norm(
        x: &[f32],
        weight: &[f32],
        bias: &[f32],
        out: &mut [f32],
        width: u32,
        rows: u32,
        eps: f32,
        #[comptime] units: u32,
    ) {
        let valid = cube_index() < rows;
        let base = u32::min(cube_index(), rows - 1) * width;
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
    /// `width` wide, `rows` of them. The scale is applied here so attention's scores need no pass of their own to
    /// be scaled. `F`: f32, or f16 where the probabilities only feed an f16-operand product (attention's
    /// `P V`): the narrowing pass before that product was a fifth of an SD 1.5 UNet's kernel time on an H200
    /// (docs/gpu-results.md, 2026-11-27).
    #[cube(launch_unchecked)]
    pub fn softmax_rows<F: Float>(
        x: &[f32],
        out: &mut [F],
        width: u32,
        rows: u32,
        scale: f32,
        #[comptime] units: u32,
    ) {
        let valid = cube_index() < rows;
        let base = u32::min(cube_index(), rows - 1) * width;
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
}

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
        let sizes = u32_args([channels, spatial, groups, parts])?;
        let partials = x.empty_like_device(vec![dims[0] * groups * chunks * 2]);
        // SAFETY: cube (chunk, group) reads its chunk of x and writes its two partials, then reads its
        // group's partials and writes its chunk of out; chunks tile each channel (the last one shorter).
        unsafe {
            kernel::group_norm_partials::launch_unchecked(
                x.client(),
                count.clone(),
                CubeDim::new_1d(REDUCE_UNITS),
                x.arg(),
                partials.arg(),
                sizes[0],
                sizes[1],
                sizes[2],
                sizes[3],
            );
            kernel::group_norm_apply::launch_unchecked(
                x.client(),
                count,
                CubeDim::new_1d(REDUCE_UNITS),
                x.arg(),
                partials.arg(),
                weight.arg(),
                bias.arg(),
                out.arg(),
                sizes[0],
                sizes[1],
                sizes[2],
                sizes[3],
                eps as f32,
                silu,
            )
        };
        return Ok(out);
    }
    let cubes = dims[0] * groups;
    let sizes = u32_args([channels, spatial, groups, cubes])?;
    let units = row_units((channels / groups) * spatial);
    // SAFETY: one cube per (batch, group) reads/writes that group's channels only.
    unsafe {
        kernel::group_norm::launch_unchecked(
            x.client(),
            grid(cubes),
            CubeDim::new_1d(units),
            x.arg(),
            weight.arg(),
            bias.arg(),
            out.arg(),
            sizes[0],
            sizes[1],
            sizes[2],
            sizes[3],
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
    let sizes = u32_args([width, rows])?;
    let out = x.empty_like_device(x.dims().to_vec());
    let units = row_units(width);
    // SAFETY: one cube per row.
    unsafe {
        kernel::layer_norm::launch_unchecked(
            x.client(),
            grid(rows),
            CubeDim::new_1d(units),
            x.arg(),
            weight.arg(),
            bias.arg(),
            out.arg(),
            sizes[0],
            sizes[1],
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
pub(super) fn softmax_scaled(x: &GpuTensor, scale: f32, half: bool) -> Result<GpuTensor> {
    let width = *x.dims().last().unwrap_or(&0);
    if width == 0 {
        candle_core::bail!("gpu softmax: empty last dimension in {:?}", x.dims());
    }
    let rows = x.elem_count() / width;
    let sizes = u32_args([width, rows])?;
    let units = row_units(width);
    let (count, dim) = (grid(rows), CubeDim::new_1d(units));
    let shape = x.dims().to_vec();
    // SAFETY: one cube per row.
    let out = unsafe {
        if half {
            let out = x.empty_half_like(shape);
            kernel::softmax_rows::launch_unchecked::<half::f16>(
                x.client(),
                count,
                dim,
                x.arg(),
                out.half_arg(),
                sizes[0],
                sizes[1],
                scale,
                units,
            );
            out
        } else {
            let out = x.empty_like_device(shape);
            kernel::softmax_rows::launch_unchecked::<f32>(
                x.client(),
                count,
                dim,
                x.arg(),
                out.arg(),
                sizes[0],
                sizes[1],
                scale,
                units,
            );
            out
        }
    };
    Ok(out)
}

#[cfg(test)]
mod tests {
    //! The row reductions against their CPU twins.

    use candle_core::Tensor;

    use super::*;
    use crate::kernels::gpu::ops::*;
    use crate::kernels::gpu::testing::*;

    #[test]
    fn norms_match_cpu() {
        let Some(dev) = device_or_skip() else {
            return;
        };
        // Offset inputs test the two-pass variance. Groups of 70, 256 and 600 elements: cubes of 32, 64
        // and 128 units.
        for (shape, groups) in [
            (&[2usize, 8, 5, 7][..], 4),
            (&[2, 16, 8, 8][..], 4),
            (&[1, 6, 300][..], 3),
        ] {
            let c = shape[1];
            let x = randn(shape).affine(2.0, 3.0).unwrap();
            let (w, b) = (randn(&[c]), randn(&[c]));
            for silu in [false, true] {
                let want = crate::kernels::group_norm(&x, &w, &b, groups, 1e-5, silu).unwrap();
                let got = group_norm_on(
                    &up(&dev, &x),
                    &up(&dev, &w),
                    &up(&dev, &b),
                    groups,
                    1e-5,
                    silu,
                    false,
                )
                .unwrap();
                check(
                    &format!("group_norm {shape:?} / {groups} silu={silu}"),
                    &got,
                    &want,
                );
            }
        }
        let x = randn(&[2, 8, 5, 7]);
        let w = randn(&[8]);
        let short_bias = up(&dev, &randn(&[7]));
        assert!(group_norm(&up(&dev, &x), &up(&dev, &w), &short_bias, 4, 1e-5, false).is_err());
        // Groups large enough to split over cubes: channels of two chunks (the second short), of one
        // partial chunk, and a 3D input; offset and scaled per channel so the combined statistics matter.
        for (shape, groups) in [
            (&[2usize, 8, 64, 70][..], 4),
            (&[1, 32, 30, 30][..], 2),
            (&[3, 6, 5000][..], 3),
        ] {
            let c = shape[1];
            let offsets = Tensor::arange(0f32, c as f32, &Device::Cpu).unwrap();
            let mut per_channel = vec![1usize; shape.len()];
            per_channel[1] = c;
            let x = randn(shape)
                .broadcast_mul(
                    &offsets
                        .affine(0.5, 1.0)
                        .unwrap()
                        .reshape(per_channel.clone())
                        .unwrap(),
                )
                .unwrap()
                .broadcast_add(
                    &offsets
                        .affine(3.0, -4.0)
                        .unwrap()
                        .reshape(per_channel)
                        .unwrap(),
                )
                .unwrap();
            let (w, b) = (randn(&[c]), randn(&[c]));
            let (gx, gw, gb) = (up(&dev, &x), up(&dev, &w), up(&dev, &b));
            for (silu, split) in [(false, true), (true, true), (true, false)] {
                let want = crate::kernels::group_norm(&x, &w, &b, groups, 1e-5, silu).unwrap();
                let got = group_norm_on(&gx, &gw, &gb, groups, 1e-5, silu, split).unwrap();
                check(
                    &format!("group_norm {shape:?} / {groups} silu={silu} split={split}"),
                    &got,
                    &want,
                );
            }
        }
        // Rows on every cube width: 32 units (5, 64 wide), 64 (256), 128 (300, 2000).
        for width in [5, 64, 256, 300, 2000] {
            let x = (randn(&[3, 4, width]) + 1.0).unwrap();
            let (w, b) = (randn(&[width]), randn(&[width]));
            let want = crate::kernels::layer_norm(&x, &w, &b, 1e-5).unwrap();
            check(
                &format!("layer_norm {width} wide"),
                &layer_norm(&up(&dev, &x), &up(&dev, &w), &up(&dev, &b), 1e-5).unwrap(),
                &want,
            );
        }
        assert_eq!(
            [5, 64, 128, 256, 300, 2000].map(row_units),
            [32, 32, 32, 64, 128, 128]
        );
    }

    #[test]
    fn softmax_and_geglu_match_cpu() {
        let Some(dev) = device_or_skip() else {
            return;
        };
        // Cubes of 32 (1, 7), 64 (200) and 128 units (300).
        for width in [1, 7, 200, 300] {
            let x = (randn(&[3, 5, width]) * 4.0).unwrap();
            let want = crate::kernels::softmax_last_dim(&x).unwrap();
            check(
                &format!("softmax width {width}"),
                &softmax_last_dim(&up(&dev, &x)).unwrap(),
                &want,
            );
        }
        let x = randn(&[2, 6, 40]);
        check(
            "geglu",
            &geglu(&up(&dev, &x)).unwrap(),
            &crate::kernels::geglu(&x).unwrap(),
        );
        assert!(geglu(&up(&dev, &randn(&[2, 3]))).is_err());
    }
}
