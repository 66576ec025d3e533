//! The GPU side of the kernels: a CubeCL client on a wgpu adapter (Vulkan/Metal/DX12, WGSL shaders; Mesa
//! lavapipe in CI), a device-resident f32 tensor ([`GpuTensor`]) and one host function per op
//! ([`ops`]), each the GPU twin of a CPU function of `kernels`.
//!
//! The ops are grouped by family, each family's file holding its `#[cube]` kernels and their launchers
//! side by side: `elementwise`, `layout` (copies), `matmul`, `conv`, `norm` (row reductions),
//! `attention` and `vgg` (LPIPS's feature-loss ops); `launch` has what they share (grids, the `meta`
//! block, the 1-D launch).
//!
//! A [`GpuDevice`] wraps the [`gpu::GpuContext`] of crates/gpu, so the splatting engine and the diffusion
//! networks share one adapter and one CubeCL client. Weights live in the network as candle CPU tensors;
//! the first GPU use of a weight uploads it into the device's cache, keyed by the tensor's id, so a model
//! runs on the GPU without a second, GPU-side copy of its definition. The weights of matrix products
//! are cached in the device's [`Precision`] (f16 by default, packed two per u32 word); everything else
//! is f32.

mod attention;
mod conv;
mod elementwise;
mod launch;
mod layout;
mod matmul;
mod norm;
pub mod ops;
mod precision;
pub(crate) mod storage;
#[cfg(test)]
pub(crate) mod testing;
mod vgg;

pub use precision::{Precision, UnknownPrecision};

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use candle_core::{DType, Device, Result, Tensor, TensorId};
use cubecl::client::Client;
use cubecl::prelude::*;
use cubecl::server::Handle;
use gpu::{DeviceChoice, F32Buffer, GpuContext, GpuError};

/// The name tuning results on `context`'s device are kept under: adapter, graphics API and compiler (a
/// timing on WGSL says nothing of SPIR-V), as one path segment of ASCII letters, digits, '-' and '.'.
fn tune_id(context: &GpuContext) -> Arc<str> {
    let name = format!(
        "{} {} {}",
        context.adapter, context.backend, context.compiler
    );
    name.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '.' {
                c
            } else {
                '-'
            }
        })
        .collect::<String>()
        .into()
}

/// An opened GPU for the networks: the shared [`GpuContext`] and the uploaded-weight cache.
#[derive(Clone)]
pub struct GpuDevice {
    inner: Arc<Inner>,
}

struct Inner {
    context: GpuContext,
    precision: Precision,
    /// Names the device's tuning results (adapter, graphics API, compiler) in cubecl's persistent cache;
    /// shared, as the tuner clones it on every lookup.
    tune_id: Arc<str>,
    /// Weights already on the device, keyed by tensor id and whether the copy is f16. The CPU tensor is
    /// kept beside its copy so its id stays unique.
    weights: Mutex<HashMap<(TensorId, bool), CachedWeight>>,
}

struct CachedWeight {
    _source: Tensor,
    copy: GpuTensor,
}

impl std::fmt::Debug for GpuDevice {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "GpuDevice({}, {} weights)",
            self.inner.context.describe(),
            self.inner.precision
        )
    }
}

impl GpuDevice {
    /// The networks' view of an opened GPU (with an empty weight cache), storing matrix weights in the
    /// default precision (f16; see [`Precision`]).
    pub fn new(context: GpuContext) -> GpuDevice {
        GpuDevice::with_precision(context, Precision::default())
    }

    /// [`GpuDevice::new`] with the weights of matrix products stored in `precision`.
    pub fn with_precision(context: GpuContext, precision: Precision) -> GpuDevice {
        GpuDevice {
            inner: Arc::new(Inner {
                tune_id: tune_id(&context),
                context,
                precision,
                weights: Mutex::new(HashMap::new()),
            }),
        }
    }

    /// How the weights of matrix products are stored.
    pub fn precision(&self) -> Precision {
        self.inner.precision
    }

    /// Opens the device `choice` names (`None` for the CPU); see [`gpu::open`].
    pub fn open(choice: DeviceChoice) -> std::result::Result<Option<GpuDevice>, GpuError> {
        Ok(gpu::open(choice)?.map(GpuDevice::new))
    }

    /// The shared context (the same client the splatting kernels use).
    pub fn context(&self) -> &GpuContext {
        &self.inner.context
    }

    /// The adapter's name, e.g. "llvmpipe (LLVM 15.0.6, 256 bits)".
    pub fn name(&self) -> &str {
        &self.inner.context.adapter
    }

    pub(crate) fn client(&self) -> &Client {
        &self.inner.context.client
    }

    /// What the device's tuning results are kept under (see [`tune_id`]).
    pub(crate) fn tune_id(&self) -> &Arc<str> {
        &self.inner.tune_id
    }

    /// The f32 device copy of a (weight) tensor, uploaded on first use.
    pub fn cached(&self, weight: &Tensor) -> candle_core::Result<GpuTensor> {
        self.cached_as(weight, false)
    }

