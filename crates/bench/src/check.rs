//! The GPU's kernels against the CPU path, on small inputs, in one process: what the GPU test suite checks
//! on lavapipe, carried in the binary so that a card without a Rust toolchain (`tools/gpu-check`, on each
//! runtime) proves its results as well as its speed.
//!
//! `vcedit bench check [--device gpu|cuda|wgpu] [--fixtures DIR]`: the renderer (forward and backward)
//! and CCM's lifting round on a generated scene; with the repository's conformance fixtures (`DIR`,
//! default `./fixtures` where it exists) also LPIPS-VGG (value and input gradient, the narrow network of
//! `fixtures/lpips`) and the tiny pipeline's CLIP text encoder, AutoencoderKL and UNet
//! (`fixtures/models/tiny-lcm`), the networks with f32 weights so that only summation order separates the
//! two paths. One `RESULT` line per check with its relative error (largest absolute difference over the
//! largest magnitude of the CPU's values) and tolerance; the exit code is 1 when any check fails. The
//! fits' Adam and L1 + D-SSIM kernels are checked end to end by a fit's held-out PSNR (gpu-check's `fit`
//! rows).

// Why not the full-width LPIPS with generated weights: at 64² its gradient moved by up to 8.5 % of its
// largest component between lavapipe and the CPU (148 of 12288 entries), the value bit for bit equal:
// near-zero pre-activations of the generated network flip their ReLU masks on the last bits of a sum,
// which says nothing about the kernels (the narrow fixture network agrees to 1e-4, as in the tests).

use std::path::Path;

use candle_core::{DType, Device, Tensor};
use diffusion::clip::ClipTextModel;
use diffusion::device::{GpuDevice, Precision};
use diffusion::loader::{Component, ModelDir};
use diffusion::lpips::Lpips;
use diffusion::unet::UNet2DConditionModel;
use diffusion::vae::Autoencoder;
use splat::lift::{MapGrid, Resample};
use splat::render::RenderSettings;
use splat::SplatDevice;

use crate::lift::{cameras, map};
use crate::scenes::{ball_scene, camera};
use crate::{arg_value, report, required_gpu, BenchError, Result};

/// Largest absolute difference over the largest magnitude of `want`.
fn rel_err(got: &[f32], want: &[f32]) -> f32 {
    if got.len() != want.len() {
        return f32::INFINITY;
    }
    let scale = want.iter().fold(0f32, |m, v| m.max(v.abs())).max(1e-12);
    let diff = got
        .iter()
        .zip(want)
        .fold(0f32, |m, (a, b)| m.max((a - b).abs()));
    // A NaN anywhere fails the check.
    if diff.is_nan() || got.iter().any(|v| !v.is_finite()) {
        f32::INFINITY
    } else {
        diff / scale
    }
}

fn values(t: &Tensor) -> Result<Vec<f32>> {
    Ok(t.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?)
}

/// The checks' outcomes, reported as they come.
struct Checks {
    on: String,
    failed: Vec<String>,
    count: usize,
}

impl Checks {
    fn record(&mut self, what: &str, err: f32, tol: f32) {
        let pass = err <= tol;
        self.count += 1;
        eprintln!(
            "  {what}: relative error {err:.2e} (tolerance {tol:.0e}) {}",
            if pass { "ok" } else { "FAILED" }
        );
        report(serde_json::json!({
            "bench": "check", "what": what, "rel_err": if err.is_finite() { Some(err) } else { None },
            "tolerance": tol, "pass": pass, "device": self.on,
        }));
        if !pass {
            self.failed.push(what.to_string());
        }
    }
}

