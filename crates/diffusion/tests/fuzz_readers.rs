//! Fuzzing the model-file readers (see `testkit::fuzz`): safetensors headers and the CLIP tokenizer
//! (vocab.json, merges.txt, tokenizer_config.json), seeded from the tiny test model and hand-made files
//! and mutated for `VCEDIT_FUZZ_SECONDS` (default 5 s) per target. Any error is fine; a panic fails the
//! test and the input is saved under target/fuzz-crashes/.

use std::path::Path;

use diffusion::loader::read_safetensors_header;
use diffusion::tokenizer::ClipTokenizer;
use testkit::paths::tiny_lcm;

// Every input's allocations are measured (an input that makes its reader claim too much fails).
#[global_allocator]
static ALLOC: testkit::fuzz::CountingAlloc = testkit::fuzz::CountingAlloc;

/// A small valid safetensors file: two tensors of different dtypes and a metadata table.
fn small_safetensors() -> Vec<u8> {
    let header = r#"{"__metadata__":{"format":"pt"},"a.weight":{"dtype":"F32","shape":[2,3],"data_offsets":[0,24]},"b.bias":{"dtype":"F16","shape":[4],"data_offsets":[24,32]}}"#;
    let mut header = header.as_bytes().to_vec();
    // Headers are padded with spaces to a multiple of 8 bytes.
    header.resize(header.len().div_ceil(8) * 8, b' ');
    let mut file = (header.len() as u64).to_le_bytes().to_vec();
    file.extend(header);
    file.extend((0..32u8).map(|i| i.wrapping_mul(37)));
    file
}

#[test]
fn fuzz_safetensors_header() {
    let seeds = vec![
        small_safetensors(),
        std::fs::read(tiny_lcm().join("text_encoder/model.safetensors")).unwrap(),
    ];
    testkit::fuzz::run_file_and_assert(
        "safetensors_header",
        "model.safetensors",
        &seeds,
        &testkit::fuzz::crash_dir(),
        |path| {
            let _ = read_safetensors_header(path);
        },
    );
}

/// Loads the tokenizer in `dir` and, when it loads, encodes a few prompts with it.
fn load_and_encode(dir: &Path) {
    let Ok(tok) = ClipTokenizer::from_dir(dir) else {
        return;
    };
    for prompt in [
        "a photo of a cat",
        "A RED  ball, on grass!",
        "",
        "ünïcödé 123 <|endoftext|>",
    ] {
        let _ = tok.encode(prompt);
        let _ = tok.encode_strict(prompt);
        let ids = tok.encode_unpadded(prompt);
        let _ = tok.token_strings(&ids);
    }
}

#[test]
fn fuzz_tokenizer_files() {
    testkit::fuzz::run_file_set_and_assert(
        "tokenizer",
        &tiny_lcm().join("tokenizer"),
        &["vocab.json", "merges.txt", "tokenizer_config.json"],
        &testkit::fuzz::crash_dir(),
        load_and_encode,
    );
}

/// The model folder's JSON files (`model_index.json`, the components' `config.json`s and
/// `scheduler_config.json`), each mutated in a copy of the tiny model whose other files stay valid, read
/// by `model check` (headers, configs, shapes) and the schedulers.
#[test]
fn fuzz_model_configs() {
    const CONFIGS: [&str; 5] = [
        "model_index.json",
        "scheduler/scheduler_config.json",
        "unet/config.json",
        "vae/config.json",
        "text_encoder/config.json",
    ];
    let copy = tempfile::tempdir().unwrap();
    for entry in testkit::paths::files_under(&tiny_lcm()) {
        let rel = entry.strip_prefix(tiny_lcm()).unwrap();
        std::fs::create_dir_all(copy.path().join(rel).parent().unwrap()).unwrap();
        std::fs::copy(&entry, copy.path().join(rel)).unwrap();
    }
    let seeds: Vec<Vec<u8>> = CONFIGS
        .iter()
        .enumerate()
        .map(|(i, name)| {
            let mut seed = vec![i as u8];
            seed.extend(std::fs::read(tiny_lcm().join(name)).unwrap());
            seed
        })
        .collect();
    testkit::fuzz::run_and_assert(
        "model-configs",
        &seeds,
        &testkit::fuzz::crash_dir(),
        |input| {
            let Some((&which, content)) = input.split_first() else {
                return;
            };
            let name = CONFIGS[which as usize % CONFIGS.len()];
            let path = copy.path().join(name);
            std::fs::write(&path, content).unwrap();
            let _ = diffusion::model_check::check_model(
                copy.path(),
                diffusion::model_check::CheckDepth::HeadersOnly,
            );
            let _ = diffusion::scheduler::Scheduler::from_config_file(
                &copy.path().join(CONFIGS[1]),
                diffusion::scheduler::LcmVariant::default(),
            );
            std::fs::copy(tiny_lcm().join(name), &path).unwrap();
        },
    );
}
