//! InfEdit's unified attention control, as one [`AttentionHook`] per view.
//!
//! The UNet runs the three latent branches as one batch, `[S_u, T_u, M_u, S_c, T_c, M_c]` with classifier-free
//! guidance (or `[S, T, M]` without), less the samples nobody reads ([`BatchLayout`], `batch.rs`): the
//! controller derives each pass's layout and finds the samples by it. The controller
//! - rewrites self-attention Q/K/V in every layer and both CFG halves: early steps give all branches the
//!   source's queries and keys (the target keeps its own values); late steps let the layout branch M query
//!   with the target's queries into the source's keys/values ("mutual self-attention");
//! - refines the conditional cross-attention probabilities: target token j takes the source map of its aligned
//!   token (`mapper`, `alphas`) while the progress is within `cross_replace`; the layout branch is untouched;
//! - accumulates, over steps, the refined maps of the blend layers for the local blend;
//! - for VcEdit's CCM, records the conditional maps of the small layers during a recording pass, and replaces
//!   them with the 3D-consistent maps during the following real pass.
//!
//! The step counter is explicit: the sampler calls [`EditController::end_step`] after each real UNet pass.
//!
//! Everything runs where the UNet runs (the hook's tensors are [`DeviceTensor`]s): the swaps, the refinement,
//! the blend accumulation and CCM's recorded and substituted maps never leave the GPU (the lifting takes
//! the maps from there); the blend store is read when the blend needs it.

use std::collections::HashMap;

use candle_core::{Result, Tensor};
use diffusion::device::DeviceTensor;
use diffusion::unet::{edit_maps, AttentionHook, AttnCall, AttnKind, MapEdit, Qkv};

use super::align::TokenAlignment;
use super::batch::{BatchLayout, SampleSettings};

/// Which attention maps count as "small" for CCM recording (query length ≤ this); the reference's 32².
pub const DEFAULT_STORE_MAX_TOKENS: usize = 32 * 32;

/// Schedules and shapes of one controller.
#[derive(Clone, Debug)]
pub struct ControlSettings {
    /// Total number of steps of the schedule (before strength truncation).
    pub num_steps: usize,
    /// Steps skipped at the start (denoise mode with strength < 1).
    pub start_steps: usize,
    /// Progress ≤ this: the target's cross-attention is refined from the source's.
    pub cross_replace: f64,
    /// Progress < this: source Q/K for every branch; else mutual self-attention.
    pub self_replace: f64,
    /// Spatial size (h, w) of the down/up cross-attention layers used for blending.
    pub blend_size: (usize, usize),
    /// CCM records/replaces cross-attention layers whose query count is at most this.
    pub store_max_tokens: usize,
    /// What decides which samples a pass computes.
    pub samples: SampleSettings,
}

/// Progress of executed step `step` as the reference defines it: (step + start + 1) / num_steps.
pub(crate) fn progress_at(step: usize, start_steps: usize, num_steps: usize) -> f64 {
    (step + start_steps + 1) as f64 / num_steps as f64
}

/// Whether a pass at `progress` swaps self-attention in its mutual phase (from `self_replace` on).
pub(crate) fn mutual_at(progress: f64, self_replace: f64) -> bool {
    progress >= self_replace
}

/// Cross-attention maps of one layer as recorded for CCM: `[3 branches, heads, h*w, tokens]`, on the
/// UNet's device (CCM lifts them from there).
#[derive(Clone, Debug)]
pub struct RecordedMaps {
    pub layer: String,
    pub size: (usize, usize),
    pub maps: DeviceTensor,
}

/// The attention controller of one view.
pub struct EditController {
    settings: ControlSettings,
    /// `mapper` as gather indices over the source's token axis (unmatched → 0, weight 0).
    mapper: Vec<u32>,
    /// The alignment's `alphas`, one per target token.
    alphas: Vec<f32>,
    cur_step: usize,
    /// Σ over steps of [refine(A_S), refine(A_M)] per blend layer, `[2, heads, h*w, tokens]`, in call order,
    /// on the UNet's device.
    blend_store: Vec<(String, DeviceTensor)>,
    /// True during CCM's recording pass: nothing is accumulated, maps are recorded instead.
    recording: Option<Vec<RecordedMaps>>,
    /// 3D-consistent conditional maps to substitute in the next real pass (CCM), on the UNet's device.
    consistent: Option<HashMap<String, DeviceTensor>>,
    /// Small cross-attention calls of the current real pass so far, and of the last whole one: a
    /// recording pass has seen all it records once it has recorded that many.
    small_calls: usize,
    small_calls_per_pass: Option<usize>,
}

