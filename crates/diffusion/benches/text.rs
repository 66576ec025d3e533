//! Tokenizer and CLIP text encoder timing (SD 1.5 text encoder config, random weights, f32 on the CPU).
//!
//! `cargo bench -p vcedit-diffusion --bench text`; `python tools/bench_text.py` times transformers on the same
//! shapes. Threads: RAYON_NUM_THREADS (candle) / torch.set_num_threads.

use std::collections::HashMap;
use std::path::Path;
use std::time::Instant;

use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use diffusion::clip::{ClipActivation, ClipTextConfig, ClipTextModel};
use diffusion::tokenizer::ClipTokenizer;

fn time<T>(label: &str, runs: usize, mut f: impl FnMut() -> T) {
    f(); // warm-up
    let start = Instant::now();
    for _ in 0..runs {
        std::hint::black_box(f());
    }
    println!(
        "{label}: {:.3} ms",
        1e3 * start.elapsed().as_secs_f64() / runs as f64
    );
}

fn main() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let real = root.join("../shared/assets/clip-bpe");
    let tokenizer = if real.join("vocab.json").is_file() {
        println!("tokenizer: real CLIP vocabulary");
        ClipTokenizer::from_dir(&real).unwrap()
    } else {
        println!("tokenizer: tiny fixture vocabulary (../shared absent)");
        ClipTokenizer::from_dir(root.join("fixtures/models/tiny-lcm/tokenizer")).unwrap()
    };
    let start = Instant::now();
    let _ = ClipTokenizer::from_dir(&real);
    println!("tokenizer load: {:.3} s", start.elapsed().as_secs_f64());
    let prompt = "a highly detailed photograph of a red fox sitting in a snowy forest at dawn, soft golden light";
    time("tokenizer encode (one prompt)", 1000, || {
        tokenizer.encode(prompt)
    });

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
    let varmap = VarMap::new();
    ClipTextModel::new(
        VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu),
        cfg.clone(),
    )
    .unwrap();
    // Plain tensors (no Vars) so inference kernels run as with loaded weights.
    let tensors: HashMap<String, Tensor> = varmap
        .data()
        .lock()
        .unwrap()
        .iter()
        .map(|(k, v)| (k.clone(), (v.as_tensor().detach() * 0.05).unwrap()))
        .collect();
    let model = ClipTextModel::new(
        VarBuilder::from_tensors(tensors, DType::F32, &Device::Cpu),
        cfg,
    )
    .unwrap();
    println!("threads {}", rayon::current_num_threads());
    for batch in [1usize, 2, 6] {
        let prompts = vec![prompt; batch];
        time(
            &format!("SD 1.5 text encoder, batch {batch} x 77"),
            5,
            || {
                model
                    .encode_prompts(&tokenizer.clone().with_max_length(77), &prompts)
                    .unwrap()
            },
        );
    }
}