    /// The device copy of the weight of a matrix product (a linear or convolution weight), in the
    /// device's [`Precision`], uploaded on first use. An f16 copy is only an operand of
    /// [`ops::linear`] and [`ops::conv2d`] (and can be read back); other ops take f32 tensors.
    pub fn cached_matrix(&self, weight: &Tensor) -> candle_core::Result<GpuTensor> {
        self.cached_as(weight, self.inner.precision == Precision::F16)
    }

    fn cached_as(&self, weight: &Tensor, half: bool) -> candle_core::Result<GpuTensor> {
        let mut weights = self.inner.weights.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(cached) = weights.get(&(weight.id(), half)) {
            return Ok(cached.copy.clone());
        }
        let copy = if half {
            GpuTensor::upload_f16(self, weight)?
        } else {
            GpuTensor::upload(self, weight)?
        };
        weights.insert(
            (weight.id(), half),
            CachedWeight {
                _source: weight.clone(),
                copy: copy.clone(),
            },
        );
        Ok(copy)
    }

    /// Bytes of device memory CubeCL's pools hold for the shared client (weights, activations, freed
    /// pages kept for reuse, the splatting engine's buffers), and the bytes of it in use now. Pools keep
    /// their pages, so after a UNet call the reserved figure includes that call's peak.
    pub fn memory_reserved_and_in_use(&self) -> (usize, usize) {
        let usage = self
            .client()
            .memory_report(cubecl_runtime::memory_management::MemoryScope::Device)
            .usage();
        (usage.bytes_reserved as usize, usage.bytes_in_use as usize)
    }

    /// Bytes of device memory the weight cache holds.
    pub fn weight_bytes(&self) -> usize {
        let weights = self.inner.weights.lock().unwrap_or_else(|e| e.into_inner());
        weights.values().map(|w| w.copy.storage_bytes()).sum()
    }

    /// Drops every cached weight (after a model is dropped or its weights change).
    pub fn clear_weight_cache(&self) {
        self.inner
            .weights
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clear();
    }
}

/// A contiguous row-major tensor in GPU memory: f32, or (weights only) f16 packed two per u32 word.
#[derive(Clone)]
pub struct GpuTensor {
    device: GpuDevice,
    handle: Handle,
    shape: Vec<usize>,
    /// Packed f16 storage (see [`GpuDevice::cached_matrix`]).
    half: bool,
}

impl std::fmt::Debug for GpuTensor {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let dtype = if self.half { " f16" } else { "" };
        write!(f, "GpuTensor{:?}{dtype}", self.shape)
    }
}

impl GpuTensor {
    /// Copies a CPU tensor (any float dtype, any layout) to the device as f32.
    pub fn upload(device: &GpuDevice, t: &Tensor) -> Result<GpuTensor> {
        let data: Vec<f32> = t.to_dtype(DType::F32)?.flatten_all()?.to_vec1()?;
        Ok(Self::from_slice(device, &data, t.dims().to_vec()))
    }

    /// Copies a CPU tensor to the device as f16 (rounded to nearest), packed two per word.
    fn upload_f16(device: &GpuDevice, t: &Tensor) -> Result<GpuTensor> {
        let data: Vec<f32> = t.to_dtype(DType::F32)?.flatten_all()?.to_vec1()?;
        let mut words = precision::pack_f16(&data);
        // wgpu rejects empty buffers: keep at least one word.
        if words.is_empty() {
            words.push(0);
        }
        Ok(GpuTensor {
            device: device.clone(),
            handle: device.client().create_from_slice(u32::as_bytes(&words)),
            shape: t.dims().to_vec(),
            half: true,
        })
    }

    pub(crate) fn from_slice(device: &GpuDevice, data: &[f32], shape: Vec<usize>) -> GpuTensor {
        let client = device.client();
        debug_assert_eq!(data.len(), shape.iter().product::<usize>());
        // wgpu rejects empty buffers: keep at least one element.
        let handle = if data.is_empty() {
            client.create_from_slice(f32::as_bytes(&[0.0]))
        } else {
            client.create_from_slice(f32::as_bytes(data))
        };
        GpuTensor {
            device: device.clone(),
            handle,
            shape,
            half: false,
        }
    }

    /// An f32 tensor of `shape` over values another engine made on the same context (the splatting
    /// engine's render); an error when the buffer holds another number of values.
    pub fn from_buffer(
        device: &GpuDevice,
        buffer: F32Buffer,
        shape: Vec<usize>,
    ) -> Result<GpuTensor> {
        if shape.iter().product::<usize>() != buffer.len() {
            candle_core::bail!(
                "a GPU buffer of {} f32 values is not a {shape:?} tensor",
                buffer.len()
            );
        }
        Ok(GpuTensor {
            device: device.clone(),
            handle: buffer.into_handle(),
            shape,
            half: false,
        })
    }

    /// The values as a buffer another engine on the same context can take; an error for packed f16
    /// storage (weights, never a result handed on).
    pub fn into_buffer(self) -> Result<F32Buffer> {
        if self.half {
            candle_core::bail!(
                "a packed f16 GPU tensor {:?} is not an f32 buffer",
                self.shape
            );
        }
        let len = self.shape.iter().product();
        F32Buffer::new(self.handle, len).map_err(|e| candle_core::Error::Msg(e.to_string()))
    }