impl EditController {
    pub fn new(settings: ControlSettings, alignment: &TokenAlignment) -> Self {
        let mapper: Vec<u32> = alignment
            .mapper
            .iter()
            .map(|m| m.unwrap_or(0) as u32)
            .collect();
        Self {
            settings,
            mapper,
            alphas: alignment.alphas.clone(),
            cur_step: 0,
            blend_store: Vec::new(),
            recording: None,
            consistent: None,
            small_calls: 0,
            small_calls_per_pass: None,
        }
    }

    pub fn settings(&self) -> &ControlSettings {
        &self.settings
    }

    /// Steps completed so far (real passes).
    pub fn cur_step(&self) -> usize {
        self.cur_step
    }

    /// Progress of the current pass as the reference defines it: (step + start + 1) / num_steps.
    pub fn progress(&self) -> f64 {
        progress_at(
            self.cur_step,
            self.settings.start_steps,
            self.settings.num_steps,
        )
    }

    /// Marks the end of a real UNet pass.
    pub fn end_step(&mut self) {
        self.cur_step += 1;
        // Consistent maps hold for one step only.
        self.consistent = None;
        self.small_calls_per_pass = Some(std::mem::take(&mut self.small_calls));
    }

    /// The accumulated blend-layer maps: (layer, `[2, heads, h*w, tokens]`), read back to the host.
    pub fn blend_store(&self) -> Result<Vec<(String, Tensor)>> {
        self.blend_store
            .iter()
            .map(|(name, maps)| Ok((name.clone(), maps.to_cpu()?)))
            .collect()
    }

    /// Starts a recording pass (CCM): the next UNet pass records the small layers' conditional maps and
    /// changes no state.
    pub fn start_recording(&mut self) {
        self.recording = Some(Vec::new());
    }

    /// Ends the recording pass and returns what it recorded, in call order.
    pub fn finish_recording(&mut self) -> Vec<RecordedMaps> {
        self.recording.take().unwrap_or_default()
    }

    /// Sets the 3D-consistent conditional maps (`[3, heads, h*w, tokens]` per layer, f32 on the UNet's
    /// device) for the next real pass.
    pub fn set_consistent_maps(&mut self, maps: HashMap<String, DeviceTensor>) {
        self.consistent = Some(maps);
    }

    /// A copy that shares nothing mutable (for a view's independent controller).
    pub fn duplicate(&self) -> Self {
        Self {
            settings: self.settings.clone(),
            mapper: self.mapper.clone(),
            alphas: self.alphas.clone(),
            cur_step: self.cur_step,
            blend_store: self.blend_store.clone(),
            recording: None,
            consistent: None,
            small_calls: 0,
            small_calls_per_pass: self.small_calls_per_pass,
        }
    }

    /// The refinement's weights for `tokens` key tokens, as a [`MapEdit`]'s (keep, take): target token j
    /// keeps `1 − α_j` of its own map and takes `α_j` of the source's map of token `mapper_j`. When the
    /// encoder length differs from the alignment's, the overlap is aligned and the rest keeps its own maps.
    fn refinement(&self, tokens: usize) -> (Vec<f32>, Vec<(usize, f32)>) {
        let n = tokens.min(self.mapper.len());
        let aligned = self.mapper[..n].iter().zip(&self.alphas[..n]);
        let take: Vec<(usize, f32)> = aligned
            .map(|(&m, &a)| (m as usize, a))
            .chain((n..tokens).map(|j| (j, 0.0)))
            .collect();
        let keep = take.iter().map(|&(_, a)| 1.0 - a).collect();
        (keep, take)
    }

    /// Whether the target's maps are refined from the source's in the current pass.
    fn refining(&self) -> bool {
        self.settings.cross_replace >= self.progress()
    }

