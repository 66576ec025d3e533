//! Token alignment between the source and target prompts (InfEdit's `seq_aligner.get_mapper`).
//!
//! The target's cross-attention maps are refined from the source's: target token j takes the map of source
//! token `mapper[j]` with weight `alphas[j]` (1 = matched, 0 = a new word that keeps its own map). Matching is
//! a Needleman-Wunsch global alignment of the CLIP token ids (gap 0, match 1, mismatch -1); then, inside every
//! run of unmatched target tokens, the single (target, source) pair with the highest cosine similarity of
//! text-encoder hidden states is matched too. Blend words become per-token indicators (`alpha_e` for the
//! "local"/target-blend words, `alpha_m` for the "mutual"/source-blend words).
//!
//! The behaviour follows the reference implementation exactly, including two quirks kept on purpose so that
//! edits reproduce the reference's (both are noted where they happen):
//! - the cosine similarity compares the *source* hidden state at the target index with the *target* hidden
//!   state at the source index;
//! - after a blend word is found, the target cursor does not advance, so a repeated blend token maps to the
//!   same position.

/// Result of aligning a target prompt to a source prompt, padded to the text encoder's length.
#[derive(Clone, Debug, PartialEq)]
pub struct TokenAlignment {
    /// For every target position (0..max_len), the source position whose attention it takes.
    /// `None` = no source token (the target keeps its own map; only where `alphas` is 0).
    pub mapper: Vec<Option<usize>>,
    /// 1 where the target token takes the mapped source map, 0 where it keeps its own.
    pub alphas: Vec<f32>,
    /// Target-blend ("local") word indicator per target position.
    pub alpha_e: Vec<f32>,
    /// Source-blend ("mutual") word indicator per target position.
    pub alpha_m: Vec<f32>,
    /// Number of real target tokens including SOT and EOT.
    pub target_len: usize,
}

impl TokenAlignment {
    /// `alpha_e AND alpha_m`.
    pub fn alpha_me(&self) -> Vec<f32> {
        self.alpha_e
            .iter()
            .zip(&self.alpha_m)
            .map(|(&e, &m)| if e > 0.0 && m > 0.0 { 1.0 } else { 0.0 })
            .collect()
    }
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum AlignError {
    #[error("the source-blend (mutual) words must appear in both prompts; token {token} is not in the target prompt")]
    MutualNotInTarget { token: u32 },
    #[error("the source-blend (mutual) words must appear in both prompts; token {token} of the target is not aligned to the same token of the source")]
    MutualNotInSource { token: u32 },
    #[error("prompt has {len} tokens, more than the text encoder's {max_len} positions")]
    TooLong { len: usize, max_len: usize },
}

/// Needleman-Wunsch with gap 0, match 1, mismatch -1. Returns, for each target token, the aligned source
/// index (or `None` for a gap), following the reference's tie-breaking (left, then up, then diagonal).
pub fn global_align(source: &[u32], target: &[u32]) -> Vec<Option<usize>> {
    const GAP: i32 = 0;
    let (n, m) = (source.len(), target.len());
    let mut score = vec![vec![0i32; m + 1]; n + 1];
    // Traceback codes as in the reference: 1 = left (target gap), 2 = up (source skipped), 3 = diagonal,
    // 4 = origin.
    let mut trace = vec![vec![0u8; m + 1]; n + 1];
    for j in 1..=m {
        score[0][j] = j as i32 * GAP;
        trace[0][j] = 1;
    }
    for i in 1..=n {
        score[i][0] = i as i32 * GAP;
        trace[i][0] = 2;
    }
    trace[0][0] = 4;
    for i in 1..=n {
        for j in 1..=m {
            let left = score[i][j - 1] + GAP;
            let up = score[i - 1][j] + GAP;
            let diag = score[i - 1][j - 1]
                + if source[i - 1] == target[j - 1] {
                    1
                } else {
                    -1
                };
            let best = left.max(up).max(diag);
            score[i][j] = best;
            trace[i][j] = if best == left {
                1
            } else if best == up {
                2
            } else {
                3
            };
        }
    }
    let mut mapper = Vec::with_capacity(m);
    let (mut i, mut j) = (n, m);
    while i > 0 || j > 0 {
        match trace[i][j] {
            3 => {
                i -= 1;
                j -= 1;
                mapper.push(Some(i));
            }
            1 => {
                j -= 1;
                mapper.push(None);
            }
            2 => i -= 1,
            _ => break,
        }
    }
    mapper.reverse();
    mapper
}

fn cosine(a: &[f32], b: &[f32]) -> f32 {
    let dot: f32 = a.iter().zip(b).map(|(x, y)| x * y).sum();
    let na: f32 = a.iter().map(|x| x * x).sum::<f32>().sqrt();
    let nb: f32 = b.iter().map(|x| x * x).sum::<f32>().sqrt();
    // torch's cosine_similarity clamps each norm at eps = 1e-8.
    dot / (na.max(1e-8) * nb.max(1e-8))
}

/// Inputs of [`align_prompts`]: token ids include SOT and EOT and are unpadded; hidden states are the text
/// encoder's last hidden states of the *padded* prompts (one row per position, at least `max_len` rows).
pub struct AlignInputs<'a> {
    pub source_ids: &'a [u32],
    pub target_ids: &'a [u32],
    /// Token ids of the target-blend ("local") words, with SOT/EOT (empty string = just SOT, EOT).
    pub local_ids: &'a [u32],
    /// Token ids of the source-blend ("mutual") words, with SOT/EOT.
    pub mutual_ids: &'a [u32],
    pub source_hidden: &'a [Vec<f32>],
    pub target_hidden: &'a [Vec<f32>],
    pub max_len: usize,
}

