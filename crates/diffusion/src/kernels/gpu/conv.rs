//! Convolutions: a pointwise one is one product; the others run as im2col columns and a product, or on
//! the convolution library's direct kernel, whichever the tuner timed faster for the problem on this device
//! ([`tuned_conv_path`]).

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex, OnceLock};

use candle_core::Result;
use cubecl::prelude::*;

use super::elementwise::add;
use super::launch::{
    contiguous_strides, forced_by_env, transient_cap, Meta, ELEMENTWISE_UNITS, GRID_LIMIT,
};
use super::layout::{cat, permute};
use super::matmul::{gemm, half_operands, matmul_path, widen_f16, Gemm, GemmBias, MatmulPath};
use super::{GpuDevice, GpuTensor};
use crate::kernels::op_args::Addend;

/// The kernels of this family (their host launchers follow the module).
mod kernel {
    use cubecl::prelude::*;

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
}

/// 2D convolution of x [batch, cin, h, w] with weight [cout, cin, kh, kw]: a pointwise one as one product
/// (the image is its own im2col matrix), others on the path [`tuned_conv_path`] picks (im2col +
/// products, or the library's direct kernel). The bias and `addend` join the product's finishing pass;
/// after the direct kernel the addend is a pass of its own.
pub fn conv2d(
    x: &GpuTensor,
    weight: &GpuTensor,
    bias: Option<&GpuTensor>,
    stride: usize,
    padding: usize,
    addend: Addend<'_, GpuTensor>,
) -> Result<GpuTensor> {
    let (&[n, cin, h, w], &[cout, wcin, kh, kw]) = (x.dims(), weight.dims()) else {
        candle_core::bail!(
            "gpu conv2d: input {:?}, weight {:?} are not 4D",
            x.dims(),
            weight.dims()
        );
    };
    if cin != wcin || stride == 0 || h + 2 * padding < kh || w + 2 * padding < kw {
        candle_core::bail!(
            "gpu conv2d: input {:?}, weight {:?}, stride {stride}, padding {padding}",
            x.dims(),
            weight.dims()
        );
    }
    let oh = (h + 2 * padding - kh) / stride + 1;
    let ow = (w + 2 * padding - kw) / stride + 1;
    match addend {
        Addend::Residual(r) if r.dims() != [n, cout, oh, ow] => candle_core::bail!(
            "gpu conv2d: residual {:?} for an output [{n}, {cout}, {oh}, {ow}]",
            r.dims()
        ),
        Addend::PerChannel(t) if t.elem_count() != n * cout => candle_core::bail!(
            "gpu conv2d: per-channel addend {:?} for {n} images × {cout} channels",
            t.dims()
        ),
        _ => {}
    }
    if kh == 1 && kw == 1 && stride == 1 && padding == 0 {
        // A pointwise convolution: the image [cin, h·w] is its own im2col matrix.
        let g = Gemm::shared_weight(n, cout, h * w, cin);
        let product = |bias: GemmBias, residual: Option<&GpuTensor>| {
            gemm(weight, x, bias, residual, &g, vec![n, cout, h * w])
        };
        return whole_batch_conv(product, bias, addend, [n, cout, oh, ow]);
    }
    let path = match forced_conv_path() {
        Some(path) => path,
        // Timing without a place to keep its result would choose anew in every process, and the paths'
        // results differ in their last bits: one fixed path keeps a seed's result the same run to run.
        None if !gpu::tuning_persists() => UNTUNED_CONV_PATH,
        None => {
            let key = conv_key(x, weight, bias.is_some(), stride, padding);
            // The tensors are cloned (handles only) only for a problem the tuner has not settled.
            let problem = || ConvProblem {
                x: x.clone(),
                weight: weight.clone(),
                bias: bias.cloned(),
                stride,
                padding,
                out: [oh, ow],
            };
            match tuned_conv_path(x.device(), key, problem) {
                Tuned::Settled(path) => path,
                // The tuning round's own result, without the addend.
                Tuned::Ran(out) => return with_addend(out, addend),
            }
        }
    };
    if path == ConvPath::Direct {
        if let Some(out) = direct_conv2d(x, weight, bias, stride, padding, [oh, ow])? {
            return with_addend(out, addend);
        }
    }
    // The im2col buffer is cin·kh·kw times the output's pixels: in a full-resolution VAE layer it alone
    // outgrows a device's largest buffer (lavapipe: 128 MiB; 512² × 128 channels × 9 = 1.2 GB per image).
    // Past the cap the convolution runs in blocks of whole images, then of output rows.
    conv2d_blocked(x, weight, bias, stride, padding, addend, transient_cap(x))
}

