//! CLIP byte-level BPE tokenizer, giving the same ids as `transformers.CLIPTokenizer` (5.x, backed by
//! `tokenizers`).
//!
//! Pipeline, in the order the reference applies it:
//! 1. special ("added") tokens are cut out of the raw text (`<|startoftext|>`, `<|endoftext|>`, and the pad
//!    token, e.g. `!` for SD2-style tokenizers, so a literal `!` in a prompt becomes the pad id);
//! 2. each remaining piece is normalised: Unicode NFC, every whitespace run becomes one space, lowercase
//!    (char by char, so a final Σ becomes σ, not ς);
//! 3. it is split with CLIP's pattern (contractions, letter runs, single digits, punctuation runs; spaces
//!    are dropped), then each piece again with the byte-level pre-tokenizer's GPT-2 pattern (this only
//!    matters for the special-token alternatives: a lowercased `<|ENDOFTEXT|>` ends up as `<|`,
//!    `endoftext`, `|>`);
//! 4. every piece's UTF-8 bytes are mapped to printable characters (the GPT-2/CLIP byte table) and merged
//!    with BPE, the last symbol of a word carrying the `</w>` suffix;
//! 5. `<|startoftext|>` and `<|endoftext|>` surround the ids; the text encoder's positions (77) bound the
//!    length: longer prompts are truncated keeping the end token, shorter ones padded with the pad token.
//!
//! Vocabularies load from `vocab.json` + `merges.txt` (older hub folders) or from `tokenizer.json` (what
//! current `transformers` saves), with `tokenizer_config.json` naming the special tokens.

use std::collections::HashMap;
use std::fs;
use std::path::{Path, PathBuf};

use regex::Regex;
use serde::Deserialize;
use unicode_normalization::UnicodeNormalization;

/// Errors from loading a tokenizer or from strict encoding.
#[derive(Debug, thiserror::Error)]
pub enum TokenizerError {
    #[error("{}: {source}", .path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{}: {message}", .path.display())]
    Format { path: PathBuf, message: String },
    #[error("tokenizer folder {} has neither tokenizer.json nor vocab.json + merges.txt", .0.display())]
    NoVocabulary(PathBuf),
    #[error(
        "prompt is too long: {tokens} tokens with start/end, the text encoder takes {max}; \
         {dropped} would be cut off (\"{dropped_text}\")"
    )]
    PromptTooLong {
        tokens: usize,
        max: usize,
        dropped: usize,
        dropped_text: String,
    },
}

/// Where the vocabulary came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TokenizerSource {
    VocabAndMerges,
    TokenizerJson,
}

impl std::fmt::Display for TokenizerSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            TokenizerSource::VocabAndMerges => "vocab.json + merges.txt",
            TokenizerSource::TokenizerJson => "tokenizer.json",
        })
    }
}

/// A prompt as the text encoder receives it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Encoding {
    /// Exactly `max_length` ids: start token, prompt tokens, end token, padding.
    pub ids: Vec<u32>,
    /// Real tokens including start and end (InfEdit's "L"); the rest is padding.
    pub num_tokens: usize,
    /// Prompt tokens cut off by truncation (0 when the prompt fits).
    pub dropped_tokens: usize,
}

impl Encoding {
    pub fn truncated(&self) -> bool {
        self.dropped_tokens > 0
    }
}

/// A special token matched verbatim in the text before normalisation (or after, if `normalized`).
#[derive(Debug, Clone)]
struct AddedToken {
    content: String,
    id: u32,
    normalized: bool,
    special: bool,
}

/// The CLIP tokenizer. Cheap to share; encoding takes `&self`.
#[derive(Debug, Clone)]
pub struct ClipTokenizer {
    vocab: HashMap<String, u32>,
    /// id -> token string (added tokens included).
    tokens: Vec<String>,
    /// (left id, right id) -> (merge rank, merged id)
    merges: HashMap<(u32, u32), (u32, u32)>,
    added: Vec<AddedToken>,
    byte_to_char: [char; 256],
    char_to_byte: HashMap<char, u8>,
    split_pattern: Regex,
    byte_level_pattern: Regex,
    whitespace: Regex,
    bos_id: u32,
    eos_id: u32,
    pad_id: u32,
    unk_id: Option<u32>,
    max_length: usize,
    source: TokenizerSource,
}

/// The positions of the SD 1.x/2.x text encoder; used until the encoder's config says otherwise.
pub const DEFAULT_MAX_LENGTH: usize = 77;

