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
//! The network runs on a [`Device`] (CPU or GPU) through [`DeviceTensor`], so a fit with LPIPS evaluates
//! the loss where it renders. The backward pass is written out rather than taken from candle's autograd:
//! the network is frozen, so only the gradient with respect to the image is needed (autograd would also
//! form every kernel gradient), and the GPU tensors have no autograd. The input gradient of a 3x3/pad-1
//! convolution is itself a 3x3/pad-1 convolution with the kernel flipped and its channel axes swapped
//! ([`Conv::adjoint`]), so forward and backward use the one convolution op of each backend (on the CPU
//! the im2col + GEMM kernel of `kernels::conv2d`); pooling, ReLU, normalisation and the distance have
//! their own ops (`kernels::vgg`).
//!
//! ```ignore
//! let lpips = Lpips::load(dir)?.on(device);          // once; InputRange::AsIs like the reference
//! let mut targets = TargetCache::new(2 << 30);      // clear() when a new round of edits replaces the targets
//! // per fitting step, with the render (H*W*3 in [0,1]) and the view's fixed target image:
//! let target = targets.get_or_compute(&lpips, view, &target_rgb, h, w)?;
//! let lp = lpips.loss_and_grad(&render.rgb, h, w, &target)?;
//! for (g, d) in rgb_grad.iter_mut().zip(&lp.grad) { *g += lambda_lpips * d; }
//! ```
//!
//! Memory: [`Lpips::loss_and_grad`] keeps all 13 ReLU outputs, about 1.1 KB per pixel with full-width VGG16
//! (~290 MB at 512x512; ~1.6 KB per pixel at its peak, [`Lpips::activation_bytes`]); a target holds its five
//! normalised taps, ~0.5 KB per pixel ([`Lpips::target_bytes`]), on the network's device.
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

use candle_core::{DType, Tensor};

use crate::device::{Device, DeviceTensor, GpuDevice, Precision};

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
    #[error("LPIPS on {device}: {cause}")]
    Compute {
        device: String,
        #[source]
        cause: candle_core::Error,
    },
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

/// One 3x3/pad-1 convolution of the VGG backbone.
struct Conv {
    c_out: usize,
    /// `[c_out, c_in, 3, 3]`.
    weight: Tensor,
    bias: Tensor,
    /// The kernel of the input gradient, `[c_in, c_out, 3, 3]` with `adjoint[i][o][kh][kw] =
    /// weight[o][i][2 - kh][2 - kw]`: convolving the output gradient with it (padding 1) gives the input
    /// gradient.
    adjoint: Tensor,
}

impl Conv {
    fn new(
        c_out: usize,
        c_in: usize,
        weight: Vec<f32>,
        bias: Vec<f32>,
    ) -> candle_core::Result<Conv> {
        let mut adjoint = vec![0.0f32; weight.len()];
        for o in 0..c_out {
            for i in 0..c_in {
                for tap in 0..9 {
                    adjoint[(i * c_out + o) * 9 + 8 - tap] = weight[(o * c_in + i) * 9 + tap];
                }
            }
        }
        let cpu = &candle_core::Device::Cpu;
        Ok(Conv {
            c_out,
            weight: Tensor::from_vec(weight, (c_out, c_in, 3, 3), cpu)?,
            bias: Tensor::from_vec(bias, c_out, cpu)?,
            adjoint: Tensor::from_vec(adjoint, (c_in, c_out, 3, 3), cpu)?,
        })
    }
}