/// The path when tuning results cannot persist (see `gpu::tuning_persists`): im2col runs on tensor
/// cores where a device has them and never declines a problem.
pub const UNTUNED_CONV_PATH: ConvPath = ConvPath::Im2col;

/// How a convolution that is not pointwise runs on the GPU (pointwise ones are one product each).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ConvPath {
    /// im2col columns, then one product per block: the product runs on tensor cores where the device
    /// has them, which a direct kernel cannot use.
    Im2col,
    /// The convolution library's direct kernel (`cubek-convolution`'s `launch_direct`, burn's pick on
    /// lavapipe) on channels-last copies of the input and weights: a unit per output pixel and vector of
    /// output channels, its input read as vectors along the input channels; no im2col buffer.
    Direct,
}

impl std::fmt::Display for ConvPath {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Im2col => "im2col",
            Self::Direct => "direct",
        })
    }
}

thread_local! {
    /// Set by tests to pick a convolution path on their thread.
    static CONV_OVERRIDE: std::cell::Cell<Option<ConvPath>> = const { std::cell::Cell::new(None) };
}

/// Runs `f` with the convolutions of this thread on `path` (tests, benches).
pub fn with_conv_path<T>(path: ConvPath, f: impl FnOnce() -> T) -> T {
    let before = CONV_OVERRIDE.replace(Some(path));
    let result = f();
    CONV_OVERRIDE.set(before);
    result
}

/// The path `VCEDIT_GPU_CONV=im2col|direct` (A/B switch for benches) or a test's [`with_conv_path`]
/// forces on every convolution, or `None`: each problem takes the path the tuner timed faster for it on
/// its device ([`tuned_conv_paths`]).
pub fn forced_conv_path() -> Option<ConvPath> {
    static FORCED: OnceLock<Option<ConvPath>> = OnceLock::new();
    CONV_OVERRIDE.get().or(forced_by_env(
        &FORCED,
        "VCEDIT_GPU_CONV",
        |name| match name {
            "im2col" => Some(ConvPath::Im2col),
            "direct" => Some(ConvPath::Direct),
            _ => None,
        },
    ))
}

/// One convolution as the tuner sees it: what it reads and where it writes, without the addend (which
/// joins afterwards, fused on the im2col path).
#[derive(Clone)]
struct ConvProblem {
    x: GpuTensor,
    weight: GpuTensor,
    bias: Option<GpuTensor>,
    stride: usize,
    padding: usize,
    /// Output rows and columns.
    out: [usize; 2],
}

/// The tuner's key of the convolution of `x` by `weight` (shapes checked by [`conv2d`]).
fn conv_key(
    x: &GpuTensor,
    weight: &GpuTensor,
    bias: bool,
    stride: usize,
    padding: usize,
) -> ConvKey {
    let dims4 = |t: &GpuTensor| <[usize; 4]>::try_from(t.dims()).unwrap_or_default();
    let mut input = dims4(x);
    // Batches of 5 to 8 images share one result (an edit's view batches vary in size).
    input[0] = input[0].next_power_of_two();
    ConvKey {
        input,
        weight: dims4(weight),
        stride,
        padding,
        f16_weights: weight.is_f16(),
        bias,
        matmul: matmul_path(x.device()),
    }
}

impl ConvProblem {
    fn key(&self) -> ConvKey {
        conv_key(
            &self.x,
            &self.weight,
            self.bias.is_some(),
            self.stride,
            self.padding,
        )
    }

