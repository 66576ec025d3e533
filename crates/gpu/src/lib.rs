//! GPU device selection and error handling for vcedit's compute kernels (CubeCL on wgpu).
//!
//! - [`DeviceChoice`]: what the user asked for (`cpu`, `gpu`, `auto`; also the `VCEDIT_DEVICE` variable).
//! - [`open`]: turns a choice into an optional [`GpuContext`] without panicking. `auto` takes a hardware
//!   adapter (Vulkan, Metal or DX12) when there is one; a software rasteriser such as Mesa's llvmpipe is
//!   ~100x slower than the CPU path, so it is used only when asked for explicitly (`gpu`) or allowed
//!   with `VCEDIT_ALLOW_SOFTWARE_GPU=1`. The backend is pinned so wgpu never silently falls back to GL.
//! - [`gpu_call`]: runs a unit of GPU work ("launch…; read") and maps every failure, panics included, to
//!   one [`GpuError`].
//!
//! Kernels report failures (out of memory, lost device) when their results are read, not at launch, and
//! a bug in a kernel's compile-time code panics on the caller's thread: hence one wrapper around whole
//! units of work rather than around each launch.

use std::fmt;
use std::str::FromStr;

pub use cubecl;
use cubecl::client::Client;
use cubecl::device::{WgpuBackend, WgpuDeviceKind};
use cubecl::wgpu::{wgpu, AutoGraphicsApi, RuntimeOptions, WgpuDevice};

mod memory;
pub mod prims;
pub mod reduce;
pub mod testing;

/// Environment variable holding the default device choice.
pub const DEVICE_ENV: &str = "VCEDIT_DEVICE";
/// Set to `1` to let `auto` pick a software adapter (lavapipe/llvmpipe, WARP, SwiftShader).
pub const ALLOW_SOFTWARE_ENV: &str = "VCEDIT_ALLOW_SOFTWARE_GPU";

/// Where the compute runs.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum DeviceChoice {
    Cpu,
    Gpu,
    #[default]
    Auto,
}

impl FromStr for DeviceChoice {
    type Err = GpuError;

    fn from_str(s: &str) -> Result<Self, GpuError> {
        match s.trim().to_ascii_lowercase().as_str() {
            "cpu" => Ok(Self::Cpu),
            "gpu" => Ok(Self::Gpu),
            "auto" => Ok(Self::Auto),
            other => Err(GpuError::BadChoice(other.to_string())),
        }
    }
}

impl fmt::Display for DeviceChoice {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::Cpu => "cpu",
            Self::Gpu => "gpu",
            Self::Auto => "auto",
        })
    }
}

impl DeviceChoice {
    /// The choice in `VCEDIT_DEVICE`, or `default` when it is unset or empty.
    pub fn from_env_or(default: DeviceChoice) -> Result<DeviceChoice, GpuError> {
        match std::env::var(DEVICE_ENV) {
            Ok(v) if !v.trim().is_empty() => v.parse(),
            _ => Ok(default),
        }
    }
}

/// Errors of the GPU path, each meant to be shown as one line.
#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    #[error("no GPU found (no Vulkan, Metal or DX12 adapter)")]
    NoAdapter,
    #[error("GPU out of memory: {0}")]
    OutOfMemory(String),
    #[error("GPU device lost: {0}")]
    DeviceLost(String),
    #[error("GPU kernel failed: {0}")]
    Kernel(String),
    #[error("unknown device '{0}' (expected cpu, gpu or auto)")]
    BadChoice(String),
}

/// Hardware limits the kernels size themselves by.
#[derive(Clone, Copy, Debug)]
pub struct GpuLimits {
    pub max_shared_bytes: usize,
    pub max_units_per_cube: u32,
    /// Largest cube count per dimension.
    pub max_cube_count: u32,
    pub plane_size: u32,
    /// Largest single buffer (the smaller of the storage-binding and buffer limits).
    pub max_buffer_bytes: u64,
    /// Device memory the runtime states for the adapter (`None` where its API has no figure, as wgpu's
    /// portable path: gfx-rs/wgpu#2447).
    pub memory_bytes: Option<u64>,
    /// The card's free memory when the device was opened, from the vendor's interface (NVML, amdgpu's
    /// sysfs counters; `None` elsewhere, see `memory.rs`). Read once, so every plan made in one
    /// process sees the same figure.
    pub free_bytes_at_open: Option<u64>,
}

/// An opened GPU: the CubeCL client plus what the run log reports.
#[derive(Clone)]
pub struct GpuContext {
    pub client: Client,
    /// Adapter name, e.g. "NVIDIA H100" or "llvmpipe (LLVM 15.0.6, 256 bits)".
    pub adapter: String,
    /// Graphics API the kernels run through ("Vulkan", "Metal", "Dx12").
    pub backend: String,
    /// Whether the adapter is a software rasteriser on the CPU.
    pub software: bool,
    pub limits: GpuLimits,
}

