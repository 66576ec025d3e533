//! A byte-level BPE learner that writes CLIP-format tokenizer files for the demo's small vocabulary.
//!
//! CLIP's tokenizer (and [`diffusion::tokenizer::ClipTokenizer`]) maps every UTF-8 byte of a word to a
//! printable character (the GPT-2 byte table), marks the word's last symbol with `</w>` and applies the
//! merges of `merges.txt` in rank order. The vocabulary (`vocab.json`) lists, in id order: the 256 byte
//! characters, the same 256 with `</w>`, one token per merge, then `<|startoftext|>` and `<|endoftext|>`.
//!
//! [`learn`] runs classic BPE on word counts: count adjacent symbol pairs over all words (weighted by
//! frequency), merge the most frequent pair (ties: the lexicographically smallest pair, so the result is
//! deterministic), repeat until every word is a single symbol or `max_merges` is reached. With the caption
//! words as input and no limit, every caption word becomes exactly one token, which keeps the cross-attention
//! maps of the demo model one map per word.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};

pub const END_OF_WORD: &str = "</w>";
pub const START_OF_TEXT: &str = "<|startoftext|>";
pub const END_OF_TEXT: &str = "<|endoftext|>";

#[derive(Debug, thiserror::Error)]
pub enum BpeError {
    #[error("{}: cannot write: {source}", .path.display())]
    Write {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("word {0:?} contains whitespace; BPE words are whitespace-free")]
    BadWord(String),
}

/// The GPT-2/CLIP byte table: printable bytes map to themselves, the others to code points from U+0100 up,
/// in byte order. Returned in CLIP's vocabulary order (the printable ranges first, then the remapped bytes).
pub fn byte_chars() -> Vec<(u8, char)> {
    let printable =
        |b: u32| (33..=126).contains(&b) || (161..=172).contains(&b) || (174..=255).contains(&b);
    let mut kept: Vec<(u8, char)> = (0..256u32)
        .filter(|&b| printable(b))
        .map(|b| (b as u8, char::from_u32(b).expect("latin-1 code point")))
        .collect();
    for (next, b) in (256u32..).zip((0..256u32).filter(|&b| !printable(b))) {
        kept.push((b as u8, char::from_u32(next).expect("valid code point")));
    }
    kept
}

/// A learnt BPE: merges in rank order.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Bpe {
    pub merges: Vec<(String, String)>,
}

/// Splits a word into its initial symbols: byte characters, the last one carrying `</w>`.
fn initial_symbols(word: &str, table: &[char; 256]) -> Vec<String> {
    let mut symbols: Vec<String> = word
        .bytes()
        .map(|b| table[b as usize].to_string())
        .collect();
    if let Some(last) = symbols.last_mut() {
        last.push_str(END_OF_WORD);
    }
    symbols
}

/// Learns merges from `(word, count)` pairs (words are lowercased, as CLIP's tokenizer lowercases text).
pub fn learn<'a>(
    words: impl IntoIterator<Item = (&'a str, u64)>,
    max_merges: Option<usize>,
) -> Result<Bpe, BpeError> {
    let mut table = ['\0'; 256];
    for (b, c) in byte_chars() {
        table[b as usize] = c;
    }
    // BTreeMap: a deterministic word order.
    let mut counts: BTreeMap<String, u64> = BTreeMap::new();
    for (word, n) in words {
        if word.is_empty() {
            continue;
        }
        if word.chars().any(char::is_whitespace) {
            return Err(BpeError::BadWord(word.to_string()));
        }
        *counts.entry(word.to_lowercase()).or_default() += n;
    }
    let mut seqs: Vec<(Vec<String>, u64)> = counts
        .iter()
        .map(|(w, &n)| (initial_symbols(w, &table), n))
        .collect();
    let mut merges = Vec::new();
    while max_merges.is_none_or(|m| merges.len() < m) {
        let mut pairs: HashMap<(&str, &str), u64> = HashMap::new();
        for (seq, n) in &seqs {
            for pair in seq.windows(2) {
                *pairs.entry((&pair[0], &pair[1])).or_default() += n;
            }
        }
        let Some(best) = pairs
            .into_iter()
            .max_by(|(a, na), (b, nb)| na.cmp(nb).then_with(|| b.cmp(a)))
            .map(|((a, b), _)| (a.to_string(), b.to_string()))
        else {
            break;
        };
        let merged = format!("{}{}", best.0, best.1);
        for (seq, _) in &mut seqs {
            let mut out = Vec::with_capacity(seq.len());
            let mut i = 0;
            while i < seq.len() {
                if i + 1 < seq.len() && seq[i] == best.0 && seq[i + 1] == best.1 {
                    out.push(merged.clone());
                    i += 2;
                } else {
                    out.push(std::mem::take(&mut seq[i]));
                    i += 1;
                }
            }
            *seq = out;
        }
        merges.push(best);
    }
    Ok(Bpe { merges })
}