    /// `refine(base → target)`: A'[.., j] = α_j · base[.., mapper_j] + (1 − α_j) · target[.., j].
    fn refine(&self, base: &DeviceTensor, target: &DeviceTensor) -> Result<DeviceTensor> {
        let (keep, take) = self.refinement(base.dims()[base.dims().len() - 1]);
        edit_maps(target, base, &keep, &take)
    }

    /// Whether the self-attention swap is in its mutual phase (from `self_replace` on).
    fn mutual(&self) -> bool {
        mutual_at(self.progress(), self.settings.self_replace)
    }

    /// The samples of this view's next UNet pass (see [`BatchLayout::needed`]).
    pub fn layout(&self) -> BatchLayout {
        BatchLayout::needed(
            &self.settings.samples,
            self.mutual(),
            self.recording.is_some(),
        )
    }
}

impl AttentionHook for EditController {
    fn qkv(&mut self, call: &AttnCall, qkv: Qkv) -> Result<Qkv> {
        if call.kind == AttnKind::CrossAttn
            && self.recording.is_none()
            && call.height * call.width <= self.settings.store_max_tokens
        {
            self.small_calls += 1;
        }
        let layout = self.layout();
        if call.kind != AttnKind::SelfAttn || call.batch != layout.len() {
            return Ok(qkv);
        }
        let [qi, ki, vi] = layout.self_attention_indices(self.mutual());
        Ok(Qkv {
            q: qkv.q.index_select(&qi, 0)?,
            k: qkv.k.index_select(&ki, 0)?,
            v: qkv.v.index_select(&vi, 0)?,
        })
    }

    /// Only the cross-attention calls whose maps [`Self::probs`] reads or replaces: the blend layers
    /// (accumulated) and CCM's small layers while recording or substituting. Every other call runs the
    /// fused attention (no probability matrix); its refinement goes to the values ([`Self::map_edits`]).
    fn wants_probs(&self, call: &AttnCall) -> bool {
        if call.kind != AttnKind::CrossAttn || call.batch != self.layout().len() {
            return false;
        }
        let small = call.height * call.width <= self.settings.store_max_tokens;
        let substituted = self
            .consistent
            .as_ref()
            .is_some_and(|m| m.contains_key(call.layer));
        if small && (self.recording.is_some() || substituted) {
            return true;
        }
        self.recording.is_none()
            && (call.height, call.width) == self.settings.blend_size
            && !call.layer.starts_with("mid")
    }

    /// The target's refinement as a [`MapEdit`] of the conditional target row from the conditional
    /// source row (for the calls whose maps nothing reads).
    fn map_edits(&self, call: &AttnCall) -> Vec<MapEdit> {
        let layout = self.layout();
        if call.kind != AttnKind::CrossAttn || call.batch != layout.len() || !self.refining() {
            return Vec::new();
        }
        let cond_start = layout.conditional_start();
        let (keep, take) = self.refinement(call.keys);
        vec![MapEdit {
            row: cond_start + 1,
            source: cond_start,
            keep,
            take,
        }]
    }

    /// A recording pass is finished once it has recorded as many small layers as a whole real pass
    /// calls (unknown before the first real pass: then it runs to the end).
    fn finished(&self) -> bool {
        let recorded = self.recording.as_ref().map(Vec::len);
        self.settings.samples.skip_unread
            && matches!((recorded, self.small_calls_per_pass), (Some(r), Some(n)) if n > 0 && r >= n)
    }

