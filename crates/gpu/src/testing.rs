//! Helpers for tests that need a GPU: on machines without one (a fresh clone, CI without lavapipe) they
//! skip with one printed line instead of failing.

use crate::{open, DeviceChoice, GpuContext, GpuError};
use std::sync::OnceLock;

/// The test device (any adapter, software ones included), opened once per test binary; `None` after
/// printing "skipping: no Vulkan device" when there is none. `VCEDIT_GPU_RUNTIME=cuda|wgpu` runs the
/// tests on one runtime of a machine that has both.
pub fn context_or_skip() -> Option<GpuContext> {
    static CONTEXT: OnceLock<Result<GpuContext, String>> = OnceLock::new();
    let ctx = CONTEXT.get_or_init(|| match open(DeviceChoice::Gpu) {
        Ok(Some(ctx)) => {
            // Which compiler path the tests ran on (SPIR-V, or WGSL under VCEDIT_GPU_COMPILER=wgsl).
            println!("GPU tests on {}", ctx.describe());
            Ok(ctx)
        }
        Ok(None) | Err(GpuError::NoAdapter) => Err(String::new()),
        // Asked for by name: a test run that meant to check CUDA must not pass by skipping.
        Err(e @ (GpuError::CudaUnavailable(_) | GpuError::BadRuntime(_))) => {
            panic!("{}: {e}", crate::RUNTIME_ENV)
        }
        Err(e) => Err(format!(" ({e})")),
    });
    match ctx {
        Ok(ctx) => Some(ctx.clone()),
        Err(why) => {
            println!("skipping: no Vulkan device{why}");
            None
        }
    }
}
