//! CCM, the cross-attention consistency module (docs/algorithm.md §1.1).
//!
//! At its steps (by default 6 and 13) a recording pass per view captures the conditional cross-attention
//! maps of the small layers (after InfEdit's refinement). For each layer the maps of the real tokens
//! (3 branches × heads × L channels) are upsampled to the render resolution, lifted onto the Gaussians over
//! all views, rendered back, downsampled, clamped to [0, 1] and substituted in that step's real pass
//! (padding tokens keep the recorded values; no renormalisation over tokens). The layers of one map size
//! share a lifting round, their channels stacked (the reference lifts layer by layer; each channel's
//! result is the same). On a GPU the maps never leave it: the stacking, the lifting and the split back
//! into layers all run there.

use std::collections::HashMap;

use diffusion::device::DeviceTensor;
use gpu::F32Values;
use splat::lift::{MapGrid, Resample};
use splat::LiftSession;

use super::{MultiView, MultiViewError};
use crate::ledger::StageWork;
use crate::sampler::{RecordedMaps, ViewState};

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
        let layers = recorded[0].len();
        if recorded.iter().any(|r| {
            r.len() != layers
                || r.iter()
                    .zip(&recorded[0])
                    .any(|(a, b)| a.size != b.size || a.maps.dims() != b.maps.dims())
        }) {
            return Err(MultiViewError::Input(
                "views recorded different attention layers".into(),
            ));
        }
        let lifting = std::time::Instant::now();
        let real = plan.alignment.target_len.max(plan.source_len);
        let networks = self.model.compute.networks();
        let mut consistent: Vec<HashMap<String, DeviceTensor>> = vec![HashMap::new(); views.len()];
        // One lifting round per map size, the layers of that size stacked as channels: lifting and
        // rendering back treat every channel alike and alone, so a stacked round gives each layer what
        // its own round gave, for one projection, binning and traversal per view instead of one per layer
        // (SD 1.5: 3 rounds instead of 11). The maps stay where the UNet made them: on a GPU they are
        // stacked, lifted, rendered back and split there, and nothing is read back.
        for members in layers_by_size(&recorded[0]) {
            let (sh, sw) = recorded[0][members[0]].size;
            // Per member: the maps' [branches, heads, N, tokens] and the real tokens lifted.
            let mut shapes = Vec::with_capacity(members.len());
            for &k in &members {
                let (branches, heads, nq, tokens) = recorded[0][k].maps.dims4()?;
                shapes.push((branches, heads, nq, tokens, real.min(tokens)));
            }
            let nq = shapes[0].2;
            if shapes.iter().any(|s| s.2 != nq) || nq != sh * sw {
                return Err(MultiViewError::Input(format!(
                    "attention maps of {sh}×{sw} with other query counts"
                )));
            }
            let widths: Vec<usize> = shapes.iter().map(|&(b, h, _, _, l)| b * h * l).collect();
            let channels: usize = widths.iter().sum();
            // Per view: [N, channels], per pixel the members' channels one after the other, each member's
            // interleaved as channel = (branch*heads + head)*L + token.
            let stacked = |v: usize| -> candle_core::Result<F32Values> {
                let parts = members
                    .iter()
                    .zip(&shapes)
                    .map(|(&k, &(branches, heads, nq, _, l))| {
                        recorded[v][k]
                            .maps
                            .narrow_permute(3, 0, l, &[2, 0, 1, 3])?
                            .reshape(&[nq, branches * heads * l])
                    })
                    .collect::<candle_core::Result<Vec<_>>>()?;
                DeviceTensor::cat(&parts.iter().collect::<Vec<_>>(), 1)?.into_f32_values()
            };
            let mut read = StageWork::default();
            lift.lift_values_and_render_back::<MultiViewError>(
                &MapGrid {
                    height: sh,
                    width: sw,
                    channels,
                    up: Resample::Bilinear,
                    down: Resample::Bilinear,
                },
                &mut |v| {
                    let values = stacked(v)?;
                    if !values.is_on_device() {
                        read.map_reads += 1;
                        read.map_read_bytes += 4 * values.len() as u64;
                    }
                    Ok(values)
                },
                &mut |v, back| {
                    let back = DeviceTensor::from_f32_values(networks, back, vec![nq, channels])?;
                    let mut offset = 0;
                    for ((&k, &(branches, heads, nq, tokens, l)), &width) in
                        members.iter().zip(&shapes).zip(&widths)
                    {
                        let maps = &recorded[v][k].maps;
                        let lifted = back
                            .narrow(1, offset, width)?
                            .reshape(&[nq, branches * heads, l])?
                            .permute_contiguous(&[1, 0, 2])?
                            .reshape(&[branches, heads, nq, l])?;
                        offset += width;
                        let merged = if l < tokens {
                            let unlifted = maps.to_f32()?.narrow(3, l, tokens - l)?;
                            DeviceTensor::cat(&[&lifted, &unlifted], 3)?
                        } else {
                            lifted
                        };
                        consistent[v].insert(recorded[v][k].layer.clone(), merged.clamp(0.0, 1.0)?);
                    }
                    Ok(())
                },
            )?;
            work.map_reads += read.map_reads;
            work.map_read_bytes += read.map_read_bytes;
            work.lifting_rounds += 1;
            work.render_backs += views.len();
        }
        for (view, maps) in views.iter_mut().zip(consistent) {
            view.controller.set_consistent_maps(maps);
        }
        Ok(lifting.elapsed().as_secs_f64())
    }
}

/// The recorded layers' indices grouped by map size, in the order the sizes first appear (the UNet's:
/// finest first); within a group in recording order.
fn layers_by_size(layers: &[RecordedMaps]) -> Vec<Vec<usize>> {
    let mut groups: Vec<((usize, usize), Vec<usize>)> = Vec::new();
    for (k, layer) in layers.iter().enumerate() {
        match groups.iter_mut().find(|(size, _)| *size == layer.size) {
            Some((_, members)) => members.push(k),
            None => groups.push((layer.size, vec![k])),
        }
    }
    groups.into_iter().map(|(_, members)| members).collect()
}