const END_OF_WORD: &str = "</w>";
const CLIP_SPLIT: &str =
    r"<\|startoftext\|>|<\|endoftext\|>|'s|'t|'re|'ve|'m|'ll|'d|[\p{L}]+|[\p{N}]|[^\s\p{L}\p{N}]+";
/// GPT-2's pattern as the ByteLevel pre-tokenizer applies it, without its whitespace alternatives (the
/// pieces it sees never contain whitespace, and the lookahead they use is not supported by `regex`).
const BYTE_LEVEL_SPLIT: &str = r"'s|'t|'re|'ve|'m|'ll|'d|\p{L}+|\p{N}+|[^\s\p{L}\p{N}]+";

/// Special token names of `tokenizer_config.json`; each is a string or `{"content": ...}`.
#[derive(Deserialize, Default)]
struct TokenizerConfig {
    bos_token: Option<serde_json::Value>,
    eos_token: Option<serde_json::Value>,
    pad_token: Option<serde_json::Value>,
    unk_token: Option<serde_json::Value>,
    #[serde(default)]
    added_tokens_decoder: HashMap<String, AddedTokenSpec>,
}

/// An added token as both files describe it (tokenizer.json gives its id beside it, the config as its key).
#[derive(Deserialize, Clone)]
struct AddedTokenSpec {
    content: String,
    #[serde(default)]
    normalized: bool,
    #[serde(default)]
    special: bool,
}

impl AddedTokenSpec {
    fn with_id(self, id: u32) -> AddedToken {
        AddedToken {
            content: self.content,
            id,
            normalized: self.normalized,
            special: self.special,
        }
    }
}

#[derive(Deserialize)]
struct TokenizerJsonAdded {
    id: u32,
    #[serde(flatten)]
    spec: AddedTokenSpec,
}

#[derive(Deserialize)]
struct TokenizerJson {
    #[serde(default)]
    added_tokens: Vec<TokenizerJsonAdded>,
    model: TokenizerJsonModel,
}

#[derive(Deserialize)]
struct TokenizerJsonModel {
    #[serde(rename = "type", default)]
    kind: Option<String>,
    vocab: HashMap<String, u32>,
    merges: Vec<MergeEntry>,
    #[serde(default)]
    end_of_word_suffix: Option<String>,
    #[serde(default)]
    unk_token: Option<String>,
}

/// `tokenizers` wrote merges as "a b" strings before 0.20 and as `["a", "b"]` pairs since.
#[derive(Deserialize)]
#[serde(untagged)]
enum MergeEntry {
    Joined(String),
    Pair([String; 2]),
}

fn token_name(value: &Option<serde_json::Value>) -> Option<String> {
    match value.as_ref()? {
        serde_json::Value::String(s) => Some(s.clone()),
        serde_json::Value::Object(map) => map.get("content")?.as_str().map(str::to_owned),
        _ => None,
    }
}

/// The GPT-2/CLIP table mapping each byte to a printable character (printable Latin-1 bytes map to
/// themselves, the others to U+0100 onwards), so BPE can work on text without control characters.
fn byte_table() -> [char; 256] {
    let keeps =
        |b: u32| (33..=126).contains(&b) || (161..=172).contains(&b) || (174..=255).contains(&b);
    let mut table = ['\0'; 256];
    let mut next = 256u32;
    for b in 0..256u32 {
        table[b as usize] = if keeps(b) {
            char::from_u32(b).unwrap_or('\0')
        } else {
            let c = char::from_u32(next).unwrap_or('\0');
            next += 1;
            c
        };
    }
    table
}

impl ClipTokenizer {
    /// Loads from a tokenizer folder: `tokenizer.json` if present, else `vocab.json` + `merges.txt`;
    /// special tokens from `tokenizer_config.json` when it exists (CLIP defaults otherwise). The maximum
    /// length starts at 77; set the text encoder's `max_position_embeddings` with [`Self::with_max_length`]
    /// (the config's `model_max_length` is ignored: some folders carry 1e30 there).
    pub fn from_dir(dir: impl AsRef<Path>) -> Result<Self, TokenizerError> {
        let dir = dir.as_ref();
        let config_path = dir.join("tokenizer_config.json");
        let config: TokenizerConfig = if config_path.is_file() {
            read_json(&config_path)?
        } else {
            TokenizerConfig::default()
        };
        let json = dir.join("tokenizer.json");
        if json.is_file() {
            return Self::from_tokenizer_json_with(&json, &config);
        }
        let (vocab, merges) = (dir.join("vocab.json"), dir.join("merges.txt"));
        if vocab.is_file() && merges.is_file() {
            return Self::from_vocab_merges_with(&vocab, &merges, &config);
        }
        Err(TokenizerError::NoVocabulary(dir.to_path_buf()))
    }

