//! Tokenizer and CLIP text encoder: SD 1.5's text encoder config with random weights, or a pipeline's
//! (`--model DIR`: its `text_encoder/` and `tokenizer/`), on the CPU or a GPU.
//!
//! `vcedit bench text [--model DIR] [--vocab DIR] [--batches 1,2,6] [--runs 5] [--device cpu|gpu|auto]
//! [--precision f16|f32]`. Without `--model`, the tokenizer is read from `--vocab` (a folder with
//! `vocab.json` + `merges.txt`; default ../shared/assets/clip-bpe beside the repository, else the tiny
//! fixture vocabulary). `python tools/bench_text.py` times transformers on the same shapes.
//! Threads: RAYON_NUM_THREADS (candle) / torch.set_num_threads.

use std::path::{Path, PathBuf};

use candle_core::{DType, Device};
use diffusion::clip::{ClipActivation, ClipTextConfig, ClipTextModel};
use diffusion::loader::{Component, ModelDir};
use diffusion::tokenizer::ClipTokenizer;

use crate::{
    arg_list, arg_parsed, arg_value, network_device, networks_on, random_weights, report, Result,
    Timed,
};

const PROMPT: &str = "a highly detailed photograph of a red fox sitting in a snowy forest at dawn, soft golden light";

/// SD 1.5's text encoder (CLIP ViT-L/14) with random weights.
fn random_encoder() -> Result<ClipTextModel> {
    let cfg = ClipTextConfig {
        vocab_size: 49408,
        hidden_size: 768,
        intermediate_size: 3072,
        num_hidden_layers: 12,
        num_attention_heads: 12,
        max_position_embeddings: 77,
        hidden_act: ClipActivation::QuickGelu,
        layer_norm_eps: 1e-5,
        eos_token_id: 2,
        projection_dim: Some(768),
    };
    Ok(ClipTextModel::new(
        random_weights(|vb| ClipTextModel::new(vb, cfg.clone()))?,
        cfg,
    )?)
}

/// The vocabulary folder when no model is given: `--vocab`, the shared real one, or the tiny fixture's.
fn vocab_dir(args: &[String]) -> PathBuf {
    if let Some(dir) = arg_value(args, "--vocab") {
        return dir.into();
    }
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let real = root.join("../shared/assets/clip-bpe");
    if real.join("vocab.json").is_file() {
        real
    } else {
        root.join("fixtures/models/tiny-lcm/tokenizer")
    }
}

pub fn main(args: &[String]) -> Result<()> {
    let batches: Vec<usize> = arg_list(args, "--batches", "1,2,6")?;
    let runs: usize = arg_parsed(args, "--runs", 5)?;
    let gpu = network_device(args, "cpu")?;
    let gpu = gpu.as_ref();
    let device = diffusion::device::Device::from(gpu.cloned());
    let on = networks_on(gpu);
    let (tokenizer, model, which) = match arg_value(args, "--model") {
        Some(dir) => {
            let model_dir =
                ModelDir::open_components(&dir, &[Component::TextEncoder, Component::Tokenizer])?;
            let encoder = ClipTextModel::load(&model_dir, DType::F32, &Device::Cpu)?;
            let tokenizer = ClipTokenizer::from_dir(model_dir.component_dir(Component::Tokenizer))?;
            (tokenizer, encoder, dir)
        }
        None => {
            let dir = vocab_dir(args);
            let tokenizer = ClipTokenizer::from_dir(&dir)?;
            (
                tokenizer,
                random_encoder()?,
                format!(
                    "SD 1.5 config, random weights, vocabulary {}",
                    dir.display()
                ),
            )
        }
    };
    let tokenizer = tokenizer.with_max_length(model.max_positions());
    eprintln!("text bench: {which}, {on}");
    let timed = Timed::measure(1000, || Ok(tokenizer.encode(PROMPT)))?;
    report(timed.json(serde_json::json!({
        "bench": "text", "what": "tokenize", "model": which,
    })));
    for &batch in &batches {
        let prompts = vec![PROMPT; batch];
        let timed = Timed::measure(runs, || {
            let encodings: Vec<_> = prompts.iter().map(|p| tokenizer.encode(p)).collect();
            let ids = diffusion::clip::ids_tensor(&encodings, &Device::Cpu)?;
            Ok(model.forward_skip_on(&ids, 0, &device)?)
        })?;
        eprintln!(
            "  encoder, batch {batch}: best {:.2} ms (first call {:.1} ms)",
            timed.best().as_secs_f64() * 1e3,
            timed.first.as_secs_f64() * 1e3
        );
        report(timed.json(serde_json::json!({
            "bench": "text", "what": "encode", "model": which, "batch": batch, "device": on,
        })));
    }
    Ok(())
}
