//! GPU device selection and error handling for vcedit's compute kernels (CubeCL on wgpu or CUDA).
//!
//! - [`DeviceChoice`]: what the user asked for (`cpu`, `gpu`, `auto`, `cuda`, `wgpu`; also the
//!   `VCEDIT_DEVICE` variable).
//! - [`open`]: turns a choice into an optional [`GpuContext`] without panicking. The kernels are written
//!   once in CubeCL and run on one of two runtimes: CUDA (NVIDIA cards, kernels compiled by NVRTC at run
//!   time, built with the `cuda` feature; see `cuda.rs`) or wgpu (Vulkan, Metal or DX12). `auto` and
//!   `gpu` take CUDA where it opens and wgpu's best hardware adapter otherwise, saying why CUDA was
//!   passed over ([`GpuContext::passed_over`]); a software rasteriser such as Mesa's llvmpipe is ~100x
//!   slower than the CPU path, so it is used only when asked for explicitly (`gpu`, `wgpu`) or allowed
//!   with `VCEDIT_ALLOW_SOFTWARE_GPU=1`. The backend is pinned so wgpu never silently falls back to GL.
//! - The shader compiler: SPIR-V on Vulkan adapters with the features cubecl's SPIR-V path needs (Vulkan
//!   memory model, 16-bit storage; it also brings cooperative matrices, i.e. tensor cores, and native
//!   f16) and `VK_KHR_workgroup_memory_explicit_layout` (without it cubecl-spirv's workgroup memory is
//!   invalid SPIR-V), WGSL everywhere else, lavapipe included; splatting-only commands take WGSL.
//!   `VCEDIT_GPU_COMPILER=wgsl|spirv` forces one (an A/B switch for benchmarks and the tests);
//!   [`GpuContext::compiler`] says which one a device got.
//! - [`gpu_call`]: runs a unit of GPU work ("launch…; read") and maps every failure, panics included, to
//!   one [`GpuError`].
//!
//! Kernels report failures (out of memory, lost device) when their results are read, not at launch, and
//! a bug in a kernel's compile-time code panics on the caller's thread: hence one wrapper around whole
//! units of work rather than around each launch.

use std::fmt;
use std::str::FromStr;

pub use buffer::{BufferTooSmall, F32Buffer, F32Values};
pub use cubecl;
use cubecl::client::Client;
use cubecl::device::{WgpuBackend, WgpuDeviceKind};
use cubecl::ir::{ElemType, FloatKind};
use cubecl::wgpu::{wgpu, AutoGraphicsApi, RuntimeOptions, WgpuDevice, WgpuRuntime, WgslCompiler};
use cubecl_runtime::runtime::Runtime;

mod buffer;
mod cuda;
mod memory;
pub mod prims;
pub mod reduce;
pub mod testing;
pub mod traffic;

/// Environment variable holding the default device choice.
pub const DEVICE_ENV: &str = "VCEDIT_DEVICE";
/// Set to `1` to let `auto` pick a software adapter (lavapipe/llvmpipe, WARP, SwiftShader).
pub const ALLOW_SOFTWARE_ENV: &str = "VCEDIT_ALLOW_SOFTWARE_GPU";
/// `wgsl` forces the WGSL compiler, `spirv` SPIR-V where the adapter supports it (lavapipe included);
/// `auto` (the default) takes SPIR-V where the adapter supports it and runs it well.
pub const COMPILER_ENV: &str = "VCEDIT_GPU_COMPILER";

/// What a process will mostly run, which decides the shader compiler under `auto`: measured on an
/// NVIDIA H200 (docs/gpu-results.md, 2026-11-26), SPIR-V with tensor cores runs the SD 1.5 UNet 3.2×
/// faster than WGSL, but `vcedit fit` 2.6× slower (86 s against 34 s on lego-200: the splatting
/// backward and training steps are slower there, not yet understood). On an H100 the demo, whose
/// networks are tiny and whose time is splatting, was slower on SPIR-V too, so it runs as `Splatting`.
/// A process has one client (the engines share buffers), so the choice is per process.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Workload {
    /// The diffusion networks (edit, edit-image): SPIR-V where the adapter supports it.
    #[default]
    Networks,
    /// Mostly splatting (fit, render, metrics, the demo): WGSL.
    Splatting,
}