    /// Loads `vocab.json` + `merges.txt` with CLIP's default special tokens.
    pub fn from_vocab_merges(vocab: &Path, merges: &Path) -> Result<Self, TokenizerError> {
        Self::from_vocab_merges_with(vocab, merges, &TokenizerConfig::default())
    }

    /// Loads a `tokenizer.json` with CLIP's default special tokens (plus those it lists itself).
    pub fn from_tokenizer_json(path: &Path) -> Result<Self, TokenizerError> {
        Self::from_tokenizer_json_with(path, &TokenizerConfig::default())
    }

    fn from_vocab_merges_with(
        vocab_path: &Path,
        merges_path: &Path,
        config: &TokenizerConfig,
    ) -> Result<Self, TokenizerError> {
        let vocab: HashMap<String, u32> = read_json(vocab_path)?;
        if vocab.is_empty() {
            return Err(TokenizerError::Format {
                path: vocab_path.to_path_buf(),
                message: "the vocabulary is empty".into(),
            });
        }
        let text = fs::read_to_string(merges_path).map_err(|source| TokenizerError::Io {
            path: merges_path.to_path_buf(),
            source,
        })?;
        let mut merges = Vec::new();
        for (lineno, line) in text.lines().enumerate() {
            // The first line is a "#version" header; blank lines carry nothing.
            if line.starts_with("#version") || line.trim().is_empty() {
                continue;
            }
            let Some((a, b)) = line.split_once(' ') else {
                return Err(TokenizerError::Format {
                    path: merges_path.to_path_buf(),
                    message: format!("line {} is not a merge \"a b\": {line:?}", lineno + 1),
                });
            };
            merges.push((a.to_string(), b.to_string()));
        }
        Self::build(
            vocab,
            merges,
            Vec::new(),
            config,
            None,
            (vocab_path, merges_path),
            TokenizerSource::VocabAndMerges,
        )
    }

    fn from_tokenizer_json_with(
        path: &Path,
        config: &TokenizerConfig,
    ) -> Result<Self, TokenizerError> {
        let parsed: TokenizerJson = read_json(path)?;
        let format_err = |message: String| TokenizerError::Format {
            path: path.to_path_buf(),
            message,
        };
        if let Some(kind) = &parsed.model.kind {
            if kind != "BPE" {
                return Err(format_err(format!(
                    "model type {kind} is not BPE, not a CLIP tokenizer"
                )));
            }
        }
        if let Some(suffix) = &parsed.model.end_of_word_suffix {
            if suffix != END_OF_WORD {
                return Err(format_err(format!(
                    "end_of_word_suffix {suffix:?} is not CLIP's \"{END_OF_WORD}\""
                )));
            }
        }
        let mut merges = Vec::with_capacity(parsed.model.merges.len());
        for m in parsed.model.merges {
            match m {
                MergeEntry::Pair([a, b]) => merges.push((a, b)),
                MergeEntry::Joined(s) => match s.split_once(' ') {
                    Some((a, b)) => merges.push((a.to_string(), b.to_string())),
                    None => return Err(format_err(format!("merge {s:?} is not \"a b\""))),
                },
            }
        }
        let added = parsed
            .added_tokens
            .into_iter()
            .map(|t| t.spec.with_id(t.id))
            .collect();
        Self::build(
            parsed.model.vocab,
            merges,
            added,
            config,
            parsed.model.unk_token,
            (path, path),
            TokenizerSource::TokenizerJson,
        )
    }

