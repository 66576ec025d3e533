//! What the op families share: launch grids, the `meta` parameter block, the strided walk of the
//! elementwise and copy kernels, and [`launch_per_element`], the launch of the common 1-D case.
//!
//! Every tensor is a contiguous row-major buffer; launch sizes are 2D (`CUBE_COUNT_X` ≤ 65535), read back
//! as one linear position by [`linear_pos`]. The kernels are kept simple and bounds-checked first: they
//! are tested on Mesa lavapipe, where barriers are expensive, and tuned on real GPUs later.

use std::sync::OnceLock;

use candle_core::Result;
use cubecl::prelude::*;
use cubecl::server::Handle;

use super::GpuTensor;

/// Units per cube of the elementwise kernels.
pub(super) const ELEMENTWISE_UNITS: u32 = 256;

/// The linear index of this unit over a 2D launch of 1D cubes.
#[cube]
pub(super) fn linear_pos() -> u32 {
    (CUBE_POS_Y * CUBE_COUNT_X + CUBE_POS_X) * CUBE_DIM_X + UNIT_POS_X
}

/// The linear index of this cube over a 2D launch.
#[cube]
pub(super) fn cube_index() -> u32 {
    CUBE_POS_Y * CUBE_COUNT_X + CUBE_POS_X
}

