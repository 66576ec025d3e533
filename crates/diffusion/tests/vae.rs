//! AutoencoderKL against diffusers references made by tools/make_vae_fixtures.py on the tiny models.

use std::collections::HashMap;

use candle_core::Tensor;
use diffusion::vae::{Autoencoder, AutoencoderKL};
use testkit::paths::{load_tensors, repo};

mod common;
use common::{in_bf16, max_abs_diff, relative_l2};

fn fixture(name: &str) -> HashMap<String, Tensor> {
    load_tensors(&repo().join("fixtures/vae").join(name))
}

/// Posterior mean/logvar, the sample for diffusers' noise, and decode, all within 1e-4.
fn check_model(model: &str) {
    let vae = AutoencoderKL::load(&repo().join("fixtures/models").join(model).join("vae")).unwrap();
    let refs = fixture(&format!("kl-{model}.safetensors"));
    let post = vae.encode(&refs["image"]).unwrap();
    let errs = [
        ("mean", max_abs_diff(&post.mean, &refs["mean"])),
        ("logvar", max_abs_diff(&post.logvar, &refs["logvar"])),
        (
            "sample",
            max_abs_diff(
                &vae.encode_sample(&refs["image"], &refs["noise"]).unwrap(),
                &refs["sample"],
            ),
        ),
        (
            "decode",
            max_abs_diff(&vae.decode(&refs["latents"]).unwrap(), &refs["decoded"]),
        ),
    ];
    println!("{model}: {errs:?}");
    for (what, err) in errs {
        assert!(err <= 1e-4, "{model} {what}: max abs err {err}");
    }

    // Scaled variants are the raw ones times the config's scaling factor.
    let s = vae.config().scaling_factor;
    let scaled = vae.encode_mean_scaled(&refs["image"]).unwrap();
    assert!(max_abs_diff(&scaled, &(&refs["mean"] * s).unwrap()) <= 1e-4 * s as f32);
    let z_scaled = (&refs["latents"] * s).unwrap();
    let decoded = vae.decode_scaled(&z_scaled).unwrap();
    assert!(max_abs_diff(&decoded, &refs["decoded"]) <= 1e-4);
}

#[test]
fn tiny_lcm_vae_matches_diffusers() {
    check_model("tiny-lcm");
}

/// tiny-ip2p stores f16 weights; diffusers and we both upcast them to f32 exactly, so the f32 bound holds.
#[test]
fn tiny_ip2p_vae_f16_weights_match_diffusers() {
    check_model("tiny-ip2p");
}

/// A folder holding only diffusers' `fp16` variant file loads the same model.
/// With bf16 products the tiny VAE's posterior mean and decode stay within bf16's rounding of diffusers'
/// f32 values (relative L2 ≤ 2e-2: the decoder's many convolutions reach 1.3e-2 on tiny-lcm; above 1e-5,
/// so bf16 products did run). A model loaded under bf16 products keeps only its weights' bf16 pairs and
/// gives the very same values.
#[test]
fn tiny_vae_with_bf16_products_matches_diffusers_within_bf16() {
    for model in ["tiny-lcm", "tiny-ip2p"] {
        let load = || {
            AutoencoderKL::load(&repo().join("fixtures/models").join(model).join("vae")).unwrap()
        };
        let vae = load();
        let refs = fixture(&format!("kl-{model}.safetensors"));
        let outputs = |vae: &AutoencoderKL| {
            (
                vae.encode(&refs["image"]).unwrap().mean,
                vae.decode(&refs["latents"]).unwrap(),
            )
        };
        let Some(((mean, decoded), stored_once)) = in_bf16(|| (outputs(&vae), outputs(&load())))
        else {
            return;
        };
        assert_eq!(
            max_abs_diff(&mean, &stored_once.0),
            0.0,
            "{model}: stored once"
        );
        assert_eq!(
            max_abs_diff(&decoded, &stored_once.1),
            0.0,
            "{model}: stored once"
        );
        for (what, got, want) in [
            ("mean", &mean, &refs["mean"]),
            ("decode", &decoded, &refs["decoded"]),
        ] {
            let rel = relative_l2(got, want);
            println!("{model} {what}: bf16 relative L2 {rel:.2e}");
            assert!(
                rel <= 2e-2 && rel > 1e-5,
                "{model} {what}: relative L2 {rel}"
            );
        }
    }
}