    fn build(
        vocab: HashMap<String, u32>,
        merge_list: Vec<(String, String)>,
        mut added: Vec<AddedToken>,
        config: &TokenizerConfig,
        model_unk: Option<String>,
        (vocab_path, merges_path): (&Path, &Path),
        source: TokenizerSource,
    ) -> Result<Self, TokenizerError> {
        // Each problem is named in the file it comes from (one file for tokenizer.json).
        let vocab_err = |message: String| TokenizerError::Format {
            path: vocab_path.to_path_buf(),
            message,
        };
        let merges_err = |message: String| TokenizerError::Format {
            path: merges_path.to_path_buf(),
            message,
        };
        // A BPE vocabulary without merges would split every word into single bytes: the file is empty
        // or truncated, and the model would see text it was never trained on.
        if vocab.is_empty() {
            return Err(vocab_err("the vocabulary is empty".into()));
        }
        if merge_list.is_empty() {
            return Err(merges_err(
                "there are no BPE merges (empty or truncated merges list)".into(),
            ));
        }
        let mut vocab = vocab;
        let mut next_id = vocab.values().copied().max().map_or(0, |m| m + 1);
        for a in &added {
            next_id = next_id.max(a.id + 1);
        }
        // Added tokens listed by the config (transformers' added_tokens_decoder), then the named specials.
        let mut decoder_specs: Vec<(u32, &AddedTokenSpec)> = config
            .added_tokens_decoder
            .iter()
            .filter_map(|(id, spec)| id.parse().ok().map(|id| (id, spec)))
            .collect();
        decoder_specs.sort_by_key(|(id, _)| *id);
        for (id, spec) in decoder_specs {
            if !added.iter().any(|a| a.content == spec.content) {
                added.push(spec.clone().with_id(id));
                next_id = next_id.max(id + 1);
            }
        }
        let bos = token_name(&config.bos_token).unwrap_or_else(|| "<|startoftext|>".into());
        let eos = token_name(&config.eos_token).unwrap_or_else(|| "<|endoftext|>".into());
        let unk = token_name(&config.unk_token)
            .or(model_unk)
            .unwrap_or_else(|| "<|endoftext|>".into());
        let pad = token_name(&config.pad_token).unwrap_or_else(|| "<|endoftext|>".into());
        for name in [&bos, &eos, &unk, &pad] {
            if added.iter().any(|a| &a.content == name) {
                continue;
            }
            // A special token missing from the vocabulary gets the next free id, as transformers does.
            let id = match vocab.get(name.as_str()) {
                Some(&id) => id,
                None => {
                    let id = next_id;
                    next_id += 1;
                    id
                }
            };
            added.push(AddedToken {
                content: name.clone(),
                id,
                normalized: false,
                special: true,
            });
        }
        for a in &added {
            vocab.entry(a.content.clone()).or_insert(a.id);
        }
        let size = vocab.values().copied().max().map_or(0, |m| m as usize + 1);
        // Ids index a table; a vocabulary with huge gaps is malformed (and would exhaust memory).
        if size > 2 * vocab.len() + 1024 {
            return Err(vocab_err(format!(
                "token ids go up to {} for {} tokens; the vocabulary is malformed",
                size - 1,
                vocab.len()
            )));
        }
        let mut tokens = vec![String::new(); size];
        for (tok, &id) in &vocab {
            tokens[id as usize] = tok.clone();
        }
        for a in &added {
            tokens[a.id as usize] = a.content.clone();
        }
        let mut merges = HashMap::with_capacity(merge_list.len());
        for (rank, (a, b)) in merge_list.iter().enumerate() {
            let lookup = |s: &str| {
                vocab.get(s).copied().ok_or_else(|| {
                    merges_err(format!(
                        "merge \"{a} {b}\" uses {s:?}, which is not in the vocabulary"
                    ))
                })
            };
            let left = lookup(a)?;
            let right = lookup(b)?;
            let merged = lookup(&format!("{a}{b}"))?;
            // Like `tokenizers`, a repeated merge keeps its first (highest-priority) rank.
            merges.entry((left, right)).or_insert((rank as u32, merged));
        }
        let id_of = |name: &str| {
            added
                .iter()
                .find(|a| a.content == name)
                .map(|a| a.id)
                .ok_or_else(|| vocab_err(format!("special token {name:?} has no id")))
        };
        let bos_id = id_of(&bos)?;
        let eos_id = id_of(&eos)?;
        let pad_id = id_of(&pad)?;
        let unk_id = id_of(&unk).ok();
        // Longest first so that, at one position, the longest special token wins (leftmost-longest).
        added.sort_by(|x, y| y.content.len().cmp(&x.content.len()).then(x.id.cmp(&y.id)));
        let byte_to_char = byte_table();
        let char_to_byte = byte_to_char
            .iter()
            .enumerate()
            .map(|(b, &c)| (c, b as u8))
            .collect();
        Ok(ClipTokenizer {
            vocab,
            tokens,
            merges,
            added,
            byte_to_char,
            char_to_byte,
            split_pattern: Regex::new(CLIP_SPLIT).expect("CLIP split pattern is valid"),
            byte_level_pattern: Regex::new(BYTE_LEVEL_SPLIT).expect("byte-level pattern is valid"),
            whitespace: Regex::new(r"\s+").expect("whitespace pattern is valid"),
            bos_id,
            eos_id,
            pad_id,
            unk_id,
            max_length: DEFAULT_MAX_LENGTH,
            source,
        })
    }

