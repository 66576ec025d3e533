//! Matrix products: our register-blocked kernel, the matrix-product library's routines (unit and
//! tensor cores, with the f16 widening and narrowing passes they need) and the finishing pass that adds
//! a product's scale, bias and residual; linear layers and batched products on top.

use std::sync::OnceLock;

use candle_core::Result;
use cubecl::prelude::*;

use self::kernel::{MATMUL_TILE, MATMUL_UNITS};
use super::elementwise::{add, affine};
use super::launch::{forced_by_env, launch_per_element, to_u32, Meta};
use super::GpuTensor;

mod tiling;
pub use tiling::Tiling;

/// The kernels of this family (their host launchers follow the module).
mod kernel {
    use cubecl::prelude::*;

    use super::super::launch::linear_pos;

    /// Units per side of a [`matmul`] cube (`MATMUL_UNITS²` units).
    pub const MATMUL_UNITS: u32 = 16;
    /// Side of the block of outputs each [`matmul`] unit computes in registers.
    pub const MATMUL_REG: u32 = 4;
    /// Side of the square output tile of one [`matmul`] cube.
    pub const MATMUL_TILE: u32 = MATMUL_UNITS * MATMUL_REG;
    /// Depth (along k) of the shared-memory slices of A and B in [`matmul`].
    pub const MATMUL_DEPTH: u32 = 16;

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
}

/// One batched product's geometry: `out[b] = alpha · A[b] B[b] (+ bias)`, strides in elements.
pub(super) struct Gemm {
    pub(super) batch: usize,
    pub(super) m: usize,
    pub(super) n: usize,
    pub(super) k: usize,
    /// (batch, row, column) strides of A and B.
    pub(super) a_strides: [usize; 3],
    pub(super) b_strides: [usize; 3],
    pub(super) alpha: f32,
}

impl Gemm {
    /// One weight `A` [m, k] against each of `batch` contiguous matrices `B[b]` [k, n] (a convolution:
    /// the filters against each image's columns).
    pub(super) fn shared_weight(batch: usize, m: usize, n: usize, k: usize) -> Self {
        Gemm {
            batch,
            m,
            n,
            k,
            a_strides: [0, k, 1],
            b_strides: [k * n, n, 1],
            alpha: 1.0,
        }
    }
}

/// Bias of a product: none, one per output column (linear), one per output row (convolution), one per
/// output row of each matrix of the batch ([batch·m]: a convolution's bias with a time embedding folded in).
#[derive(Clone, Copy)]
pub(super) enum GemmBias<'a> {
    None,
    PerColumn(&'a GpuTensor),
    PerRow(&'a GpuTensor),
    PerBatchRow(&'a GpuTensor),
}

/// `alpha·A[b]B[b] + bias (+ residual)`, `residual` of the output's shape (a layer's skip connection).
pub(super) fn gemm(
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
        kernel::matmul::launch_unchecked(
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
    use kernel::epilogue_bias;
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
        launch_per_element!(
            kernel::product_epilogue,
            product.client(),
            product.elem_count(),
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
pub(super) fn half_operands(device: &super::GpuDevice) -> bool {
    matches!(
        matmul_path(device),
        MatmulPath::TensorCores | MatmulPath::UnitF16
    )
}

/// An f32 copy of a packed f16 tensor; an f32 tensor as it is (shared buffer).
pub(super) fn widen_f16(x: &GpuTensor) -> GpuTensor {
    if !x.is_f16() {
        return x.clone();
    }
    let out = x.empty_like_device(x.dims().to_vec());
    // SAFETY: the kernel bound-checks against out, and out's element count is x's.
    unsafe {
        launch_per_element!(
            kernel::widen_f16,
            x.client(),
            out.elem_count(),
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
        launch_per_element!(
            kernel::narrow_f16,
            x.client(),
            x.elem_count(),
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

#[cfg(test)]
mod tests;
