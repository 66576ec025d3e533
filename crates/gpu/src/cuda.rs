//! The CUDA runtime: the same CubeCL kernels as on wgpu, transpiled to CUDA C++ and compiled to PTX by
//! NVRTC when first launched (cubecl-cuda, built from the patched copy in `vendor/cubecl-cuda`). On
//! NVIDIA cards it brings what Vulkan lacks: WMMA and `mma` tensor-core products, relaxed atomics and
//! cheaper launches.
//!
//! Nothing is linked at build time: the NVIDIA driver (`libcuda`) and NVRTC (`libnvrtc`) are loaded
//! when a device opens, and NVRTC reads the CUDA headers from `$CUDA_PATH/include` (else
//! `/usr/local/cuda`, `/opt/cuda`, `/usr`). [`open`] checks each of these before it creates anything, so
//! a machine that lacks one gets a sentence naming it and how to get it instead of a panic, and ends
//! with a probe kernel compiled and run, so a broken toolchain is found before any real work starts.
//! A process probes once; the outcome (the context, or why not) is kept.

use std::fmt;
use std::path::Path;

/// Why the CUDA runtime did not open.
#[derive(Clone, Debug, PartialEq, Eq)]
// A build with CUDA never says `NotBuilt`; one without it says nothing else.
#[allow(dead_code)]
pub(crate) enum CudaMissing {
    /// This build has no CUDA runtime (the `cuda` cargo feature is off).
    NotBuilt,
    /// No NVIDIA driver: `libcuda` does not load.
    NoDriver,
    /// The driver loads but reports no CUDA device.
    NoDevice,
    /// An NVIDIA card is there but CUDA cannot run on it; the text says what is missing and how to get
    /// it.
    Unusable(String),
}

impl CudaMissing {
    /// A line for a run that fell back to another runtime: only where the user has an NVIDIA card and
    /// might want to fix CUDA. Builds without CUDA and machines without NVIDIA's driver stay silent.
    pub(crate) fn worth_saying(&self) -> Option<String> {
        match self {
            Self::Unusable(why) => Some(format!("CUDA not used: {why}")),
            Self::NotBuilt | Self::NoDriver | Self::NoDevice => None,
        }
    }
}

impl fmt::Display for CudaMissing {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::NotBuilt => f.write_str(
                "this vcedit was built without the CUDA runtime (build it with `--features cuda`)",
            ),
            Self::NoDriver => f.write_str("no NVIDIA driver found (libcuda.so does not load)"),
            Self::NoDevice => f.write_str("the NVIDIA driver reports no CUDA device"),
            Self::Unusable(why) => f.write_str(why),
        }
    }
}

/// The headers NVRTC needs for vcedit's kernels, relative to the include folder: half and bfloat16
/// types, the WMMA tensor-core API, cooperative groups (asynchronous copies), and CCCL's `cuda/barrier`
/// (the product library's pipelined routines), which CUDA 12 keeps in `include/` and CUDA 13 in
/// `include/cccl/`.
#[cfg_attr(not(feature = "cuda"), allow(dead_code))]
const HEADERS: [&str; 5] = [
    "cuda_fp16.h",
    "cuda_bf16.h",
    "mma.h",
    "cooperative_groups.h",
    "cuda/barrier",
];

/// The headers of [`HEADERS`] missing under `cuda_root/include` (CCCL's also looked for under
/// `include/cccl`).
#[cfg_attr(not(feature = "cuda"), allow(dead_code))]
pub(crate) fn missing_headers(cuda_root: &Path) -> Vec<&'static str> {
    let include = cuda_root.join("include");
    HEADERS
        .into_iter()
        .filter(|h| !include.join(h).is_file() && !include.join("cccl").join(h).is_file())
        .collect()
}

/// What a user without the headers does: a CUDA toolkit, or NVIDIA's CUDA 13 wheels, which share one
/// folder (`site-packages/nvidia/cu13`, with `include/` and `include/cccl/`).
#[cfg_attr(not(feature = "cuda"), allow(dead_code))]
const GET_HEADERS: &str = "install a CUDA toolkit and set CUDA_PATH to it, or `pip install nvidia-cuda-runtime \
     nvidia-cuda-cccl nvidia-cuda-nvrtc` (CUDA 13) and set CUDA_PATH to their site-packages/nvidia/cu13";

