//! GPU attention at SD 1.5's shapes, on each path: our flash kernel (scalar f32, no score matrix),
//! products through the matrix-product path around a row softmax (tensor cores where the device has
//! them), and the library's flash attention (see `ops::attention_path`; where the library declines a
//! problem, its line times the fallback).
//!
//! `vcedit bench attention [--runs 3] [--repeat 5] [--device gpu] [--paths flash,products,library]
//! [--shapes 48x4096x4096x40,48x1024x1024x80,48x4096x77x40]`
//!
//! A shape is `ENTRIESxQUERIESxKEYSxHEAD_DIM`, entries being batch × heads: the defaults are one 512²
//! view's six InfEdit branches with SD 1.5's 8 heads, self-attention at the first two levels (64², 32²
//! latents) and cross-attention over 77 tokens at the first. The first call (kernel compilation) is timed
//! on its own; each warm run launches the attention `--repeat` times and waits for the device once. The
//! output's first entry is checked against the CPU's f32 attention (`rel_err`). One `RESULT` line per
//! shape and path.

use std::time::Instant;

use candle_core::{Device, Tensor};
use diffusion::device::ops::{self, AttentionPath};
use diffusion::device::{DeviceTensor, GpuDevice, GpuTensor, Precision};

use crate::{
    arg_parsed, arg_value, parse_sizes, relative_error, report, required_gpu, BenchError, Launches,
    Result,
};

/// `ENTRIESxQUERIESxKEYSxHEAD_DIM`.
fn parse_shape(s: &str) -> Result<[usize; 4]> {
    parse_sizes(s, "ENTRIESxQUERIESxKEYSxHEAD_DIM (e.g. 48x4096x4096x40)")
}

fn parse_path(s: &str) -> Result<AttentionPath> {
    match s.trim() {
        "flash" => Ok(AttentionPath::Flash),
        "products" => Ok(AttentionPath::Products),
        "library" => Ok(AttentionPath::Library),
        other => Err(BenchError::new(format!(
            "--paths: unknown path '{other}' (expected flash, products or library)"
        ))),
    }
}

pub fn main(args: &[String]) -> Result<()> {
    let runs: usize = arg_parsed(args, "--runs", 3)?;
    let repeat: usize = arg_parsed(args, "--repeat", 5usize)?.max(1);
    let context = required_gpu(args, "attention")?;
    let paths = arg_value(args, "--paths")
        .unwrap_or_else(|| "flash,products,library".into())
        .split(',')
        .map(parse_path)
        .collect::<Result<Vec<_>>>()?;
    let shapes = arg_value(args, "--shapes")
        .unwrap_or_else(|| "48x4096x4096x40,48x1024x1024x80,48x4096x77x40".into())
        .split(',')
        .map(parse_shape)
        .collect::<Result<Vec<_>>>()?;
    // The precision only decides the products' operands (f16 on tensor cores): activations are f32.
    let device = GpuDevice::with_precision(context.clone(), Precision::F16);
    let matmul_path = ops::matmul_path(&device);
    eprintln!(
        "attention bench on {} ({}), products on the {matmul_path} path",
        device.name(),
        context.compiler
    );
    for [entries, queries, keys, dim] in shapes {
        let q = Tensor::randn(0f32, 1.0, (entries, queries, dim), &Device::Cpu)?;
        let k = Tensor::randn(0f32, 1.0, (entries, keys, dim), &Device::Cpu)?;
        let v = Tensor::randn(0f32, 1.0, (entries, keys, dim), &Device::Cpu)?;
        let scale = 1.0 / (dim as f64).sqrt();
        // The reference for the first entry only: the whole CPU attention at 48 × 4096² would take
        // minutes on a small machine.
        let first_entry = |t: &Tensor| t.narrow(0, 0, 1);
        let want = DeviceTensor::attention(
            &first_entry(&q)?.into(),
            &first_entry(&k)?.into(),
            &first_entry(&v)?.into(),
            scale,
        )?
        .to_cpu()?;
        let (gq, gk, gv) = (
            GpuTensor::upload(&device, &q)?,
            GpuTensor::upload(&device, &k)?,
            GpuTensor::upload(&device, &v)?,
        );
        for &path in &paths {
            let attend = || ops::with_attention_path(path, || ops::attention(&gq, &gk, &gv, scale));
            let start = Instant::now();
            let got = attend()?.to_cpu()?;
            let first = start.elapsed();
            let rel_err = relative_error(&first_entry(&got)?, &want)?;
            let timed = Launches::measure(&context, first, runs, repeat, attend)?;
            // Two products of entries × queries × keys × dim multiply-adds each.
            let flops = 4.0 * (entries * queries * keys * dim) as f64;
            eprintln!(
                "  {entries}x{queries}x{keys}x{dim} {path}: {}, relative error {rel_err:.1e}",
                timed.summary(flops)
            );
            report(timed.json(
                flops,
                serde_json::json!({
                    "bench": "attention",
                    "path": path.to_string(),
                    "matmul_path": matmul_path.to_string(),
                    "entries": entries, "queries": queries, "keys": keys, "dim": dim,
                    "device": device.name(),
                    "compiler": context.compiler,
                    "rel_err": rel_err,
                }),
            ));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shapes_and_paths_parse_or_say_what_is_wrong() {
        assert_eq!(parse_shape("48x4096x77x40").unwrap(), [48, 4096, 77, 40]);
        for bad in ["48x4096x77", "0x1x1x1", "ax1x1x1"] {
            assert!(parse_shape(bad)
                .unwrap_err()
                .to_string()
                .contains("is not ENTRIESxQUERIESxKEYSxHEAD_DIM"));
        }
        assert_eq!(parse_path("flash").unwrap(), AttentionPath::Flash);
        assert_eq!(parse_path("library").unwrap(), AttentionPath::Library);
        assert!(parse_path("cmma")
            .unwrap_err()
            .to_string()
            .contains("'cmma'"));
    }
}