pub fn main(args: &[String]) -> Result<()> {
    let ctx = required_gpu(args, "check")?;
    let mut checks = Checks {
        on: ctx.describe(),
        failed: vec![],
        count: 0,
    };
    eprintln!("check: {} against the CPU", checks.on);
    splatting(&mut checks, &SplatDevice::from(Some(ctx.clone())))?;
    let gpu = GpuDevice::with_precision(ctx, Precision::F32);
    let fixtures = arg_value(args, "--fixtures").map_or_else(
        || Path::new("fixtures").is_dir().then(|| "fixtures".into()),
        |dir| Some(std::path::PathBuf::from(dir)),
    );
    match fixtures {
        Some(dir) => {
            lpips(&mut checks, &dir.join("lpips/narrow"), &gpu)?;
            networks(&mut checks, &dir.join("models/tiny-lcm"), &gpu)?;
        }
        None => eprintln!("  (no fixtures folder: the networks are not checked; --fixtures DIR)"),
    }
    report(serde_json::json!({
        "bench": "check", "what": "summary", "passed": checks.count - checks.failed.len(),
        "failed": checks.failed.len(), "device": checks.on,
    }));
    if checks.failed.is_empty() {
        eprintln!("check: all {} checks passed", checks.count);
        Ok(())
    } else {
        Err(BenchError::new(format!(
            "{} of {} checks failed on {}: {}",
            checks.failed.len(),
            checks.count,
            checks.on,
            checks.failed.join(", ")
        )))
    }
}

/// The renderer's forward and backward passes and a lifting round, on 4000 Gaussians of SH degree 3.
fn splatting(checks: &mut Checks, gpu: &SplatDevice) -> Result<()> {
    let cpu = SplatDevice::Cpu;
    let scene = ball_scene(4000, 7);
    let cam = camera(96);
    let settings = RenderSettings {
        background: [0.2, 0.3, 0.4],
    };
    let (a, b) = (
        gpu.render(&scene, &cam, &settings, None)?,
        cpu.render(&scene, &cam, &settings, None)?,
    );
    checks.record("render: colour", rel_err(&a.rgb, &b.rgb), 1e-4);
    checks.record("render: alpha", rel_err(&a.alpha, &b.alpha), 1e-4);
    checks.record("render: depth", rel_err(&a.depth, &b.depth), 1e-4);
    // Half the squared distance to a fixed pattern: its gradient is the difference itself.
    let loss = |rgb: &[f32]| {
        let grad: Vec<f32> = rgb
            .iter()
            .enumerate()
            .map(|(i, v)| v - (0.5 + 0.4 * (i as f32 * 0.05).sin()))
            .collect();
        (0.5 * grad.iter().map(|g| g * g).sum::<f32>(), grad)
    };
    let (_, va, ga) = gpu.render_with_loss(&scene, &cam, &settings, loss)?;
    let (_, vb, gb) = cpu.render_with_loss(&scene, &cam, &settings, loss)?;
    checks.record("backward: loss", rel_err(&[va], &[vb]), 1e-4);
    // Gradients sum over many pixels in an order that differs between the paths (atomics on the GPU).
    for (what, got, want) in [
        ("backward: means", &ga.means, &gb.means),
        ("backward: log-scales", &ga.log_scales, &gb.log_scales),
        ("backward: rotations", &ga.quats, &gb.quats),
        (
            "backward: opacities",
            &ga.opacity_logits,
            &gb.opacity_logits,
        ),
        ("backward: SH", &ga.sh, &gb.sh),
    ] {
        checks.record(what, rel_err(got, want), 2e-3);
    }
    let grid = MapGrid {
        height: 8,
        width: 8,
        channels: 6,
        up: Resample::Bilinear,
        down: Resample::Bilinear,
    };
    let cams = cameras(3, 64);
    let round = |device: &SplatDevice| -> Result<Vec<f32>> {
        let mut out = vec![];
        device.lift_and_render_back::<gpu::GpuError>(
            &scene,
            &cams,
            &grid,
            &mut |v| Ok(map(&grid, v)),
            &mut |_, back| {
                out.extend(back);
                Ok(())
            },
        )?;
        Ok(out)
    };
    checks.record(
        "lifting round (3 views, 8² maps, 6 channels)",
        rel_err(&round(gpu)?, &round(&cpu)?),
        1e-3,
    );
    Ok(())
}