/// The sentence for a header check of `root` (`None`: no CUDA folder found at all).
#[cfg_attr(not(feature = "cuda"), allow(dead_code))]
fn header_problem(root: Option<&Path>) -> Option<String> {
    let Some(root) = root else {
        return Some(format!(
            "the CUDA headers NVRTC compiles against were not found (no $CUDA_PATH, /usr/local/cuda, \
             /opt/cuda or /usr/bin/nvcc): {GET_HEADERS}"
        ));
    };
    let missing = missing_headers(root);
    (!missing.is_empty()).then(|| {
        format!(
            "{} lacks {} (NVRTC compiles vcedit's kernels against them): {GET_HEADERS}",
            root.join("include").display(),
            missing.join(", ")
        )
    })
}

#[cfg(feature = "cuda")]
mod runtime {
    use super::{header_problem, CudaMissing};
    use crate::{configure_runtime, context_of, gpu_call, has_f16_tensor_cores};
    use crate::{GpuContext, GpuError, GpuRuntime};
    use cubecl::prelude::*;

    /// The first CUDA device, probed once per process.
    pub(crate) fn open() -> Result<GpuContext, CudaMissing> {
        static OPENED: std::sync::OnceLock<Result<GpuContext, CudaMissing>> =
            std::sync::OnceLock::new();
        OPENED.get_or_init(probe).clone()
    }

    fn probe() -> Result<GpuContext, CudaMissing> {
        // SAFETY: both only try to `dlopen` the libraries' usual names.
        if !unsafe { cudarc::driver::sys::is_culib_present() } {
            return Err(CudaMissing::NoDriver);
        }
        // Enumerating asks the driver for its device count; it fails soft (no device) rather than
        // panicking, unlike creating a client.
        let device = match cubecl::Device::cuda(0) {
            Ok(d) => d,
            Err(_) => return Err(CudaMissing::NoDevice),
        };
        if !unsafe { cudarc::nvrtc::sys::is_culib_present() } {
            return Err(CudaMissing::Unusable(
                "NVRTC (libnvrtc.so.13 or .12, CUDA's run-time compiler) does not load: install a CUDA \
                 toolkit, or `pip install nvidia-cuda-nvrtc` (PyTorch's CUDA wheels bring it too) and \
                 add the folder holding libnvrtc.so.13 (site-packages/nvidia/cu13/lib) to \
                 LD_LIBRARY_PATH"
                    .into(),
            ));
        }
        // cubecl-cuda's own lookup; it panics at the first kernel where this finds nothing.
        if let Some(problem) = header_problem(cubecl::cuda::install::cuda_path().as_deref()) {
            return Err(CudaMissing::Unusable(problem));
        }
        // Compiled PTX is kept per card architecture in cubecl-cuda's own store, apart from wgpu's
        // kernels, so it persists as SPIR-V does (see `configure_runtime`): NVRTC takes a while per
        // kernel.
        configure_runtime(true);
        let unusable = |e: GpuError| CudaMissing::Unusable(format!("the CUDA device failed: {e}"));
        // A driver too old for the bindings (a missing symbol) or a broken install panics in cubecl:
        // the panic becomes the reason, and its message is not printed as a crash as well.
        let client = quietly(|| gpu_call(|| Ok(device.client()))).map_err(unusable)?;
        quietly(|| probe_kernel(&client)).map_err(|e| {
            CudaMissing::Unusable(format!(
                "a probe kernel failed to compile or run (NVRTC and the driver may not match; \
                 CUDA_PATH={}): {e}",
                cubecl::cuda::install::cuda_path()
                    .map_or_else(|| "unset".into(), |p| p.display().to_string())
            ))
        })?;
        let tensor_cores = has_f16_tensor_cores(&client);
        Ok(context_of(
            client,
            GpuRuntime::Cuda,
            "CUDA".into(),
            "cuda".into(),
            tensor_cores,
            false,
        ))
    }