impl fmt::Debug for GpuContext {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("GpuContext")
            .field("adapter", &self.adapter)
            .field("backend", &self.backend)
            .field("software", &self.software)
            .finish_non_exhaustive()
    }
}

impl GpuContext {
    /// One line for run logs: "llvmpipe (LLVM 15.0.6, 256 bits) via Vulkan (software)".
    pub fn describe(&self) -> String {
        format!(
            "{} via {}{}",
            self.adapter,
            self.backend,
            if self.software { " (software)" } else { "" }
        )
    }
}

/// An adapter wgpu reports, with the CubeCL device kind that addresses it.
#[derive(Clone, Debug)]
pub struct AdapterEntry {
    pub name: String,
    pub backend: WgpuBackend,
    pub software: bool,
    kind: WgpuDeviceKind,
}

/// Adapters on the compute backends we use (Vulkan, Metal, DX12), in wgpu's order. Never panics.
pub fn list_adapters() -> Vec<AdapterEntry> {
    let backends = wgpu::Backends::VULKAN | wgpu::Backends::METAL | wgpu::Backends::DX12;
    let found = std::panic::catch_unwind(|| {
        let instance = wgpu::Instance::new(wgpu::InstanceDescriptor {
            backends,
            ..wgpu::InstanceDescriptor::new_without_display_handle()
        });
        cubecl::future::block_on(instance.enumerate_adapters(backends))
            .iter()
            .map(|a| a.get_info())
            .collect::<Vec<_>>()
    })
    .unwrap_or_default();
    // CubeCL addresses adapters as "the n-th adapter of this type", counted over all backends.
    let mut next = [0usize; 4];
    let mut out = vec![];
    for info in found {
        let kind = match info.device_type {
            wgpu::DeviceType::DiscreteGpu => WgpuDeviceKind::DiscreteGpu(bump(&mut next[0])),
            wgpu::DeviceType::IntegratedGpu => WgpuDeviceKind::IntegratedGpu(bump(&mut next[1])),
            wgpu::DeviceType::VirtualGpu => WgpuDeviceKind::VirtualGpu(bump(&mut next[2])),
            wgpu::DeviceType::Other => WgpuDeviceKind::Other(bump(&mut next[3])),
            wgpu::DeviceType::Cpu => WgpuDeviceKind::Cpu,
        };
        let backend = match info.backend {
            wgpu::Backend::Vulkan => WgpuBackend::Vulkan,
            wgpu::Backend::Metal => WgpuBackend::Metal,
            wgpu::Backend::Dx12 => WgpuBackend::Dx12,
            _ => continue,
        };
        // Some software drivers report themselves as "Other"/"Cpu" only by name.
        let lname = info.name.to_lowercase();
        let software = info.device_type == wgpu::DeviceType::Cpu
            || [
                "llvmpipe",
                "lavapipe",
                "swiftshader",
                "warp",
                "microsoft basic render",
            ]
            .iter()
            .any(|s| lname.contains(s));
        out.push(AdapterEntry {
            name: info.name,
            backend,
            software,
            kind,
        });
    }
    out
}

fn bump(n: &mut usize) -> usize {
    *n += 1;
    *n - 1
}

fn software_allowed() -> bool {
    std::env::var(ALLOW_SOFTWARE_ENV).is_ok_and(|v| v.trim() == "1")
}

/// Opens the device `choice` names: `Ok(None)` means "use the CPU" (`cpu`, or `auto` without a usable
/// GPU); `gpu` without any adapter is [`GpuError::NoAdapter`].
pub fn open(choice: DeviceChoice) -> Result<Option<GpuContext>, GpuError> {
    if choice == DeviceChoice::Cpu {
        return Ok(None);
    }
    let adapters = list_adapters();
    let hardware = adapters.iter().find(|a| !a.software);
    let software = adapters.iter().find(|a| a.software);
    let pick = match choice {
        DeviceChoice::Gpu => hardware.or(software),
        _ if software_allowed() => hardware.or(software),
        _ => hardware,
    };
    match (pick, choice) {
        (Some(a), _) => open_adapter(a).map(Some),
        (None, DeviceChoice::Gpu) => Err(GpuError::NoAdapter),
        (None, _) => Ok(None),
    }
}

fn open_adapter(a: &AdapterEntry) -> Result<GpuContext, GpuError> {
    let device = WgpuDevice::new(a.kind.clone()).on(a.backend);
    // The fallible initialisation registers the client; `.client()` on an unknown device would panic.
    let setup = gpu_call(|| {
        cubecl::wgpu::try_init_setup::<AutoGraphicsApi>(&device, RuntimeOptions::default())
            .map_err(|e| GpuError::Kernel(format!("cannot initialise {}: {e}", a.name)))
    })?;
    let backend = format!("{:?}", setup.backend);
    let client = gpu_call(|| Ok(cubecl::Device::Wgpu(device).client()))?;
    let props = client.properties();
    let hw = &props.hardware;
    let limits = GpuLimits {
        max_shared_bytes: hw.max_shared_memory_size,
        max_units_per_cube: hw.max_units_per_cube,
        max_cube_count: hw.max_cube_count.0,
        plane_size: hw.plane_size_max,
        max_buffer_bytes: props.memory.max_page_size,
        memory_bytes: props.memory.max_memory(),
        free_bytes_at_open: props
            .identity
            .physical
            .as_ref()
            .and_then(|card| card.pci_address.as_ref())
            .and_then(|pci| memory::free_bytes(&pci.to_string())),
    };
    Ok(GpuContext {
        adapter: props.identity.name.clone(),
        client,
        backend,
        software: a.software,
        limits,
    })
}

