//! The GPU side of the kernels: a CubeCL client on a wgpu adapter (Vulkan/Metal/DX12, WGSL shaders; Mesa
//! lavapipe in CI), a device-resident f32 tensor ([`GpuTensor`]) and one host function per op
//! ([`ops`]), each the GPU twin of a CPU function of `kernels`.
//!
//! A [`GpuDevice`] wraps the [`gpu::GpuContext`] of crates/gpu, so the splatting engine and the diffusion
//! networks share one adapter and one CubeCL client. Weights live in the network as candle CPU tensors;
//! the first GPU use of a weight uploads it into the device's cache, keyed by the tensor's id, so a model
//! runs on the GPU without a second, GPU-side copy of its definition.

mod cube;
pub mod ops;

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use candle_core::{DType, Device, Result, Tensor, TensorId};
use cubecl::client::Client;
use cubecl::prelude::*;
use cubecl::server::Handle;
use gpu::{DeviceChoice, GpuContext, GpuError};

/// An opened GPU for the networks: the shared [`GpuContext`] and the uploaded-weight cache.
#[derive(Clone)]
pub struct GpuDevice {
    inner: Arc<Inner>,
}

struct Inner {
    context: GpuContext,
    /// Weights already on the device: the CPU tensor is kept beside its copy so its id stays unique.
    weights: Mutex<HashMap<TensorId, (Tensor, Handle)>>,
}

impl std::fmt::Debug for GpuDevice {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "GpuDevice({})", self.inner.context.describe())
    }
}

impl GpuDevice {
    /// The networks' view of an opened GPU (with an empty weight cache).
    pub fn new(context: GpuContext) -> GpuDevice {
        GpuDevice {
            inner: Arc::new(Inner {
                context,
                weights: Mutex::new(HashMap::new()),
            }),
        }
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

    /// The device copy of a (weight) tensor, uploaded on first use.
    pub fn cached(&self, weight: &Tensor) -> candle_core::Result<GpuTensor> {
        let mut weights = self.inner.weights.lock().unwrap_or_else(|e| e.into_inner());
        if let Some((_, handle)) = weights.get(&weight.id()) {
            return Ok(GpuTensor {
                device: self.clone(),
                handle: handle.clone(),
                shape: weight.dims().to_vec(),
            });
        }
        let copy = GpuTensor::upload(self, weight)?;
        weights.insert(weight.id(), (weight.clone(), copy.handle.clone()));
        Ok(copy)
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

/// A contiguous row-major f32 tensor in GPU memory.
#[derive(Clone)]
pub struct GpuTensor {
    device: GpuDevice,
    handle: Handle,
    shape: Vec<usize>,
}

impl std::fmt::Debug for GpuTensor {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "GpuTensor{:?}", self.shape)
    }
}

/// A GPU failure as a candle error, so network code keeps one error type.
fn gpu_error(what: &str, e: impl std::fmt::Display) -> candle_core::Error {
    candle_core::Error::msg(format!("GPU {what}: {e}"))
}

impl GpuTensor {
    /// Copies a CPU tensor (any float dtype, any layout) to the device as f32.
    pub fn upload(device: &GpuDevice, t: &Tensor) -> Result<GpuTensor> {
        let data: Vec<f32> = t.to_dtype(DType::F32)?.flatten_all()?.to_vec1()?;
        Ok(Self::from_slice(device, &data, t.dims().to_vec()))
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
        }
    }

    /// An uninitialised tensor of `shape` on the same device as `self`.
    pub(crate) fn empty_like_device(&self, shape: Vec<usize>) -> GpuTensor {
        let n = shape.iter().product::<usize>().max(1);
        GpuTensor {
            device: self.device.clone(),
            handle: self.client().empty(n * std::mem::size_of::<f32>()),
            shape,
        }
    }

    /// Reads the tensor back (waits for the kernels that write it; their errors surface here).
    pub fn to_cpu(&self) -> Result<Tensor> {
        let bytes = self
            .client()
            .read_one(self.handle.clone())
            .map_err(|e| gpu_error("read-back", e))?;
        let data = f32::from_bytes(&bytes);
        let n = self.elem_count();
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

    /// The buffer as a kernel argument (its length in f32 elements).
    pub(crate) fn arg(&self) -> BufferArg {
        // SAFETY: the handle holds at least max(1, elem_count) f32 elements (see from_slice/empty_like).
        unsafe { BufferArg::from_raw_parts(self.handle.clone(), self.elem_count().max(1)) }
    }
}

#[cfg(test)]
pub(crate) mod testing {
    use std::sync::OnceLock;

    use super::GpuDevice;

    /// The test GPU (lavapipe in CI) shared by the tests of this binary, or `None` after the one line
    /// `gpu::testing::context_or_skip` prints when there is no Vulkan device.
    pub fn device_or_skip() -> Option<GpuDevice> {
        static DEVICE: OnceLock<GpuDevice> = OnceLock::new();
        if let Some(device) = DEVICE.get() {
            return Some(device.clone());
        }
        let device = GpuDevice::new(gpu::testing::context_or_skip()?);
        Some(DEVICE.get_or_init(|| device).clone())
    }
}