/// Aligns the target prompt to the source prompt (see the module docs).
pub fn align_prompts(inp: &AlignInputs<'_>) -> Result<TokenAlignment, AlignError> {
    let (x_seq, y_seq) = (inp.source_ids, inp.target_ids);
    let max_len = inp.max_len;
    for len in [x_seq.len(), y_seq.len()] {
        if len > max_len {
            return Err(AlignError::TooLong { len, max_len });
        }
    }
    let ly = y_seq.len();
    let base = global_align(x_seq, y_seq);
    debug_assert_eq!(base.len(), ly);

    let mut alphas = vec![1.0f32; max_len];
    // Positions past the prompt map onto themselves (padding to padding), as the reference's
    // `len(y_seq) + arange(...)` does.
    let mut mapper: Vec<Option<usize>> = (0..max_len).map(Some).collect();
    for (j, m) in base.iter().enumerate() {
        alphas[j] = if m.is_some() { 1.0 } else { 0.0 };
        mapper[j] = *m;
    }
    let mut alpha_e = vec![0.0f32; max_len];
    let mut alpha_m = vec![0.0f32; max_len];

    // Inside each run of unmatched target tokens, match the single most similar pair.
    let mut i = 0;
    while i < ly {
        if alphas[i] == 0.0 {
            let start = i;
            while i < max_len && alphas[i] == 0.0 {
                i += 1;
            }
            // SOT always aligns with SOT, so start >= 1 and mapper[start - 1] is a real index.
            let lo = mapper[start - 1].map_or(0, |s| s + 1);
            let hi = if i < max_len {
                mapper[i].unwrap_or(lo)
            } else {
                lo
            };
            let mut best: Option<(f32, usize, usize)> = None;
            for t in start..i {
                for s in lo..hi {
                    // Reference quirk kept: source hidden at the target index vs target hidden at the
                    // source index.
                    let sim = cosine(&inp.source_hidden[t], &inp.target_hidden[s]);
                    if best.is_none_or(|(b, _, _)| sim > b) {
                        best = Some((sim, s, t));
                    }
                }
            }
            if let Some((_, s, t)) = best {
                mapper[t] = Some(s);
                alphas[t] = 1.0;
                if s < x_seq.len() && inp.local_ids.contains(&x_seq[s]) {
                    alpha_e[t] = 1.0;
                }
            }
        }
        i += 1;
    }

    // Target-blend words: walk both sequences (inner tokens only).
    let e_seq = inp.local_ids;
    let (mut i, mut j) = (1usize, 1usize);
    while i + 1 < ly && j + 1 < e_seq.len() {
        let mut found = true;
        while e_seq[j] != y_seq[i] {
            i += 1;
            if i + 1 >= ly {
                found = false;
                break;
            }
        }
        if found {
            alpha_e[i] = 1.0;
        }
        j += 1;
    }

    // Source-blend words must be in the target and aligned to the same token of the source.
    let m_seq = inp.mutual_ids;
    let (mut i, mut j) = (1usize, 1usize);
    while i + 1 < ly && j + 1 < m_seq.len() {
        while m_seq[j] != y_seq[i] {
            i += 1;
            if i + 1 >= ly {
                return Err(AlignError::MutualNotInTarget { token: m_seq[j] });
            }
        }
        match mapper[i] {
            Some(s) if s < x_seq.len() && x_seq[s] == m_seq[j] => {
                alpha_m[i] = 1.0;
                j += 1;
            }
            _ => return Err(AlignError::MutualNotInSource { token: m_seq[j] }),
        }
    }

    Ok(TokenAlignment {
        mapper,
        alphas,
        alpha_e,
        alpha_m,
        target_len: ly,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const SOT: u32 = 1000;
    const EOT: u32 = 1001;

    fn ids(words: &[u32]) -> Vec<u32> {
        let mut v = vec![SOT];
        v.extend_from_slice(words);
        v.push(EOT);
        v
    }

    /// Hidden states where position p of each prompt is a one-hot-ish vector chosen by the test.
    fn hidden(rows: &[[f32; 3]], max_len: usize) -> Vec<Vec<f32>> {
        (0..max_len)
            .map(|p| rows.get(p).map_or(vec![0.0, 0.0, 1.0], |r| r.to_vec()))
            .collect()
    }

    #[test]
    fn identical_prompts_map_to_themselves() {
        let p = ids(&[1, 2, 3]);
        let h = hidden(&[], 8);
        let a = align_prompts(&AlignInputs {
            source_ids: &p,
            target_ids: &p,
            local_ids: &ids(&[]),
            mutual_ids: &ids(&[]),
            source_hidden: &h,
            target_hidden: &h,
            max_len: 8,
        })
        .unwrap();
        assert_eq!(a.mapper, (0..8).map(Some).collect::<Vec<_>>());
        assert!(a.alphas.iter().all(|&x| x == 1.0));
        assert_eq!(a.target_len, 5);
    }

    #[test]
    fn replaced_word_is_matched_by_similarity() {
        // "a man" -> "a clown": the alignment leaves "clown" unmatched; the similarity pass matches it to
        // "man" (the only source token in the gap).
        let src = ids(&[1, 2]);
        let tgt = ids(&[1, 3]);
        let h = hidden(&[], 8);
        let a = align_prompts(&AlignInputs {
            source_ids: &src,
            target_ids: &tgt,
            local_ids: &ids(&[1, 3]),
            mutual_ids: &ids(&[]),
            source_hidden: &h,
            target_hidden: &h,
            max_len: 8,
        })
        .unwrap();
        assert_eq!(&a.mapper[..4], &[Some(0), Some(1), Some(2), Some(3)]);
        assert_eq!(&a.alphas[..4], &[1.0; 4]);
        // Blend words = the whole target prompt: both inner tokens flagged.
        assert_eq!(&a.alpha_e[..4], &[0.0, 1.0, 1.0, 0.0]);
    }

    #[test]
    fn inserted_words_keep_their_own_maps_except_the_most_similar() {
        // source: a cat ; target: a dog wearing hat -> "dog wearing hat" is a run of 3 unmatched tokens
        // facing one unmatched source token ("cat"). Only the most similar target token takes "cat".
        let src = ids(&[1, 2]);
        let tgt = ids(&[1, 3, 4, 5]);
        let max_len = 10;
        // Source hidden rows are indexed by *target* positions (reference quirk): make target position 2
        // ("wearing") the most similar to the target hidden at source position 2.
        let mut src_rows = vec![[0.0, 0.0, 1.0]; max_len];
        src_rows[2] = [1.0, 0.0, 0.0];
        src_rows[3] = [0.5, 0.5, 0.0];
        let mut tgt_rows = vec![[0.0, 0.0, 1.0]; max_len];
        tgt_rows[2] = [1.0, 0.1, 0.0];
        let a = align_prompts(&AlignInputs {
            source_ids: &src,
            target_ids: &tgt,
            local_ids: &ids(&[]),
            mutual_ids: &ids(&[]),
            source_hidden: &hidden(&src_rows, max_len),
            target_hidden: &hidden(&tgt_rows, max_len),
            max_len,
        })
        .unwrap();
        let g = global_align(&src, &tgt);
        // With a zero gap cost "cat" is skipped and the three new target tokens are gaps.
        assert_eq!(g.iter().filter(|m| m.is_none()).count(), 3, "{g:?}");
        assert_eq!(
            a.alphas[..6].iter().sum::<f32>(),
            4.0,
            "{:?}",
            &a.alphas[..6]
        );
        assert_eq!((a.alphas[3], a.alphas[4]), (0.0, 0.0));
        assert_eq!(a.mapper[2], Some(2));
        assert_eq!(a.mapper[5], Some(3), "EOT stays aligned");
    }

    #[test]
    fn mutual_words_must_exist_in_both() {
        let src = ids(&[1, 2]);
        let tgt = ids(&[1, 3]);
        let h = hidden(&[], 8);
        let base = AlignInputs {
            source_ids: &src,
            target_ids: &tgt,
            local_ids: &[SOT, EOT],
            mutual_ids: &[SOT, 1, EOT],
            source_hidden: &h,
            target_hidden: &h,
            max_len: 8,
        };
        let a = align_prompts(&base).unwrap();
        assert_eq!(&a.alpha_m[..4], &[0.0, 1.0, 0.0, 0.0]);
        let bad = [SOT, 7, EOT];
        let e = align_prompts(&AlignInputs {
            mutual_ids: &bad,
            ..base
        })
        .unwrap_err();
        assert_eq!(e, AlignError::MutualNotInTarget { token: 7 });
    }

    #[test]
    fn too_long_is_an_error() {
        let long: Vec<u32> = (0..10).collect();
        let h = hidden(&[], 8);
        let e = align_prompts(&AlignInputs {
            source_ids: &long,
            target_ids: &long,
            local_ids: &[],
            mutual_ids: &[],
            source_hidden: &h,
            target_hidden: &h,
            max_len: 8,
        })
        .unwrap_err();
        assert!(matches!(e, AlignError::TooLong { .. }));
    }
}