/// Runs one unit of GPU work. Panics inside it (CubeCL reports kernel-expansion bugs and some device
/// failures that way) and CubeCL server errors become a [`GpuError`].
pub fn gpu_call<T>(f: impl FnOnce() -> Result<T, GpuError>) -> Result<T, GpuError> {
    match std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)) {
        Ok(r) => r,
        Err(p) => Err(GpuError::Kernel(panic_message(&*p))),
    }
}

/// Maps a CubeCL server error (returned by reads and syncs) to a [`GpuError`].
pub fn server_error(e: cubecl::server::ServerError) -> GpuError {
    let full = e.to_string();
    let msg = first_line(&full);
    let lower = full.to_lowercase();
    if e.is_device_poisoned() {
        GpuError::DeviceLost(msg)
    } else if lower.contains("can't allocate") || lower.contains("out of memory") {
        // The line that names the allocation, not the summary ("several failures at once ...").
        let line = full
            .lines()
            .find(|l| l.contains("allocate") || l.to_lowercase().contains("out of memory"))
            .map_or(msg, |l| l.trim().to_string());
        GpuError::OutOfMemory(line)
    } else {
        GpuError::Kernel(msg)
    }
}

/// The informative part of a multi-line CubeCL message (they carry "Caused by:" and backtraces).
fn first_line(s: &str) -> String {
    s.lines()
        .map(str::trim)
        .filter(|l| {
            !l.is_empty()
                && !l.starts_with("Caused by")
                && !l.starts_with("Backtrace")
                && !l.contains("No backtrace")
        })
        .take(2)
        .collect::<Vec<_>>()
        .join(": ")
}

fn panic_message(p: &(dyn std::any::Any + Send)) -> String {
    p.downcast_ref::<String>()
        .cloned()
        .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
        .unwrap_or_else(|| "panic without a message".into())
}

#[cfg(test)]
mod tests {
    use super::*;
    use cubecl::prelude::*;

    #[test]
    fn device_choice_parses() {
        assert_eq!("cpu".parse::<DeviceChoice>().unwrap(), DeviceChoice::Cpu);
        assert_eq!(" GPU ".parse::<DeviceChoice>().unwrap(), DeviceChoice::Gpu);
        assert_eq!("auto".parse::<DeviceChoice>().unwrap(), DeviceChoice::Auto);
        let e = "tpu".parse::<DeviceChoice>().unwrap_err();
        assert_eq!(
            e.to_string(),
            "unknown device 'tpu' (expected cpu, gpu or auto)"
        );
        for c in [DeviceChoice::Cpu, DeviceChoice::Gpu, DeviceChoice::Auto] {
            assert_eq!(c.to_string().parse::<DeviceChoice>().unwrap(), c);
        }
    }

    #[test]
    fn cpu_choice_opens_nothing() {
        assert!(open(DeviceChoice::Cpu).unwrap().is_none());
    }

    #[test]
    fn panics_become_errors() {
        let r: Result<(), _> = gpu_call(|| panic!("boom"));
        assert!(matches!(r, Err(GpuError::Kernel(m)) if m == "boom"));
    }

    #[cube(launch)]
    fn add_one(x: &mut [f32]) {
        if ABSOLUTE_POS < x.len() {
            x[ABSOLUTE_POS] += 1.0;
        }
    }

    #[test]
    fn runs_a_kernel_and_reports_out_of_memory() {
        let Some(ctx) = testing::context_or_skip() else {
            return;
        };
        assert!(!ctx.adapter.is_empty());
        let c = &ctx.client;
        let h = c.create_from_slice(f32::as_bytes(&[1.0, 2.0, 3.0]));
        add_one::launch(c, CubeCount::new_single(), CubeDim::new_1d(4), unsafe {
            BufferArg::from_raw_parts(h.clone(), 3)
        });
        let bytes = c.read_one(h).map_err(server_error).unwrap();
        assert_eq!(f32::from_bytes(&bytes), &[2.0, 3.0, 4.0]);
        // 1 TiB: the allocation fails when read, as one error, and the device stays usable.
        let huge = c.empty(1 << 40);
        let e = gpu_call(|| c.read_one(huge).map_err(server_error)).unwrap_err();
        assert!(matches!(e, GpuError::OutOfMemory(_)), "{e}");
        eprintln!("{e}");
        let h = c.create_from_slice(f32::as_bytes(&[5.0]));
        assert_eq!(f32::from_bytes(&c.read_one(h).unwrap()), &[5.0]);
    }
}
