//! Which UNet samples a view's pass computes: the one place that decides it (docs/algorithm.md §2.4).
//!
//! InfEdit runs three latent branches, source S, target T and layout M, each with classifier-free
//! guidance: up to six samples per view, `[S_u, T_u, M_u, S_c, T_c, M_c]`. Not all of them are read:
//! - a pass's output is read through the guidance: ε_T always needs T_c and T_u (the target guidance is
//!   above 1 whenever there is an unconditional half); ε_S and ε_M need S_u and M_u only when the source
//!   guidance is not 1 (at 1, ε = ε_c);
//! - CCM's recording pass reads only the conditional cross-attention maps, not its output;
//! - inside the UNet a sample reads other samples only through the self-attention swap, within its own
//!   half: [`self_attention_sources`] says whose queries, keys and values each branch takes.
//!
//! A pass computes the samples read plus, transitively, those whose queries, keys or values they take.
//! Every computed sample sees exactly the queries, keys and values it saw in the batch of six, so its
//! output and its maps are the same to float rounding; the samples left out are the ones nobody reads.

/// A latent branch of InfEdit.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Branch {
    Source,
    Target,
    Layout,
}

impl Branch {
    pub const ALL: [Branch; 3] = [Branch::Source, Branch::Target, Branch::Layout];

    fn index(self) -> usize {
        self as usize
    }
}

/// One UNet sample of a view: a branch in the unconditional or the conditional half.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Sample {
    pub conditional: bool,
    pub branch: Branch,
}

/// Whose (query, key, value) each branch's self-attention takes, within its half, in [`Branch::ALL`]
/// order: before `self_replace` every branch queries with the source's queries into the source's keys
/// (the target keeps its own values); from it on, "mutual self-attention": the layout branch queries with
/// the target's queries into the source's keys and values, and S and T attend to themselves.
pub fn self_attention_sources(mutual: bool) -> [[Branch; 3]; 3] {
    // Nobody takes the layout branch's queries, keys or values.
    use Branch::{Source as S, Target as T};
    if mutual {
        [[S, S, S], [T, T, T], [T, S, S]]
    } else {
        [[S, S, S], [S, S, T], [S, S, S]]
    }
}

/// What decides a pass's samples.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SampleSettings {
    /// Classifier-free guidance (an unconditional half); without it the batch is `[S, T, M]`, all
    /// conditional.
    pub cfg: bool,
    pub guidance_source: f64,
    /// Leave out the samples nobody reads; `false` computes all (the batch of six, as the reference
    /// does), for tests and comparisons.
    pub skip_unread: bool,
}

/// The samples of one view's UNet pass, in batch order: the unconditional half first, each half in
/// [`Branch::ALL`] order. The conditional S, T and M are always there (their outputs or maps are read).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct BatchLayout {
    samples: Vec<Sample>,
}

impl BatchLayout {
    /// The samples a pass needs: `mutual` is the self-attention schedule's phase, `recording` a CCM
    /// recording pass (whose output is thrown away).
    pub fn needed(settings: &SampleSettings, mutual: bool, recording: bool) -> Self {
        let halves: &[bool] = if settings.cfg {
            &[false, true]
        } else {
            &[true]
        };
        let sources = self_attention_sources(mutual);
        let mut samples = Vec::with_capacity(6);
        for &conditional in halves {
            // Read from outside the UNet.
            let mut need = [conditional; 3];
            if !conditional && !recording {
                let source_weighted = settings.guidance_source != 1.0;
                need = [source_weighted, true, source_weighted];
            }
            if !settings.skip_unread {
                need = [true; 3];
            }
            // Whose queries, keys or values the needed samples take (two rounds reach every source).
            for _ in 0..2 {
                for b in Branch::ALL {
                    if need[b.index()] {
                        for s in sources[b.index()] {
                            need[s.index()] = true;
                        }
                    }
                }
            }
            samples.extend(
                Branch::ALL
                    .into_iter()
                    .filter(|b| need[b.index()])
                    .map(|branch| Sample {
                        conditional,
                        branch,
                    }),
            );
        }
        Self { samples }
    }

    pub fn samples(&self) -> &[Sample] {
        &self.samples
    }

    pub fn len(&self) -> usize {
        self.samples.len()
    }

    pub fn is_empty(&self) -> bool {
        self.samples.is_empty()
    }

    /// Batch position of a sample, if the pass computes it.
    pub fn position(&self, conditional: bool, branch: Branch) -> Option<usize> {
        self.samples
            .iter()
            .position(|s| s.conditional == conditional && s.branch == branch)
    }