    fn probs(&mut self, call: &AttnCall, probs: DeviceTensor) -> Result<DeviceTensor> {
        let layout = self.layout();
        if call.kind != AttnKind::CrossAttn || call.batch != layout.len() {
            return Ok(probs);
        }
        // The reference only edits the conditional half; without CFG (which the reference does not
        // support correctly) the whole batch is conditional.
        let cond_start = layout.conditional_start();
        let n_q = call.height * call.width;
        let small = n_q <= self.settings.store_max_tokens;
        let mut cond = probs.narrow(0, cond_start, 3)?;
        if small {
            if let Some(maps) = self.consistent.as_ref().and_then(|m| m.get(call.layer)) {
                cond = maps.clone();
            }
        }
        // Each branch keeps its batch axis ([1, heads, h*w, tokens]) so the parts concatenate back.
        let (a_s, a_t, a_m) = (
            cond.narrow(0, 0, 1)?,
            cond.narrow(0, 1, 1)?,
            cond.narrow(0, 2, 1)?,
        );
        let refined_s = self.refine(&a_s, &a_t)?;
        let new_t = if self.refining() {
            refined_s.clone()
        } else {
            a_t.clone()
        };
        let cond = DeviceTensor::cat(&[&a_s, &new_t, &a_m], 0)?;

        if let Some(rec) = self.recording.as_mut() {
            if small {
                rec.push(RecordedMaps {
                    layer: call.layer.to_string(),
                    size: (call.height, call.width),
                    maps: cond.clone(),
                });
            }
        } else if (call.height, call.width) == self.settings.blend_size
            && !call.layer.starts_with("mid")
        {
            let refined_m = self.refine(&a_m, &a_t)?;
            let both = DeviceTensor::cat(&[&refined_s, &refined_m], 0)?;
            match self
                .blend_store
                .iter_mut()
                .find(|(name, _)| name == call.layer)
            {
                Some((_, acc)) => *acc = acc.add(&both)?,
                None => self.blend_store.push((call.layer.to_string(), both)),
            }
        }

        if cond_start == 0 {
            Ok(cond)
        } else {
            DeviceTensor::cat(&[&probs.narrow(0, 0, cond_start)?, &cond], 0)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Device, IndexOp};

    fn alignment(mapper: Vec<Option<usize>>, alphas: Vec<f32>) -> TokenAlignment {
        let n = mapper.len();
        TokenAlignment {
            mapper,
            alphas,
            alpha_e: vec![0.0; n],
            alpha_m: vec![0.0; n],
            target_len: n,
        }
    }

    fn settings(cross: f64, selfr: f64) -> ControlSettings {
        ControlSettings {
            num_steps: 4,
            start_steps: 0,
            cross_replace: cross,
            self_replace: selfr,
            blend_size: (2, 2),
            store_max_tokens: 1024,
            // The batch of six the tests below build by hand.
            samples: SampleSettings {
                cfg: true,
                guidance_source: 1.0,
                skip_unread: false,
            },
        }
    }

    fn call(kind: AttnKind, batch: usize) -> AttnCall<'static> {
        AttnCall {
            layer: "down_blocks.0.attentions.0.transformer_blocks.0.attn2",
            kind,
            height: 2,
            width: 2,
            batch,
            heads: 1,
            keys: 3,
        }
    }

    /// A controller whose passes compute only the samples that are read (`skip_unread`).
    fn skipping_unread(settings: ControlSettings, al: &TokenAlignment) -> EditController {
        EditController::new(
            ControlSettings {
                samples: SampleSettings {
                    skip_unread: true,
                    ..settings.samples
                },
                ..settings
            },
            al,
        )
    }

    /// The values of `t`, read back and flattened.
    fn values(t: &DeviceTensor) -> Vec<f32> {
        t.to_cpu()
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap()
    }

    /// `x` as the queries, the keys and the values.
    fn all_three(x: impl Into<DeviceTensor>) -> Qkv {
        let x = x.into();
        Qkv {
            q: x.clone(),
            k: x.clone(),
            v: x,
        }
    }

    /// [6, 1, 4, 3] probabilities whose value encodes (batch, query, token).
    fn probs() -> Tensor {
        let v: Vec<f32> = (0..6 * 4 * 3).map(|i| i as f32).collect();
        Tensor::from_vec(v, (6, 1, 4, 3), &Device::Cpu).unwrap()
    }

