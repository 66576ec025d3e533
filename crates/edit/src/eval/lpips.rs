//! LPIPS (Zhang et al., 2018), VGG16 variant, as a training loss with an analytic gradient w.r.t. the image.
//!
//! Computes what `lpips.LPIPS(net='vgg', version='0.1')` of the `lpips` pip package computes:
//! the ScalingLayer (`(x - shift) / scale`), VGG16 `features` tapped after relu1_2, relu2_2, relu3_3, relu4_3
//! and relu5_3, unit-normalisation of every feature vector over channels (`f / (‖f‖ + 1e-10)`), the squared
//! difference of the two images' normalised features, the 1x1 `lin` layers (no bias; dropout is off in eval
//! mode), the spatial mean, and the sum over the five taps.
//!
//! The fitting loop compares a render against a fixed target image, so the target's normalised features are
//! computed once ([`Lpips::target`], cached per view by [`TargetCache`]) and only the render goes through the
//! network with its activations kept for the backward pass ([`Lpips::loss_and_grad`]).
//!
//! Why not candle's autograd: its conv2d backward always computes the kernel gradient too (unused here: the
//! network is frozen) and runs the input gradient through a direct transposed convolution, and its CPU
//! conv2d reaches 20-58 GFLOP/s on VGG shapes where a plain gemm reaches ~100 on the same machine. Here every
//! convolution, forward or backward, is one im2col + gemm over zero-padded HWC maps: the input gradient of a
//! 3x3/pad-1 convolution is itself a 3x3/pad-1 convolution with the kernel flipped and its channel axes
//! swapped. Candle only reads the weight files.
//!
//! ```ignore
//! let lpips = Lpips::load(dir)?;                    // once; InputRange::AsIs like the reference
//! let mut targets = TargetCache::new(2 << 30);      // clear() when a new round of edits replaces the targets
//! // per fitting step, with the render (H*W*3 in [0,1]) and the view's fixed target image:
//! let target = targets.get_or_compute(&lpips, view, &target_rgb, h, w)?;
//! let lp = lpips.loss_and_grad(&render.rgb, h, w, &target)?;
//! for (g, d) in rgb_grad.iter_mut().zip(&lp.grad) { *g += lambda_lpips * d; }
//! ```
//!
//! Memory: [`Lpips::loss_and_grad`] keeps all 13 ReLU outputs, about 1.1 KB per pixel with full-width VGG16
//! (~290 MB at 512x512); a target holds its five normalised taps, ~0.5 KB per pixel ([`Lpips::target_bytes`]).
//!
//! # Input range
//! The package's networks were calibrated on images in [-1, 1] (`forward(..., normalize=False)` expects that;
//! `normalize=True` maps [0, 1] to [-1, 1] first). VcEdit/GaussianEditor feed [0, 1] renders straight in
//! without rescaling (reference algorithm §1.3), so [`InputRange::AsIs`] is the default and reproduces the
//! reference; [`InputRange::UnitToSigned`] gives the package's calibrated metric for [0, 1] images.
//!
//! # Weights
//! A folder (`--lpips DIR`) with two safetensors files, made by `tools/convert_lpips_weights.py`:
//! - `vgg16.safetensors`: torchvision `vgg16` key names `features.{0,2,5,7,10,12,14,17,19,21,24,26,28}.{weight,bias}`;
//! - `lpips_vgg.safetensors`: `lin0.model.1.weight` ... `lin4.model.1.weight` (shape `[1, C, 1, 1]`), as in the
//!   package's `weights/v0.1/vgg.pth`.
//!
//! Only the VGG16 topology is fixed (13 3x3 convolutions in stages of 2, 2, 3, 3, 3 with 2x2 max-pools between
//! stages); channel widths are read from the tensors, so narrow test networks use the same code path.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use candle_core::{DType, Device, Tensor};
use rayon::prelude::*;

/// File with the VGG16 backbone inside an LPIPS weights folder.
pub const VGG_WEIGHTS_FILE: &str = "vgg16.safetensors";
/// File with the five `lin` layers inside an LPIPS weights folder.
pub const LIN_WEIGHTS_FILE: &str = "lpips_vgg.safetensors";
/// Output channels of the five VGG16 stages.
pub const VGG16_WIDTHS: [usize; 5] = [64, 128, 256, 512, 512];
/// Smallest image side: four 2x2 poolings must leave at least one pixel for relu5_3.
pub const MIN_SIDE: usize = 16;

const CONVS_PER_STAGE: [usize; 5] = [2, 2, 3, 3, 3];
/// Index of each conv layer inside torchvision's `vgg16().features`.
const TORCHVISION_CONV_INDEX: [usize; 13] = [0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28];
/// lpips ScalingLayer constants (ImageNet mean/std expressed for inputs in [-1, 1]).
const SHIFT: [f32; 3] = [-0.030, -0.088, -0.188];
const SCALE: [f32; 3] = [0.458, 0.448, 0.450];
/// `lpips.normalize_tensor` adds this to the feature norm.
const NORM_EPS: f32 = 1e-10;
/// Output pixels per gemm tile: large enough for gemm efficiency, small enough to keep the im2col buffer in L2.
const TILE_PIXELS: usize = 256;

/// Errors from loading LPIPS weights or from bad inputs. Every message names the folder or the problem.
#[derive(Debug, thiserror::Error)]
pub enum LpipsError {
    #[error(
        "LPIPS weights folder {}: missing {} (make it with tools/convert_lpips_weights.py)",
        .dir.display(), .missing.join(", ")
    )]
    MissingFiles { dir: PathBuf, missing: Vec<String> },
    #[error("{}: cannot read safetensors: {cause}", .path.display())]
    Read {
        path: PathBuf,
        #[source]
        cause: candle_core::Error,
    },
    #[error("LPIPS weights {origin} are unusable: {}", .problems.join("; "))]
    BadWeights {
        origin: String,
        problems: Vec<String>,
    },
    #[error("LPIPS input: {0}")]
    BadInput(String),
}

/// How image values are mapped before the ScalingLayer.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum InputRange {
    /// Values go in unchanged (the package's `normalize=False`). With [0, 1] renders this is what the
    /// VcEdit reference does, hence the editor's default.
    #[default]
    AsIs,
    /// [0, 1] values are mapped to [-1, 1] first (the package's `normalize=True`).
    UnitToSigned,
}