/// Which shader compiler serves the device.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum CompilerChoice {
    /// SPIR-V on capable Vulkan adapters, WGSL elsewhere.
    #[default]
    Auto,
    /// WGSL on every adapter (no cooperative matrices, f32 arithmetic).
    Wgsl,
    /// SPIR-V wherever the adapter supports it, lavapipe included (its kernels with workgroup memory
    /// then crash: see `AdapterEntry::spirv_workgroup_memory_invalid`).
    Spirv,
}

impl CompilerChoice {
    /// The choice in `VCEDIT_GPU_COMPILER` (`auto` when unset).
    pub fn from_env() -> Result<CompilerChoice, GpuError> {
        std::env::var(COMPILER_ENV).map_or(Ok(Self::Auto), |v| v.parse())
    }
}

impl FromStr for CompilerChoice {
    type Err = GpuError;

    fn from_str(s: &str) -> Result<Self, GpuError> {
        match s.trim().to_ascii_lowercase().as_str() {
            "" | "auto" => Ok(Self::Auto),
            "wgsl" => Ok(Self::Wgsl),
            "spirv" if cfg!(feature = "spirv") => Ok(Self::Spirv),
            "spirv" => Err(GpuError::SpirvNotBuilt),
            other => Err(GpuError::BadCompiler(other.to_string())),
        }
    }
}

/// Where the compute runs.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum DeviceChoice {
    Cpu,
    /// A GPU on the best runtime that opens (CUDA, else wgpu), software adapters included; an error
    /// without one.
    Gpu,
    /// A hardware GPU on the best runtime that opens, else the CPU.
    #[default]
    Auto,
    /// The CUDA runtime only (an error where it cannot open, naming what is missing).
    Cuda,
    /// The wgpu runtime only: Vulkan, Metal or DX12, whichever the platform has (`vulkan`, `metal` and
    /// `dx12` are accepted as its names).
    Wgpu,
}

impl FromStr for DeviceChoice {
    type Err = GpuError;

    fn from_str(s: &str) -> Result<Self, GpuError> {
        match s.trim().to_ascii_lowercase().as_str() {
            "cpu" => Ok(Self::Cpu),
            "gpu" => Ok(Self::Gpu),
            "auto" => Ok(Self::Auto),
            "cuda" => Ok(Self::Cuda),
            "wgpu" | "vulkan" | "metal" | "dx12" => Ok(Self::Wgpu),
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
            Self::Cuda => "cuda",
            Self::Wgpu => "wgpu",
        })
    }
}

/// Which runtime `gpu` and `auto` may take (`VCEDIT_GPU_RUNTIME`): both, CUDA first (the default), or
/// one of them, so that benchmarks, the tests and `tools/gpu-check` run every GPU step on one runtime
/// without a flag on each command. `--device cuda`/`wgpu` name a runtime themselves and ignore it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum RuntimeChoice {
    #[default]
    Auto,
    Cuda,
    Wgpu,
}

/// Environment variable holding the [`RuntimeChoice`].
pub const RUNTIME_ENV: &str = "VCEDIT_GPU_RUNTIME";

impl RuntimeChoice {
    /// The choice in `VCEDIT_GPU_RUNTIME` (`auto` when unset or empty).
    pub fn from_env() -> Result<RuntimeChoice, GpuError> {
        match std::env::var(RUNTIME_ENV) {
            Ok(v) => match v.trim().to_ascii_lowercase().as_str() {
                "" | "auto" => Ok(Self::Auto),
                "cuda" => Ok(Self::Cuda),
                "wgpu" | "vulkan" | "metal" | "dx12" => Ok(Self::Wgpu),
                other => Err(GpuError::BadRuntime(other.to_string())),
            },
            Err(_) => Ok(Self::Auto),
        }
    }
}