    #[test]
    fn cross_replace_maps_source_onto_target_tokens() {
        // Target token 1 takes source token 2; token 2 is new (alpha 0) and keeps its own map.
        let al = alignment(vec![Some(0), Some(2), None], vec![1.0, 1.0, 0.0]);
        let mut c = EditController::new(settings(1.0, 0.0), &al);
        let p = probs();
        let out = c
            .probs(&call(AttnKind::CrossAttn, 6), p.clone().into())
            .unwrap()
            .to_cpu()
            .unwrap();
        let src = p.i((3, 0)).unwrap().to_vec2::<f32>().unwrap();
        let tgt = p.i((4, 0)).unwrap().to_vec2::<f32>().unwrap();
        let new_t = out.i((4, 0)).unwrap().to_vec2::<f32>().unwrap();
        for q in 0..4 {
            assert_eq!(new_t[q], vec![src[q][0], src[q][2], tgt[q][2]]);
        }
        // Layout branch untouched, unconditional half untouched.
        assert_eq!(
            out.i(5).unwrap().to_vec3::<f32>().unwrap(),
            p.i(5).unwrap().to_vec3::<f32>().unwrap()
        );
        assert_eq!(
            out.i(1).unwrap().to_vec3::<f32>().unwrap(),
            p.i(1).unwrap().to_vec3::<f32>().unwrap()
        );
        // Stored for blending: [refine(S), refine(M)].
        assert_eq!(c.blend_store().unwrap().len(), 1);
        let stored = &c.blend_store().unwrap()[0].1;
        assert_eq!(stored.dims(), &[2, 1, 4, 3]);
        assert_eq!(stored.i((0, 0)).unwrap().to_vec2::<f32>().unwrap(), new_t);
    }

    #[test]
    fn refinement_as_a_map_edit_is_the_refinement_of_the_maps() {
        // Token 3 of the encoder is beyond the alignment: it keeps its own map.
        let al = alignment(vec![Some(0), Some(2), None], vec![1.0, 0.6, 0.0]);
        let mut c = EditController::new(settings(1.0, 0.0), &al);
        let unread = AttnCall {
            height: 4,
            width: 1,
            keys: 4,
            ..call(AttnKind::CrossAttn, 6)
        };
        assert!(!c.wants_probs(&unread));
        let scores = Tensor::randn(0f32, 1.0, (6, 2, 5, 4), &Device::Cpu).unwrap();
        let p = candle_nn::ops::softmax_last_dim(&scores).unwrap();
        let refined = c
            .probs(&unread, p.clone().into())
            .unwrap()
            .to_cpu()
            .unwrap();
        let edits = c.map_edits(&unread);
        assert_eq!(edits.len(), 1);
        let edited = edits[0].apply_to_probs(&p).unwrap();
        let flat = |t: &Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        assert_eq!(flat(&edited), flat(&refined));
        assert_ne!(flat(&edited), flat(&p));
    }

    #[test]
    fn after_cross_replace_the_target_keeps_its_maps() {
        let al = alignment(vec![Some(0), Some(2), None], vec![1.0, 1.0, 0.0]);
        let mut c = EditController::new(settings(0.5, 0.0), &al);
        let p = probs();
        c.end_step();
        c.end_step(); // progress 3/4 > 0.5
        let out = c
            .probs(&call(AttnKind::CrossAttn, 6), p.clone().into())
            .unwrap()
            .to_cpu()
            .unwrap();
        assert_eq!(
            out.i(4).unwrap().to_vec3::<f32>().unwrap(),
            p.i(4).unwrap().to_vec3::<f32>().unwrap()
        );
    }

