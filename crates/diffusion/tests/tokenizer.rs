//! The CLIP tokenizer against ids recorded from `transformers.CLIPTokenizer` (tools/make_text_fixtures.py).

use diffusion::tokenizer::{ClipTokenizer, TokenizerSource};
use serde::Deserialize;
use testkit::paths::repo;

#[derive(Deserialize)]
struct Record {
    max_length: usize,
    vocab_size: usize,
    pad_token_id: u32,
    cases: Vec<Case>,
}

#[derive(Deserialize)]
struct Case {
    prompt: String,
    ids: Vec<u32>,
    num_tokens: usize,
    full_ids: Vec<u32>,
    token_strings: Vec<String>,
    decoded: String,
    decoded_skip_special: String,
}

fn record(name: &str) -> Record {
    let path = repo().join(format!("fixtures/text/tokens-{name}.json"));
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    serde_json::from_str(&text).unwrap()
}

fn check(tok: &ClipTokenizer, rec: &Record) {
    assert_eq!(tok.max_length(), rec.max_length);
    assert_eq!(tok.vocab_size(), rec.vocab_size);
    assert_eq!(tok.pad_id(), rec.pad_token_id);
    let mut failures = Vec::new();
    for case in &rec.cases {
        let enc = tok.encode(&case.prompt);
        let full = tok.encode_unpadded(&case.prompt);
        if enc.ids != case.ids || enc.num_tokens != case.num_tokens || full != case.full_ids {
            failures.push(format!(
                "{:?}\n  got      {:?} (n={})\n  expected {:?} (n={})\n  full got {:?}\n  expected {:?}",
                case.prompt, enc.ids, enc.num_tokens, case.ids, case.num_tokens, full, case.full_ids
            ));
            continue;
        }
        let room = rec.max_length - 2;
        assert_eq!(
            enc.dropped_tokens,
            (full.len() - 2).saturating_sub(room),
            "{:?}",
            case.prompt
        );
        assert_eq!(
            enc.truncated(),
            tok.encode_strict(&case.prompt).is_err(),
            "{:?}",
            case.prompt
        );
        let strings = tok.token_strings(&full);
        if strings != case.token_strings {
            failures.push(format!(
                "{:?}: token strings {strings:?} != {:?}",
                case.prompt, case.token_strings
            ));
        }
        let decoded = tok.decode(&full, false);
        let decoded_skip = tok.decode(&full, true);
        if decoded != case.decoded || decoded_skip != case.decoded_skip_special {
            failures.push(format!(
                "{:?}: decoded {decoded:?} / {decoded_skip:?}, expected {:?} / {:?}",
                case.prompt, case.decoded, case.decoded_skip_special
            ));
        }
    }
    assert!(
        failures.is_empty(),
        "{} of {} prompts differ:\n{}",
        failures.len(),
        rec.cases.len(),
        failures.join("\n")
    );
}

#[test]
fn tiny_lcm_vocab_and_merges_match_transformers() {
    let tok = ClipTokenizer::from_dir(repo().join("fixtures/models/tiny-lcm/tokenizer")).unwrap();
    assert_eq!(tok.source(), TokenizerSource::VocabAndMerges);
    check(&tok, &record("tiny-lcm"));
}

#[test]
fn tiny_ip2p_tokenizer_json_with_bang_padding_matches_transformers() {
    let tok = ClipTokenizer::from_dir(repo().join("fixtures/models/tiny-ip2p/tokenizer")).unwrap();
    assert_eq!(tok.source(), TokenizerSource::TokenizerJson);
    // The config's model_max_length is 1e30; the tokenizer still pads to the encoder's 77 positions.
    assert_eq!(tok.max_length(), 77);
    check(&tok, &record("tiny-ip2p"));
}

#[test]
fn real_clip_vocabulary_matches_transformers() {
    let dir = repo().join("../shared/assets/clip-bpe");
    if !dir.join("vocab.json").is_file() {
        eprintln!(
            "SKIP real_clip_vocabulary_matches_transformers: {} is absent",
            dir.display()
        );
        return;
    }
    let tok = ClipTokenizer::from_dir(&dir).unwrap();
    assert_eq!(tok.vocab_size(), 49408);
    assert_eq!((tok.bos_id(), tok.eos_id()), (49406, 49407));
    check(&tok, &record("clip-bpe"));
}

#[test]
fn merges_in_string_and_pair_form_load_alike() {
    // tokenizers wrote merges as "a b" strings before 0.20; rewrite the fixture that way and compare.
    let src = repo().join("fixtures/models/tiny-ip2p/tokenizer");
    let mut json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(src.join("tokenizer.json")).unwrap())
            .unwrap();
    let merges = json["model"]["merges"].as_array().unwrap().clone();
    assert!(
        merges[0].is_array(),
        "fixture is expected to use the pair form"
    );
    json["model"]["merges"] = merges
        .iter()
        .map(|m| {
            serde_json::Value::String(format!(
                "{} {}",
                m[0].as_str().unwrap(),
                m[1].as_str().unwrap()
            ))
        })
        .collect();
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("tokenizer.json"), json.to_string()).unwrap();
    std::fs::copy(
        src.join("tokenizer_config.json"),
        dir.path().join("tokenizer_config.json"),
    )
    .unwrap();
    let strings = ClipTokenizer::from_dir(dir.path()).unwrap();
    let pairs = ClipTokenizer::from_dir(&src).unwrap();
    for p in ["a photograph of clowns wearing hats!", "striped spheres"] {
        assert_eq!(strings.encode(p), pairs.encode(p));
    }
}

#[test]
fn missing_vocabulary_is_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let err = ClipTokenizer::from_dir(dir.path()).unwrap_err().to_string();
    assert!(
        err.contains("neither tokenizer.json nor vocab.json + merges.txt"),
        "{err}"
    );
}

#[test]
fn empty_merges_or_vocabulary_are_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("vocab.json"), r#"{"a</w>": 0, "b</w>": 1}"#).unwrap();
    std::fs::write(dir.path().join("merges.txt"), "#version: 0.2\n").unwrap();
    let err = ClipTokenizer::from_dir(dir.path()).unwrap_err().to_string();
    assert!(
        err.contains("merges.txt") && err.contains("no BPE merges"),
        "{err}"
    );
    std::fs::write(dir.path().join("vocab.json"), "{}").unwrap();
    let err = ClipTokenizer::from_dir(dir.path()).unwrap_err().to_string();
    assert!(
        err.contains("vocab.json") && err.contains("vocabulary is empty"),
        "{err}"
    );
}