    /// The convolution on `path`; an error where the path declines the problem.
    fn run(&self, path: ConvPath) -> std::result::Result<GpuTensor, String> {
        let (x, weight, bias) = (&self.x, &self.weight, self.bias.as_ref());
        match path {
            ConvPath::Im2col => {
                let cap = transient_cap(x);
                conv2d_blocked(
                    x,
                    weight,
                    bias,
                    self.stride,
                    self.padding,
                    Addend::None,
                    cap,
                )
                .map_err(|e| e.to_string())
            }
            ConvPath::Direct => direct_conv2d(x, weight, bias, self.stride, self.padding, self.out)
                .map_err(|e| e.to_string())?
                .ok_or_else(|| "the direct kernel declines this problem".to_string()),
        }
    }
}

impl cubecl::tune::AutotuneOutput for GpuTensor {}

/// What a convolution's timing depends on: its shapes (the batch rounded up to a power of two), the
/// weights' storage, and the product path im2col's columns go to (which follows the precision and
/// `VCEDIT_GPU_MATMUL`).
#[derive(Clone, Debug, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
pub struct ConvKey {
    input: [usize; 4],
    weight: [usize; 4],
    stride: usize,
    padding: usize,
    f16_weights: bool,
    bias: bool,
    matmul: MatmulPath,
}

impl std::fmt::Display for ConvKey {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let dims = |d: &[usize; 4]| d.map(|v| v.to_string()).join("x");
        write!(
            f,
            "x {} w {}{} s{} p{}{}, {} products",
            dims(&self.input),
            dims(&self.weight),
            if self.f16_weights { " f16" } else { "" },
            self.stride,
            self.padding,
            if self.bias { " +bias" } else { "" },
            self.matmul
        )
    }
}

impl cubecl::tune::AutotuneKey for ConvKey {}

/// What [`tuned_conv_path`] has for a problem.
enum Tuned {
    /// The path settled for it.
    Settled(ConvPath),
    /// The problem's output from the round that just timed its paths (or read the persisted result).
    Ran(GpuTensor),
}

/// The paths settled in this process, each problem described (for reports only: the tuner's own cache
/// decides).
fn settled_report() -> &'static Mutex<BTreeMap<String, ConvPath>> {
    static SETTLED: OnceLock<Mutex<BTreeMap<String, ConvPath>>> = OnceLock::new();
    SETTLED.get_or_init(Default::default)
}

/// The path for `problem` on its device, timed once per problem and device like burn's autotune: the
/// first call runs each path twice (cubecl's tuner: a warm-up and one sample, see `gpu`'s
/// `configure_runtime`) and keeps the faster in cubecl's persistent cache (`files::cache_dir()/cubecl`),
/// so later processes only look it up. Neither path wins everywhere: on lavapipe (Mesa 25.0.7, WGSL,
/// 2026-11-29) the direct kernel took the small UNet (channels 32–256 at 16² and below) from 7.6–8.2 s
/// to 6.6–6.7 s a forward, but LPIPS-VGG16 at 64² (channels 64–512) from 4.9 s to 14.1 s for value and
/// gradient, and no rule on channels or pixels separated the two; on a GPU with tensor cores im2col's
/// product runs on them, which the direct kernel cannot use. The one-off cost is two runs of the slower
/// path per problem: on lavapipe 26 s for LPIPS at 64² (18 problems), a few milliseconds a problem on
/// a hardware GPU.
fn tuned_conv_path(
    device: &GpuDevice,
    key: ConvKey,
    problem: impl FnOnce() -> ConvProblem,
) -> Tuned {
    use cubecl::tune::{local_tuner, LocalTuner, Tunable, TunableSet};
    static TUNER: LocalTuner<ConvKey, Arc<str>> = local_tuner!("conv2d");
    let id = device.tune_id();
    let set = TUNER.init(id, || {
        let candidate = |path: ConvPath| {
            Tunable::<ConvKey, ConvProblem, GpuTensor, ConvPath>::identified(
                path,
                move |problem: ConvProblem| problem.run(path),
            )
        };
        TunableSet::new_cloning_inputs(|problem: &ConvProblem| problem.key())
            .with(candidate(ConvPath::Im2col))
            .with(candidate(ConvPath::Direct))
    });
    // Settled in this process: the tuner's in-memory result. Otherwise this call times the paths, or
    // validates the result persisted by an earlier process, and runs the problem on the faster.
    if let Some(path) = TUNER.fastest_identity(id, &set, &key) {
        return Tuned::Settled(path);
    }
    let out = TUNER.execute(id, device.client(), set.clone(), problem());
    if let Some(path) = TUNER.fastest_identity(id, &set, &key) {
        settled_report()
            .lock()
            .expect("settled paths")
            .insert(key.to_string(), path);
    }
    Tuned::Ran(out)
}