/// LPIPS-VGG (the network in `dir`) at 64²: the value and its gradient w.r.t. the render.
fn lpips(checks: &mut Checks, dir: &Path, gpu: &GpuDevice) -> Result<()> {
    let image = |phase: f32| -> Vec<f32> {
        (0..64 * 64 * 3)
            .map(|i| 0.5 + 0.4 * ((i as f32) * 0.0137 + phase).sin())
            .collect()
    };
    let (render, target) = (image(0.0), image(1.0));
    let run = |device: diffusion::device::Device| -> Result<(f32, Vec<f32>)> {
        let net = Lpips::load(dir)?.on(device);
        let target = net.target(&target, 64, 64)?;
        let out = net.loss_and_grad(&render, 64, 64, &target)?;
        Ok((out.value, out.grad))
    };
    let (a, b) = (
        run(diffusion::device::Device::from(Some(gpu.clone())))?,
        run(diffusion::device::Device::Cpu)?,
    );
    checks.record("LPIPS: value", rel_err(&[a.0], &[b.0]), 1e-3);
    checks.record("LPIPS: gradient", rel_err(&a.1, &b.1), 1e-3);
    Ok(())
}

/// The text encoder, the codec and the UNet of the pipeline in `dir`.
fn networks(checks: &mut Checks, dir: &Path, gpu: &GpuDevice) -> Result<()> {
    let on = diffusion::device::Device::from(Some(gpu.clone()));
    let cpu = diffusion::device::Device::Cpu;
    let model = ModelDir::open_components(
        dir,
        &[Component::TextEncoder, Component::Vae, Component::Unet],
    )?;
    let encoder = ClipTextModel::load(&model, DType::F32, &Device::Cpu)?;
    let positions = encoder.max_positions();
    let ids = Tensor::arange(0u32, positions as u32, &Device::Cpu)?
        .unsqueeze(0)?
        .repeat((2, 1))?;
    let (a, b) = (
        encoder.forward_skip_on(&ids, 0, &on)?,
        encoder.forward_skip_on(&ids, 0, &cpu)?,
    );
    checks.record(
        "CLIP text encoder",
        rel_err(&values(&a)?, &values(&b)?),
        1e-3,
    );
    let context = b;

    let codec = Autoencoder::load(&model.component_dir(Component::Vae))?;
    let f = codec.spatial_factor();
    let size = 8 * f;
    let image = Tensor::rand(-1f32, 1.0, (1, 3, size, size), &Device::Cpu)?;
    let latents = Tensor::randn(0f32, 1.0, (1, codec.latent_channels(), 8, 8), &Device::Cpu)?;
    let (a, b) = (
        codec.encode_scaled_on(&image, None, &on)?,
        codec.encode_scaled_on(&image, None, &cpu)?,
    );
    checks.record(
        "AutoencoderKL: encode",
        rel_err(&values(&a)?, &values(&b)?),
        1e-3,
    );
    let (a, b) = (
        codec.decode_scaled_on(&latents, &on)?,
        codec.decode_scaled_on(&latents, &cpu)?,
    );
    checks.record(
        "AutoencoderKL: decode",
        rel_err(&values(&a)?, &values(&b)?),
        1e-3,
    );

    let weights = model.weight_files(Component::Unet)?;
    let unet =
        UNet2DConditionModel::from_files(&model.config_path(Component::Unet), &weights.files)?;
    let config = unet.config();
    let sample = Tensor::randn(0f32, 1.0, (2, config.in_channels, 8, 8), &Device::Cpu)?;
    let t = Tensor::new(&[500f32], &Device::Cpu)?;
    let (a, b) = (
        unet.forward_on(&sample, &t, &context, None, None, &on)?,
        unet.forward_on(&sample, &t, &context, None, None, &cpu)?,
    );
    checks.record("UNet", rel_err(&values(&a)?, &values(&b)?), 1e-3);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::rel_err;

    #[test]
    fn the_error_is_relative_and_nan_fails() {
        assert_eq!(rel_err(&[1.0, 2.0], &[1.0, 2.0]), 0.0);
        assert!((rel_err(&[1.0, 2.1], &[1.0, 2.0]) - 0.05).abs() < 1e-6);
        assert!(rel_err(&[f32::NAN, 2.0], &[1.0, 2.0]).is_infinite());
        assert!(rel_err(&[1.0], &[1.0, 2.0]).is_infinite());
    }
}