#[test]
fn fp16_variant_file_is_accepted() {
    let src = repo().join("fixtures/models/tiny-ip2p/vae");
    let dir = tempfile::tempdir().unwrap();
    std::fs::copy(src.join("config.json"), dir.path().join("config.json")).unwrap();
    std::fs::copy(
        src.join("diffusion_pytorch_model.safetensors"),
        dir.path().join("diffusion_pytorch_model.fp16.safetensors"),
    )
    .unwrap();
    let vae = AutoencoderKL::load(dir.path()).unwrap();
    let refs = fixture("kl-tiny-ip2p.safetensors");
    assert!(max_abs_diff(&vae.decode(&refs["latents"]).unwrap(), &refs["decoded"]) <= 1e-4);
}

#[test]
fn autoencoder_enum_picks_the_right_model() {
    let kl = Autoencoder::load(&repo().join("fixtures/models/tiny-lcm/vae")).unwrap();
    assert!(matches!(kl, Autoencoder::Kl(_)));
    assert_eq!((kl.latent_channels(), kl.spatial_factor()), (4, 4));
    let refs = fixture("kl-tiny-lcm.safetensors");
    let z = kl.encode_scaled(&refs["image"]).unwrap();
    assert!(max_abs_diff(&z, &(&refs["mean"] * 0.18215).unwrap()) <= 1e-4);

    let tmp = tempfile::tempdir().unwrap();
    for dir in [
        repo().join("fixtures/vae/tiny-taesd"),
        common::tiny_original_layout(tmp.path()),
    ] {
        let tiny = Autoencoder::load(&dir).unwrap();
        assert!(matches!(tiny, Autoencoder::Tiny(_)), "{}", dir.display());
        assert_eq!(tiny.spatial_factor(), 4);
    }
    let tiny = Autoencoder::load(&repo().join("fixtures/vae/tiny-taesd")).unwrap();
    let refs = fixture("taesd-tiny.safetensors");
    let out = tiny.decode_scaled(&refs["decode_in"]).unwrap();
    assert!(max_abs_diff(&out, &refs["decoded"]) <= 1e-4);
}

/// One definition on both devices: the AutoencoderKL (ResNet blocks, mid-block attention, down/up
/// sampling) on the GPU (lavapipe in CI) matches the CPU to f32 precision (to 1e-2 with f16 weights).
#[test]
fn tiny_vae_on_gpu_matches_cpu() {
    for (gpu, tolerance) in common::gpus_or_skip() {
        for model in ["tiny-lcm", "tiny-ip2p"] {
            let vae = AutoencoderKL::load(&repo().join("fixtures/models").join(model).join("vae"))
                .unwrap();
            let refs = fixture(&format!("kl-{model}.safetensors"));
            let cpu = vae.encode(&refs["image"]).unwrap();
            let on_gpu = vae
                .encode_on(&refs["image"], &diffusion::device::Device::Gpu(gpu.clone()))
                .unwrap();
            let decoded_cpu = vae.decode(&refs["latents"]).unwrap();
            let decoded_gpu = vae
                .decode_on(
                    &refs["latents"],
                    &diffusion::device::Device::Gpu(gpu.clone()),
                )
                .unwrap();
            let errs = [
                ("mean", common::relative_error(&on_gpu.mean, &cpu.mean)),
                (
                    "logvar",
                    common::relative_error(&on_gpu.logvar, &cpu.logvar),
                ),
                ("decode", common::relative_error(&decoded_gpu, &decoded_cpu)),
            ];
            let precision = gpu.precision();
            println!(
                "{model} on {}, {precision} weights: relative errors {errs:?}",
                gpu.name()
            );
            for (what, err) in errs {
                assert!(
                    err <= tolerance,
                    "{model} {what}, {precision} weights: relative error {err}"
                );
            }
        }
    }
}