/// Normalised features of a target image, computed once and compared against many renders.
pub struct LpipsTarget {
    height: usize,
    width: usize,
    range: InputRange,
    network: u64,
    /// The five taps' normalised features, [1, C, h, w] each, on the network's device.
    features: Vec<DeviceTensor>,
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
        self.features
            .iter()
            .map(|f| f.dims().iter().product::<usize>() * 4)
            .sum()
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
    convs: Vec<Conv>,
    /// The five `lin` layers' channel weights, [C] each.
    lins: Vec<Tensor>,
    range: InputRange,
    device: Device,
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
            candle_core::safetensors::load(&path, &candle_core::Device::Cpu)
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
                (Ok(w), Ok(b)) => match Conv::new(c_out, c_in, w, b) {
                    Ok(conv) => convs.push(conv),
                    Err(e) => problems.push(format!("{} {weight_key}: {e}", labels[0])),
                },
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
            match tensor_values(t).and_then(|v| {
                let n = v.len();
                Tensor::from_vec(v, n, &candle_core::Device::Cpu).map_err(|e| e.to_string())
            }) {
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
            device: Device::Cpu,
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

    /// Runs the network on `device` (the CPU by default). Targets must be made again afterwards.
    ///
    /// On a GPU the convolution weights stay f32 whatever the device's precision: with f16 operands the
    /// ReLU masks of near-zero pre-activations flip, and on the conformance fixtures the gradient moved by
    /// up to 6.5 % of its largest component (7e-6 in f32). A loss that steers a fit must be the loss it
    /// names; VGG at 512² is a few milliseconds in f32 on a GPU either way.
    pub fn on(mut self, device: Device) -> Lpips {
        self.device = match device {
            Device::Gpu(g) if g.precision() != Precision::F32 => Device::Gpu(
                GpuDevice::with_precision(g.context().clone(), Precision::F32),
            ),
            other => other,
        };
        self.id = NEXT_NETWORK_ID.fetch_add(1, Ordering::Relaxed);
        self
    }

    /// Where the network runs.
    pub fn device(&self) -> &Device {
        &self.device
    }

    /// Output channels of the five stages, as read from the weights.
    pub fn widths(&self) -> [usize; 5] {
        tap_convs().map(|i| self.convs[i].c_out)
    }

    /// Bytes [`Lpips::loss_and_grad`] holds at its peak for an h x w render: the 13 ReLU outputs it keeps
    /// for the backward pass, plus two maps of the widest layer in flight (a convolution's output and the
    /// gradient passed down). About 1.6 KB per pixel with the full-width VGG16 (1.1 KB of it kept).
    pub fn activation_bytes(&self, height: usize, width: usize) -> usize {
        let (mut kept, mut widest) = (0, 0);
        let mut conv = 0;
        for (s, &n) in CONVS_PER_STAGE.iter().enumerate() {
            let (h, w) = (height >> s, width >> s);
            for _ in 0..n {
                let map = self.convs[conv].c_out * h * w * 4;
                kept += map;
                widest = widest.max(map);
                conv += 1;
            }
        }
        kept + 2 * widest
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

    /// The error of a failed op, naming the device.
    fn compute_error(&self, cause: candle_core::Error) -> LpipsError {
        LpipsError::Compute {
            device: self.device.describe(),
            cause,
        }
    }

    /// A host image (H*W*3 interleaved) on the network's device.
    fn upload(&self, image: &[f32]) -> candle_core::Result<DeviceTensor> {
        self.device.tensor(&Tensor::from_slice(
            image,
            image.len(),
            &candle_core::Device::Cpu,
        )?)
    }

    /// The ScalingLayer's per-channel multiplier and offset for image values (the input range's affine
    /// map folded in), as [1, 3, 1, 1] tensors on `like`'s device.
    fn scaling(&self, like: &DeviceTensor) -> candle_core::Result<(DeviceTensor, DeviceTensor)> {
        let (mul, add) = self.range.affine();
        let cpu = &candle_core::Device::Cpu;
        let factor: Vec<f32> = (0..3).map(|ch| mul / SCALE[ch]).collect();
        let offset: Vec<f32> = (0..3).map(|ch| (add - SHIFT[ch]) / SCALE[ch]).collect();
        Ok((
            like.same_device(&Tensor::from_vec(factor, (1, 3, 1, 1), cpu)?)?,
            like.same_device(&Tensor::from_vec(offset, (1, 3, 1, 1), cpu)?)?,
        ))
    }

    /// Interleaved image (H*W*3 on the network's device) -> ScalingLayer output, [1, 3, h, w].
    fn scaled_input(
        &self,
        image: &DeviceTensor,
        height: usize,
        width: usize,
    ) -> candle_core::Result<DeviceTensor> {
        let (factor, offset) = self.scaling(image)?;
        image
            .reshape(&[1, height, width, 3])?
            .permute_contiguous(&[0, 3, 1, 2])?
            .broadcast_mul(&factor)?
            .broadcast_add(&offset)
    }

    /// ReLU outputs of all 13 convs; with `keep_all` false only the five taps are kept (`None` elsewhere).
    fn forward(
        &self,
        input: DeviceTensor,
        keep_all: bool,
    ) -> candle_core::Result<Vec<Option<DeviceTensor>>> {
        let mut acts: Vec<Option<DeviceTensor>> = Vec::with_capacity(self.convs.len());
        let mut stage_input = input;
        for (s, &n) in CONVS_PER_STAGE.iter().enumerate() {
            if s > 0 {
                stage_input = kept(&acts, acts.len() - 1).max_pool2x2()?;
            }
            for j in 0..n {
                let layer = &self.convs[acts.len()];
                let src = if j == 0 {
                    &stage_input
                } else {
                    kept(&acts, acts.len() - 1)
                };
                let out = src
                    .conv2d(&layer.weight.clone().into(), Some(&layer.bias), 1, 1)?
                    .relu()?;
                if !keep_all && j > 0 {
                    // Within a stage only the last output is a tap.
                    *acts.last_mut().expect("a previous conv") = None;
                }
                acts.push(Some(out));
            }
        }
        Ok(acts)
    }

    /// Normalised features of `image` (H*W*3 interleaved), to compare renders against.
    pub fn target(
        &self,
        image: &[f32],
        height: usize,
        width: usize,
    ) -> Result<LpipsTarget, LpipsError> {
        self.check_image(image, height, width)?;
        let features = (|| {
            let input = self.scaled_input(&self.upload(image)?, height, width)?;
            let acts = self.forward(input, false)?;
            tap_convs()
                .iter()
                .map(|&i| kept(&acts, i).normalize_channels(NORM_EPS))
                .collect::<candle_core::Result<Vec<_>>>()
        })()
        .map_err(|e| self.compute_error(e))?;
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
        let per_layer = (|| {
            let input = self.scaled_input(&self.upload(render)?, height, width)?;
            let acts = self.forward(input, false)?;
            let mut per_layer = [0.0f32; 5];
            for (s, &tap) in tap_convs().iter().enumerate() {
                let (map, _) = self.tap_distance(kept(&acts, tap), target, s, false)?;
                per_layer[s] = tap_mean(&map)?;
            }
            Ok(per_layer)
        })()
        .map_err(|e| self.compute_error(e))?;
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
        let on_device = self.upload(render).map_err(|e| self.compute_error(e))?;
        let out = self.loss_and_grad_on(&on_device, height, width, target)?;
        let per_layer = out.per_layer()?;
        let grad = (|| out.grad.to_cpu()?.flatten_all()?.to_vec1::<f32>())()
            .map_err(|e| self.compute_error(e))?;
        Ok(LpipsLoss {
            value: per_layer.iter().sum(),
            per_layer,
            grad,
        })
    }

    /// [`Lpips::loss_and_grad`] of a render already on the network's device (H*W*3 interleaved, e.g.
    /// the splatting engine's render on the same GPU): nothing is read back until
    /// [`DeviceLpips::per_layer`] is asked for. The render's values are not checked for NaN here (that
    /// would read them back).
    pub fn loss_and_grad_on(
        &self,
        render: &DeviceTensor,
        height: usize,
        width: usize,
        target: &LpipsTarget,
    ) -> Result<DeviceLpips, LpipsError> {
        if render.dims().iter().product::<usize>() != height * width * 3 {
            return Err(LpipsError::BadInput(format!(
                "render has shape {:?}, expected {width}x{height}x3 values",
                render.dims()
            )));
        }
        self.check_target(target, height, width)?;
        self.backward(render, height, width, target)
            .map(|(maps, grad)| DeviceLpips {
                maps,
                grad,
                device: self.device.describe(),
            })
            .map_err(|e| self.compute_error(e))
    }

    /// Tap `s`'s per-pixel distance between the ReLU output `act` and the target's features, and with
    /// `with_grad` the gradient of its mean w.r.t. `act`.
    fn tap_distance(
        &self,
        act: &DeviceTensor,
        target: &LpipsTarget,
        s: usize,
        with_grad: bool,
    ) -> candle_core::Result<(DeviceTensor, Option<DeviceTensor>)> {
        act.lpips_distance(&target.features[s], &self.lins[s], NORM_EPS, with_grad)
    }

    /// The five taps' distance maps and the gradient w.r.t. the interleaved render.
    fn backward(
        &self,
        render: &DeviceTensor,
        height: usize,
        width: usize,
        target: &LpipsTarget,
    ) -> candle_core::Result<(Vec<DeviceTensor>, DeviceTensor)> {
        let mut acts = self.forward(self.scaled_input(render, height, width)?, true)?;
        let taps = tap_convs();
        let mut maps = Vec::with_capacity(5);
        // Gradient w.r.t. the input of stage s + 1 (a pooled map), carried down the stages.
        let mut upstream: Option<DeviceTensor> = None;
        for s in (0..5).rev() {
            let tap = taps[s];
            let first = tap + 1 - CONVS_PER_STAGE[s];
            let (map, grad) = self.tap_distance(kept(&acts, tap), target, s, true)?;
            maps.push(map);
            // The gradient w.r.t. the tap's ReLU output: its own term plus what came through the pool.
            let mut grad = grad.expect("asked for the gradient");
            if let Some(up) = upstream.take() {
                grad = grad.add(&kept(&acts, tap).max_pool2x2_backward(&up)?)?;
            }
            for conv in (first..=tap).rev() {
                let layer = &self.convs[conv];
                grad = kept(&acts, conv).relu_backward(&grad)?.conv2d(
                    &layer.adjoint.clone().into(),
                    None,
                    1,
                    1,
                )?;
            }
            acts.truncate(first);
            upstream = Some(grad);
        }
        maps.reverse();
        // Through the ScalingLayer (a per-channel affine map) back to the interleaved image.
        let (factor, _) = self.scaling(render)?;
        let grad = upstream
            .expect("five stages ran")
            .broadcast_mul(&factor)?
            .permute_contiguous(&[0, 2, 3, 1])?
            .reshape(&[height * width * 3])?;
        Ok((maps, grad))
    }
}

/// LPIPS of a render on the network's device ([`Lpips::loss_and_grad_on`]).
pub struct DeviceLpips {
    /// The five taps' per-pixel distances, [1, 1, h, w] each.
    maps: Vec<DeviceTensor>,
    /// d LPIPS / d render, H*W*3 interleaved like the render, on the device.
    pub grad: DeviceTensor,
    device: String,
}

impl DeviceLpips {
    /// The terms of relu1_2 ... relu5_3 (their sum is the LPIPS value); reads the maps back.
    pub fn per_layer(&self) -> Result<[f32; 5], LpipsError> {
        let mut per_layer = [0.0f32; 5];
        for (v, map) in per_layer.iter_mut().zip(&self.maps) {
            *v = tap_mean(map).map_err(|cause| LpipsError::Compute {
                device: self.device.clone(),
                cause,
            })?;
        }
        Ok(per_layer)
    }
}

/// Spatial mean of one tap's distance map.
fn tap_mean(map: &DeviceTensor) -> candle_core::Result<f32> {
    let values = map.to_cpu()?.flatten_all()?.to_vec1::<f32>()?;
    let sum: f64 = values.iter().map(|&v| f64::from(v)).sum();
    Ok((sum / values.len().max(1) as f64) as f32)
}

/// The activation `i`, which the forward pass kept.
fn kept(acts: &[Option<DeviceTensor>], i: usize) -> &DeviceTensor {
    acts[i]
        .as_ref()
        .expect("the forward pass keeps every activation the caller reads")
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
        Tensor::from_vec(v, shape, &candle_core::Device::Cpu).expect("length matches shape")
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

    /// Whether the features of `view` are kept (a computed entry over the budget is not).
    pub fn holds(&self, view: usize) -> bool {
        self.entries.contains_key(&view)
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

    #[test]
    fn the_adjoint_kernel_gives_the_input_gradient() {
        // <conv(x), g> = <x, conv_adjoint(g)> for a 3x3/pad-1 convolution without bias.
        let (h, w, c_in, c_out) = (7, 9, 3, 5);
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let mut random =
            |n: usize| -> Vec<f32> { (0..n).map(|_| rng.gen::<f32>() - 0.5).collect() };
        let conv = Conv::new(c_out, c_in, random(c_out * c_in * 9), vec![0.0; c_out]).unwrap();
        let cpu = &candle_core::Device::Cpu;
        let x = Tensor::from_vec(random(c_in * h * w), (1, c_in, h, w), cpu).unwrap();
        let g = Tensor::from_vec(random(c_out * h * w), (1, c_out, h, w), cpu).unwrap();
        let y = x.conv2d(&conv.weight, 1, 1, 1, 1).unwrap();
        let back = g.conv2d(&conv.adjoint, 1, 1, 1, 1).unwrap();
        let dot = |a: &Tensor, b: &Tensor| -> f64 {
            let (a, b) = (a.flatten_all().unwrap(), b.flatten_all().unwrap());
            let (a, b) = (a.to_vec1::<f32>().unwrap(), b.to_vec1::<f32>().unwrap());
            a.iter().zip(&b).map(|(a, b)| f64::from(a * b)).sum()
        };
        let (lhs, rhs) = (dot(&y, &g), dot(&x, &back));
        assert!(
            (lhs - rhs).abs() < 1e-4 * lhs.abs().max(1.0),
            "{lhs} vs {rhs}"
        );
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
            Tensor::zeros((1, 7, 1, 1), DType::F32, &candle_core::Device::Cpu).unwrap(),
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
            Tensor::zeros((6, 5, 3, 3), DType::F32, &candle_core::Device::Cpu).unwrap(),
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
    fn activation_memory_is_what_the_documentation_says() {
        // 1080 bytes per pixel kept (64·2·4 + 128·2·4/4 + 256·3·4/16 + 512·3·4/64 + 512·3·4/256) and two
        // maps of 64 channels in flight.
        let full = Lpips::synthetic(VGG16_WIDTHS, 0);
        let per_pixel = full.activation_bytes(512, 512) as f64 / (512.0 * 512.0);
        assert_eq!(per_pixel, 1080.0 + 512.0);
        assert!(small().activation_bytes(64, 64) < full.activation_bytes(64, 64));
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
        assert!(cache.holds(1) && !cache.holds(2));
        cache.clear();
        assert!(cache.is_empty());
    }
}