impl InputRange {
    /// (multiplier, offset) applied before the ScalingLayer; torch computes `2 * x - 1` in this order.
    fn affine(self) -> (f32, f32) {
        match self {
            InputRange::AsIs => (1.0, 0.0),
            InputRange::UnitToSigned => (2.0, -1.0),
        }
    }
}

/// A feature map in HWC order with a one-pixel zero border, so 3x3/pad-1 convolutions need no bounds checks.
struct Map {
    h: usize,
    w: usize,
    c: usize,
    data: Vec<f32>,
}

impl Map {
    fn zeros(h: usize, w: usize, c: usize) -> Map {
        Map {
            h,
            w,
            c,
            data: vec![0.0; (h + 2) * (w + 2) * c],
        }
    }

    /// Stands in for an activation that is no longer needed.
    fn empty() -> Map {
        Map {
            h: 0,
            w: 0,
            c: 0,
            data: Vec::new(),
        }
    }

    fn row_stride(&self) -> usize {
        (self.w + 2) * self.c
    }

    /// Offset of interior pixel (y, x).
    fn at(&self, y: usize, x: usize) -> usize {
        ((y + 1) * (self.w + 2) + x + 1) * self.c
    }

    /// Interior pixel (y, x) as a channel slice.
    fn pixel(&self, y: usize, x: usize) -> &[f32] {
        let o = self.at(y, x);
        &self.data[o..o + self.c]
    }

    /// The padded rows 1..=h (interior rows with their zero border columns), for splitting across threads.
    fn interior_rows_mut(&mut self) -> &mut [f32] {
        let stride = self.row_stride();
        &mut self.data[stride..(self.h + 1) * stride]
    }
}

/// One 3x3/pad-1 convolution with its kernel laid out for the forward and the input-gradient gemm.
struct Conv3x3 {
    c_in: usize,
    c_out: usize,
    /// `[(tap * c_in + i) * c_out + o] = W[o][i][kh][kw]`, tap = kh * 3 + kw.
    forward: Vec<f32>,
    /// `[(tap * c_out + o) * c_in + i] = W[o][i][2 - kh][2 - kw]`: flipped, channel axes swapped.
    backward: Vec<f32>,
    bias: Vec<f32>,
}

impl Conv3x3 {
    /// From torch's `[c_out, c_in, 3, 3]` weight.
    fn new(c_out: usize, c_in: usize, weight: &[f32], bias: Vec<f32>) -> Conv3x3 {
        let mut forward = vec![0.0; 9 * c_in * c_out];
        let mut backward = vec![0.0; 9 * c_in * c_out];
        for o in 0..c_out {
            for i in 0..c_in {
                for tap in 0..9 {
                    let value = weight[(o * c_in + i) * 9 + tap];
                    forward[(tap * c_in + i) * c_out + o] = value;
                    backward[((8 - tap) * c_out + o) * c_in + i] = value;
                }
            }
        }
        Conv3x3 {
            c_in,
            c_out,
            forward,
            backward,
            bias,
        }
    }
}

