//! The latent codecs' encode and decode: SD 1.x's AutoencoderKL and TAESD with random weights, or the
//! codec of a folder (`--model DIR`: a pipeline's `vae/`, or a VAE/TAESD folder itself), on the CPU or a
//! GPU.
//!
//! `vcedit bench codec [--size 256] [--batch 1] [--runs 2] [--model DIR] [--device cpu|gpu|auto]
//! [--precision f16|f32]` (`gpu` takes a software adapter such as lavapipe too; a bare number is the
//! size, as in earlier versions). `python tools/bench_vae.py SIZE` times diffusers on the same shapes.
//! Threads: RAYON_NUM_THREADS. One `RESULT` line per network and direction, the first call (kernel
//! compilation, weight upload) apart.

use std::path::{Path, PathBuf};

use candle_core::{Device, Tensor};
use diffusion::taesd::{AutoencoderTiny, TaesdConfig};
use diffusion::vae::{Autoencoder, AutoencoderKL, AutoencoderKLConfig};

use crate::{
    arg_parsed, arg_value, network_device, networks_on, random_weights, report, Result, Timed,
};

/// The codec folder of `dir`: its `vae/` when it is a pipeline, else `dir` itself.
fn codec_dir(dir: &Path) -> PathBuf {
    let vae = dir.join("vae");
    if vae.is_dir() {
        vae
    } else {
        dir.to_path_buf()
    }
}

pub fn main(args: &[String]) -> Result<()> {
    // The size: `--size N`, or the first bare number (the older form).
    let bare = args
        .iter()
        .enumerate()
        .find(|&(i, a)| (i == 0 || !args[i - 1].starts_with("--")) && a.parse::<usize>().is_ok())
        .and_then(|(_, a)| a.parse().ok());
    let size: usize = arg_parsed(args, "--size", bare.unwrap_or(256))?;
    let batch: usize = arg_parsed(args, "--batch", 1)?;
    let runs: usize = arg_parsed(args, "--runs", 2)?;
    let gpu = network_device(args, "cpu")?;
    let gpu = gpu.as_ref();
    let device = diffusion::device::Device::from(gpu.cloned());
    let on = networks_on(gpu);
    let codecs: Vec<(String, Autoencoder)> = match arg_value(args, "--model") {
        Some(dir) => {
            let dir = codec_dir(Path::new(&dir));
            let codec = Autoencoder::load(&dir)?;
            vec![(dir.display().to_string(), codec)]
        }
        None => {
            let cfg = AutoencoderKLConfig::sd15();
            let vae = AutoencoderKL::new(&cfg, random_weights(|vb| AutoencoderKL::new(&cfg, vb))?)?;
            let cfg = TaesdConfig::default();
            let tiny =
                AutoencoderTiny::new(&cfg, random_weights(|vb| AutoencoderTiny::new(&cfg, vb))?)?;
            vec![
                (
                    "AutoencoderKL (SD 1.5, random)".into(),
                    Autoencoder::Kl(Box::new(vae)),
                ),
                ("TAESD (random)".into(), Autoencoder::Tiny(Box::new(tiny))),
            ]
        }
    };
    let dev = Device::Cpu;
    let image = Tensor::rand(-1f32, 1.0, (batch, 3, size, size), &dev)?;
    for (name, codec) in &codecs {
        let f = codec.spatial_factor();
        let latents = Tensor::randn(
            0f32,
            1.0,
            (batch, codec.latent_channels(), size / f, size / f),
            &dev,
        )?;
        eprintln!("codec bench: {name}, image {size}², batch {batch}, {on}");
        let encode = Timed::measure(runs, || Ok(codec.encode_scaled_on(&image, None, &device)?))?;
        let decode = Timed::measure(runs, || Ok(codec.decode_scaled_on(&latents, &device)?))?;
        for (what, timed) in [("encode", encode), ("decode", decode)] {
            eprintln!(
                "  {what}: best {:.3} s (first call {:.3} s)",
                timed.best().as_secs_f64(),
                timed.first.as_secs_f64()
            );
            report(timed.json(serde_json::json!({
                "bench": "codec",
                "codec": name,
                "kind": if matches!(codec, Autoencoder::Kl(_)) { "kl" } else { "tiny" },
                "what": what,
                "size": size,
                "batch": batch,
                "device": on,
            })));
        }
    }
    Ok(())
}
