//! The adapter vcedit's GPU path opens, as the run log would name it, with the shader compiler CubeCL
//! uses on it and the limits the kernels size themselves by.
//!
//! `vcedit bench device [--device gpu|auto] [--require-hardware]`: one `RESULT` line with every adapter
//! wgpu lists and the one opened. `--require-hardware` fails (exit 1) when the opened adapter is a
//! software rasteriser (lavapipe/llvmpipe): a hardware measurement must never silently run on the CPU.

use crate::{arg_value, has_flag, report, BenchError, Result};

pub fn main(args: &[String]) -> Result<()> {
    let choice: gpu::DeviceChoice = arg_value(args, "--device")
        .unwrap_or_else(|| "gpu".into())
        .parse()?;
    let adapters: Vec<serde_json::Value> = gpu::list_adapters()
        .iter()
        .map(|a| {
            serde_json::json!({
                "name": a.name,
                "backend": format!("{:?}", a.backend),
                "driver": a.driver_info,
                "software": a.software,
            })
        })
        .collect();
    eprintln!("adapters: {}", serde_json::Value::from(adapters.clone()));
    let Some(ctx) = gpu::open(choice)? else {
        report(serde_json::json!({"bench": "device", "adapters": adapters, "opened": null}));
        return Err(BenchError::new(format!(
            "no GPU opened (device {choice}); adapters seen: {}",
            adapters.len()
        )));
    };
    let limits = &ctx.limits;
    let opened = serde_json::json!({
        "adapter": ctx.adapter,
        "api": ctx.backend,
        "compiler": ctx.compiler,
        "tensor_cores": ctx.tensor_cores,
        "cmma": ctx
            .client
            .properties()
            .features
            .matmul
            .cmma
            .iter()
            .map(|c| format!("{:?}x{:?}->{:?} {}x{}x{}", c.a_type, c.b_type, c.cd_type, c.m, c.n, c.k))
            .collect::<Vec<_>>(),
        "software": ctx.software,
        "max_shared_bytes": limits.max_shared_bytes,
        "max_units_per_cube": limits.max_units_per_cube,
        "plane_size": limits.plane_size,
        "max_buffer_bytes": limits.max_buffer_bytes,
        "memory_bytes": limits.memory_bytes,
        "free_bytes_at_open": limits.free_bytes_at_open,
    });
    eprintln!("opened: {} (compiler {})", ctx.describe(), ctx.compiler);
    report(serde_json::json!({"bench": "device", "adapters": adapters, "opened": opened}));
    if ctx.software && has_flag(args, "--require-hardware") {
        return Err(BenchError::new(format!(
            "the opened adapter is a software rasteriser ({}), not a hardware GPU",
            ctx.describe()
        )));
    }
    Ok(())
}