/// What a convolution does with each gemm result before storing it.
#[derive(Clone, Copy)]
enum Epilogue<'a> {
    /// Forward layer: `max(x + bias, 0)`.
    BiasRelu(&'a [f32]),
    /// Input gradient of a layer whose input was a ReLU output: zero where that output was zero.
    ReluMask(&'a Map),
    /// Input gradient of a layer whose input was not a ReLU output (image, pooled map).
    Plain,
}

/// Rows per tile so that a tile has about [`TILE_PIXELS`] pixels but the map still splits into several tiles.
fn band_rows(h: usize, w: usize) -> usize {
    (TILE_PIXELS / w.max(1)).clamp(1, h.div_ceil(4).max(1))
}

/// 3x3 convolution, stride 1, zero padding 1, via im2col + gemm per band of output rows.
/// `kernel` is `[9 * input.c, c_out]` row-major (a [`Conv3x3`] layout).
fn conv3x3(input: &Map, kernel: &[f32], c_out: usize, epilogue: Epilogue<'_>) -> Map {
    let (h, w, c_in) = (input.h, input.w, input.c);
    let k = 9 * c_in;
    debug_assert_eq!(kernel.len(), k * c_out);
    let mut out = Map::zeros(h, w, c_out);
    let in_stride = input.row_stride();
    let out_stride = out.row_stride();
    let band = band_rows(h, w);
    out.interior_rows_mut()
        .par_chunks_mut(band * out_stride)
        .enumerate()
        .for_each_init(
            || (Vec::new(), Vec::new()),
            |(col, product): &mut (Vec<f32>, Vec<f32>), (b, rows)| {
                let y0 = b * band;
                let n_rows = rows.len() / out_stride;
                let m = n_rows * w;
                col.resize(m * k, 0.0);
                product.resize(m * c_out, 0.0);
                // im2col: the three taps of one kernel row are adjacent in the padded input.
                for r in 0..n_rows {
                    for x in 0..w {
                        let dst = &mut col[(r * w + x) * k..(r * w + x + 1) * k];
                        for kh in 0..3 {
                            let src = (y0 + r + kh) * in_stride + x * c_in;
                            dst[kh * 3 * c_in..(kh + 1) * 3 * c_in]
                                .copy_from_slice(&input.data[src..src + 3 * c_in]);
                        }
                    }
                }
                // SAFETY: `col` is m x k, `kernel` k x c_out and `product` m x c_out, all row-major and
                // contiguous with exactly those lengths; the buffers do not overlap.
                unsafe {
                    gemm::gemm(
                        m,
                        c_out,
                        k,
                        product.as_mut_ptr(),
                        1,
                        c_out as isize,
                        false,
                        col.as_ptr(),
                        1,
                        k as isize,
                        kernel.as_ptr(),
                        1,
                        c_out as isize,
                        0.0,
                        1.0,
                        false,
                        false,
                        false,
                        gemm::Parallelism::None,
                    );
                }
                for r in 0..n_rows {
                    for x in 0..w {
                        let start = r * out_stride + (x + 1) * c_out;
                        let dst = &mut rows[start..start + c_out];
                        let src = &product[(r * w + x) * c_out..(r * w + x + 1) * c_out];
                        match epilogue {
                            Epilogue::BiasRelu(bias) => {
                                for ((d, s), b) in dst.iter_mut().zip(src).zip(bias) {
                                    *d = (s + b).max(0.0);
                                }
                            }
                            Epilogue::ReluMask(act) => {
                                let a = act.pixel(y0 + r, x);
                                for ((d, s), a) in dst.iter_mut().zip(src).zip(a) {
                                    *d = if *a > 0.0 { *s } else { 0.0 };
                                }
                            }
                            Epilogue::Plain => dst.copy_from_slice(src),
                        }
                    }
                }
            },
        );
    out
}

/// Index (0..4, row-major in the 2x2 window) of the first maximum, as torch's max_pool2d picks it.
fn window_argmax(values: [f32; 4]) -> usize {
    let mut best = 0;
    for i in 1..4 {
        if values[i] > values[best] {
            best = i;
        }
    }
    best
}

/// 2x2 max-pool, stride 2, floor mode (odd trailing rows/columns are dropped, as in torch).
fn max_pool(input: &Map) -> Map {
    let (h, w, c) = (input.h / 2, input.w / 2, input.c);
    let mut out = Map::zeros(h, w, c);
    let stride = out.row_stride();
    out.interior_rows_mut()
        .par_chunks_mut(stride)
        .enumerate()
        .for_each(|(y, row)| {
            for x in 0..w {
                let p00 = input.pixel(2 * y, 2 * x);
                let p01 = input.pixel(2 * y, 2 * x + 1);
                let p10 = input.pixel(2 * y + 1, 2 * x);
                let p11 = input.pixel(2 * y + 1, 2 * x + 1);
                let dst = &mut row[(x + 1) * c..(x + 2) * c];
                for ch in 0..c {
                    dst[ch] = p00[ch].max(p01[ch]).max(p10[ch]).max(p11[ch]);
                }
            }
        });
    out
}

/// Routes each pooled gradient to the window's maximum in `input` (the pool's forward input).
fn max_pool_backward(grad: &Map, input: &Map) -> Map {
    let c = input.c;
    let mut out = Map::zeros(input.h, input.w, c);
    let stride = out.row_stride();
    out.interior_rows_mut()
        .par_chunks_mut(2 * stride)
        .enumerate()
        .filter(|(y, _)| *y < grad.h)
        .for_each(|(y, rows)| {
            for x in 0..grad.w {
                let g = grad.pixel(y, x);
                let p00 = input.pixel(2 * y, 2 * x);
                let p01 = input.pixel(2 * y, 2 * x + 1);
                let p10 = input.pixel(2 * y + 1, 2 * x);
                let p11 = input.pixel(2 * y + 1, 2 * x + 1);
                for ch in 0..c {
                    let best = window_argmax([p00[ch], p01[ch], p10[ch], p11[ch]]);
                    let (dy, dx) = (best / 2, best % 2);
                    rows[dy * stride + (2 * x + dx + 1) * c + ch] = g[ch];
                }
            }
        });
    out
}

/// Norm of a feature vector and the divisor `lpips.normalize_tensor` uses (f32, as torch computes it).
fn feature_norm(f: &[f32]) -> (f32, f32) {
    let sum: f64 = f.iter().map(|&v| f64::from(v) * f64::from(v)).sum();
    let norm = sum.sqrt() as f32;
    (norm, norm + NORM_EPS)
}

/// Normalised features of a tap, compact HWC (no border).
fn normalized(act: &Map) -> Vec<f32> {
    let (h, w, c) = (act.h, act.w, act.c);
    let mut out = vec![0.0; h * w * c];
    out.par_chunks_mut(w * c).enumerate().for_each(|(y, row)| {
        for x in 0..w {
            let f = act.pixel(y, x);
            let (_, denom) = feature_norm(f);
            for (d, v) in row[x * c..(x + 1) * c].iter_mut().zip(f) {
                *d = v / denom;
            }
        }
    });
    out
}

/// This tap's LPIPS term: the spatial mean of `sum_c lin_c * (n_c - t_c)^2`.
fn tap_value(act: &Map, target: &[f32], lin: &[f32]) -> f64 {
    let (h, w, c) = (act.h, act.w, act.c);
    let sum: f64 = (0..h)
        .into_par_iter()
        .map(|y| {
            let mut row_sum = 0.0f64;
            for x in 0..w {
                let f = act.pixel(y, x);
                let t = &target[(y * w + x) * c..(y * w + x + 1) * c];
                let (_, denom) = feature_norm(f);
                let mut s = 0.0f64;
                for ((v, t), l) in f.iter().zip(t).zip(lin) {
                    let d = v / denom - t;
                    s += f64::from(l * d * d);
                }
                row_sum += s;
            }
            row_sum
        })
        .sum();
    sum / (h * w) as f64
}

/// This tap's LPIPS term and the gradient w.r.t. the tap's ReLU *pre-activation*: the tap's own gradient
/// plus `upstream` (the gradient arriving through the next stage's pooling), masked by the ReLU.
fn tap_backward(act: &Map, target: &[f32], lin: &[f32], upstream: Option<&Map>) -> (f64, Map) {
    let (h, w, c) = (act.h, act.w, act.c);
    let inv_area = 1.0 / (h * w) as f32;
    let mut grad = Map::zeros(h, w, c);
    let stride = grad.row_stride();
    let sum: f64 = grad
        .interior_rows_mut()
        .par_chunks_mut(stride)
        .enumerate()
        .map_init(
            || vec![0.0f32; c],
            |grad_n, (y, row)| {
                let mut row_sum = 0.0f64;
                for x in 0..w {
                    let f = act.pixel(y, x);
                    let t = &target[(y * w + x) * c..(y * w + x + 1) * c];
                    let (norm, denom) = feature_norm(f);
                    // d value / d n_c = 2 lin_c (n_c - t_c) / area; then through n = f / (|f| + eps):
                    // d/df_k = g_k / denom - f_k (g . f) / (|f| denom^2).
                    let mut value = 0.0f64;
                    let mut g_dot_f = 0.0f64;
                    for ch in 0..c {
                        let d = f[ch] / denom - t[ch];
                        value += f64::from(lin[ch] * d * d);
                        grad_n[ch] = 2.0 * lin[ch] * d * inv_area;
                        g_dot_f += f64::from(grad_n[ch]) * f64::from(f[ch]);
                    }
                    row_sum += value;
                    // An all-zero feature vector has a zero ReLU mask everywhere; skipping it avoids 0/0.
                    let radial = if norm > 0.0 {
                        (g_dot_f / (f64::from(norm) * f64::from(denom) * f64::from(denom))) as f32
                    } else {
                        0.0
                    };
                    let up = upstream.map(|u| u.pixel(y, x));
                    let dst = &mut row[(x + 1) * c..(x + 2) * c];
                    for ch in 0..c {
                        if f[ch] > 0.0 {
                            let from_pool = up.map_or(0.0, |u| u[ch]);
                            dst[ch] = from_pool + grad_n[ch] / denom - f[ch] * radial;
                        }
                    }
                }
                row_sum
            },
        )
        .sum();
    (sum / (h * w) as f64, grad)
}

/// Normalised features of a target image, computed once and compared against many renders.
pub struct LpipsTarget {
    height: usize,
    width: usize,
    range: InputRange,
    network: u64,
    features: Vec<Vec<f32>>,
}

impl LpipsTarget {
    pub fn height(&self) -> usize {
        self.height
    }

    pub fn width(&self) -> usize {
        self.width
    }

    /// Memory held by the features.
    pub fn bytes(&self) -> usize {
        self.features.iter().map(|f| f.len() * 4).sum()
    }
}

/// LPIPS value of a render against a target, per tap, and its gradient w.r.t. the render.
#[derive(Debug, Clone)]
pub struct LpipsLoss {
    pub value: f32,
    /// Terms of relu1_2 ... relu5_3; `value` is their sum.
    pub per_layer: [f32; 5],
    /// d value / d render, H*W*3 interleaved like the render.
    pub grad: Vec<f32>,
}

/// The LPIPS-VGG network with frozen weights.
pub struct Lpips {
    convs: Vec<Conv3x3>,
    lins: Vec<Vec<f32>>,
    range: InputRange,
    /// Distinguishes networks so a [`LpipsTarget`] is never used with one it was not made by.
    id: u64,
}

static NEXT_NETWORK_ID: AtomicU64 = AtomicU64::new(1);

/// Index of the last conv of each stage (its ReLU output is the tap).
fn tap_convs() -> [usize; 5] {
    let mut taps = [0; 5];
    let mut end = 0;
    for (s, n) in CONVS_PER_STAGE.iter().enumerate() {
        end += n;
        taps[s] = end - 1;
    }
    taps
}

/// Tensor as f32 values, or a problem description.
fn tensor_values(t: &Tensor) -> Result<Vec<f32>, String> {
    if !t.dtype().is_float() {
        return Err(format!("has dtype {:?}, expected a float type", t.dtype()));
    }
    let values = t
        .to_dtype(DType::F32)
        .and_then(|t| t.flatten_all())
        .and_then(|t| t.to_vec1::<f32>())
        .map_err(|e| e.to_string())?;
    if values.iter().any(|v| !v.is_finite()) {
        return Err("contains NaN or infinite values".into());
    }
    Ok(values)
}

impl Lpips {
    /// Loads `vgg16.safetensors` and `lpips_vgg.safetensors` from `dir`.
    pub fn load(dir: &Path) -> Result<Lpips, LpipsError> {
        let files = [VGG_WEIGHTS_FILE, LIN_WEIGHTS_FILE];
        let missing: Vec<String> = files
            .iter()
            .filter(|f| !dir.join(f).is_file())
            .map(|f| f.to_string())
            .collect();
        if !missing.is_empty() {
            return Err(LpipsError::MissingFiles {
                dir: dir.to_path_buf(),
                missing,
            });
        }
        let read = |file: &str| {
            let path = dir.join(file);
            candle_core::safetensors::load(&path, &Device::Cpu)
                .map_err(|cause| LpipsError::Read { path, cause })
        };
        let vgg = read(VGG_WEIGHTS_FILE)?;
        let lin = read(LIN_WEIGHTS_FILE)?;
        Self::build(
            &vgg,
            &lin,
            &format!("in {}", dir.display()),
            [VGG_WEIGHTS_FILE, LIN_WEIGHTS_FILE],
        )
    }

    /// From tensors keyed as in the two weight files (see the module docs).
    pub fn from_tensors(
        vgg: &HashMap<String, Tensor>,
        lin: &HashMap<String, Tensor>,
    ) -> Result<Lpips, LpipsError> {
        Self::build(
            vgg,
            lin,
            "(in-memory tensors)",
            ["VGG tensors", "lin tensors"],
        )
    }

    fn build(
        vgg: &HashMap<String, Tensor>,
        lin: &HashMap<String, Tensor>,
        origin: &str,
        labels: [&str; 2],
    ) -> Result<Lpips, LpipsError> {
        let mut problems = Vec::new();
        let mut convs = Vec::new();
        // Input channels of the next conv: 3 (RGB) at the start; unknown after a broken layer.
        let mut expected_in = Some(3usize);
        // Output channels of each conv as far as its weight shape tells, for checking the lin layers.
        let mut out_widths: Vec<Option<usize>> = Vec::new();
        for index in TORCHVISION_CONV_INDEX {
            let weight_key = format!("features.{index}.weight");
            let bias_key = format!("features.{index}.bias");
            let (weight, bias) = (vgg.get(&weight_key), vgg.get(&bias_key));
            for (key, t) in [(&weight_key, weight), (&bias_key, bias)] {
                if t.is_none() {
                    problems.push(format!("{} lacks {key}", labels[0]));
                }
            }
            let shape = match weight.map(|w| w.dims()) {
                Some(&[c_out, c_in, 3, 3]) if c_out > 0 && c_in > 0 => Some((c_out, c_in)),
                Some(dims) => {
                    problems.push(format!(
                        "{} {weight_key} has shape {dims:?}, expected [c_out, c_in, 3, 3]",
                        labels[0]
                    ));
                    None
                }
                None => None,
            };
            out_widths.push(shape.map(|(c_out, _)| c_out));
            let Some((c_out, c_in)) = shape else {
                expected_in = None;
                continue;
            };
            expected_in = match expected_in {
                Some(e) if e != c_in => {
                    problems.push(format!(
                        "{} {weight_key} takes {c_in} input channels, the previous layer gives {e}",
                        labels[0]
                    ));
                    None
                }
                _ => Some(c_out),
            };
            let (Some(weight), Some(bias)) = (weight, bias) else {
                continue;
            };
            if bias.dims() != [c_out] {
                problems.push(format!(
                    "{} {bias_key} has shape {:?}, expected [{c_out}]",
                    labels[0],
                    bias.dims()
                ));
                continue;
            }
            match (tensor_values(weight), tensor_values(bias)) {
                (Ok(w), Ok(b)) => convs.push(Conv3x3::new(c_out, c_in, &w, b)),
                (w, b) => {
                    for (key, r) in [(&weight_key, w.err()), (&bias_key, b.err())] {
                        if let Some(e) = r {
                            problems.push(format!("{} {key} {e}", labels[0]));
                        }
                    }
                }
            }
        }
        let mut lins = Vec::new();
        for (s, &tap) in tap_convs().iter().enumerate() {
            let key = format!("lin{s}.model.1.weight");
            let Some(t) = lin.get(&key) else {
                problems.push(format!("{} lacks {key}", labels[1]));
                continue;
            };
            let width = out_widths[tap];
            let dims = t.dims();
            let ok_shape = dims.iter().filter(|&&d| d != 1).count() <= 1
                && width.is_none_or(|c| t.elem_count() == c);
            if !ok_shape {
                let expected = width.map_or("C".to_string(), |c| c.to_string());
                problems.push(format!(
                    "{} {key} has shape {dims:?}, expected [1, {expected}, 1, 1]",
                    labels[1]
                ));
                continue;
            }
            match tensor_values(t) {
                Ok(v) => lins.push(v),
                Err(e) => problems.push(format!("{} {key} {e}", labels[1])),
            }
        }
        if !problems.is_empty() {
            return Err(LpipsError::BadWeights {
                origin: origin.to_string(),
                problems,
            });
        }
        Ok(Lpips {
            convs,
            lins,
            range: InputRange::default(),
            id: NEXT_NETWORK_ID.fetch_add(1, Ordering::Relaxed),
        })
    }

    /// Deterministic pseudo-random weights of the VGG16 topology with the given stage widths, for benchmarks
    /// and tests (`tools/make_lpips_fixtures.py` mirrors the generator; see [`synthetic_tensors`]).
    pub fn synthetic(widths: [usize; 5], seed: u64) -> Lpips {
        let (vgg, lin) = synthetic_tensors(widths, seed);
        Self::from_tensors(&vgg, &lin).expect("synthetic tensors have the VGG16 layout")
    }

    /// Sets how image values are mapped before the ScalingLayer. Targets must be made again afterwards.
    pub fn with_input_range(mut self, range: InputRange) -> Lpips {
        self.range = range;
        self.id = NEXT_NETWORK_ID.fetch_add(1, Ordering::Relaxed);
        self
    }

    pub fn input_range(&self) -> InputRange {
        self.range
    }

    /// Output channels of the five stages, as read from the weights.
    pub fn widths(&self) -> [usize; 5] {
        tap_convs().map(|i| self.convs[i].c_out)
    }

    /// Bytes a [`LpipsTarget`] of an h x w image takes.
    pub fn target_bytes(&self, height: usize, width: usize) -> usize {
        let (mut h, mut w) = (height, width);
        let mut total = 0;
        for (s, c) in self.widths().iter().enumerate() {
            if s > 0 {
                (h, w) = (h / 2, w / 2);
            }
            total += h * w * c * 4;
        }
        total
    }

    fn check_image(&self, image: &[f32], height: usize, width: usize) -> Result<(), LpipsError> {
        if height < MIN_SIDE || width < MIN_SIDE {
            return Err(LpipsError::BadInput(format!(
                "image is {width}x{height}, LPIPS-VGG needs at least {MIN_SIDE}x{MIN_SIDE}"
            )));
        }
        if image.len() != height * width * 3 {
            return Err(LpipsError::BadInput(format!(
                "image has {} values, expected {width}x{height}x3 = {}",
                image.len(),
                height * width * 3
            )));
        }
        if let Some(i) = image.iter().position(|v| !v.is_finite()) {
            return Err(LpipsError::BadInput(format!(
                "image value {i} (pixel {}, channel {}) is {}",
                i / 3,
                i % 3,
                image[i]
            )));
        }
        Ok(())
    }

    /// Interleaved image -> ScalingLayer output as a padded map.
    fn scaled_input(&self, image: &[f32], height: usize, width: usize) -> Map {
        let (mul, add) = self.range.affine();
        let mut map = Map::zeros(height, width, 3);
        let stride = map.row_stride();
        map.interior_rows_mut()
            .par_chunks_mut(stride)
            .enumerate()
            .for_each(|(y, row)| {
                let src = &image[y * width * 3..(y + 1) * width * 3];
                for (i, v) in src.iter().enumerate() {
                    let ch = i % 3;
                    row[3 + i] = (v * mul + add - SHIFT[ch]) / SCALE[ch];
                }
            });
        map
    }

    /// ReLU outputs of all 13 convs; with `keep_all` false only the five taps are kept.
    fn forward(&self, input: Map, keep_all: bool) -> Vec<Map> {
        let mut acts: Vec<Map> = Vec::with_capacity(self.convs.len());
        let mut stage_input = input;
        for (s, &n) in CONVS_PER_STAGE.iter().enumerate() {
            if s > 0 {
                stage_input = max_pool(acts.last().expect("a previous stage"));
            }
            for j in 0..n {
                let layer = &self.convs[acts.len()];
                let src = if j == 0 {
                    &stage_input
                } else {
                    acts.last().expect("a previous conv")
                };
                let out = conv3x3(
                    src,
                    &layer.forward,
                    layer.c_out,
                    Epilogue::BiasRelu(&layer.bias),
                );
                if !keep_all && j > 0 {
                    // Within a stage only the last output is a tap.
                    *acts.last_mut().expect("a previous conv") = Map::empty();
                }
                acts.push(out);
            }
        }
        acts
    }

    /// Normalised features of `image` (H*W*3 interleaved), to compare renders against.
    pub fn target(
        &self,
        image: &[f32],
        height: usize,
        width: usize,
    ) -> Result<LpipsTarget, LpipsError> {
        self.check_image(image, height, width)?;
        let acts = self.forward(self.scaled_input(image, height, width), false);
        let features = tap_convs().iter().map(|&i| normalized(&acts[i])).collect();
        Ok(LpipsTarget {
            height,
            width,
            range: self.range,
            network: self.id,
            features,
        })
    }

    fn check_target(
        &self,
        target: &LpipsTarget,
        height: usize,
        width: usize,
    ) -> Result<(), LpipsError> {
        if target.network != self.id || target.range != self.range {
            return Err(LpipsError::BadInput(
                "target features were made by another LPIPS network or input range".into(),
            ));
        }
        if (target.height, target.width) != (height, width) {
            return Err(LpipsError::BadInput(format!(
                "render is {width}x{height} but the target is {}x{}",
                target.width, target.height
            )));
        }
        Ok(())
    }

    /// LPIPS of `render` against a target, per tap, without the gradient.
    pub fn value(
        &self,
        render: &[f32],
        height: usize,
        width: usize,
        target: &LpipsTarget,
    ) -> Result<(f32, [f32; 5]), LpipsError> {
        self.check_image(render, height, width)?;
        self.check_target(target, height, width)?;
        let acts = self.forward(self.scaled_input(render, height, width), false);
        let mut per_layer = [0.0f32; 5];
        for (s, &tap) in tap_convs().iter().enumerate() {
            per_layer[s] = tap_value(&acts[tap], &target.features[s], &self.lins[s]) as f32;
        }
        Ok((per_layer.iter().sum(), per_layer))
    }

    /// LPIPS distance between two images (symmetric up to rounding).
    pub fn distance(
        &self,
        a: &[f32],
        b: &[f32],
        height: usize,
        width: usize,
    ) -> Result<f32, LpipsError> {
        let target = self.target(b, height, width)?;
        Ok(self.value(a, height, width, &target)?.0)
    }

    /// LPIPS of `render` against a target and its gradient w.r.t. `render`.
    pub fn loss_and_grad(
        &self,
        render: &[f32],
        height: usize,
        width: usize,
        target: &LpipsTarget,
    ) -> Result<LpipsLoss, LpipsError> {
        self.check_image(render, height, width)?;
        self.check_target(target, height, width)?;
        let mut acts = self.forward(self.scaled_input(render, height, width), true);
        let taps = tap_convs();
        let mut per_layer = [0.0f32; 5];
        // Gradient w.r.t. the input of stage s + 1 (a pooled map), carried down the stages.
        let mut upstream: Option<Map> = None;
        for s in (0..5).rev() {
            let tap = taps[s];
            let first = tap + 1 - CONVS_PER_STAGE[s];
            let pooled = upstream.take().map(|g| max_pool_backward(&g, &acts[tap]));
            let (value, mut grad) = tap_backward(
                &acts[tap],
                &target.features[s],
                &self.lins[s],
                pooled.as_ref(),
            );
            per_layer[s] = value as f32;
            for conv in (first..=tap).rev() {
                let layer = &self.convs[conv];
                let epilogue = if conv > first {
                    Epilogue::ReluMask(&acts[conv - 1])
                } else {
                    Epilogue::Plain
                };
                grad = conv3x3(&grad, &layer.backward, layer.c_in, epilogue);
            }
            acts.truncate(first);
            upstream = Some(grad);
        }
        let input_grad = upstream.expect("five stages ran");
        let (mul, _) = self.range.affine();
        let factor = SCALE.map(|s| mul / s);
        let mut grad = vec![0.0f32; height * width * 3];
        grad.par_chunks_mut(width * 3)
            .enumerate()
            .for_each(|(y, row)| {
                for x in 0..width {
                    let g = input_grad.pixel(y, x);
                    for ch in 0..3 {
                        row[x * 3 + ch] = g[ch] * factor[ch];
                    }
                }
            });
        Ok(LpipsLoss {
            value: per_layer.iter().sum(),
            per_layer,
            grad,
        })
    }
}

/// splitmix64: the mixing function behind [`synthetic_tensors`].
fn splitmix64(x: u64) -> u64 {
    let mut z = x.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Uniform [0, 1) value `i` of stream `stream`, exactly representable in f32 (24 bits).
fn synthetic_uniform(seed: u64, stream: u64, i: u64) -> f64 {
    let x = (seed << 40) | (stream << 32) | i;
    (splitmix64(x) >> 40) as f64 / (1u64 << 24) as f64
}

/// Deterministic weights with the VGG16 topology and the given stage widths, keyed like the weight files.
///
/// Value `i` of stream `s` is `u = (splitmix64(seed << 40 | s << 32 | i) >> 40) / 2^24`. Streams `2j` and
/// `2j + 1` are conv `j`'s weight `(2u - 1) * sqrt(6 / (9 c_in))` (He-uniform, so activations keep their
/// scale through 13 ReLU layers) and bias `(2u - 1) / 20`; stream `26 + s` is `lin{s}` = `u` (non-negative,
/// like the trained ones). Computed in f64, then rounded to f32.
pub fn synthetic_tensors(
    widths: [usize; 5],
    seed: u64,
) -> (HashMap<String, Tensor>, HashMap<String, Tensor>) {
    let values = |stream: u64, n: usize, f: &dyn Fn(f64) -> f64| -> Vec<f32> {
        (0..n as u64)
            .map(|i| f(synthetic_uniform(seed, stream, i)) as f32)
            .collect()
    };
    let tensor = |v: Vec<f32>, shape: &[usize]| {
        Tensor::from_vec(v, shape, &Device::Cpu).expect("length matches shape")
    };
    let mut vgg = HashMap::new();
    let mut c_in = 3;
    let mut conv = 0;
    for (s, &n) in CONVS_PER_STAGE.iter().enumerate() {
        let c_out = widths[s];
        for _ in 0..n {
            let index = TORCHVISION_CONV_INDEX[conv];
            let bound = (6.0 / (9 * c_in) as f64).sqrt();
            let w = values(2 * conv as u64, c_out * c_in * 9, &|u| {
                (2.0 * u - 1.0) * bound
            });
            let b = values(2 * conv as u64 + 1, c_out, &|u| (2.0 * u - 1.0) / 20.0);
            vgg.insert(
                format!("features.{index}.weight"),
                tensor(w, &[c_out, c_in, 3, 3]),
            );
            vgg.insert(format!("features.{index}.bias"), tensor(b, &[c_out]));
            c_in = c_out;
            conv += 1;
        }
    }
    let lin = (0..5)
        .map(|s| {
            let v = values(26 + s as u64, widths[s], &|u| u);
            (
                format!("lin{s}.model.1.weight"),
                tensor(v, &[1, widths[s], 1, 1]),
            )
        })
        .collect();
    (vgg, lin)
}

/// Target features per view, computed on first use and reused while the view's target image is unchanged
/// (checked by a fingerprint of the pixels, so an edited target is never compared against stale features).
///
/// Entries are added while they fit in the byte budget and are never evicted: the fitting loop visits views
/// in shuffled epochs, an access pattern for which least-recently-used eviction would drop every entry just
/// before its next use, while keeping a fixed subset gives a hit rate of (cached views / views).
pub struct TargetCache {
    budget: usize,
    used: usize,
    entries: HashMap<usize, (u64, Arc<LpipsTarget>)>,
}

/// FNV-1a over the pixel bits and the size: cheap next to a VGG forward pass.
fn fingerprint(image: &[f32], height: usize, width: usize) -> u64 {
    let mut h = 0xcbf2_9ce4_8422_2325u64;
    for v in [height as u32, width as u32]
        .into_iter()
        .chain(image.iter().map(|v| v.to_bits()))
    {
        h = (h ^ u64::from(v)).wrapping_mul(0x0000_0100_0000_01B3);
    }
    h
}

impl TargetCache {
    /// A cache holding at most `budget_bytes` of features (see [`Lpips::target_bytes`]).
    pub fn new(budget_bytes: usize) -> TargetCache {
        TargetCache {
            budget: budget_bytes,
            used: 0,
            entries: HashMap::new(),
        }
    }

    /// Features of `image` as the target of `view`, from the cache when the image is unchanged.
    pub fn get_or_compute(
        &mut self,
        lpips: &Lpips,
        view: usize,
        image: &[f32],
        height: usize,
        width: usize,
    ) -> Result<Arc<LpipsTarget>, LpipsError> {
        let key = fingerprint(image, height, width);
        if let Some((k, target)) = self.entries.get(&view) {
            if *k == key && target.network == lpips.id {
                return Ok(target.clone());
            }
        }
        if let Some((_, old)) = self.entries.remove(&view) {
            self.used -= old.bytes();
        }
        let target = Arc::new(lpips.target(image, height, width)?);
        if self.used + target.bytes() <= self.budget {
            self.used += target.bytes();
            self.entries.insert(view, (key, target.clone()));
        }
        Ok(target)
    }

    /// Forgets every view (e.g. when all targets are replaced by a new round of edits).
    pub fn clear(&mut self) {
        self.entries.clear();
        self.used = 0;
    }

    pub fn len(&self) -> usize {
        self.entries.len()
    }

    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// Bytes of features held.
    pub fn bytes(&self) -> usize {
        self.used
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn random_image(h: usize, w: usize, seed: u64) -> Vec<f32> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        (0..h * w * 3).map(|_| rng.gen::<f32>()).collect()
    }

    fn small() -> Lpips {
        Lpips::synthetic([4, 6, 8, 8, 10], 3)
    }

    /// Direct 3x3 convolution on unpadded CHW data, as a check of the im2col path.
    fn naive_conv(
        input: &[f32],
        h: usize,
        w: usize,
        c_in: usize,
        weight: &[f32],
        c_out: usize,
    ) -> Vec<f32> {
        let mut out = vec![0.0; c_out * h * w];
        for o in 0..c_out {
            for y in 0..h {
                for x in 0..w {
                    let mut s = 0.0f64;
                    for i in 0..c_in {
                        for kh in 0..3 {
                            for kw in 0..3 {
                                let (yy, xx) =
                                    (y as isize + kh as isize - 1, x as isize + kw as isize - 1);
                                if yy < 0 || xx < 0 || yy >= h as isize || xx >= w as isize {
                                    continue;
                                }
                                let v = input[(i * h + yy as usize) * w + xx as usize];
                                s += f64::from(v)
                                    * f64::from(weight[((o * c_in + i) * 3 + kh) * 3 + kw]);
                            }
                        }
                    }
                    out[(o * h + y) * w + x] = s as f32;
                }
            }
        }
        out
    }

    fn map_from_chw(chw: &[f32], h: usize, w: usize, c: usize) -> Map {
        let mut m = Map::zeros(h, w, c);
        for ch in 0..c {
            for y in 0..h {
                for x in 0..w {
                    let o = m.at(y, x) + ch;
                    m.data[o] = chw[(ch * h + y) * w + x];
                }
            }
        }
        m
    }

    #[test]
    fn conv_matches_direct_convolution_and_its_transpose() {
        let (h, w, c_in, c_out) = (7, 9, 3, 5);
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let x: Vec<f32> = (0..c_in * h * w).map(|_| rng.gen::<f32>() - 0.5).collect();
        let g: Vec<f32> = (0..c_out * h * w).map(|_| rng.gen::<f32>() - 0.5).collect();
        let weight: Vec<f32> = (0..c_out * c_in * 9)
            .map(|_| rng.gen::<f32>() - 0.5)
            .collect();
        let conv = Conv3x3::new(c_out, c_in, &weight, vec![0.0; c_out]);
        let expected = naive_conv(&x, h, w, c_in, &weight, c_out);
        let got = conv3x3(
            &map_from_chw(&x, h, w, c_in),
            &conv.forward,
            c_out,
            Epilogue::Plain,
        );
        for o in 0..c_out {
            for y in 0..h {
                for xx in 0..w {
                    let e = expected[(o * h + y) * w + xx];
                    assert!((got.pixel(y, xx)[o] - e).abs() < 1e-5);
                }
            }
        }
        // Adjoint identity <conv(x), g> = <x, conv_backward(g)> checks the flipped kernel.
        let back = conv3x3(
            &map_from_chw(&g, h, w, c_out),
            &conv.backward,
            c_in,
            Epilogue::Plain,
        );
        let lhs: f64 = expected.iter().zip(&g).map(|(a, b)| f64::from(a * b)).sum();
        let mut rhs = 0.0f64;
        for i in 0..c_in {
            for y in 0..h {
                for xx in 0..w {
                    rhs += f64::from(x[(i * h + y) * w + xx] * back.pixel(y, xx)[i]);
                }
            }
        }
        assert!(
            (lhs - rhs).abs() < 1e-4 * lhs.abs().max(1.0),
            "{lhs} vs {rhs}"
        );
    }

    #[test]
    fn max_pool_drops_odd_edges_and_routes_gradient_to_the_maximum() {
        let (h, w) = (5, 3);
        let mut input = Map::zeros(h, w, 1);
        for y in 0..h {
            for x in 0..w {
                let o = input.at(y, x);
                input.data[o] = ((y * 7 + x * 3) % 5) as f32;
            }
        }
        let pooled = max_pool(&input);
        assert_eq!((pooled.h, pooled.w), (2, 1));
        assert_eq!(pooled.pixel(0, 0)[0], 3.0); // max of 0, 3, 2, 0
        let mut grad = Map::zeros(2, 1, 1);
        let o = grad.at(0, 0);
        grad.data[o] = 1.5;
        let back = max_pool_backward(&grad, &input);
        assert_eq!(back.pixel(0, 1)[0], 1.5);
        let total: f32 = back.data.iter().sum();
        assert_eq!(total, 1.5);
    }

    #[test]
    fn gradient_matches_finite_differences() {
        let net = small().with_input_range(InputRange::UnitToSigned);
        let (h, w) = (20, 18);
        let render = random_image(h, w, 5);
        let target = net.target(&random_image(h, w, 6), h, w).unwrap();
        let loss = net.loss_and_grad(&render, h, w, &target).unwrap();
        let (value, _) = net.value(&render, h, w, &target).unwrap();
        assert!((loss.value - value).abs() <= 1e-6 * value.abs());
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        // Directional derivative along a random direction, central differences in f32. The step is small
        // because ReLU and max-pool kinks crossed within it bias the difference (1e-3 is already 3% off).
        let dir: Vec<f32> = (0..render.len()).map(|_| rng.gen::<f32>() - 0.5).collect();
        let eps = 1e-4f32;
        let shifted = |sign: f32| -> f64 {
            let img: Vec<f32> = render
                .iter()
                .zip(&dir)
                .map(|(r, d)| r + sign * eps * d)
                .collect();
            f64::from(net.value(&img, h, w, &target).unwrap().0)
        };
        let numeric = (shifted(1.0) - shifted(-1.0)) / (2.0 * f64::from(eps));
        let analytic: f64 = loss
            .grad
            .iter()
            .zip(&dir)
            .map(|(g, d)| f64::from(g * d))
            .sum();
        assert!(
            (numeric - analytic).abs() <= 1e-2 * analytic.abs().max(1e-3),
            "numeric {numeric} analytic {analytic}"
        );
    }

    #[test]
    fn identical_images_have_zero_distance_and_zero_gradient() {
        let net = small();
        let img = random_image(16, 24, 2);
        let target = net.target(&img, 16, 24).unwrap();
        let loss = net.loss_and_grad(&img, 16, 24, &target).unwrap();
        assert!(loss.value.abs() < 1e-10);
        assert!(loss.grad.iter().all(|g| g.abs() < 1e-10));
        assert!(
            net.distance(&img, &random_image(16, 24, 3), 16, 24)
                .unwrap()
                > 0.0
        );
    }

    #[test]
    fn bad_inputs_are_errors() {
        let net = small();
        let img = random_image(16, 16, 1);
        assert!(matches!(
            net.target(&img[..10], 16, 16),
            Err(LpipsError::BadInput(_))
        ));
        assert!(net.target(&random_image(8, 8, 1), 8, 8).is_err());
        let mut nan = img.clone();
        nan[5] = f32::NAN;
        let err = net.target(&nan, 16, 16).err().unwrap().to_string();
        assert!(err.contains("pixel 1, channel 2"), "{err}");
        let target = net.target(&img, 16, 16).unwrap();
        let other = small();
        assert!(other.loss_and_grad(&img, 16, 16, &target).is_err());
        let wide = random_image(16, 20, 1);
        assert!(net.loss_and_grad(&wide, 16, 20, &target).is_err());
    }

    #[test]
    fn loading_reports_every_missing_file_and_key() {
        let dir = tempfile::tempdir().unwrap();
        let err = Lpips::load(dir.path()).err().unwrap().to_string();
        assert!(
            err.contains(VGG_WEIGHTS_FILE) && err.contains(LIN_WEIGHTS_FILE),
            "{err}"
        );
        assert!(err.contains(&dir.path().display().to_string()));

        let (mut vgg, mut lin) = synthetic_tensors([4, 6, 8, 8, 10], 1);
        vgg.remove("features.12.bias");
        lin.remove("lin3.model.1.weight");
        lin.insert(
            "lin1.model.1.weight".into(),
            Tensor::zeros((1, 7, 1, 1), DType::F32, &Device::Cpu).unwrap(),
        );
        candle_core::safetensors::save(&vgg, dir.path().join(VGG_WEIGHTS_FILE)).unwrap();
        candle_core::safetensors::save(&lin, dir.path().join(LIN_WEIGHTS_FILE)).unwrap();
        let err = Lpips::load(dir.path()).err().unwrap().to_string();
        for part in [
            "features.12.bias",
            "lin3.model.1.weight",
            "lin1.model.1.weight",
        ] {
            assert!(err.contains(part), "{err}");
        }
        assert!(err.contains(&dir.path().display().to_string()));

        let (mut vgg, lin) = synthetic_tensors([4, 6, 8, 8, 10], 1);
        vgg.insert(
            "features.5.weight".into(),
            Tensor::zeros((6, 5, 3, 3), DType::F32, &Device::Cpu).unwrap(),
        );
        let err = Lpips::from_tensors(&vgg, &lin).err().unwrap().to_string();
        assert!(
            err.contains("features.5.weight takes 5 input channels"),
            "{err}"
        );
    }

    #[test]
    fn weights_round_trip_through_a_folder_and_widths_come_from_shapes() {
        let dir = tempfile::tempdir().unwrap();
        let (vgg, lin) = synthetic_tensors([4, 6, 8, 8, 10], 1);
        candle_core::safetensors::save(&vgg, dir.path().join(VGG_WEIGHTS_FILE)).unwrap();
        candle_core::safetensors::save(&lin, dir.path().join(LIN_WEIGHTS_FILE)).unwrap();
        let loaded = Lpips::load(dir.path()).unwrap();
        assert_eq!(loaded.widths(), [4, 6, 8, 8, 10]);
        let direct = Lpips::from_tensors(&vgg, &lin).unwrap();
        let (a, b) = (random_image(17, 19, 1), random_image(17, 19, 2));
        assert_eq!(
            loaded.distance(&a, &b, 17, 19).unwrap(),
            direct.distance(&a, &b, 17, 19).unwrap()
        );
    }

    #[test]
    fn cache_reuses_features_until_the_target_changes() {
        let net = small();
        let (h, w) = (16, 16);
        let per_view = net.target_bytes(h, w);
        let mut cache = TargetCache::new(2 * per_view);
        let img = random_image(h, w, 1);
        let first = cache.get_or_compute(&net, 0, &img, h, w).unwrap();
        let again = cache.get_or_compute(&net, 0, &img, h, w).unwrap();
        assert!(Arc::ptr_eq(&first, &again));
        assert_eq!(cache.bytes(), per_view);
        let edited = random_image(h, w, 2);
        let changed = cache.get_or_compute(&net, 0, &edited, h, w).unwrap();
        assert!(!Arc::ptr_eq(&first, &changed));
        assert_eq!(cache.len(), 1);
        cache.get_or_compute(&net, 1, &img, h, w).unwrap();
        // Over budget: computed but not kept.
        cache.get_or_compute(&net, 2, &img, h, w).unwrap();
        assert_eq!((cache.len(), cache.bytes()), (2, 2 * per_view));
        cache.clear();
        assert!(cache.is_empty());
    }
}