/// The convolution paths settled in this process (for reports): each problem, described, and its path.
pub fn tuned_conv_paths() -> Vec<(String, ConvPath)> {
    let report = settled_report().lock().expect("settled paths");
    report
        .iter()
        .map(|(key, &path)| (key.clone(), path))
        .collect()
}

/// x [batch, cin, h, w] ⊛ weight [cout, cin, kh, kw] (+ bias) into [batch, cout, oh, ow] by the
/// library's direct kernel on channels-last copies, or `None` where it declines the problem (shapes
/// checked by [`conv2d`]).
fn direct_conv2d(
    x: &GpuTensor,
    weight: &GpuTensor,
    bias: Option<&GpuTensor>,
    stride: usize,
    padding: usize,
    [oh, ow]: [usize; 2],
) -> Result<Option<GpuTensor>> {
    use cubecl::ir::{ElemType, FloatKind};
    use cubek_convolution::{launch_direct, ConvolutionArgs, DirectTensors};
    let (n, cout) = (x.dims()[0], weight.dims()[0]);
    let input = permute(x, &[0, 2, 3, 1])?;
    let kernel = permute(&widen_f16(weight), &[0, 2, 3, 1])?;
    let bias = bias.map(widen_f16);
    let out = x.empty_like_device(vec![n, oh, ow, cout]);
    let bind = |t: &GpuTensor| t.binding(t.dims(), &contiguous_strides(t.dims()));
    let launched = launch_direct::<2>(
        x.client(),
        DirectTensors {
            input: bind(&input),
            weight: bind(&kernel),
            bias: bias.as_ref().map(bind),
            out: bind(&out),
        },
        ConvolutionArgs {
            stride: [stride; 2],
            padding: [padding; 2],
            dilation: [1; 2],
        },
        1,
        ElemType::Float(FloatKind::F32),
    );
    if launched.is_err() {
        return Ok(None);
    }
    Ok(Some(permute(&out, &[0, 3, 1, 2])?))
}

