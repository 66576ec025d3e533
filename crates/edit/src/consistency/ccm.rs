//! CCM, the cross-attention consistency module (docs/algorithm.md §1.1).
//!
//! At its steps (by default 6 and 13) a recording pass per view captures the conditional cross-attention
//! maps of the small layers (after InfEdit's refinement). For each layer the maps of the real tokens
//! (3 branches × heads × L channels) are upsampled to the render resolution, lifted onto the Gaussians over
//! all views, rendered back, downsampled, clamped to [0, 1] and substituted in that step's real pass
//! (padding tokens keep the recorded values; no renormalisation over tokens).

use std::collections::HashMap;

use candle_core::{DType, Tensor};

use splat::lift::{MapGrid, Resample};
use splat::LiftSession;

use super::lift::make_consistent;
use super::{MultiView, MultiViewError};
use crate::ledger::StageWork;
use crate::sampler::ViewState;

impl MultiView<'_> {
    /// CCM at step `i`: record, lift, render back, substitute. Returns the seconds from the recorded
    /// maps to the consistent ones (the lifting rounds of every layer).
    pub(super) fn cross_attention_consistency(
        &self,
        views: &mut [ViewState],
        i: usize,
        lift: &mut LiftSession<'_>,
        work: &mut StageWork,
    ) -> Result<f64, MultiViewError> {
        let plan = self.plan;
        let mut recorded = Vec::with_capacity(views.len());
        for batch in views.chunks_mut(self.view_batch.max(1)) {
            let mut batch: Vec<&mut ViewState> = batch.iter_mut().collect();
            let (maps, samples_per_view) = plan.record_views(self.model, &mut batch, i)?;
            work.unet_calls += 1;
            work.unet_samples += batch.len() * samples_per_view;
            recorded.extend(maps);
        }
        for rec in recorded.iter().flatten() {
            work.map_reads += 1;
            work.map_read_bytes +=
                (rec.maps.elem_count() * rec.maps.dtype().size_in_bytes()) as u64;
        }
        let layers = recorded[0].len();
        if recorded.iter().any(|r| r.len() != layers) {
            return Err(MultiViewError::Input(
                "views recorded different attention layers".into(),
            ));
        }
        let lifting = std::time::Instant::now();
        let real = plan.alignment.target_len.max(plan.source_len);
        let mut consistent: Vec<HashMap<String, Tensor>> = vec![HashMap::new(); views.len()];
        for k in 0..layers {
            let (sh, sw) = recorded[0][k].size;
            let dims = recorded[0][k].maps.dims4()?; // [3, heads, N, tokens]
            let (branches, heads, nq, tokens) = dims;
            let l = real.min(tokens);
            let channels = branches * heads * l;
            // Per view: [N, 3*heads*L] interleaved, channel = (branch*heads + head)*L + token.
            let as_map = |maps: &Tensor| -> candle_core::Result<Vec<f32>> {
                maps.to_dtype(DType::F32)?
                    .narrow(3, 0, l)?
                    .reshape((branches * heads, nq, l))?
                    .permute((1, 0, 2))?
                    .flatten_all()?
                    .to_vec1()
            };
            let rec = &recorded;
            let mut backs: Vec<Option<Vec<f32>>> = vec![None; views.len()];
            make_consistent(
                lift,
                &MapGrid {
                    height: sh,
                    width: sw,
                    channels,
                    up: Resample::Bilinear,
                    down: Resample::Bilinear,
                },
                &mut |v| as_map(&rec[v][k].maps),
                &mut |v, back| {
                    backs[v] = Some(back);
                    Ok(())
                },
            )?;
            work.lifting_rounds += 1;
            work.render_backs += views.len();
            for (v, back) in backs.into_iter().enumerate() {
                let back = back.expect("every view rendered");
                let maps = &recorded[v][k].maps;
                let lifted =
                    Tensor::from_vec(back, (nq, branches * heads, l), &candle_core::Device::Cpu)?
                        .permute((1, 0, 2))?
                        .reshape((branches, heads, nq, l))?;
                let merged = if l < tokens {
                    Tensor::cat(
                        &[
                            &lifted,
                            &maps.to_dtype(DType::F32)?.narrow(3, l, tokens - l)?,
                        ],
                        3,
                    )?
                } else {
                    lifted
                };
                consistent[v].insert(recorded[v][k].layer.clone(), merged.clamp(0f32, 1f32)?);
            }
        }
        for (view, maps) in views.iter_mut().zip(consistent) {
            view.controller.set_consistent_maps(maps);
        }
        Ok(lifting.elapsed().as_secs_f64())
    }
}