    /// Sets the padded length, i.e. the text encoder's `max_position_embeddings` (at least 2).
    pub fn with_max_length(mut self, max_length: usize) -> Self {
        self.max_length = max_length.max(2);
        self
    }

    pub fn max_length(&self) -> usize {
        self.max_length
    }

    /// Number of ids, including added tokens.
    pub fn vocab_size(&self) -> usize {
        self.tokens.len()
    }

    pub fn source(&self) -> TokenizerSource {
        self.source
    }

    pub fn bos_id(&self) -> u32 {
        self.bos_id
    }

    pub fn eos_id(&self) -> u32 {
        self.eos_id
    }

    pub fn pad_id(&self) -> u32 {
        self.pad_id
    }

    /// The id of a token string (e.g. `"cat</w>"`), if it is in the vocabulary.
    pub fn token_to_id(&self, token: &str) -> Option<u32> {
        self.vocab.get(token).copied()
    }

    /// The token string of an id (with its `</w>` suffix), if the id exists.
    pub fn id_to_token(&self, id: u32) -> Option<&str> {
        self.tokens.get(id as usize).map(String::as_str)
    }

    /// The prompt's token ids without start/end tokens, untruncated.
    pub fn tokenize(&self, text: &str) -> Vec<u32> {
        let mut ids = Vec::new();
        for (piece, special) in self.split_added(text, false) {
            if let Some(id) = special {
                ids.push(id);
                continue;
            }
            let normalized = self.normalize(piece);
            for (piece, special) in self.split_added(&normalized, true) {
                match special {
                    Some(id) => ids.push(id),
                    None => self.tokenize_normalized(piece, &mut ids),
                }
            }
        }
        ids
    }

    /// Start token, prompt tokens, end token: no truncation, no padding (what `tokenizer.encode(text)`
    /// returns, used by InfEdit's token alignment).
    pub fn encode_unpadded(&self, text: &str) -> Vec<u32> {
        let mut ids = Vec::with_capacity(self.max_length);
        ids.push(self.bos_id);
        ids.extend(self.tokenize(text));
        ids.push(self.eos_id);
        ids
    }

    /// The text encoder input: truncated to `max_length` keeping the end token, then padded. A truncated
    /// prompt is not an error here; `dropped_tokens` tells the caller to warn.
    pub fn encode(&self, text: &str) -> Encoding {
        let mut ids = self.tokenize(text);
        let room = self.max_length - 2;
        let dropped_tokens = ids.len().saturating_sub(room);
        ids.truncate(room);
        let mut out = Vec::with_capacity(self.max_length);
        out.push(self.bos_id);
        out.extend_from_slice(&ids);
        out.push(self.eos_id);
        let num_tokens = out.len();
        out.resize(self.max_length, self.pad_id);
        Encoding {
            ids: out,
            num_tokens,
            dropped_tokens,
        }
    }

    /// Like [`Self::encode`] but a prompt that does not fit is an error naming the words cut off.
    pub fn encode_strict(&self, text: &str) -> Result<Encoding, TokenizerError> {
        let ids = self.tokenize(text);
        let room = self.max_length - 2;
        if ids.len() > room {
            return Err(TokenizerError::PromptTooLong {
                tokens: ids.len() + 2,
                max: self.max_length,
                dropped: ids.len() - room,
                dropped_text: self.decode(&ids[room..], true),
            });
        }
        Ok(self.encode(text))
    }

    /// A one-line warning naming the words cut off when `text` does not fit, for callers that print
    /// warnings (the default, non-strict path); `None` when it fits.
    pub fn truncation_warning(&self, text: &str) -> Option<String> {
        match self.encode_strict(text) {
            Ok(_) => None,
            Err(TokenizerError::PromptTooLong {
                tokens,
                max,
                dropped,
                dropped_text,
            }) => Some(format!(
                "prompt has {tokens} tokens but the text encoder takes {max}; the last {dropped} \
                 are ignored: \"{dropped_text}\""
            )),
            Err(other) => Some(other.to_string()),
        }
    }

