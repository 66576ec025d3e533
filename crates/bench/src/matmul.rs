//! GPU matrix products at the shapes of SD 1.5's first level at 512² (4096 tokens × 320 channels): the
//! projections (k = n = 320) and the feed-forward (n = 1280), as a linear layer (weight [n, k], read
//! transposed, in the device's weight precision) and, for f32, as a plain activation × activation product.
//!
//! `vcedit bench matmul [--runs 3] [--repeat 20] [--device gpu] [--precisions f32,f16]
//! [--shapes 4096x320x320,4096x320x1280] [--routines simple_cyclic_cmma,double_cyclic_cmma,…|all]
//! [--tilings grid|SPEC;SPEC…]`
//!
//! `--routines` times the f16 products (the linear layer and, as f16 operands, the activation ×
//! activation product) on each of the library's tensor-core routines
//! (`ops::TENSOR_CORE_ROUTINES`; `all` for every one): which is fastest differs between cards. Each
//! result names the route the product took (`route`): the routine, or `unit` where the card has no tensor
//! cores or the routine declined the shape.
//!
//! `--tilings grid|SPEC;SPEC…` times the f16 linear product on each tiling (`ops::Tiling`: `grid` is
//! `Tiling::grid()`, a SPEC is e.g. `planes=8,k=4,rows=2,buffer=double`) of the default routine, or of
//! each of `--routines`. `tiled` in the result says whether the product ran on the tiling (false: the
//! inference or the launch declined it for the shape, and the routine's own tiling ran).
//!
//! The first call (kernel compilation) is timed on its own; each warm run then launches the product
//! `--repeat` times and waits for the device once, so the time is the device's, not one read-back's
//! round trip. One `RESULT` line per product and precision, with ms and TFLOP/s of the best run.

use std::time::Instant;

use candle_core::{Device, Tensor};
use diffusion::device::{ops, GpuDevice, GpuTensor, Precision};

use crate::{
    arg_list, arg_parsed, arg_value, parse_sizes, relative_error, report, required_gpu, BenchError,
    Launches, Result,
};

/// One product launch (its result stays on the device).
type Product<'a> = dyn Fn() -> candle_core::Result<GpuTensor> + 'a;

/// `MxKxN`.
fn parse_shape(s: &str) -> Result<(usize, usize, usize)> {
    let [m, k, n] = parse_sizes(s, "MxKxN (e.g. 4096x320x1280)")?;
    Ok((m, k, n))
}

pub fn main(args: &[String]) -> Result<()> {
    let runs: usize = arg_parsed(args, "--runs", 3)?;
    let repeat: usize = arg_parsed(args, "--repeat", 20usize)?.max(1);
    let context = required_gpu(args, "matmul")?;
    let precisions: Vec<Precision> = arg_list(args, "--precisions", "f32,f16")?;
    let shapes = arg_value(args, "--shapes")
        .unwrap_or_else(|| "4096x320x320,4096x320x1280".into())
        .split(',')
        .map(parse_shape)
        .collect::<Result<Vec<_>>>()?;
    let asked_routines = parse_routines(arg_value(args, "--routines").as_deref())?;
    let tilings = parse_tilings(arg_value(args, "--tilings").as_deref())?;
    let mut routines = asked_routines.clone();
    if !tilings.is_empty() && routines.is_empty() {
        routines.push(ops::DEFAULT_TENSOR_CORE_ROUTINE);
    }
    for precision in precisions {
        let device = GpuDevice::with_precision(context.clone(), precision);
        eprintln!(
            "matmul bench on {} ({}), {precision} weights",
            device.name(),
            context.compiler
        );
        for &(m, k, n) in &shapes {
            let a = Tensor::randn(0f32, 1.0, (m, k), &Device::Cpu)?;
            let b = Tensor::randn(0f32, 1.0, (k, n), &Device::Cpu)?;
            let w = Tensor::randn(0f32, 1.0, (n, k), &Device::Cpu)?;
            let ga = GpuTensor::upload(&device, &a)?;
            let gb = GpuTensor::upload(&device, &b)?;
            let gw = device.cached_matrix(&w)?;
            let mut products: Vec<(&str, Box<Product>)> =
                vec![("linear", Box::new(|| ops::linear(&ga, &gw, None, None)))];
            // Activation × activation products do not depend on the weight precision, but with f16
            // weights they take f16 operands on tensor cores, and some routines take only row-major
            // operands (a linear layer's weight is read transposed): each routine meets both.
            if precision == Precision::F32 || !asked_routines.is_empty() {
                products.push(("matmul", Box::new(|| ops::matmul(&ga, &gb))));
            }
            let path = ops::matmul_path(&device);
            // Each product once per asked routine and tiling (f16 weights: tensor-core operands),
            // else once.
            let runs_of = |what: &str| -> Vec<(Option<&'static str>, Option<ops::Tiling>)> {
                if precision != Precision::F16 || routines.is_empty() {
                    return vec![(None, None)];
                }
                // Tilings for the linear layer only: the networks' products are mostly weights.
                let tilings: Vec<Option<ops::Tiling>> = if tilings.is_empty() || what != "linear" {
                    vec![None]
                } else {
                    tilings.iter().copied().map(Some).collect()
                };
                routines
                    .iter()
                    .flat_map(|r| tilings.iter().map(move |t| (Some(*r), *t)))
                    .collect()
            };
            for (what, product) in &products {
                // The product checked against the CPU's f32 one (the error the path's rounding costs):
                // once per product, not per routine and tiling (a grid's 73 at 24576 rows add up).
                let want = if *what == "linear" {
                    a.matmul(&w.t()?)?
                } else {
                    a.matmul(&b)?
                };
                for (routine, tiling) in runs_of(what) {
                    let product = || -> candle_core::Result<GpuTensor> {
                        let tiled = || match tiling {
                            Some(t) => ops::with_matmul_tiling(t, product),
                            None => product(),
                        };
                        match routine {
                            Some(name) => ops::with_tensor_core_routine(name, tiled)?,
                            None => tiled(),
                        }
                    };
                    let start = Instant::now();
                    // A routine or tiling the library accepts but cannot compile panics inside it: say
                    // so and go on with the next (one failed tiling must not end a card's sweep).
                    let first_call = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                        product().and_then(|p| p.to_cpu())
                    }));
                    let Ok(got) = first_call else {
                        eprintln!(
                            "  {what} {m}x{k}x{n}: routine {} tiling {} panicked; skipped",
                            routine.unwrap_or("default"),
                            tiling.map_or("default".into(), |t| t.to_string())
                        );
                        continue;
                    };
                    let got = got?;
                    let first = start.elapsed();
                    let route = ops::last_product_route();
                    let tiled = ops::last_product_tiled();
                    let tiling_name = tiling.map(|t| t.to_string());
                    let rel_err = relative_error(&got, &want)?;
                    let timed = Launches::measure(&context, first, runs, repeat, product)?;
                    let flops = 2.0 * (m * k * n) as f64;
                    let on_tiling = match (tiling, tiled) {
                        (None, _) => String::new(),
                        (Some(t), _) if t.is_default() => ", the routine's own tiling".into(),
                        (Some(t), true) => format!(", tiling {t}"),
                        (Some(t), false) => format!(", tiling {t} not taken"),
                    };
                    eprintln!(
                        "  {what} {m}x{k}x{n} ({path}, {route}{on_tiling}): {}, relative error \
                         {rel_err:.1e}",
                        timed.summary(flops)
                    );
                    report(timed.json(
                        flops,
                        serde_json::json!({
                            "bench": "matmul",
                            "what": what,
                            "precision": precision.to_string(),
                            "m": m, "k": k, "n": n,
                            "device": device.name(),
                            "compiler": context.compiler,
                            "path": path.to_string(),
                            "routine": routine,
                            "route": route,
                            "tiling": tiling_name,
                            "tiled": tiled,
                            "rel_err": rel_err,
                        }),
                    ));
                }
            }
        }
    }
    Ok(())
}