/// [`conv2d`] with im2col blocks of at most `cap` bytes (where one output row does not fit, one row).
pub(super) fn conv2d_blocked(
    x: &GpuTensor,
    weight: &GpuTensor,
    bias: Option<&GpuTensor>,
    stride: usize,
    padding: usize,
    addend: Addend<'_, GpuTensor>,
    cap: usize,
) -> Result<GpuTensor> {
    let (&[n, cin, h, w], &[cout, _, kh, kw]) = (x.dims(), weight.dims()) else {
        candle_core::bail!("gpu conv2d: input or weight not 4D");
    };
    let oh = (h + 2 * padding - kh) / stride + 1;
    let ow = (w + 2 * padding - kw) / stride + 1;
    let depth = cin * kh * kw;
    // The columns in the product's operand precision: f16 columns need no narrowing pass.
    let half = half_operands(x.device());
    let per_row = depth * ow * if half { 2 } else { 4 };
    let per_image = per_row * oh;
    let row_bias = bias.map_or(GemmBias::None, GemmBias::PerRow);
    let block = |n0: usize,
                 images: usize,
                 oy0: usize,
                 rows: usize,
                 bias: GemmBias,
                 residual: Option<&GpuTensor>|
     -> Result<GpuTensor> {
        let window = ConvWindow {
            kh,
            kw,
            stride,
            padding,
            n0,
            images,
            oy0,
            rows,
            ow,
        };
        let cols = im2col(x, &window, half)?;
        let g = Gemm::shared_weight(images, cout, rows * ow, depth);
        gemm(
            weight,
            &cols,
            bias,
            residual,
            &g,
            vec![images, cout, rows * ow],
        )
    };
    if n * per_image <= cap {
        return whole_batch_conv(
            |bias, residual| block(0, n, 0, oh, bias, residual),
            bias,
            addend,
            [n, cout, oh, ow],
        );
    }
    let mut parts = Vec::new();
    if per_image <= cap {
        let images = cap / per_image;
        for n0 in (0..n).step_by(images) {
            parts.push(block(n0, images.min(n - n0), 0, oh, row_bias, None)?);
        }
    } else {
        let rows = (cap / per_row).max(1);
        for n0 in 0..n {
            let bands = (0..oh)
                .step_by(rows)
                .map(|oy0| block(n0, 1, oy0, rows.min(oh - oy0), row_bias, None))
                .collect::<Result<Vec<_>>>()?;
            parts.push(cat(&bands.iter().collect::<Vec<_>>(), 2)?);
        }
    }
    let out = cat(&parts.iter().collect::<Vec<_>>(), 0)?.reshape(&[n, cout, oh, ow])?;
    // Blocks: the addend follows in a pass of its own.
    with_addend(out, addend)
}

/// A convolution's output [n, cout, oh, ow] plus `addend`, in a pass of its own.
fn with_addend(out: GpuTensor, addend: Addend<'_, GpuTensor>) -> Result<GpuTensor> {
    match addend {
        Addend::None => Ok(out),
        Addend::Residual(r) => add(&out, r),
        Addend::PerChannel(t) => add(&out, &t.reshape(&[out.dims()[0], out.dims()[1], 1, 1])?),
    }
}

/// A convolution's output [n, cout, oh, ow] from one `product` over the whole batch (its rows the output
/// channels, its columns the pixels): the bias and the addend join the product's finishing pass.
fn whole_batch_conv(
    product: impl Fn(GemmBias, Option<&GpuTensor>) -> Result<GpuTensor>,
    bias: Option<&GpuTensor>,
    addend: Addend<'_, GpuTensor>,
    [n, cout, oh, ow]: [usize; 4],
) -> Result<GpuTensor> {
    let row_bias = bias.map_or(GemmBias::None, GemmBias::PerRow);
    let out = match addend {
        Addend::None => product(row_bias, None)?,
        Addend::Residual(r) => product(row_bias, Some(&r.reshape(&[n, cout, oh * ow])?))?,
        Addend::PerChannel(t) => {
            let t = t.reshape(&[n, cout])?;
            let per_image = match bias {
                Some(b) => add(&t, &b.reshape(&[1, cout])?)?,
                None => t,
            };
            product(GemmBias::PerBatchRow(&per_image), None)?
        }
    };
    out.reshape(&[n, cout, oh, ow])
}

/// Which part of a convolution's output one im2col block covers.
#[derive(Clone, Copy)]
pub(super) struct ConvWindow {
    pub(super) kh: usize,
    pub(super) kw: usize,
    pub(super) stride: usize,
    pub(super) padding: usize,
    /// Images `n0..n0 + images` of the batch.
    pub(super) n0: usize,
    pub(super) images: usize,
    /// Output rows `oy0..oy0 + rows`, each `ow` wide.
    pub(super) oy0: usize,
    pub(super) rows: usize,
    pub(super) ow: usize,
}

/// The im2col columns [images, cin·kh·kw, rows·ow] of x [batch, cin, h, w] over `window`: f16 when
/// `half` (the product reads them as they are, no narrowing pass), else f32.
pub(super) fn im2col(x: &GpuTensor, window: &ConvWindow, half: bool) -> Result<GpuTensor> {
    im2col_on_grid(x, window, half, GRID_LIMIT)
}