    /// Batch position of the conditional source sample; T_c and M_c follow it.
    pub fn conditional_start(&self) -> usize {
        self.samples.iter().take_while(|s| !s.conditional).count()
    }

    /// For each sample, the batch positions of the (query, key, value) its self-attention takes.
    pub fn self_attention_indices(&self, mutual: bool) -> [Vec<u32>; 3] {
        let sources = self_attention_sources(mutual);
        let mut out: [Vec<u32>; 3] = Default::default();
        for s in &self.samples {
            for (k, from) in sources[s.branch.index()].iter().enumerate() {
                let p = self
                    .position(s.conditional, *from)
                    .expect("a layout holds every sample its samples take from");
                out[k].push(p as u32);
            }
        }
        out
    }

    /// Position of each sample in the full batch (`[S_u, T_u, M_u, S_c, T_c, M_c]`, or `[S, T, M]`
    /// without guidance), e.g. to pick its text conditioning.
    pub fn full_positions(&self, cfg: bool) -> Vec<u32> {
        self.samples
            .iter()
            .map(|s| (s.branch.index() + if cfg && s.conditional { 3 } else { 0 }) as u32)
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(layout: &BatchLayout) -> Vec<String> {
        layout
            .samples()
            .iter()
            .map(|s| {
                let b = match s.branch {
                    Branch::Source => "S",
                    Branch::Target => "T",
                    Branch::Layout => "M",
                };
                format!("{b}{}", if s.conditional { "c" } else { "u" })
            })
            .collect()
    }

    fn settings(cfg: bool, guidance_source: f64) -> SampleSettings {
        SampleSettings {
            cfg,
            guidance_source,
            skip_unread: true,
        }
    }

    #[test]
    fn default_guidance_drops_the_unread_unconditional_samples() {
        let s = settings(true, 1.0);
        // Early: T_u takes S_u's queries and keys; M_u is read by nobody.
        let early = BatchLayout::needed(&s, false, false);
        assert_eq!(names(&early), ["Su", "Tu", "Sc", "Tc", "Mc"]);
        // Mutual: T_u attends to itself, so S_u is read by nobody either.
        let late = BatchLayout::needed(&s, true, false);
        assert_eq!(names(&late), ["Tu", "Sc", "Tc", "Mc"]);
        // A recording pass reads only the conditional maps.
        for mutual in [false, true] {
            let rec = BatchLayout::needed(&s, mutual, true);
            assert_eq!(names(&rec), ["Sc", "Tc", "Mc"]);
            assert_eq!(rec.conditional_start(), 0);
        }
        assert_eq!(early.conditional_start(), 2);
        assert_eq!(early.full_positions(true), [0, 1, 3, 4, 5]);
        assert_eq!(late.full_positions(true), [1, 3, 4, 5]);
    }

    #[test]
    fn settings_that_read_a_sample_bring_it_back() {
        let full = ["Su", "Tu", "Mu", "Sc", "Tc", "Mc"];
        for mutual in [false, true] {
            assert_eq!(
                names(&BatchLayout::needed(&settings(true, 2.0), mutual, false)),
                full
            );
            let every = SampleSettings {
                skip_unread: false,
                ..settings(true, 1.0)
            };
            assert_eq!(names(&BatchLayout::needed(&every, mutual, false)), full);
            assert_eq!(names(&BatchLayout::needed(&every, mutual, true)), full);
            assert_eq!(
                names(&BatchLayout::needed(&settings(false, 1.0), mutual, false)),
                ["Sc", "Tc", "Mc"]
            );
        }
    }

    #[test]
    fn swap_indices_point_at_the_same_samples_as_in_the_batch_of_six() {
        let every = SampleSettings {
            skip_unread: false,
            ..settings(true, 1.0)
        };
        for mutual in [false, true] {
            let full = BatchLayout::needed(&every, mutual, false);
            let [fq, fk, fv] = full.self_attention_indices(mutual);
            for recording in [false, true] {
                let layout = BatchLayout::needed(&settings(true, 1.0), mutual, recording);
                let [q, k, v] = layout.self_attention_indices(mutual);
                let at = layout.full_positions(true);
                for (p, &f) in at.iter().enumerate() {
                    let f = f as usize;
                    // Translate the reduced layout's positions into the full batch's.
                    assert_eq!(at[q[p] as usize], fq[f]);
                    assert_eq!(at[k[p] as usize], fk[f]);
                    assert_eq!(at[v[p] as usize], fv[f]);
                }
            }
        }
    }
}