    /// Each id as its own text, as `tokenizer.decode([id])` gives it (no `</w>`, specials verbatim; a
    /// byte token that is part of a longer UTF-8 character shows as U+FFFD).
    pub fn token_strings(&self, ids: &[u32]) -> Vec<String> {
        ids.iter().map(|&id| self.decode(&[id], false)).collect()
    }

    /// Whether the id is one of the added/special tokens (start, end, pad, ...).
    pub fn is_special(&self, id: u32) -> bool {
        self.added.iter().any(|a| a.id == id && a.special)
    }

    /// Ids back to text like `transformers` decodes: bytes restored, `</w>` becomes a space, ends trimmed.
    pub fn decode(&self, ids: &[u32], skip_special_tokens: bool) -> String {
        let mut bytes = Vec::new();
        for &id in ids {
            if skip_special_tokens && self.is_special(id) {
                continue;
            }
            let Some(token) = self.tokens.get(id as usize) else {
                continue;
            };
            if self.added.iter().any(|a| a.id == id) {
                bytes.extend_from_slice(token.as_bytes());
                continue;
            }
            for c in token.chars() {
                match self.char_to_byte.get(&c) {
                    Some(&b) => bytes.push(b),
                    // Characters outside the byte table (only "</w>" parts are ASCII and in it) pass through.
                    None => {
                        let mut buf = [0u8; 4];
                        bytes.extend_from_slice(c.encode_utf8(&mut buf).as_bytes());
                    }
                }
            }
        }
        String::from_utf8_lossy(&bytes)
            .replace(END_OF_WORD, " ")
            .trim()
            .to_string()
    }

    /// NFC, whitespace runs to one space, then lowercase per character (as `tokenizers`' Lowercase does).
    fn normalize(&self, text: &str) -> String {
        let nfc: String = text.nfc().collect();
        let spaced = self.whitespace.replace_all(&nfc, " ");
        spaced.chars().flat_map(char::to_lowercase).collect()
    }

    /// Splits text at added tokens (those matched before or after normalisation, per `normalized`).
    /// Leftmost match wins; at equal start the longest.
    fn split_added<'t>(&self, text: &'t str, normalized: bool) -> Vec<(&'t str, Option<u32>)> {
        let mut out = Vec::new();
        let mut rest_start = 0;
        let mut pos = 0;
        let candidates: Vec<&AddedToken> = self
            .added
            .iter()
            .filter(|a| a.normalized == normalized && !a.content.is_empty())
            .collect();
        if candidates.is_empty() {
            out.push((text, None));
            return out;
        }
        while pos < text.len() {
            let here = &text[pos..];
            if let Some(tok) = candidates
                .iter()
                .find(|a| here.starts_with(a.content.as_str()))
            {
                if rest_start < pos {
                    out.push((&text[rest_start..pos], None));
                }
                out.push((&text[pos..pos + tok.content.len()], Some(tok.id)));
                pos += tok.content.len();
                rest_start = pos;
            } else {
                pos += here.chars().next().map_or(1, char::len_utf8);
            }
        }
        if rest_start < text.len() {
            out.push((&text[rest_start..], None));
        }
        out
    }

    fn tokenize_normalized(&self, text: &str, ids: &mut Vec<u32>) {
        let mut symbols = Vec::new();
        for piece in self.split_pattern.find_iter(text) {
            for word in self.byte_level_pattern.find_iter(piece.as_str()) {
                self.bpe_word(word.as_str(), &mut symbols);
                ids.extend_from_slice(&symbols);
            }
        }
    }

    /// BPE on one pre-token: start from its byte characters (last one with `</w>`), then repeatedly apply
    /// the lowest-ranked merge, leftmost first, until none applies.
    fn bpe_word(&self, word: &str, symbols: &mut Vec<u32>) {
        symbols.clear();
        let bytes = word.as_bytes();
        let mut buf = String::new();
        for (i, &b) in bytes.iter().enumerate() {
            buf.clear();
            buf.push(self.byte_to_char[b as usize]);
            if i + 1 == bytes.len() {
                buf.push_str(END_OF_WORD);
            }
            match self.vocab.get(buf.as_str()) {
                Some(&id) => symbols.push(id),
                // Not in a well-formed CLIP vocabulary; tokenizers emits the unknown token per symbol.
                None => symbols.extend(self.unk_id),
            }
        }
        self.merge_symbols(symbols);
    }

    /// Applies merges lowest rank first, leftmost first among equal ranks (`tokenizers`' order), with a
    /// priority queue over a linked list so long words stay O(n log n).
    fn merge_symbols(&self, symbols: &mut Vec<u32>) {
        use std::cmp::Reverse;
        use std::collections::BinaryHeap;
        let n = symbols.len();
        if n < 2 {
            return;
        }
        // Neighbour links over the original positions; usize::MAX marks "none", `alive` merged-away ones.
        let mut next: Vec<usize> = (1..=n)
            .map(|i| if i == n { usize::MAX } else { i })
            .collect();
        let mut prev: Vec<usize> = (0..n)
            .map(|i| i.checked_sub(1).unwrap_or(usize::MAX))
            .collect();
        let mut alive = vec![true; n];
        let mut heap = BinaryHeap::new();
        for pos in 0..n - 1 {
            if let Some(&(rank, _)) = self.merges.get(&(symbols[pos], symbols[pos + 1])) {
                heap.push(Reverse((rank, pos)));
            }
        }
        while let Some(Reverse((rank, pos))) = heap.pop() {
            let right = next[pos];
            if !alive[pos] || right == usize::MAX {
                continue;
            }
            // The pair may have changed since this entry was queued.
            let Some(&(current_rank, merged)) = self.merges.get(&(symbols[pos], symbols[right]))
            else {
                continue;
            };
            if current_rank != rank {
                continue;
            }
            symbols[pos] = merged;
            alive[right] = false;
            next[pos] = next[right];
            if next[pos] != usize::MAX {
                prev[next[pos]] = pos;
            }
            if prev[pos] != usize::MAX {
                let left = prev[pos];
                if let Some(&(r, _)) = self.merges.get(&(symbols[left], symbols[pos])) {
                    heap.push(Reverse((r, left)));
                }
            }
            if next[pos] != usize::MAX {
                if let Some(&(r, _)) = self.merges.get(&(symbols[pos], symbols[next[pos]])) {
                    heap.push(Reverse((r, pos)));
                }
            }
        }
        let mut out = 0;
        for i in 0..n {
            if alive[i] {
                symbols[out] = symbols[i];
                out += 1;
            }
        }
        symbols.truncate(out);
    }
}