/// The CubeCL runtime a [`GpuContext`] launches its kernels on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GpuRuntime {
    /// wgpu: Vulkan (SPIR-V or WGSL), Metal or DX12.
    Wgpu,
    /// CUDA: C++ kernels compiled to PTX by NVRTC.
    Cuda,
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
    #[error("unknown device '{0}' (expected cpu, gpu, auto, cuda or wgpu)")]
    BadChoice(String),
    #[error("unknown GPU runtime '{0}' in VCEDIT_GPU_RUNTIME (expected auto, cuda or wgpu)")]
    BadRuntime(String),
    /// `--device cuda` where CUDA cannot run: the reason names what is missing and how to get it.
    #[error("CUDA unavailable: {0}")]
    CudaUnavailable(String),
    #[error("unknown shader compiler '{0}' in VCEDIT_GPU_COMPILER (expected auto, wgsl or spirv)")]
    BadCompiler(String),
    #[error("{COMPILER_ENV}=spirv: this build has no SPIR-V compiler (built without vcedit-gpu's `spirv` feature)")]
    SpirvNotBuilt,
    /// One engine handed another a buffer too small for what it said it held (a bug, not a user error).
    #[error(transparent)]
    BufferTooSmall(BufferTooSmall),
    /// Values in a GPU buffer handed to work on the CPU (both engines run on one device: a bug, not a
    /// user error).
    #[error("values in a GPU buffer handed to {0} on the CPU")]
    BufferOnCpu(&'static str),
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
    /// The runtime the kernels launch on.
    pub runtime: GpuRuntime,
    /// API the kernels run through ("Vulkan", "Metal", "Dx12", "CUDA").
    pub backend: String,
    /// The kernel compiler serving the device, as CubeCL names its runtime: "wgpu<spirv>", "wgpu<wgsl>"
    /// or "cuda".
    pub compiler: String,
    /// Whether the device multiplies f16 tiles into f32 sums with cooperative matrices (tensor cores):
    /// registered by CUDA (WMMA, sm_70 and newer) and by wgpu's SPIR-V path, never by WGSL.
    pub tensor_cores: bool,
    /// Whether the adapter is a software rasteriser on the CPU.
    pub software: bool,
    pub limits: GpuLimits,
    /// Why a runtime that `auto`/`gpu` prefers was not taken (e.g. "CUDA: NVRTC not found ..."), for the
    /// run log; `None` when the first choice opened or was never in question.
    pub passed_over: Option<String>,
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

/// CubeCL's name for the SPIR-V compiler of the wgpu runtime (`GpuContext::compiler`).
const SPIRV_COMPILER: &str = "wgpu<spirv>";

impl GpuContext {
    /// Whether the kernels go through the SPIR-V compiler (else WGSL).
    pub fn on_spirv(&self) -> bool {
        self.compiler == SPIRV_COMPILER
    }

    /// One line for run logs: "llvmpipe (LLVM 15.0.6, 256 bits) via Vulkan, SPIR-V (software)",
    /// "NVIDIA H200 via CUDA, C++ (NVRTC) with tensor cores".
    pub fn describe(&self) -> String {
        let compiler = match self.compiler.as_str() {
            SPIRV_COMPILER => "SPIR-V",
            "wgpu<wgsl>" => "WGSL",
            "wgpu<msl>" => "MSL",
            _ if self.runtime == GpuRuntime::Cuda => "C++ (NVRTC)",
            other => other,
        };
        format!(
            "{} via {}, {compiler}{}{}",
            self.adapter,
            self.backend,
            if self.tensor_cores {
                " with tensor cores"
            } else {
                ""
            },
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
    /// The driver's own description, e.g. "Mesa 25.0.7-2~bpo12+1 (LLVM 15.0.6)".
    pub driver_info: String,
    /// A Vulkan adapter offering `VK_KHR_workgroup_memory_explicit_layout` (false elsewhere).
    pub explicit_workgroup_layout: bool,
    kind: WgpuDeviceKind,
}

impl AdapterEntry {
    /// Whether cubecl's SPIR-V kernels with workgroup (shared) memory are invalid on this adapter.
    /// cubecl-spirv 0.11.3 lowers workgroup memory two ways: through
    /// `VK_KHR_workgroup_memory_explicit_layout` where the device has it (NVIDIA, RADV, ANV), and
    /// otherwise as plain `Workgroup` variables, where it declares each variable with the *pointer* type
    /// as its contents and takes its address as the array type. The Vulkan validation layer rejects
    /// that module ("OpInBoundsAccessChain reached non-composite type while indexes still remain to be
    /// traversed") and Mesa's lavapipe (22.3 and 25.0.7, which lack the extension) crashes compiling it.
    /// `tools/spirv-lavapipe` holds the two-line fix and runs the tests with it. Such adapters get WGSL
    /// under `auto`; `VCEDIT_GPU_COMPILER=spirv` still forces SPIR-V (the tests of the kernels without
    /// workgroup memory).
    fn spirv_workgroup_memory_invalid(&self) -> bool {
        self.backend == WgpuBackend::Vulkan && !self.explicit_workgroup_layout
    }
}

/// Whether a Vulkan adapter offers `VK_KHR_workgroup_memory_explicit_layout` (see
/// [`AdapterEntry::spirv_workgroup_memory_invalid`]); false for other backends.
fn has_explicit_workgroup_layout(adapter: &wgpu::Adapter) -> bool {
    // SAFETY: the raw adapter is only queried for its extension list, not used to create anything.
    unsafe { adapter.as_hal::<wgpu::hal::api::Vulkan>() }.is_some_and(|hal| {
        hal.physical_device_capabilities()
            .supports_extension(c"VK_KHR_workgroup_memory_explicit_layout")
    })
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
            .map(|a| (a.get_info(), has_explicit_workgroup_layout(a)))
            .collect::<Vec<_>>()
    })
    .unwrap_or_default();
    // CubeCL addresses adapters as "the n-th adapter of this type", counted over all backends.
    let mut next = [0usize; 4];
    let mut out = vec![];
    for (info, explicit_workgroup_layout) in found {
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
            driver_info: info.driver_info,
            explicit_workgroup_layout,
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

/// Opens the device `choice` names for the networks (see [`open_for`]).
pub fn open(choice: DeviceChoice) -> Result<Option<GpuContext>, GpuError> {
    open_for(choice, Workload::Networks)
}

/// Opens the device `choice` names: `Ok(None)` means "use the CPU" (`cpu`, or `auto` without a usable
/// GPU); `gpu` without any adapter is [`GpuError::NoAdapter`], `cuda` where CUDA cannot run
/// [`GpuError::CudaUnavailable`]. `auto` and `gpu` try CUDA first (a process probes it once), then wgpu.
/// On wgpu, `workload` picks the shader compiler unless `VCEDIT_GPU_COMPILER` names one; CUDA has one
/// compiler for every workload.
pub fn open_for(choice: DeviceChoice, workload: Workload) -> Result<Option<GpuContext>, GpuError> {
    let open_cuda = || {
        cuda::open()
            .map(Some)
            .map_err(|e| GpuError::CudaUnavailable(e.to_string()))
    };
    match (choice, RuntimeChoice::from_env()?) {
        (DeviceChoice::Cpu, _) => Ok(None),
        (DeviceChoice::Cuda, _) | (DeviceChoice::Gpu | DeviceChoice::Auto, RuntimeChoice::Cuda) => {
            open_cuda()
        }
        (DeviceChoice::Wgpu, _) => open_wgpu(DeviceChoice::Gpu, workload),
        (DeviceChoice::Gpu | DeviceChoice::Auto, RuntimeChoice::Wgpu) => {
            open_wgpu(choice, workload)
        }
        (DeviceChoice::Gpu | DeviceChoice::Auto, RuntimeChoice::Auto) => match cuda::open() {
            Ok(ctx) => Ok(Some(ctx)),
            Err(why) => {
                let mut ctx = open_wgpu(choice, workload)?;
                if let Some(ctx) = &mut ctx {
                    ctx.passed_over = why.worth_saying();
                }
                Ok(ctx)
            }
        },
    }
}

/// Why `auto` passed CUDA over on this machine, where that is worth a line in the run log: an NVIDIA
/// driver is installed but CUDA could not run (NVRTC or the CUDA headers missing, a failed probe
/// kernel). `None` on machines without an NVIDIA driver or CUDA device, and in builds without CUDA.
pub fn cuda_passed_over() -> Option<String> {
    cuda::open().err().and_then(|why| why.worth_saying())
}

/// Opens a wgpu adapter for `choice` (`Gpu`: software adapters too; `Auto`: hardware ones unless
/// allowed).
fn open_wgpu(choice: DeviceChoice, workload: Workload) -> Result<Option<GpuContext>, GpuError> {
    let compiler = CompilerChoice::from_env()?;
    let adapters = list_adapters();
    let hardware = adapters.iter().find(|a| !a.software);
    let software = adapters.iter().find(|a| a.software);
    let pick = match choice {
        DeviceChoice::Gpu => hardware.or(software),
        _ if software_allowed() => hardware.or(software),
        _ => hardware,
    };
    match (pick, choice) {
        (Some(a), _) => open_adapter(a, forces_wgsl(compiler, workload, a)).map(Some),
        (None, DeviceChoice::Gpu) => Err(GpuError::NoAdapter),
        (None, _) => Ok(None),
    }
}

/// The one decision of the shader compiler: whether the device gets WGSL where cubecl would take SPIR-V.
/// A build without the `spirv` feature has WGSL only.
fn forces_wgsl(compiler: CompilerChoice, workload: Workload, a: &AdapterEntry) -> bool {
    if !cfg!(feature = "spirv") {
        return true;
    }
    match compiler {
        CompilerChoice::Wgsl => true,
        CompilerChoice::Spirv => false,
        CompilerChoice::Auto => {
            workload == Workload::Splatting || a.spirv_workgroup_memory_invalid()
        }
    }
}

/// cubecl's runtime configuration, set once before the first device opens: compiled SPIR-V kernels and
/// autotune results persist in vcedit's user cache folder (`files::cache_dir()/cubecl`). Left alone,
/// cubecl reads a `cubecl.toml` from the working directory and keeps its cache under the outermost
/// `Cargo.toml` above it (`target/environment`), so a run inside any Rust project wrote there, and it
/// compiled every kernel again in each process (~35 s of the first UNet call on an H100; WGSL kernels
/// are never persisted, SPIR-V ones are with `compilation.cache`). Its `CUBECL_*` variables still apply.
///
/// Kernels persist only in a process whose first device is on SPIR-V or CUDA (`spirv`; CUDA keeps its
/// PTX in a store of its own, per card architecture): cubecl 0.11.3 keys a
/// persisted kernel by the kernel and the device, not by the compiler, so a WGSL-typed device loads the
/// SPIR-V kernels an earlier process stored and runs them instead of its own. That made `vcedit fit`
/// (WGSL under `auto`) run SPIR-V's splatting kernels whenever an edit had run before it: 83-90 s
/// instead of 31-34 s on an H200 (docs/gpu-results.md, 2026-11-27 third run). `VCEDIT_GPU_CACHE=off`
/// persists nothing, kernels or tuning results (for a read-only cache folder). Returns whether this
/// process persists kernels.
fn configure_runtime(spirv: bool) -> bool {
    use cubecl::config::cache::CacheConfig;
    use cubecl::config::{CubeClRuntimeConfig, RuntimeConfig};
    use std::sync::atomic::{AtomicBool, Ordering};
    static ONCE: std::sync::Once = std::sync::Once::new();
    static PERSISTING: AtomicBool = AtomicBool::new(false);
    ONCE.call_once(|| {
        let persist = spirv && tuning_persists();
        let mut config = CubeClRuntimeConfig::default().override_from_env();
        config.environment.path = CacheConfig::Directory(runtime_cache_dir());
        config.compilation.cache = persist;
        // Tuning results are kept per adapter and compiler (vcedit names them so), so they persist on
        // either compiler; `VCEDIT_GPU_CACHE=off` keeps them in memory only.
        config.autotune.disable_cache = !tuning_persists();
        // vcedit's only tuned op is the convolution path, two candidates, which cubecl's tuner never
        // eliminates (it keeps two survivors): by default each runs until its best time stops improving,
        // up to 10 samples after a warm-up. One sample each decides as well where it matters: where the
        // paths differ by more than lavapipe's run-to-run spread (~2 %), and where they do not, either is
        // fine. It cuts the one-off cost on slow devices: on lavapipe the direct kernel takes ~0.6 s a pass
        // on some of LPIPS's layers, and tuning LPIPS at 64² took 37 s with the default (2026-11-29).
        config.autotune.bench.min_samples = 1;
        config.autotune.bench.max_samples = 1;
        // `false`: something read the configuration first; it keeps cubecl's defaults (nothing
        // persisted).
        if CubeClRuntimeConfig::try_set(config) {
            PERSISTING.store(persist, Ordering::Relaxed);
        }
    });
    PERSISTING.load(Ordering::Relaxed)
}

/// Whether what cubecl compiles and tunes persists between processes: `VCEDIT_GPU_CACHE` allows it
/// ([`persist_kernels`]) and the cache folder can be written (a read-only folder or a file in its place
/// cannot keep anything; this says so once, on stderr). Where tuning results do not persist, timing
/// would choose again in every process, and two paths of one operation differ in their last bits: the
/// callers (the convolution path) then choose by a fixed rule, so the same seed gives the same bytes.
pub fn tuning_persists() -> bool {
    static PERSISTS: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *PERSISTS.get_or_init(|| {
        if !persist_kernels() {
            return false;
        }
        let dir = runtime_cache_dir();
        match std::fs::create_dir_all(&dir).and_then(|()| files::check_writable_folder(&dir)) {
            Ok(()) => true,
            Err(e) => {
                eprintln!(
                    "warning: the GPU cache folder {} cannot be written ({e}): compiled kernels and \
                     tuning results are not kept, and convolutions take one fixed path",
                    dir.display()
                );
                false
            }
        }
    })
}

/// Whether compiled kernels may persist between processes: unless `VCEDIT_GPU_CACHE` is `off`, `0` or
/// `false`.
fn persist_kernels() -> bool {
    !matches!(
        std::env::var(CACHE_ENV).as_deref().map(str::trim),
        Ok("off" | "0" | "false")
    )
}

/// The switch that keeps compiled kernels from being persisted.
const CACHE_ENV: &str = "VCEDIT_GPU_CACHE";

/// Where cubecl's caches go: `cubecl` in vcedit's cache folder.
fn runtime_cache_dir() -> std::path::PathBuf {
    files::cache_dir().join("cubecl")
}

/// Opens `a` on cubecl's automatic compiler (SPIR-V where the adapter supports it), or on WGSL.
fn open_adapter(a: &AdapterEntry, wgsl: bool) -> Result<GpuContext, GpuError> {
    // cubecl's automatic compiler takes SPIR-V on Vulkan only.
    if configure_runtime(!wgsl && a.backend == WgpuBackend::Vulkan) && wgsl {
        // Its kernels would be the SPIR-V ones this process persists (see `configure_runtime`).
        return Err(GpuError::Kernel(format!(
            "cannot open {} on WGSL in a process that opened a device on SPIR-V and persists its \
             kernels: set {CACHE_ENV}=off, or {COMPILER_ENV} to one compiler",
            a.name
        )));
    }
    let device = WgpuDevice::new(a.kind.clone()).on(a.backend);
    let cannot =
        |e: &dyn fmt::Display| GpuError::Kernel(format!("cannot initialise {}: {e}", a.name));
    let (backend, client) = if wgsl {
        // A runtime typed on the WGSL compiler is a separate service: its client is created on first
        // use (a failure there panics, which `gpu_call` turns into an error).
        let client = gpu_call(|| Ok(WgpuRuntime::<WgslCompiler>::client(&device)))?;
        (format!("{:?}", a.backend), client)
    } else {
        // The fallible initialisation registers the client; `.client()` on an unknown device would
        // panic.
        let setup = gpu_call(|| {
            cubecl::wgpu::try_init_setup::<AutoGraphicsApi>(&device, RuntimeOptions::default())
                .map_err(|e| cannot(&e))
        })?;
        let client = gpu_call(|| Ok(cubecl::Device::Wgpu(device).client()))?;
        (format!("{:?}", setup.backend), client)
    };
    // A WGSL-typed runtime names itself after the adapter's capabilities ("wgpu<spirv>" on a Vulkan
    // adapter that could take SPIR-V), not after its compiler.
    let compiler = if wgsl {
        "wgpu<wgsl>".to_string()
    } else {
        client.name().to_string()
    };
    let tensor_cores = compiler == SPIRV_COMPILER && has_f16_tensor_cores(&client);
    Ok(context_of(
        client,
        GpuRuntime::Wgpu,
        backend,
        compiler,
        tensor_cores,
        a.software,
    ))
}

/// The [`GpuContext`] of an opened `client`: its name, limits and the card's free memory.
fn context_of(
    client: Client,
    runtime: GpuRuntime,
    backend: String,
    compiler: String,
    tensor_cores: bool,
    software: bool,
) -> GpuContext {
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
    GpuContext {
        adapter: props.identity.name.clone(),
        client,
        runtime,
        backend,
        compiler,
        tensor_cores,
        software,
        limits,
        passed_over: None,
    }
}

/// Whether the device registers a cooperative-matrix shape multiplying f16 tiles into f32 sums.
fn has_f16_tensor_cores(client: &Client) -> bool {
    let (f16, f32) = (
        ElemType::Float(FloatKind::F16),
        ElemType::Float(FloatKind::F32),
    );
    client
        .properties()
        .features
        .matmul
        .cmma
        .iter()
        .any(|c| c.a_type == f16 && c.b_type == f16 && c.cd_type == f32)
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
        assert_eq!("CUDA".parse::<DeviceChoice>().unwrap(), DeviceChoice::Cuda);
        for wgpu in ["wgpu", "vulkan", "Metal", "dx12"] {
            assert_eq!(wgpu.parse::<DeviceChoice>().unwrap(), DeviceChoice::Wgpu);
        }
        let e = "tpu".parse::<DeviceChoice>().unwrap_err();
        assert_eq!(
            e.to_string(),
            "unknown device 'tpu' (expected cpu, gpu, auto, cuda or wgpu)"
        );
        for c in [
            DeviceChoice::Cpu,
            DeviceChoice::Gpu,
            DeviceChoice::Auto,
            DeviceChoice::Cuda,
            DeviceChoice::Wgpu,
        ] {
            assert_eq!(c.to_string().parse::<DeviceChoice>().unwrap(), c);
        }
    }

    /// `cargo test -p vcedit-gpu --no-default-features`.
    #[test]
    #[cfg(not(feature = "spirv"))]
    fn without_spirv_every_adapter_gets_wgsl() {
        let card = AdapterEntry {
            name: "NVIDIA H200".into(),
            backend: WgpuBackend::Vulkan,
            software: false,
            driver_info: String::new(),
            explicit_workgroup_layout: true,
            kind: WgpuDeviceKind::Cpu,
        };
        for compiler in [CompilerChoice::Auto, CompilerChoice::Spirv] {
            assert!(forces_wgsl(compiler, Workload::Networks, &card));
        }
        assert!(matches!(
            "spirv".parse::<CompilerChoice>(),
            Err(GpuError::SpirvNotBuilt)
        ));
    }

    #[test]
    #[cfg(feature = "spirv")]
    fn the_compiler_follows_workload_adapter_and_override() {
        let entry = |name: &str, explicit_workgroup_layout: bool| AdapterEntry {
            name: name.into(),
            backend: WgpuBackend::Vulkan,
            software: true,
            driver_info: String::new(),
            explicit_workgroup_layout,
            kind: WgpuDeviceKind::Cpu,
        };
        // What the adapters report: lavapipe lacks the extension, the NVIDIA driver has it.
        let (lavapipe, card) = (
            entry("llvmpipe (LLVM 15.0.6, 256 bits)", false),
            entry("NVIDIA H200", true),
        );
        use {CompilerChoice as C, Workload as W};
        assert!(forces_wgsl(C::Auto, W::Networks, &lavapipe));
        assert!(!forces_wgsl(C::Spirv, W::Networks, &lavapipe));
        assert!(!forces_wgsl(C::Auto, W::Networks, &card));
        assert!(forces_wgsl(C::Auto, W::Splatting, &card));
        assert!(!forces_wgsl(C::Spirv, W::Splatting, &card));
        assert!(forces_wgsl(C::Wgsl, W::Networks, &card));
        // The decision follows the extension, not the name: a hardware adapter without it (older
        // mobile drivers) gets WGSL too, and Metal/DX12 never compile SPIR-V anyway.
        assert!(forces_wgsl(C::Auto, W::Networks, &entry("Mali-G78", false)));
        let metal = AdapterEntry {
            backend: WgpuBackend::Metal,
            ..entry("Apple M2", false)
        };
        assert!(!forces_wgsl(C::Auto, W::Networks, &metal));
    }

    #[test]
    fn lavapipe_reports_no_explicit_workgroup_layout() {
        // Mesa's lavapipe (22.3, 25.0.7) is the adapter CI has: it lacks the extension, so `auto`
        // keeps it on WGSL whatever its name.
        let lavapipes: Vec<_> = list_adapters()
            .into_iter()
            .filter(|a| a.name.contains("llvmpipe"))
            .collect();
        if lavapipes.is_empty() {
            eprintln!("skipped: no lavapipe adapter");
        }
        for a in lavapipes {
            assert!(
                !a.explicit_workgroup_layout,
                "{}: {}",
                a.name, a.driver_info
            );
            assert!(a.spirv_workgroup_memory_invalid());
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

    /// The smallest kernel with workgroup memory: each unit writes its slot and reads it back.
    #[cube(launch)]
    fn workgroup_round_trip(out: &mut [f32]) {
        let mut s = Shared::<[f32]>::new_slice(64usize);
        let u = UNIT_POS as usize;
        s[u] = u as f32;
        out[u] = s[u];
    }

    /// The minimal case of cubecl-spirv's invalid workgroup memory (`AdapterEntry::
    /// spirv_workgroup_memory_invalid`): on lavapipe's SPIR-V path it crashes the process unless
    /// cubecl-spirv carries tools/spirv-lavapipe's patch (`tools/spirv-lavapipe/run.sh test
    /// workgroup_memory`); on WGSL and on adapters with the explicit layout it runs.
    #[test]
    fn workgroup_memory_round_trips() {
        let Some(ctx) = testing::context_or_skip() else {
            return;
        };
        let c = &ctx.client;
        let out = prims::empty32(c, 64);
        workgroup_round_trip::launch(
            c,
            CubeCount::new_single(),
            CubeDim::new_1d(64),
            prims::arg(&out, 64),
        );
        let got = prims::read_f32(c, &out, 64).unwrap();
        assert!(
            got.iter().enumerate().all(|(i, &v)| v == i as f32),
            "{got:?}"
        );
    }

    /// Kernels persist only where the device compiles SPIR-V, and a process that persists them opens
    /// no WGSL device: cubecl 0.11.3's kernel store is blind to the compiler, so that device would run
    /// the stored SPIR-V kernels in place of its own (`configure_runtime`). CI runs this on both paths.
    #[test]
    fn kernels_persist_only_on_spirv() {
        use cubecl::config::{CubeClRuntimeConfig, RuntimeConfig};
        let Some(ctx) = testing::context_or_skip() else {
            return;
        };
        let persisting = CubeClRuntimeConfig::get().compilation.cache;
        // CUDA's compiled kernels live in a store of their own (per card architecture), so they persist.
        assert_eq!(
            persisting,
            (ctx.on_spirv() || ctx.runtime == GpuRuntime::Cuda) && tuning_persists(),
            "{}",
            ctx.describe()
        );
        if persisting {
            let same = list_adapters()
                .into_iter()
                .find(|a| a.name == ctx.adapter)
                .unwrap();
            let e = open_adapter(&same, true).map(|_| ()).unwrap_err();
            assert!(e.to_string().contains(CACHE_ENV), "{e}");
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
