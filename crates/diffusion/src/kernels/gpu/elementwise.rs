//! Elementwise ops: the activations (one `unary` kernel, the op a compile-time code), the broadcasting
//! binary ops, GEGLU, and constants. One unit per element.

use candle_core::Result;

use self::kernel::{binary_op, unary_op};
use super::launch::{coalesce, contiguous_strides, launch_per_element, to_u32, Meta};
use super::GpuTensor;

/// The kernels of this family (their host launchers follow the module).
pub(super) mod kernel {
    use cubecl::prelude::*;

    use super::super::launch::{linear_pos, strided_offsets};

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
        /// `min(max(x, a), b)`, candle's `clamp` (the same two comparisons, so the same values).
        pub const CLAMP: u32 = 11;
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
    pub(crate) fn apply_unary(x: f32, a: f32, b: f32, #[comptime] op: u32) -> f32 {
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
        } else if comptime!(op == unary_op::CLAMP) {
            f32::min(f32::max(x, a), b)
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
}

fn unary(x: &GpuTensor, op: u32, a: f32, b: f32) -> GpuTensor {
    let out = x.empty_like_device(x.dims().to_vec());
    // SAFETY: out and x have the same element count; the kernel bound-checks against out.
    unsafe {
        launch_per_element!(
            kernel::unary,
            x.client(),
            x.elem_count(),
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
/// `x` clamped to `[min, max]`.
pub fn clamp(x: &GpuTensor, min: f32, max: f32) -> GpuTensor {
    unary(x, unary_op::CLAMP, min, max)
}
/// A tensor of `shape` filled with `value`, on `like`'s device.
pub fn full(like: &GpuTensor, shape: Vec<usize>, value: f32) -> GpuTensor {
    let out = like.empty_like_device(shape);
    // The kernel does not read its input; a separate one-element buffer avoids binding `out` twice.
    let unused = GpuTensor::from_slice(like.device(), &[0.0], vec![1]);
    // SAFETY: the kernel writes out only, bound-checked.
    unsafe {
        launch_per_element!(
            kernel::unary,
            like.client(),
            out.elem_count(),
            unused.arg(),
            out.arg(),
            value,
            0.0,
            unary_op::FILL,
        )
    };
    out
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
        launch_per_element!(
            kernel::binary,
            a.client(),
            out.elem_count(),
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
        launch_per_element!(
            kernel::geglu,
            x.client(),
            out.elem_count(),
            x.arg(),
            out.arg(),
            to_u32(width / 2, "geglu width")?,
        )
    };
    Ok(out)
}

#[cfg(test)]
mod tests {
    //! The elementwise ops against their CPU twins.

    use super::*;
    use crate::kernels::gpu::testing::*;

    #[test]
    fn elementwise_ops_match_cpu() {
        let Some(dev) = device_or_skip() else {
            return;
        };
        let x = (randn(&[3, 5, 7]) * 3.0).unwrap();
        let g = up(&dev, &x);
        check(
            "affine",
            &affine(&g, 0.5, -2.0),
            &x.affine(0.5, -2.0).unwrap(),
        );
        check("relu", &relu(&g), &x.relu().unwrap());
        check("silu", &silu(&g), &candle_nn::ops::silu(&x).unwrap());
        check("gelu", &gelu(&g), &x.gelu_erf().unwrap());
        check("tanh", &tanh(&g), &x.tanh().unwrap());
        check(
            "scaled tanh",
            &scaled_tanh(&g, 1.0 / 3.0, 3.0),
            &((&x / 3.0).unwrap().tanh().unwrap() * 3.0).unwrap(),
        );
        check("exp", &exp(&g), &x.exp().unwrap());
        check(
            "clamp",
            &clamp(&g, -1.0, 2.0),
            &x.clamp(-1f32, 2f32).unwrap(),
        );
        let quick = (&x * candle_nn::ops::sigmoid(&(&x * 1.702).unwrap()).unwrap()).unwrap();
        check("quick gelu", &quick_gelu(&g), &quick);
        check("gelu tanh", &gelu_tanh(&g), &x.gelu().unwrap());
        let mish_cpu = candle_nn::Activation::Mish;
        check(
            "mish",
            &mish(&g),
            &candle_core::Module::forward(&mish_cpu, &x).unwrap(),
        );
    }

    #[test]
    fn broadcasting_binary_ops_match_cpu() {
        let Some(dev) = device_or_skip() else {
            return;
        };
        let a = randn(&[2, 3, 4, 5]);
        for shape in [
            vec![2, 3, 4, 5],
            vec![3, 1, 1],
            vec![1, 3, 1, 5],
            vec![5],
            vec![2, 1, 4, 1],
        ] {
            let b = (randn(&shape).abs().unwrap() + 0.5).unwrap();
            let (ga, gb) = (up(&dev, &a), up(&dev, &b));
            check(
                "add",
                &add(&ga, &gb).unwrap(),
                &a.broadcast_add(&b).unwrap(),
            );
            check(
                "sub",
                &sub(&ga, &gb).unwrap(),
                &a.broadcast_sub(&b).unwrap(),
            );
            check(
                "mul",
                &mul(&ga, &gb).unwrap(),
                &a.broadcast_mul(&b).unwrap(),
            );
            check(
                "div",
                &div(&ga, &gb).unwrap(),
                &a.broadcast_div(&b).unwrap(),
            );
            // The broadcast operand on the left.
            check(
                "add (swapped)",
                &add(&gb, &ga).unwrap(),
                &b.broadcast_add(&a).unwrap(),
            );
        }
        assert!(add(&up(&dev, &a), &up(&dev, &randn(&[3]))).is_err());
    }
}