/// [`im2col`] with at most `limit` cubes along each grid dimension (tests take a small one, so that the
/// kernel's strides past the grid are exercised).
pub(super) fn im2col_on_grid(
    x: &GpuTensor,
    window: &ConvWindow,
    half: bool,
    limit: u32,
) -> Result<GpuTensor> {
    let &[_, cin, h, w] = x.dims() else {
        candle_core::bail!("gpu im2col: input {:?} is not 4D", x.dims());
    };
    let ConvWindow {
        kh, kw, rows, ow, ..
    } = *window;
    let shape = vec![window.images, cin * kh * kw, rows * ow];
    let (stride, padding, oy0, n0) = (window.stride, window.padding, window.oy0, window.n0);
    let images = window.images;
    let meta = Meta::new(
        x,
        &[
            cin, h, w, kh, kw, stride, padding, rows, ow, oy0, n0, images,
        ],
    )?;
    // x: output pixels, y: input channels, z: images (the kernel strides past the grid's size). Deep
    // layers have few pixels (8² at SD 1.5's lowest level), so a cube is only as wide as they need.
    let pixels = rows * ow;
    let width = pixels
        .next_power_of_two()
        .clamp(32, ELEMENTWISE_UNITS as usize);
    let cap = |n: usize| n.clamp(1, limit as usize) as u32;
    let count = CubeCount::Static(cap(pixels.div_ceil(width)), cap(cin), cap(images));
    let units = CubeDim::new_1d(width as u32);
    // SAFETY: the kernel writes the [images, cin·kh·kw, rows·ow] columns it walks, and reads x only
    // inside images n0..n0 + images of the batch and [0, h) × [0, w).
    let cols = unsafe {
        if half {
            let cols = x.empty_half_like(shape);
            kernel::im2col::launch_unchecked::<half::f16>(
                x.client(),
                count,
                units,
                x.arg(),
                cols.half_arg(),
                meta.arg(),
            );
            cols
        } else {
            let cols = x.empty_like_device(shape);
            kernel::im2col::launch_unchecked::<f32>(
                x.client(),
                count,
                units,
                x.arg(),
                cols.arg(),
                meta.arg(),
            );
            cols
        }
    };
    Ok(cols)
}

#[cfg(test)]
mod tests {
    //! The convolution paths and im2col against the CPU.

    use candle_core::Tensor;

    use super::*;
    use crate::kernels::gpu::testing::*;

    /// im2col's f16 columns (what an f16-operand product reads) are exactly its f32 columns rounded: one
    /// kernel, only the store narrows. Elementwise, so it also runs on Mesa 25's SPIR-V path (f16, no
    /// workgroup memory); skipped where the device has no native f16.
    #[test]
    fn f16_im2col_is_the_f32_columns_rounded() {
        let Some(dev) = device_or_skip() else {
            return;
        };
        let f16 = cubecl::ir::ElemType::Float(cubecl::ir::FloatKind::F16);
        if !dev.client().properties().supports_type(f16) {
            eprintln!("skipped: {} has no native f16", dev.context().describe());
            return;
        }
        // Output rows 1..3 of the second image, stride 2 and padding 1: a 7×6 input gives 4×3 outputs.
        let x = up(&dev, &randn(&[2, 3, 7, 6]));
        let window = ConvWindow {
            kh: 3,
            kw: 3,
            stride: 2,
            padding: 1,
            n0: 1,
            images: 1,
            oy0: 1,
            rows: 2,
            ow: 3,
        };
        let (full, half) = (
            im2col(&x, &window, false).unwrap(),
            im2col(&x, &window, true).unwrap(),
        );
        assert!(half.is_f16() && !full.is_f16());
        assert_eq!(half.dims(), [1, 27, 6]);
        let values = |t: Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let want = full
            .to_cpu()
            .unwrap()
            .to_dtype(candle_core::DType::F16)
            .unwrap()
            .to_dtype(candle_core::DType::F32)
            .unwrap();
        assert_eq!(values(half.to_cpu().unwrap()), values(want));
    }