/// `--routines`: names of `ops::TENSOR_CORE_ROUTINES`, or `all`; none when absent.
fn parse_routines(value: Option<&str>) -> Result<Vec<&'static str>> {
    match value {
        None => Ok(Vec::new()),
        Some("all") => Ok(ops::TENSOR_CORE_ROUTINES.to_vec()),
        Some(list) => list
            .split(',')
            .map(|name| {
                ops::TENSOR_CORE_ROUTINES
                    .iter()
                    .copied()
                    .find(|r| *r == name.trim())
                    .ok_or_else(|| {
                        BenchError::new(format!(
                            "--routines: unknown routine '{name}' (expected all, or some of {})",
                            ops::TENSOR_CORE_ROUTINES.join(", ")
                        ))
                    })
            })
            .collect(),
    }
}

/// `--tilings`: `grid`, or tilings separated by `;`; none when absent.
fn parse_tilings(value: Option<&str>) -> Result<Vec<ops::Tiling>> {
    match value {
        None => Ok(Vec::new()),
        Some("grid") => Ok(ops::Tiling::grid()),
        Some(list) => list
            .split(';')
            .map(|spec| {
                ops::Tiling::parse(spec).map_err(|e| BenchError::new(format!("--tilings: {e}")))
            })
            .collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn routines_parse_or_say_what_is_wrong() {
        assert!(parse_routines(None).unwrap().is_empty());
        assert_eq!(
            parse_routines(Some("all")).unwrap().len(),
            ops::TENSOR_CORE_ROUTINES.len()
        );
        assert_eq!(
            parse_routines(Some("double_cyclic_cmma, simple_cyclic_mma")).unwrap(),
            ["double_cyclic_cmma", "simple_cyclic_mma"]
        );
        let e = parse_routines(Some("fast")).unwrap_err().to_string();
        assert!(e.contains("unknown routine 'fast'"), "{e}");
    }

    #[test]
    fn tilings_parse_or_say_what_is_wrong() {
        assert!(parse_tilings(None).unwrap().is_empty());
        assert_eq!(parse_tilings(Some("grid")).unwrap(), ops::Tiling::grid());
        let two = parse_tilings(Some("default;planes=4,k=4")).unwrap();
        assert_eq!(two.len(), 2);
        assert!(two[0].is_default());
        assert_eq!(two[1].to_string(), "planes=4,k=4");
        let e = parse_tilings(Some("planes=4;k=0")).unwrap_err().to_string();
        assert!(
            e.starts_with("--tilings: ") && e.contains("k must be"),
            "{e}"
        );
    }

    #[test]
    fn shapes_parse_or_say_what_is_wrong() {
        assert_eq!(parse_shape("4096x320x1280").unwrap(), (4096, 320, 1280));
        for bad in ["4096x320", "0x1x1", "ax1x1"] {
            assert!(parse_shape(bad)
                .unwrap_err()
                .to_string()
                .contains("is not MxKxN"));
        }
    }
}
