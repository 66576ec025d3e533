//! Helpers for tests that need a GPU: on machines without one (a fresh clone, CI without lavapipe) they
//! skip with one printed line instead of failing.

use crate::{open, DeviceChoice, GpuContext};
use std::sync::OnceLock;

/// The test device (any adapter, software ones included), opened once per test binary; `None` after
/// printing "skipping: no Vulkan device" when there is none.
pub fn context_or_skip() -> Option<GpuContext> {
    static CONTEXT: OnceLock<Option<GpuContext>> = OnceLock::new();
    let ctx = CONTEXT.get_or_init(|| match open(DeviceChoice::Gpu) {
        Ok(ctx) => ctx,
        Err(e) => {
            eprintln!("GPU tests: {e}");
            None
        }
    });
    if ctx.is_none() {
        println!("skipping: no Vulkan device");
    }
    ctx.clone()
}