impl Bpe {
    /// Token strings in id order (duplicates, which two merges can produce, keep their first id).
    pub fn vocabulary(&self) -> Vec<String> {
        let chars = byte_chars();
        let mut tokens: Vec<String> = chars.iter().map(|(_, c)| c.to_string()).collect();
        tokens.extend(chars.iter().map(|(_, c)| format!("{c}{END_OF_WORD}")));
        tokens.extend(self.merges.iter().map(|(a, b)| format!("{a}{b}")));
        tokens.push(START_OF_TEXT.into());
        tokens.push(END_OF_TEXT.into());
        let mut seen = std::collections::HashSet::new();
        tokens.retain(|t| seen.insert(t.clone()));
        tokens
    }

    /// Number of distinct tokens (the text encoder's `vocab_size`).
    pub fn vocab_size(&self) -> usize {
        self.vocabulary().len()
    }

    /// Writes `vocab.json`, `merges.txt`, `tokenizer_config.json` and `special_tokens_map.json` into `dir`
    /// (created if needed): a tokenizer folder `transformers.CLIPTokenizer` and [`ClipTokenizer`] load.
    ///
    /// [`ClipTokenizer`]: diffusion::tokenizer::ClipTokenizer
    pub fn write_tokenizer(&self, dir: &Path, max_length: usize) -> Result<(), BpeError> {
        let write = |name: &str, text: String| {
            let path = dir.join(name);
            files::atomic_write(&path, text.as_bytes())
                .map_err(|source| BpeError::Write { path, source })
        };
        std::fs::create_dir_all(dir).map_err(|source| BpeError::Write {
            path: dir.to_path_buf(),
            source,
        })?;
        let vocab: serde_json::Map<String, serde_json::Value> = self
            .vocabulary()
            .into_iter()
            .enumerate()
            .map(|(id, t)| (t, serde_json::Value::from(id)))
            .collect();
        write("vocab.json", serde_json::to_string(&vocab).expect("json"))?;
        let mut merges = String::from("#version: 0.2\n");
        for (a, b) in &self.merges {
            merges.push_str(&format!("{a} {b}\n"));
        }
        write("merges.txt", merges)?;
        let config = serde_json::json!({
            "tokenizer_class": "CLIPTokenizer",
            "model_max_length": max_length,
            "bos_token": START_OF_TEXT,
            "eos_token": END_OF_TEXT,
            "unk_token": END_OF_TEXT,
            "pad_token": END_OF_TEXT,
            "do_lower_case": true,
            "clean_up_tokenization_spaces": true,
        });
        write("tokenizer_config.json", pretty(&config))?;
        let special = serde_json::json!({
            "bos_token": START_OF_TEXT,
            "eos_token": END_OF_TEXT,
            "unk_token": END_OF_TEXT,
            "pad_token": END_OF_TEXT,
        });
        write("special_tokens_map.json", pretty(&special))
    }
}

fn pretty(value: &serde_json::Value) -> String {
    let mut s = serde_json::to_string_pretty(value).expect("json");
    s.push('\n');
    s
}

