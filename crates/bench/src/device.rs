//! The adapter vcedit's GPU path opens, as the run log would name it, with the shader compiler CubeCL
//! uses on it and the limits the kernels size themselves by.
//!
//! `vcedit bench device [--device gpu|auto|cuda|wgpu] [--require-hardware]`: one `RESULT` line with every
//! adapter wgpu lists and the device opened (its runtime: CUDA or wgpu, see `VCEDIT_GPU_RUNTIME`). `--require-hardware` fails (exit 1) when the opened adapter is a
//! software rasteriser (lavapipe/llvmpipe): a hardware measurement must never silently run on the CPU.
//! `--overhead` adds a second `RESULT` line: what the host costs around the kernels (see `overhead`).

use std::time::Instant;

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
        "runtime": format!("{:?}", ctx.runtime),
        "passed_over": ctx.passed_over,
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
    if has_flag(args, "--overhead") {
        let measured = overhead(&ctx)?;
        eprintln!("overhead: {measured}");
        report(measured);
    }
    Ok(())
}

/// What the host costs around the kernels, in the runtime's own terms (a splatting fit step is ~75
/// launches, a radix sort and two reads; on an H200 `vcedit fit` spent 86 % of its wall time outside
/// its kernels, docs/gpu-results.md 2026-11-27):
/// - `launch_us`: one launch of a one-element kernel, 2000 in a row and one read at the end;
/// - `round_trip_us`: one launch and a 4-byte read, waited for (what every read of a count or a loss
///   costs a fit step);
/// - `read_mib_ms`: reading 1 MiB back;
/// - `fill_reused_us` / `fill_fresh_us`: filling a 16 MiB buffer, the same buffer each time against a
///   fresh one of a slightly different size each time (a fit's buffers change size every step);
/// - `sort_60k_ms`: the fit's depth sort, 60k pairs by 32-bit keys, with the read that follows it.
fn overhead(ctx: &gpu::GpuContext) -> Result<serde_json::Value> {
    use gpu::prims::{empty32, fill32, read_u32, sort_pairs, upload_u32};
    let c = &ctx.client;
    let one = empty32(c, 1);
    // Seconds per round of `n` rounds of `round`, ended by one waited-for read (after one warm-up
    // round, which compiles what the rounds launch).
    let timed = |n: usize, round: &mut dyn FnMut(usize) -> Result<()>| -> Result<f64> {
        round(0)?;
        read_u32(c, &one, 1)?;
        let start = Instant::now();
        for i in 0..n {
            round(i)?;
        }
        read_u32(c, &one, 1)?;
        Ok(start.elapsed().as_secs_f64() / n as f64)
    };
    let launch_us = timed(2000, &mut |i| {
        fill32(c, &one, 1, i as u32);
        Ok(())
    })? * 1e6;
    let round_trip_us = timed(200, &mut |i| {
        fill32(c, &one, 1, i as u32);
        read_u32(c, &one, 1)?;
        Ok(())
    })? * 1e6;
    let mib = 1 << 18;
    let big = empty32(c, mib);
    fill32(c, &big, mib, 7);
    let read_mib_ms = timed(20, &mut |_| {
        read_u32(c, &big, mib)?;
        Ok(())
    })? * 1e3;
    let words = 1 << 22;
    let reused = empty32(c, words);
    let fill_reused_us = timed(50, &mut |i| {
        fill32(c, &reused, words, i as u32);
        Ok(())
    })? * 1e6;
    let fill_fresh_us = timed(50, &mut |i| {
        fill32(c, &empty32(c, words + 1024 * i), words, i as u32);
        Ok(())
    })? * 1e6;

    let n = 60_000;
    // A fixed pseudo-random key per pair (splitmix-style), so runs compare.
    let keys: Vec<u32> = (0..n as u64)
        .map(|i| {
            let z = (i + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15);
            ((z ^ (z >> 31)) >> 16) as u32
        })
        .collect();
    let vals: Vec<u32> = (0..n as u32).collect();
    let mut pairs = Some((upload_u32(c, &keys), upload_u32(c, &vals)));
    let sort_60k_ms = timed(20, &mut |_| {
        let (k, v) = pairs.take().expect("put back every round");
        let (k, v) = sort_pairs(c, k, v, n, 32);
        read_u32(c, &k, 1)?;
        pairs = Some((k, v));
        Ok(())
    })? * 1e3;

    let round = |x: f64| (x * 100.0).round() / 100.0;
    Ok(serde_json::json!({
        "bench": "overhead",
        "device": ctx.adapter,
        "compiler": ctx.compiler,
        "launch_us": round(launch_us),
        "round_trip_us": round(round_trip_us),
        "read_mib_ms": round(read_mib_ms),
        "fill_reused_us": round(fill_reused_us),
        "fill_fresh_us": round(fill_fresh_us),
        "sort_60k_ms": round(sort_60k_ms),
    }))
}
