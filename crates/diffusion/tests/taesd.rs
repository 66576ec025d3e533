//! TAESD (AutoencoderTiny) against diffusers references made by tools/make_vae_fixtures.py.

use std::collections::HashMap;
use std::path::PathBuf;

use candle_core::Tensor;
use diffusion::taesd::{AutoencoderTiny, TaesdConfig, TaesdLayout};
use testkit::paths::{load_tensors, repo};

mod common;
use common::max_abs_diff;

fn fixture(name: &str) -> HashMap<String, Tensor> {
    load_tensors(&repo().join("fixtures/vae").join(name))
}

/// Encodes the fixture image and decodes its `decode_in` (or the latents), returning both errors.
fn check(model: &AutoencoderTiny, refs: &HashMap<String, Tensor>, label: &str) -> (f32, f32) {
    let latents = model.encode(&refs["image"]).unwrap();
    let enc_err = max_abs_diff(&latents, &refs["latents"]);
    let decode_in = refs.get("decode_in").unwrap_or(&refs["latents"]);
    let decoded = model.decode(decode_in).unwrap();
    let dec_err = max_abs_diff(&decoded, &refs["decoded"]);
    println!("{label}: encode max abs err {enc_err:.3e}, decode max abs err {dec_err:.3e}");
    (enc_err, dec_err)
}

#[test]
fn tiny_diffusers_layout_matches_diffusers() {
    let model = AutoencoderTiny::load(&repo().join("fixtures/vae/tiny-taesd")).unwrap();
    assert_eq!(model.layout(), TaesdLayout::Diffusers);
    assert_eq!(model.config().act_fn, "silu");
    assert_eq!(model.config().num_decoder_blocks, vec![2, 1, 1]);
    let (e, d) = check(&model, &fixture("taesd-tiny.safetensors"), "tiny-taesd");
    assert!(e <= 1e-4 && d <= 1e-4, "encode {e}, decode {d}");
}

#[test]
fn tiny_original_layout_bf16_matches_diffusers() {
    let tmp = tempfile::tempdir().unwrap();
    let model = AutoencoderTiny::load(&common::tiny_original_layout(tmp.path())).unwrap();
    assert_eq!(model.layout(), TaesdLayout::Original);
    let cfg = model.config();
    assert_eq!(cfg.num_encoder_blocks, vec![1, 1, 2]);
    assert_eq!(cfg.num_decoder_blocks, vec![1, 2, 1]);
    assert_eq!(cfg.encoder_block_out_channels, vec![8, 8, 8]);
    let (e, d) = check(
        &model,
        &fixture("taesd-tiny-original.safetensors"),
        "tiny-taesd-original",
    );
    assert!(e <= 1e-4 && d <= 1e-4, "encode {e}, decode {d}");
}

#[test]
fn unit_range_and_scaled_variants_agree_with_the_plain_api() {
    let model = AutoencoderTiny::load(&repo().join("fixtures/vae/tiny-taesd")).unwrap();
    let refs = fixture("taesd-tiny.safetensors");
    let image = &refs["image"];
    let unit = ((image + 1.0).unwrap() / 2.0).unwrap();
    let a = model.encode(image).unwrap();
    assert!(max_abs_diff(&a, &model.encode_unit(&unit).unwrap()) <= 1e-6);
    assert!(max_abs_diff(&a, &model.encode_scaled(image).unwrap()) == 0.0);
    let z = &refs["decode_in"];
    let pm1 = model.decode(z).unwrap();
    let u = model.decode_unit(z).unwrap();
    assert!(max_abs_diff(&pm1, &((u * 2.0).unwrap() - 1.0).unwrap()) <= 1e-6);
    assert!(max_abs_diff(&pm1, &model.decode_scaled(z).unwrap()) == 0.0);
    // diffusers' 8-bit latent storage mapping round-trips inside its clamp range.
    let back = model
        .latents_from_unit(&model.latents_to_unit(&a).unwrap())
        .unwrap();
    assert!(max_abs_diff(&a, &back) <= 1e-6);
}

fn real_weights() -> Option<PathBuf> {
    testkit::paths::shared_asset("taesd")
}

/// Real bf16 weights: both sides upcast the same bf16 values to f32 and compute in f32, so the only
/// difference is f32 summation order (64-channel 3x3 convs, ~20 layers). Measured max abs errors:
/// 3.8e-6 (latents, |z| up to 2.7) and 1.0e-5 (128x128 image); so the bound stays the f32 one, 1e-4.
#[test]
fn real_taesd_matches_diffusers_on_lego() {
    let Some(dir) = real_weights() else { return };
    let model = AutoencoderTiny::load(&dir).unwrap();
    assert_eq!(model.layout(), TaesdLayout::Original);
    assert_eq!(model.config(), &TaesdConfig::default());
    let (e, d) = check(&model, &fixture("taesd-lego.safetensors"), "taesd-lego");
    assert!(e <= 1e-4 && d <= 1e-4, "encode {e}, decode {d}");
}

/// One network definition on both devices: TAESD on the GPU (lavapipe in CI) matches the CPU to f32
/// precision with f32 weights and to 1e-2 with f16 weights, in both weight layouts (the original one
/// holds bf16 weights, upcast to f32 on upload).
#[test]
fn tiny_taesd_on_gpu_matches_cpu() {
    let tmp = tempfile::tempdir().unwrap();
    for (gpu, tolerance) in common::gpus_or_skip() {
        for (model, fixture_name) in [
            (
                AutoencoderTiny::load(&repo().join("fixtures/vae/tiny-taesd")).unwrap(),
                "taesd-tiny.safetensors",
            ),
            (
                AutoencoderTiny::load(&common::tiny_original_layout(tmp.path())).unwrap(),
                "taesd-tiny-original.safetensors",
            ),
        ] {
            let refs = fixture(fixture_name);
            let latents_cpu = model.encode(&refs["image"]).unwrap();
            let latents_gpu = model
                .encode_on(&refs["image"], &diffusion::device::Device::Gpu(gpu.clone()))
                .unwrap();
            let decode_in = refs.get("decode_in").unwrap_or(&refs["latents"]);
            let image_cpu = model.decode(decode_in).unwrap();
            let image_gpu = model
                .decode_on(decode_in, &diffusion::device::Device::Gpu(gpu.clone()))
                .unwrap();
            let (e, d) = (
                common::relative_error(&latents_gpu, &latents_cpu),
                common::relative_error(&image_gpu, &image_cpu),
            );
            println!(
                "{fixture_name} on {}, {} weights: encode rel err {e:.2e}, decode rel err {d:.2e}",
                gpu.name(),
                gpu.precision()
            );
            assert!(
                e <= tolerance && d <= tolerance,
                "{} weights: encode {e}, decode {d}",
                gpu.precision()
            );
        }
    }
}