/// The demo tokenizer: every word of [`crate::world::VOCABULARY`] becomes one token.
pub fn demo_bpe() -> Bpe {
    let words = crate::world::VOCABULARY.iter().map(|w| (*w, 1u64));
    learn(words, None).expect("the vocabulary has no whitespace")
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::world::{GeneratorSettings, SceneSpec, VOCABULARY};
    use diffusion::tokenizer::ClipTokenizer;

    #[test]
    fn byte_table_is_a_bijection_in_clip_order() {
        let chars = byte_chars();
        assert_eq!(chars.len(), 256);
        let bytes: std::collections::HashSet<u8> = chars.iter().map(|(b, _)| *b).collect();
        let cs: std::collections::HashSet<char> = chars.iter().map(|(_, c)| *c).collect();
        assert_eq!((bytes.len(), cs.len()), (256, 256));
        // CLIP's vocabulary starts with "!" (byte 33) and its 189th entry is the remapped byte 0 (U+0100).
        assert_eq!(chars[0], (b'!', '!'));
        assert_eq!(chars[188], (0, '\u{100}'));
        assert_eq!(chars[255].1, '\u{143}');
    }

    #[test]
    fn learning_merges_the_most_frequent_pair_first() {
        let bpe = learn(
            [("low", 5), ("lower", 2), ("newest", 6), ("widest", 3)],
            Some(3),
        )
        .unwrap();
        // "e s" appears in newest (6) and widest (3) = 9; "s t</w>" also 9; ties break to the smaller pair.
        assert_eq!(bpe.merges[0], ("e".to_string(), "s".to_string()));
        assert_eq!(bpe.merges[1], ("es".to_string(), "t</w>".to_string()));
        assert_eq!(bpe.merges.len(), 3);
        // Without a limit every word ends as one symbol: the last merges build whole words.
        let full = learn([("low", 5), ("lower", 2)], None).unwrap();
        let vocab = full.vocabulary();
        assert!(vocab.contains(&"low</w>".to_string()) && vocab.contains(&"lower</w>".to_string()));
    }

    #[test]
    fn vocabulary_has_the_clip_layout() {
        let bpe = demo_bpe();
        let vocab = bpe.vocabulary();
        assert_eq!(vocab[0], "!");
        assert_eq!(vocab[256], "!</w>");
        assert_eq!(vocab[vocab.len() - 2], START_OF_TEXT);
        assert_eq!(vocab[vocab.len() - 1], END_OF_TEXT);
        assert_eq!(vocab.len(), bpe.vocab_size());
        assert!(vocab.len() < 1000, "small vocabulary: {}", vocab.len());
    }

    #[test]
    fn clip_tokenizer_encodes_every_caption_word_as_one_token() {
        let dir = tempfile::tempdir().unwrap();
        let bpe = demo_bpe();
        bpe.write_tokenizer(dir.path(), 77).unwrap();
        let merges = std::fs::read_to_string(dir.path().join("merges.txt")).unwrap();
        assert!(merges.starts_with("#version: 0.2\n"));
        let tok = ClipTokenizer::from_dir(dir.path()).unwrap();
        assert_eq!(tok.vocab_size(), bpe.vocab_size());
        assert_eq!(tok.bos_id() as usize, bpe.vocab_size() - 2);
        assert_eq!(tok.eos_id() as usize, bpe.vocab_size() - 1);
        let mut ids = std::collections::HashSet::new();
        for word in VOCABULARY {
            let t = tok.tokenize(word);
            assert_eq!(t.len(), 1, "{word}: {:?}", tok.token_strings(&t));
            assert_eq!(tok.token_to_id(&format!("{word}</w>")), Some(t[0]));
            ids.insert(t[0]);
        }
        assert_eq!(
            ids.len(),
            VOCABULARY.len(),
            "distinct words get distinct tokens"
        );
        // Whole captions: one token per word plus start and end, padded with the end token.
        let settings = GeneratorSettings::default();
        for seed in 0..200 {
            let caption = SceneSpec::random(seed, &settings).caption();
            let enc = tok.encode(&caption);
            assert_eq!(
                enc.num_tokens,
                caption.split_whitespace().count() + 2,
                "{caption}"
            );
            assert_eq!(enc.ids.len(), 77);
            assert_eq!(tok.decode(&enc.ids, true), caption);
        }
    }

    #[test]
    fn whitespace_in_a_word_is_rejected() {
        assert!(matches!(
            learn([("a b", 1)], None),
            Err(BpeError::BadWord(_))
        ));
    }
}