/// The offsets into two operands of the element at linear index `i` of a contiguous `shape`, each
/// operand read at its own strides: `meta = [shape; rank][first strides; rank][second strides; rank]`. The host merges dimensions first (`ops::coalesce`), so `rank` is
/// usually 1–3; the outermost coordinate is what is left of `i`, so a rank-1 walk divides nothing
/// (integer division is the dearest instruction of these kernels: tens of cycles on a GPU, and
/// scalarised on a SIMD CPU).
#[cube]
pub(super) fn strided_offsets(i: u32, meta: &[u32], #[comptime] rank: u32) -> (u32, u32) {
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

/// `$kernel::launch_unchecked` on `$client` with one unit per element over `$count` elements
/// ([`ELEMENTWISE_UNITS`]-unit cubes on a [`grid_for`] grid); the other arguments are the kernel's. As
/// unsafe as the launch: the caller says why the kernel stays in bounds.
macro_rules! launch_per_element {
    ($($kernel:ident)::+, $client:expr, $count:expr, $($arg:expr),+ $(,)?) => {
        $($kernel)::+::launch_unchecked(
            $client,
            $crate::kernels::gpu::launch::grid_for(
                $count,
                $crate::kernels::gpu::launch::ELEMENTWISE_UNITS,
            ),
            cubecl::prelude::CubeDim::new_1d($crate::kernels::gpu::launch::ELEMENTWISE_UNITS),
            $($arg),+
        )
    };
}
pub(super) use launch_per_element;

/// A 2D launch of `cubes` cubes (the X count is capped at 65535; kernels bound-check the excess).
pub(super) fn grid(cubes: usize) -> CubeCount {
    let cubes = cubes.max(1) as u32;
    let x = cubes.min(GRID_LIMIT);
    CubeCount::Static(x, cubes.div_ceil(x), 1)
}

/// Cubes of `units` units covering `n` elements.
pub(super) fn grid_for(n: usize, units: u32) -> CubeCount {
    grid(n.div_ceil(units as usize))
}

pub(super) fn to_u32(v: usize, what: &str) -> Result<u32> {
    u32::try_from(v).map_err(|_| candle_core::Error::msg(format!("gpu: {what} {v} exceeds u32")))
}

/// Shape values as u32 kernel arguments (the typed form of a [`Meta`] block of fixed length).
pub(super) fn u32_args<const N: usize>(values: [usize; N]) -> Result<[u32; N]> {
    let mut args = [0; N];
    for (arg, value) in args.iter_mut().zip(values) {
        *arg = to_u32(value, "shape value")?;
    }
    Ok(args)
}

/// Uploads a small u32 parameter block (shapes and index tables whose length varies: strides of a
/// walk, an index list); fixed sets of sizes are plain kernel arguments ([`u32_args`]).
pub(super) struct Meta(Handle, usize);

impl Meta {
    pub(super) fn new(x: &GpuTensor, values: &[usize]) -> Result<Meta> {
        let values = values
            .iter()
            .map(|&v| to_u32(v, "shape value"))
            .collect::<Result<Vec<u32>>>()?;
        Ok(Meta(
            x.client().create_from_slice(u32::as_bytes(&values)),
            values.len(),
        ))
    }

    pub(super) fn arg(&self) -> BufferArg {
        // SAFETY: the handle holds exactly `self.1` u32 values.
        unsafe { BufferArg::from_raw_parts(self.0.clone(), self.1) }
    }
}

pub(super) fn contiguous_strides(shape: &[usize]) -> Vec<usize> {
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
pub(super) fn coalesce<const S: usize>(
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

/// The path an A/B environment variable `var` forces, read once per process (`once`): `parse` of its
/// trimmed, lower-case value; `None` (the default path) where it is unset or names no path.
pub(super) fn forced_by_env<T: Copy>(
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

/// The most cubes along one dimension of a launch (Vulkan guarantees 65535).
pub(super) const GRID_LIMIT: u32 = 65535;

/// Largest transient buffer one block of a blocked op may take (a convolution's im2col buffer, a chunk of
/// attention scores): the device's largest buffer, at most [`TRANSIENT_CAP_BYTES`] (beyond that a larger
/// block saves nothing: each product is already long).
pub(super) fn transient_cap(x: &GpuTensor) -> usize {
    let most = TRANSIENT_CAP_BYTES as u64;
    let limit = x.device().context().limits.max_buffer_bytes;
    let limit = if limit == 0 { most } else { limit.min(most) };
    usize::try_from(limit).unwrap_or(usize::MAX)
}

/// The most bytes [`transient_cap`] allows on any device (the memory estimate counts it).
pub const TRANSIENT_CAP_BYTES: usize = 256 << 20;

#[cfg(test)]
mod tests {
    //! The shared walk helpers.

    use super::*;

    #[test]
    fn coalesced_walks_keep_every_offset() {
        // Offsets of every index along (shape, strides) and along the coalesced walk must agree.
        fn offsets(shape: &[usize], strides: &[usize]) -> Vec<usize> {
            let count: usize = shape.iter().product();
            (0..count)
                .map(|mut i| {
                    let mut offset = 0;
                    for d in (0..shape.len()).rev() {
                        offset += (i % shape[d]) * strides[d];
                        i /= shape[d];
                    }
                    offset
                })
                .collect()
        }
        /// Shape, two stride sets, the coalesced rank.
        type Case<'a> = (&'a [usize], &'a [usize], &'a [usize], usize);
        let cases: [Case; 6] = [
            // Equal shapes: one dimension.
            (&[2, 3, 4, 5], &[60, 20, 5, 1], &[60, 20, 5, 1], 1),
            // A per-channel bias over [batch, channels, h, w]: [batch, channels, h·w].
            (&[2, 3, 4, 5], &[60, 20, 5, 1], &[0, 1, 0, 0], 3),
            // A time embedding [batch, channels, 1, 1]: [batch·channels, h·w].
            (&[2, 3, 4, 5], &[60, 20, 5, 1], &[3, 1, 0, 0], 2),
            // A permute [0, 2, 3, 1] read from a contiguous [2, 3, 4, 5].
            (&[2, 4, 5, 3], &[60, 5, 1, 20], &[60, 15, 3, 1], 3),
            // Size-1 dimensions vanish; a broadcast of a scalar.
            (&[1, 6, 1, 7], &[42, 7, 7, 1], &[0, 0, 0, 0], 1),
            (&[1, 1], &[1, 1], &[1, 1], 1),
        ];
        for (shape, a, b, rank) in cases {
            let (walk, [wa, wb]) = coalesce(shape, [a, b]);
            assert_eq!(walk.len(), rank, "{shape:?} {a:?} {b:?} → {walk:?}");
            assert_eq!(
                walk.iter().product::<usize>(),
                shape.iter().product::<usize>()
            );
            assert_eq!(offsets(&walk, &wa), offsets(shape, a), "{shape:?} {a:?}");
            assert_eq!(offsets(&walk, &wb), offsets(shape, b), "{shape:?} {b:?}");
        }
    }
}