    /// The buffer (f32, or packed f16 for [`GpuTensor::is_f16`]), for another engine on the same context.
    pub fn handle(&self) -> &Handle {
        &self.handle
    }

    /// An uninitialised tensor of `shape` on the same device as `self`.
    pub(crate) fn empty_like_device(&self, shape: Vec<usize>) -> GpuTensor {
        let n = shape.iter().product::<usize>().max(1);
        GpuTensor {
            device: self.device.clone(),
            handle: self.client().empty(n * std::mem::size_of::<f32>()),
            shape,
            half: false,
        }
    }

    /// An uninitialised f16 tensor of `shape` (packed two per word) on the same device as `self`.
    pub(crate) fn empty_half_like(&self, shape: Vec<usize>) -> GpuTensor {
        let words = shape.iter().product::<usize>().div_ceil(2).max(1);
        GpuTensor {
            device: self.device.clone(),
            handle: self.client().empty(words * std::mem::size_of::<u32>()),
            shape,
            half: true,
        }
    }

    /// Reads the tensor back (waits for the kernels that write it; their errors surface here).
    pub fn to_cpu(&self) -> Result<Tensor> {
        // Classified (out of memory, lost device) and cut to its informative line; counted.
        let bytes = gpu::prims::read_raw(self.client(), &self.handle)
            .map_err(|e| candle_core::Error::msg(e.to_string()))?;
        let n = self.elem_count();
        if self.half {
            let data = precision::unpack_f16(u32::from_bytes(&bytes), n);
            return Tensor::from_vec(data, self.shape.as_slice(), &Device::Cpu);
        }
        let data = f32::from_bytes(&bytes);
        Tensor::from_slice(&data[..n], self.shape.as_slice(), &Device::Cpu)
    }

    pub fn dims(&self) -> &[usize] {
        &self.shape
    }

    pub fn elem_count(&self) -> usize {
        self.shape.iter().product()
    }

    /// The same data under another shape of equal size (no copy).
    pub fn reshape(&self, shape: &[usize]) -> Result<GpuTensor> {
        if shape.iter().product::<usize>() != self.elem_count() {
            candle_core::bail!(
                "gpu reshape: {:?} to {shape:?} changes the size",
                self.shape
            );
        }
        Ok(GpuTensor {
            device: self.device.clone(),
            handle: self.handle.clone(),
            shape: shape.to_vec(),
            half: self.half,
        })
    }

    /// Whether both tensors are views of one buffer.
    pub fn same_buffer(&self, other: &GpuTensor) -> bool {
        self.handle.clone().memory.binding().id() == other.handle.clone().memory.binding().id()
    }

    /// The device holding the tensor.
    pub fn device(&self) -> &GpuDevice {
        &self.device
    }

    pub(crate) fn client(&self) -> &Client {
        self.device.client()
    }

    /// Whether the tensor is stored as packed f16 (a weight matrix of an f16 device).
    pub fn is_f16(&self) -> bool {
        self.half
    }

    /// 32-bit words of the buffer: one per f32 element, one per two f16 elements (at least one).
    fn storage_words(&self) -> usize {
        let n = self.elem_count();
        if self.half { n.div_ceil(2) } else { n }.max(1)
    }

    /// Bytes of device memory the tensor's buffer holds.
    pub fn storage_bytes(&self) -> usize {
        self.storage_words() * 4
    }

    /// The buffer as a kernel argument of an f32 kernel (its length in f32 elements). An f16 tensor here
    /// is a caller's bug (only the matrix products read packed weights).
    pub(crate) fn arg(&self) -> BufferArg {
        debug_assert!(!self.half, "an f16 weight passed to an f32 kernel");
        self.word_arg()
    }

    /// The buffer as a strided tensor argument of a library kernel (cubek), f32 or f16 as stored;
    /// `shape`/`strides` in elements describe a view inside the buffer.
    pub(crate) fn binding(&self, shape: &[usize], strides: &[usize]) -> TensorBinding {
        TensorBinding {
            handle: self.handle.clone().binding(),
            strides: strides.into(),
            shape: shape.into(),
            tiling: cubecl::zspace::Tiling::UNTILED,
        }
    }

    /// A packed f16 buffer as a kernel argument of f16 elements (its length in halves).
    pub(crate) fn half_arg(&self) -> BufferArg {
        debug_assert!(self.half, "an f32 tensor passed as f16");
        // SAFETY: the handle holds storage_words() words, i.e. at least elem_count() halves.
        unsafe { BufferArg::from_raw_parts(self.handle.clone(), self.elem_count().max(1)) }
    }

    /// The buffer as 32-bit words (f32 bits or two packed halves), for the matrix-product kernel.
    pub(crate) fn word_arg(&self) -> BufferArg {
        // SAFETY: the handle holds exactly storage_words() words (see from_slice, upload_f16, empty_like).
        unsafe { BufferArg::from_raw_parts(self.handle.clone(), self.storage_words()) }
    }
}