    #[test]
    fn im2col_strides_past_a_small_grid() {
        let Some(dev) = device_or_skip() else {
            return;
        };
        // Images 1..3 of three, 2 channels, 3×3 taps: 360 output pixels (two cubes of 256) in the first
        // window, 5×4 from rows 1.. at stride 2 in the second. Grids of 1 and 2 cubes per dimension make
        // units walk several pixels, channels and images.
        let (cin, h, w) = (2, 20, 18);
        let cpu = randn(&[3, cin, h, w]);
        let x = up(&dev, &cpu);
        let values = cpu.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        for (stride, padding, oy0, rows, ow) in [(1, 1, 0, 20, 18), (2, 1, 1, 5, 4)] {
            let window = ConvWindow {
                kh: 3,
                kw: 3,
                stride,
                padding,
                n0: 1,
                images: 2,
                oy0,
                rows,
                ow,
            };
            // The columns by their definition: image n0 + i, channel c, tap (ky, kx), output pixel p.
            let mut want = Vec::new();
            for image in 1..3 {
                for r in 0..cin * 9 {
                    let (c, ky, kx) = (r / 9, r / 3 % 3, r % 3);
                    for p in 0..rows * ow {
                        let y = ((oy0 + p / ow) * stride + ky) as isize - padding as isize;
                        let x = (p % ow * stride + kx) as isize - padding as isize;
                        let inside = (0..h as isize).contains(&y) && (0..w as isize).contains(&x);
                        want.push(if inside {
                            values[((image * cin + c) * h + y as usize) * w + x as usize]
                        } else {
                            0.0
                        });
                    }
                }
            }
            // Every result stays alive, so no run can land in a buffer an earlier one filled.
            let mut kept = Vec::new();
            for limit in [1, 2, GRID_LIMIT] {
                let got = im2col_on_grid(&x, &window, false, limit).unwrap();
                assert_eq!(got.dims(), [2, cin * 9, rows * ow]);
                let got_values = got.to_cpu().unwrap().flatten_all().unwrap();
                let got_values = got_values.to_vec1::<f32>().unwrap();
                assert!(got_values == want, "stride {stride}, grid limit {limit}");
                kept.push(got);
            }
        }
    }

    #[test]
    fn conv2d_matches_cpu() {
        let Some(dev) = device_or_skip() else {
            return;
        };
        on_both_engines(|| conv2d_matches_cpu_on(&dev, &[ConvPath::Im2col, ConvPath::Direct]));
    }

    /// The direct kernel alone (no product, no workgroup memory: it runs on Mesa 25's SPIR-V path too).
    #[test]
    fn direct_conv2d_matches_cpu() {
        let Some(dev) = device_or_skip() else {
            return;
        };
        conv2d_matches_cpu_on(&dev, &[ConvPath::Direct]);
    }

    /// Without a forced path a convolution takes the tuner's: the first call (the tuning round's output plus
    /// the addend in a pass of its own) and the next (the settled path, the addend fused where that is
    /// im2col) both agree with the CPU, and the problem is among the settled ones after the first.
    #[test]
    fn tuned_conv2d_matches_cpu() {
        let Some(dev) = device_or_skip() else {
            return;
        };
        if let Some(path) = forced_conv_path() {
            eprintln!("skipped: VCEDIT_GPU_CONV forces {path}");
            return;
        }
        // A shape no other test takes, so that this test's first call is the one that settles it.
        let (n, cin, cout, h, w) = (2, 12, 20, 11, 13);
        let x = randn(&[n, cin, h, w]);
        let weight = randn(&[cout, cin, 3, 3]);
        let bias = randn(&[cout]);
        let residual = randn(&[n, cout, h, w]);
        let plain = crate::kernels::conv2d(&x, &weight.clone().into(), Some(&bias), 1, 1).unwrap();
        let want = (&plain + &residual).unwrap();
        let (gx, gw, gb, gr) = (
            up(&dev, &x),
            up(&dev, &weight),
            up(&dev, &bias),
            up(&dev, &residual),
        );
        let described = "x 2x12x11x13 w 20x12x3x3 s1 p1 +bias";
        for call in ["first", "second"] {
            let got = conv2d(&gx, &gw, Some(&gb), 1, 1, Addend::Residual(&gr)).unwrap();
            check(&format!("tuned conv2d, {call} call"), &got, &want);
            let settled = tuned_conv_paths();
            assert!(
                settled.iter().any(|(key, _)| key.starts_with(described)),
                "{described} not among the settled problems {settled:?}"
            );
        }
    }

