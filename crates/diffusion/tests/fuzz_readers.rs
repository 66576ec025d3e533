//! Fuzzing the model-file readers (see `files::fuzz`): safetensors headers and the CLIP tokenizer
//! (vocab.json, merges.txt, tokenizer_config.json), seeded from the tiny test model and hand-made files
//! and mutated for `VCEDIT_FUZZ_SECONDS` (default 5 s) per target. Any error is fine; a panic fails the
//! test and the input is saved under target/fuzz-crashes/.

use std::path::{Path, PathBuf};

use diffusion::loader::read_safetensors_header;
use diffusion::tokenizer::ClipTokenizer;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn crash_dir() -> PathBuf {
    root().join("target/fuzz-crashes")
}

fn tiny_model() -> PathBuf {
    root().join("fixtures/models/tiny-lcm")
}

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
        std::fs::read(tiny_model().join("text_encoder/model.safetensors")).unwrap(),
    ];
    files::fuzz::run_file_and_assert(
        "safetensors_header",
        "model.safetensors",
        &seeds,
        &crash_dir(),
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
    files::fuzz::run_file_set_and_assert(
        "tokenizer",
        &tiny_model().join("tokenizer"),
        &["vocab.json", "merges.txt", "tokenizer_config.json"],
        &crash_dir(),
        load_and_encode,
    );
}
