//! The CLIP text encoder against `transformers.CLIPTextModel` outputs recorded by
//! tools/make_text_fixtures.py for both tiny models (f32 weights, and f16 weights loaded as f32).

use std::collections::HashMap;

use candle_core::{DType, Device, Tensor};
use diffusion::clip::{ids_tensor, ClipTextModel};
use diffusion::loader::ModelDir;
use diffusion::tokenizer::ClipTokenizer;
use testkit::paths::{load_tensors, repo};

mod common;
use common::{in_bf16, max_abs_diff, relative_l2};

/// The tiny model `name` in f32 on the CPU, its recorded outputs, and their input ids.
fn tiny_model(name: &str) -> (ClipTextModel, HashMap<String, Tensor>, Tensor) {
    let model_dir = ModelDir::open(repo().join("fixtures/models").join(name)).unwrap();
    let model = ClipTextModel::load(&model_dir, DType::F32, &Device::Cpu).unwrap();
    let reference = load_tensors(&repo().join(format!("fixtures/text/encoder-{name}.safetensors")));
    let ids = reference["input_ids"].to_dtype(DType::U32).unwrap();
    (model, reference, ids)
}

fn check_model(name: &str) {
    let dev = Device::Cpu;
    let (model, reference, ids) = tiny_model(name);
    let model_dir = ModelDir::open(repo().join("fixtures/models").join(name)).unwrap();

    // The tokenizer produces the same ids as transformers for the recorded prompts.
    let tokenizer =
        ClipTokenizer::from_dir(model_dir.component_dir(diffusion::loader::Component::Tokenizer))
            .unwrap()
            .with_max_length(model.max_positions());
    let prompts: Vec<String> = {
        let (_, meta) = safetensors::SafeTensors::read_metadata(
            &std::fs::read(repo().join(format!("fixtures/text/encoder-{name}.safetensors")))
                .unwrap(),
        )
        .unwrap();
        serde_json::from_str(&meta.metadata().as_ref().unwrap()["prompts"]).unwrap()
    };
    let encodings: Vec<_> = prompts.iter().map(|p| tokenizer.encode(p)).collect();
    assert!(
        encodings.last().unwrap().truncated(),
        "the last recorded prompt is the long one"
    );
    let our_ids = ids_tensor(&encodings, &dev).unwrap();
    assert_eq!(
        our_ids.to_vec2::<u32>().unwrap(),
        ids.to_vec2::<u32>().unwrap()
    );

    let hidden = model.forward(&ids).unwrap();
    let err = max_abs_diff(&hidden, &reference["last_hidden_state"]);
    println!("{name}: last_hidden_state max abs error {err:.2e}");
    assert!(err <= 1e-4, "{name}: last_hidden_state error {err}");

    let pooled = model.pooled_output(&hidden, &ids).unwrap();
    assert!(max_abs_diff(&pooled, &reference["pooler_output"]) <= 1e-4);

    let skip = model.forward_skip(&ids, 1).unwrap();
    let err = max_abs_diff(&skip, &reference["clip_skip_1"]);
    assert!(err <= 1e-4, "{name}: clip_skip error {err}");

    let emb = model.token_embeddings(&ids).unwrap();
    assert_eq!(max_abs_diff(&emb, &reference["token_embeddings"]), 0.0);
}

#[test]
fn tiny_lcm_text_encoder_matches_transformers() {
    check_model("tiny-lcm");
}

#[test]
fn tiny_ip2p_f16_text_encoder_matches_transformers() {
    check_model("tiny-ip2p");
}

/// With bf16 products the tiny text encoders' hidden states stay within bf16's rounding of transformers'
/// f32 ones (relative L2 ≤ 1e-2; above 1e-5, so bf16 products did run). A model loaded under bf16
/// products keeps only its weights' bf16 pairs and gives the very same values.
#[test]
fn tiny_text_encoders_with_bf16_products_match_transformers_within_bf16() {
    for name in ["tiny-lcm", "tiny-ip2p"] {
        let (model, reference, ids) = tiny_model(name);
        let Some((hidden, stored_once)) = in_bf16(|| {
            (
                model.forward(&ids).unwrap(),
                tiny_model(name).0.forward(&ids).unwrap(),
            )
        }) else {
            return;
        };
        assert_eq!(
            max_abs_diff(&hidden, &stored_once),
            0.0,
            "{name}: stored once"
        );
        let rel = relative_l2(&hidden, &reference["last_hidden_state"]);
        println!("{name}: bf16 last_hidden_state relative L2 {rel:.2e}");
        assert!(rel <= 1e-2 && rel > 1e-5, "{name}: relative L2 {rel}");
    }
}

/// One definition on both devices: the text encoder's layers on the GPU (lavapipe in CI) give the CPU's
/// hidden states to f32 precision (to 1e-2 with f16 weights), with and without clip skip.
#[test]
fn tiny_text_encoder_on_gpu_matches_cpu() {
    for (gpu, tolerance) in common::gpus_or_skip() {
        for name in ["tiny-lcm", "tiny-ip2p"] {
            let (model, _, ids) = tiny_model(name);
            for skip in [0, 1] {
                let cpu = model.forward_skip(&ids, skip).unwrap();
                let on_gpu = model
                    .forward_skip_on(&ids, skip, &diffusion::device::Device::Gpu(gpu.clone()))
                    .unwrap();
                let rel = common::relative_error(&on_gpu, &cpu);
                let precision = gpu.precision();
                println!(
                    "{name} clip_skip {skip} on {}, {precision} weights: relative error {rel:.2e}",
                    gpu.name()
                );
                assert!(
                    rel <= tolerance,
                    "{name} clip_skip {skip}, {precision} weights: relative error {rel}"
                );
            }
        }
    }
}
