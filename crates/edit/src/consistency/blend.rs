//! Blend-map consistency (docs/algorithm.md §1.4): at every step the three local-blend maps of every view
//! (`e`, `m`, `me`) are lifted onto the Gaussians and rendered back before the local blend, which then uses
//! the dynamic threshold for `me` (VcEdit's variant).

use candle_core::Tensor;

use splat::lift::{MapGrid, Resample};
use splat::LiftSession;

use super::lift::make_consistent;
use super::{MultiView, MultiViewError};
use crate::ledger::StageWork;
use crate::sampler::{blend_maps, ViewState};

impl MultiView<'_> {
    /// Blend maps of every view, made consistent when enabled, then InfEdit's local blend. Returns the maps.
    pub(super) fn local_blend(
        &self,
        views: &mut [ViewState],
        i: usize,
        lift: &mut LiftSession<'_>,
        work: &mut StageWork,
    ) -> Result<Vec<Tensor>, MultiViewError> {
        let plan = self.plan;
        let (lh, lw) = plan.latent_size;
        let mut maps = Vec::with_capacity(views.len());
        for view in views.iter() {
            let store = view.controller.blend_store()?;
            for (_, m) in &store {
                work.map_reads += 1;
                work.map_read_bytes += (m.elem_count() * m.dtype().size_in_bytes()) as u64;
            }
            maps.push(blend_maps(
                &store,
                plan.blend_size,
                &plan.alignment,
                plan.latent_size,
                1e-6,
            )?);
        }
        if self.consistency.blend_consistency {
            let hwc = |m: &Tensor| -> candle_core::Result<Vec<f32>> {
                m.permute((1, 2, 0))?.flatten_all()?.to_vec1()
            };
            let src = maps.clone();
            make_consistent(
                lift,
                &MapGrid {
                    height: lh,
                    width: lw,
                    channels: 3,
                    up: Resample::Nearest,
                    down: Resample::Nearest,
                },
                &mut |v| hwc(&src[v]),
                &mut |v, back| {
                    maps[v] = Tensor::from_vec(back, (lh, lw, 3), &candle_core::Device::Cpu)?
                        .permute((2, 0, 1))?
                        .contiguous()?;
                    Ok(())
                },
            )?;
            work.lifting_rounds += 1;
            work.render_backs += views.len();
        }
        for (view, m) in views.iter_mut().zip(&maps) {
            plan.blend_with_maps(view, i, m)?;
        }
        Ok(maps)
    }
}