fn read_json<T: serde::de::DeserializeOwned>(path: &Path) -> Result<T, TokenizerError> {
    let text = fs::read_to_string(path).map_err(|source| TokenizerError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    serde_json::from_str(&text).map_err(|e| TokenizerError::Format {
        path: path.to_path_buf(),
        message: format!("invalid JSON: {e}"),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A tiny vocabulary: the byte characters with and without `</w>`, a few merges, the two specials.
    fn tiny() -> ClipTokenizer {
        let table = byte_table();
        let mut vocab: Vec<String> = table.iter().map(|c| c.to_string()).collect();
        vocab.extend(table.iter().map(|c| format!("{c}</w>")));
        let merges = vec![
            ("c".to_string(), "a".to_string()),
            ("ca".to_string(), "t</w>".to_string()),
            ("a".to_string(), "a".to_string()),
        ];
        for (a, b) in &merges {
            vocab.push(format!("{a}{b}"));
        }
        vocab.push("<|startoftext|>".into());
        vocab.push("<|endoftext|>".into());
        let vocab = vocab
            .into_iter()
            .enumerate()
            .map(|(i, t)| (t, i as u32))
            .collect();
        ClipTokenizer::build(
            vocab,
            merges,
            Vec::new(),
            &TokenizerConfig::default(),
            None,
            (Path::new("test"), Path::new("test")),
            TokenizerSource::VocabAndMerges,
        )
        .unwrap()
        .with_max_length(8)
    }

    #[test]
    fn byte_table_is_a_bijection() {
        let table = byte_table();
        let unique: std::collections::HashSet<char> = table.iter().copied().collect();
        assert_eq!(unique.len(), 256);
        assert_eq!(table[b'a' as usize], 'a');
        assert_eq!(table[b' ' as usize], '\u{120}'); // 'Ġ' as in GPT-2
    }

    #[test]
    fn merges_apply_by_rank_and_words_end_with_suffix() {
        let t = tiny();
        let cat = t.token_to_id("cat</w>").unwrap();
        assert_eq!(t.tokenize("CAT"), vec![cat]);
        // "aaaa": the (a, a) merge applies left to right, giving two "aa" symbols.
        let aa = t.token_to_id("aa").unwrap();
        let a_end = t.token_to_id("a</w>").unwrap();
        assert_eq!(t.tokenize("aaa"), vec![aa, a_end]);
        assert_eq!(t.decode(&t.encode_unpadded("Cat  aaa"), true), "cat aaa");
    }

    #[test]
    fn truncation_keeps_end_token_and_reports_dropped() {
        let t = tiny();
        let enc = t.encode("cat cat cat cat cat cat cat cat");
        assert_eq!(enc.ids.len(), 8);
        assert_eq!(enc.ids[7], t.eos_id());
        assert_eq!(enc.num_tokens, 8);
        assert_eq!(enc.dropped_tokens, 2);
        let err = t
            .encode_strict("cat cat cat cat cat cat cat cat")
            .unwrap_err();
        assert!(err.to_string().contains("2 would be cut off"), "{err}");
        let warning = t
            .truncation_warning("cat cat cat cat cat cat cat aaa")
            .unwrap();
        assert!(
            warning.contains("the last 3 are ignored: \"cat aaa\""),
            "{warning}"
        );
        assert!(t.truncation_warning("cat").is_none());
        let short = t.encode("cat");
        assert_eq!(short.num_tokens, 3);
        assert!(!short.truncated());
        assert!(short.ids[3..].iter().all(|&i| i == t.pad_id()));
    }

    #[test]
    fn long_words_merge_like_the_quadratic_definition() {
        let t = tiny();
        // Reference: repeatedly merge the leftmost lowest-ranked pair.
        let naive = |mut s: Vec<u32>| loop {
            let best = s
                .windows(2)
                .enumerate()
                .filter_map(|(p, w)| t.merges.get(&(w[0], w[1])).map(|&(r, m)| (r, p, m)))
                .min();
            let Some((_, p, m)) = best else { break s };
            s[p] = m;
            s.remove(p + 1);
        };
        for word in ["a", "aa", "aaaaaaa", "cacacatcat", "caaat", "acatcaaaat"] {
            let mut fast = Vec::new();
            t.bpe_word(word, &mut fast);
            let start: Vec<u32> = word
                .bytes()
                .enumerate()
                .map(|(i, b)| {
                    let mut s = t.byte_to_char[b as usize].to_string();
                    if i + 1 == word.len() {
                        s.push_str(END_OF_WORD);
                    }
                    t.token_to_id(&s).unwrap()
                })
                .collect();
            assert_eq!(fast, naive(start), "{word}");
        }
        // A 200k-letter word finishes quickly (the naive loop would take minutes).
        let long = "a".repeat(200_000);
        let started = std::time::Instant::now();
        // 99 999 "aa" pairs, then "a" and "a</w>" (no merge joins those two).
        assert_eq!(t.tokenize(&long).len(), 100_001);
        assert!(started.elapsed().as_secs_f64() < 5.0);
    }

    #[test]
    fn special_tokens_in_text_are_kept_whole() {
        let t = tiny();
        let ids = t.tokenize("cat<|endoftext|>cat");
        let cat = t.token_to_id("cat</w>").unwrap();
        assert_eq!(ids, vec![cat, t.eos_id(), cat]);
    }

    /// A problem of vocab.json is named in vocab.json, one of merges.txt in merges.txt (issue 69: a bad
    /// vocabulary was reported as merges.txt).
    #[test]
    fn errors_name_the_file_at_fault() {
        let dir = tempfile::tempdir().unwrap();
        let (vocab, merges) = (dir.path().join("vocab.json"), dir.path().join("merges.txt"));
        std::fs::write(&merges, "#version: 0.2\na b\n").unwrap();
        // Ids with a gap far beyond the tokens' count.
        std::fs::write(&vocab, r#"{"a": 0, "b": 1, "ab": 999999}"#).unwrap();
        let e = ClipTokenizer::from_vocab_merges(&vocab, &merges)
            .unwrap_err()
            .to_string();
        assert!(e.contains("vocab.json") && !e.contains("merges.txt"), "{e}");
        // A merge whose pieces the vocabulary lacks is the merges' problem.
        std::fs::write(&vocab, r#"{"a": 0, "b": 1}"#).unwrap();
        let e = ClipTokenizer::from_vocab_merges(&vocab, &merges)
            .unwrap_err()
            .to_string();
        assert!(e.contains("merges.txt"), "{e}");
    }
}