    #[test]
    fn probabilities_are_asked_for_only_where_they_are_read_or_changed() {
        let al = alignment(vec![Some(0), Some(1)], vec![1.0, 1.0]);
        let mut c = EditController::new(settings(0.5, 0.0), &al);
        let large = AttnCall {
            height: 64,
            width: 64,
            ..call(AttnKind::CrossAttn, 6)
        };
        let blend = call(AttnKind::CrossAttn, 6);
        let mid = AttnCall {
            layer: "mid_block.attentions.0.transformer_blocks.0.attn2",
            ..blend
        };
        // Refining (progress 1/4 ≤ 0.5): the blend layers read their maps; elsewhere the refinement is
        // a map edit of the conditional target row from the conditional source row.
        assert!(!c.wants_probs(&large) && c.wants_probs(&blend) && !c.wants_probs(&mid));
        assert!(!c.wants_probs(&call(AttnKind::SelfAttn, 6)));
        let edits = c.map_edits(&large);
        assert_eq!((edits.len(), edits[0].row, edits[0].source), (1, 4, 3));
        let mut no_cfg = settings(0.5, 0.0);
        no_cfg.samples.cfg = false;
        let no_cfg = EditController::new(no_cfg, &al);
        assert_eq!(no_cfg.map_edits(&AttnCall { batch: 3, ..large })[0].row, 1);
        assert!(
            c.map_edits(&AttnCall { batch: 3, ..large }).is_empty(),
            "not this pass's batch"
        );
        assert!(c.map_edits(&call(AttnKind::SelfAttn, 6)).is_empty());
        c.end_step();
        c.end_step(); // progress 3/4: refinement over
        assert!(c.map_edits(&large).is_empty());
        assert!(!c.wants_probs(&large), "nothing reads a large layer's maps");
        assert!(c.wants_probs(&blend), "blend layers accumulate");
        assert!(!c.wants_probs(&mid), "the mid block is not blended");
        c.start_recording();
        assert!(c.wants_probs(&mid), "CCM records the small layers");
        assert!(!c.wants_probs(&large));
        c.finish_recording();
        let mut maps = HashMap::new();
        maps.insert(
            mid.layer.to_string(),
            Tensor::zeros((3, 1, 4, 2), DType::F32, &Device::Cpu)
                .unwrap()
                .into(),
        );
        c.set_consistent_maps(maps);
        assert!(c.wants_probs(&mid), "CCM substitutes its maps");
    }

    #[test]
    fn self_attention_swaps_follow_the_schedule() {
        let al = alignment(vec![Some(0)], vec![1.0]);
        let mut c = EditController::new(settings(1.0, 0.5), &al);
        let x = Tensor::arange(0f32, 6.0, &Device::Cpu)
            .unwrap()
            .reshape((6, 1, 1, 1))
            .unwrap();
        // progress 1/4 < 0.5: early.
        let Qkv { q, k, v } = c
            .qkv(&call(AttnKind::SelfAttn, 6), all_three(x.clone()))
            .unwrap();
        assert_eq!(values(&q), vec![0., 0., 0., 3., 3., 3.]);
        assert_eq!(values(&k), vec![0., 0., 0., 3., 3., 3.]);
        assert_eq!(values(&v), vec![0., 1., 0., 3., 4., 3.]);
        c.end_step(); // progress 2/4 >= 0.5: mutual.
        let Qkv { q, k, v } = c
            .qkv(&call(AttnKind::SelfAttn, 6), all_three(x.clone()))
            .unwrap();
        assert_eq!(values(&q), vec![0., 1., 1., 3., 4., 4.]);
        assert_eq!(values(&k), vec![0., 1., 0., 3., 4., 3.]);
        assert_eq!(values(&v), vec![0., 1., 0., 3., 4., 3.]);
    }

    #[test]
    fn recording_and_consistent_replacement() {
        let al = alignment(vec![Some(0), Some(1), Some(2)], vec![1.0, 1.0, 1.0]);
        let mut c = EditController::new(settings(0.0, 0.0), &al);
        c.start_recording();
        let p = probs();
        c.probs(&call(AttnKind::CrossAttn, 6), p.clone().into())
            .unwrap()
            .to_cpu()
            .unwrap();
        let rec = c.finish_recording();
        assert_eq!(rec.len(), 1);
        assert_eq!(rec[0].maps.dims(), &[3, 1, 4, 3]);
        assert!(c.blend_store.is_empty(), "recording must not accumulate");
        // Replace with constant maps: the conditional half becomes them (cross_replace 0 → no refine).
        let ones = Tensor::ones((3, 1, 4, 3), DType::F32, &Device::Cpu).unwrap();
        let mut m = HashMap::new();
        m.insert(call(AttnKind::CrossAttn, 6).layer.to_string(), ones.into());
        c.set_consistent_maps(m);
        let out = c
            .probs(&call(AttnKind::CrossAttn, 6), p.into())
            .unwrap()
            .to_cpu()
            .unwrap();
        let cond = out
            .narrow(0, 3, 3)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        assert!(cond.iter().all(|&v| v == 1.0));
        c.end_step();
        assert!(c.consistent.is_none());
    }