    /// Runs `f` with panic messages silenced (the default hook prints them even where they are caught);
    /// used while probing, before any other thread of vcedit runs kernels.
    fn quietly<T>(f: impl FnOnce() -> T) -> T {
        let hook = std::panic::take_hook();
        std::panic::set_hook(Box::new(|_| {}));
        let out = f();
        std::panic::set_hook(hook);
        out
    }

    #[cube(launch)]
    fn add_half(x: &mut [f32]) {
        if ABSOLUTE_POS < x.len() {
            // Through f16, so the probe needs the half-precision header as the networks do.
            x[ABSOLUTE_POS] =
                f32::cast_from(half::f16::cast_from(x[ABSOLUTE_POS]) + half::f16::new(0.5));
        }
    }

    /// Compiles one kernel with NVRTC, runs it and checks its result.
    fn probe_kernel(client: &cubecl::client::Client) -> Result<(), GpuError> {
        gpu_call(|| {
            let input = [1.0f32, 2.0, 3.0];
            let h = client.create_from_slice(f32::as_bytes(&input));
            add_half::launch(
                client,
                CubeCount::new_single(),
                CubeDim::new_1d(4),
                unsafe { BufferArg::from_raw_parts(h.clone(), input.len()) },
            );
            let bytes = client.read_one(h).map_err(crate::server_error)?;
            let got = f32::from_bytes(&bytes);
            if got == [1.5, 2.5, 3.5] {
                Ok(())
            } else {
                Err(GpuError::Kernel(format!(
                    "expected [1.5, 2.5, 3.5], read {got:?}"
                )))
            }
        })
    }
}

#[cfg(feature = "cuda")]
pub(crate) use runtime::open;

/// Without the `cuda` feature there is nothing to open.
#[cfg(not(feature = "cuda"))]
pub(crate) fn open() -> Result<crate::GpuContext, CudaMissing> {
    Err(CudaMissing::NotBuilt)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn headers_are_found_in_both_toolkit_layouts() {
        let dir = tempfile::tempdir().unwrap();
        let include = dir.path().join("include");
        std::fs::create_dir_all(include.join("cuda")).unwrap();
        assert_eq!(missing_headers(dir.path()).len(), HEADERS.len());
        for h in [
            "cuda_fp16.h",
            "cuda_bf16.h",
            "mma.h",
            "cooperative_groups.h",
        ] {
            std::fs::write(include.join(h), "").unwrap();
        }
        assert_eq!(missing_headers(dir.path()), ["cuda/barrier"]);
        let problem = header_problem(Some(dir.path())).unwrap();
        assert!(problem.contains("lacks cuda/barrier"), "{problem}");
        assert!(problem.contains("CUDA_PATH"), "{problem}");
        // CUDA 13 keeps CCCL under include/cccl.
        std::fs::create_dir_all(include.join("cccl/cuda")).unwrap();
        std::fs::write(include.join("cccl/cuda/barrier"), "").unwrap();
        assert!(missing_headers(dir.path()).is_empty());
        assert_eq!(header_problem(Some(dir.path())), None);
        assert!(header_problem(None).unwrap().contains("/usr/local/cuda"));
    }

    #[test]
    fn only_a_broken_cuda_is_worth_a_line() {
        for quiet in [
            CudaMissing::NotBuilt,
            CudaMissing::NoDriver,
            CudaMissing::NoDevice,
        ] {
            assert_eq!(quiet.worth_saying(), None, "{quiet}");
        }
        let broken = CudaMissing::Unusable("NVRTC does not load".into());
        assert_eq!(
            broken.worth_saying().as_deref(),
            Some("CUDA not used: NVRTC does not load")
        );
    }

    /// Here (no NVIDIA driver) CUDA never opens, and `cuda` says why in one line.
    #[test]
    fn cuda_without_a_card_is_one_clear_error() {
        if cfg!(feature = "cuda") && Path::new("/dev/nvidia0").exists() {
            eprintln!("skipped: this machine has an NVIDIA card");
            return;
        }
        let e = crate::open(crate::DeviceChoice::Cuda).unwrap_err();
        let line = e.to_string();
        assert!(line.starts_with("CUDA unavailable: "), "{line}");
        assert!(!line.contains('\n'), "{line}");
        assert!(crate::cuda_passed_over().is_none());
    }
}