    /// Convolutions on each of `paths` against the CPU's; im2col's blocks too where `paths` has it.
    /// Pointwise convolutions are products on every path, so they are left out where im2col is.
    fn conv2d_matches_cpu_on(dev: &GpuDevice, paths: &[ConvPath]) {
        let dev = dev.clone();
        let im2col = paths.contains(&ConvPath::Im2col);
        // (batch, cin, cout, h, w, kernel, stride, padding, bias)
        for (n, cin, cout, h, w, k, stride, padding, with_bias) in [
            (1, 3, 5, 9, 7, 3, 1, 1, true),
            (2, 4, 6, 9, 8, 3, 2, 1, false),
            (2, 5, 3, 6, 6, 1, 1, 0, true),
            (1, 2, 4, 5, 7, 3, 2, 0, true),
            // Output channels and rows past the small cases' (the product's tiles and im2col's bands).
            (2, 3, 11, 12, 10, 3, 1, 1, true),
            // Channels the direct kernel reads and writes as vectors of four (above: one at a time).
            (2, 8, 12, 7, 9, 3, 1, 1, true),
            (1, 8, 8, 9, 9, 3, 2, 1, false),
        ] {
            if k == 1 && !im2col {
                continue;
            }
            let x = randn(&[n, cin, h, w]);
            let weight = randn(&[cout, cin, k, k]);
            let bias = with_bias.then(|| randn(&[cout]));
            let plain =
                crate::kernels::conv2d(&x, &weight.clone().into(), bias.as_ref(), stride, padding)
                    .unwrap();
            let gbias = bias.as_ref().map(|b| up(&dev, b));
            let (oh, ow) = (plain.dims()[2], plain.dims()[3]);
            // What the convolution adds in its finishing pass: nothing, a skip connection, a time embedding.
            let residual = randn(&[n, cout, oh, ow]);
            let per_channel = randn(&[n, cout]);
            let (g_residual, g_per_channel) = (up(&dev, &residual), up(&dev, &per_channel));
            let addends = [
                ("", Addend::None, plain.clone()),
                (
                    " + residual",
                    Addend::Residual(&g_residual),
                    (&plain + &residual).unwrap(),
                ),
                (
                    " + per channel",
                    Addend::PerChannel(&g_per_channel),
                    plain
                        .broadcast_add(&per_channel.reshape((n, cout, 1, 1)).unwrap())
                        .unwrap(),
                ),
            ];
            let (gx, gw) = (up(&dev, &x), up(&dev, &weight));
            for (what, addend, want) in &addends {
                for &path in paths {
                    let got = with_conv_path(path, || {
                        conv2d(&gx, &gw, gbias.as_ref(), stride, padding, *addend)
                    })
                    .unwrap();
                    check(
                        &format!("conv2d ({path}) c{cin}→{cout} k{k} s{stride} p{padding}{what}"),
                        &got,
                        want,
                    );
                }
                if !im2col {
                    continue;
                }
                // Blocked: one image per block, then bands of one and of three output rows (the last band
                // shorter where the rows do not divide).
                let per_row = cin * k * k * ow * 4;
                for cap in [per_row * oh, per_row, 3 * per_row] {
                    let got =
                        conv2d_blocked(&gx, &gw, gbias.as_ref(), stride, padding, *addend, cap)
                            .unwrap();
                    check(
                        &format!("conv2d k{k} s{stride} p{padding}{what}, im2col cap {cap}"),
                        &got,
                        want,
                    );
                }
            }
        }
    }
}