    #[test]
    fn a_reduced_batch_is_controlled_as_its_samples_were_in_the_batch_of_six() {
        let al = alignment(vec![Some(0), Some(2), None], vec![1.0, 1.0, 0.0]);
        let mut six = EditController::new(settings(1.0, 0.5), &al);
        let mut reduced = skipping_unread(settings(1.0, 0.5), &al);
        // Early (progress 1/4): [S_u, T_u, S_c, T_c, M_c], rows 0, 1, 3, 4, 5 of the six.
        assert_eq!(reduced.layout().full_positions(true), [0, 1, 3, 4, 5]);
        let rows = |t: &Tensor, rows: &[u32]| {
            let idx = Tensor::new(rows, &Device::Cpu).unwrap();
            t.index_select(&idx, 0).unwrap()
        };
        for step in 0..2 {
            let keep = reduced.layout().full_positions(true);
            let p = probs();
            let out_six = six
                .probs(&call(AttnKind::CrossAttn, 6), p.clone().into())
                .unwrap();
            let out_reduced = reduced
                .probs(
                    &call(AttnKind::CrossAttn, keep.len()),
                    rows(&p, &keep).into(),
                )
                .unwrap();
            assert_eq!(
                values(&out_reduced),
                values(&rows(&out_six.to_cpu().unwrap(), &keep).into())
            );
            let x = Tensor::arange(0f32, 6.0, &Device::Cpu)
                .unwrap()
                .reshape((6, 1, 1, 1))
                .unwrap();
            let self_call = |batch| call(AttnKind::SelfAttn, batch);
            let six_qkv = six.qkv(&self_call(6), all_three(x.clone())).unwrap();
            let Qkv { q, k, v } = reduced
                .qkv(&self_call(keep.len()), all_three(rows(&x, &keep)))
                .unwrap();
            for (a, b) in [(q, six_qkv.q), (k, six_qkv.k), (v, six_qkv.v)] {
                assert_eq!(
                    values(&a),
                    values(&rows(&b.to_cpu().unwrap(), &keep).into())
                );
            }
            six.end_step();
            reduced.end_step();
            // Mutual from progress 2/4: [T_u, S_c, T_c, M_c].
            if step == 0 {
                assert_eq!(reduced.layout().full_positions(true), [1, 3, 4, 5]);
            }
        }
        let (a, b) = (six.blend_store().unwrap(), reduced.blend_store().unwrap());
        assert_eq!(
            a[0].1.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
            b[0].1.flatten_all().unwrap().to_vec1::<f32>().unwrap()
        );
    }

    #[test]
    fn a_recording_pass_is_finished_after_as_many_small_layers_as_a_real_pass_has() {
        let al = alignment(vec![Some(0), Some(1), Some(2)], vec![1.0, 1.0, 1.0]);
        let mut c = skipping_unread(settings(0.0, 0.0), &al);
        let small = call(AttnKind::CrossAttn, 3);
        let large = AttnCall {
            height: 64,
            width: 64,
            ..small
        };
        let x: DeviceTensor = Tensor::zeros((3, 1, 4, 3), DType::F32, &Device::Cpu)
            .unwrap()
            .into();
        let pass = |c: &mut EditController| {
            for call in [small, large, small] {
                c.qkv(&call, all_three(x.clone())).unwrap();
                if c.wants_probs(&call) {
                    c.probs(&call, x.clone()).unwrap();
                }
            }
        };
        // Before any real pass the number of small layers is unknown: a recording runs to its end.
        c.start_recording();
        pass(&mut c);
        assert!(!c.finished());
        assert_eq!(c.finish_recording().len(), 2);
        pass(&mut c);
        c.end_step();
        c.start_recording();
        c.qkv(&small, all_three(x.clone())).unwrap();
        c.probs(&small, x.clone()).unwrap();
        assert!(!c.finished());
        c.probs(&small, x.clone()).unwrap();
        assert!(c.finished(), "both small layers recorded");
        c.finish_recording();
        assert!(!c.finished(), "only a recording pass finishes early");
    }
}
