//! Densification statistics on the device: [`crate::train::DensifyStats::add`] for a frame whose
//! gradients are still on the device (one kernel; read back with [`GpuDensifyStats::download`]).

use crate::render::gpu::project::{GRAD_F, INFO_U};
use crate::render::gpu::{GpuFrame, GpuSceneGrads};
use crate::train::DensifyStats;
use ::gpu::cubecl;
use ::gpu::cubecl::prelude::*;
use ::gpu::cubecl::server::Handle;
use ::gpu::gpu_call;
use ::gpu::prims::arg;
#[cfg(test)]
use ::gpu::prims::zeros32;
use ::gpu::prims::{grid, read_f32, upload_f32};
use ::gpu::{GpuContext, GpuError};

#[cube(launch)]
fn densify_stats_add(
    info: &[u32],
    splat_grads: &[f32],
    n: u32,
    sx: f32,
    sy: f32,
    grad2d: &mut [f32],
    count: &mut [f32],
    max_radius: &mut [f32],
) {
    let i = ABSOLUTE_POS;
    if i < n as usize {
        let r = info[i * 8];
        let gx = splat_grads[i * 10] * sx;
        let gy = splat_grads[i * 10 + 1] * sy;
        let norm = (gx * gx + gy * gy).sqrt();
        if r > 0 && !norm.is_nan() && !norm.is_inf() {
            grad2d[i] += norm;
            count[i] += 1.0;
            max_radius[i] = f32::max(max_radius[i], r as f32);
        }
    }
}

/// Running screen-space statistics per Gaussian, on the device (fields as [`DensifyStats`]).
pub struct GpuDensifyStats {
    len: usize,
    grad2d: Handle,
    count: Handle,
    max_radius: Handle,
}

impl GpuDensifyStats {
    #[cfg(test)]
    pub fn new(ctx: &GpuContext, n: usize) -> Self {
        let c = &ctx.client;
        Self {
            len: n,
            grad2d: zeros32(c, n),
            count: zeros32(c, n),
            max_radius: zeros32(c, n),
        }
    }

    /// Host statistics, uploaded.
    pub fn from_host(ctx: &GpuContext, stats: &DensifyStats) -> Self {
        let c = &ctx.client;
        Self {
            len: stats.len(),
            grad2d: upload_f32(c, &stats.grad2d),
            count: upload_f32(c, &stats.count),
            max_radius: upload_f32(c, &stats.max_radius),
        }
    }

    /// Adds one rendered view (as [`DensifyStats::add`]): `frame` and the `grads` of its backward.
    pub fn add(
        &mut self,
        ctx: &GpuContext,
        frame: &GpuFrame,
        grads: &GpuSceneGrads,
        batch: usize,
    ) -> Result<(), GpuError> {
        let n = self.len;
        if n == 0 {
            return Ok(());
        }
        let sx = 0.5 * frame.width as f32 * batch as f32;
        let sy = 0.5 * frame.height as f32 * batch as f32;
        gpu_call(|| {
            let (count, dim) = grid(n);
            densify_stats_add::launch(
                &ctx.client,
                count,
                dim,
                arg(&frame.info, INFO_U * n),
                arg(&grads.splat, GRAD_F * n),
                n as u32,
                sx,
                sy,
                arg(&self.grad2d, n),
                arg(&self.count, n),
                arg(&self.max_radius, n),
            );
            Ok(())
        })
    }

    /// Reads the statistics back.
    pub fn download(&self, ctx: &GpuContext) -> Result<DensifyStats, GpuError> {
        let c = &ctx.client;
        Ok(DensifyStats {
            grad2d: read_f32(c, &self.grad2d, self.len)?,
            count: read_f32(c, &self.count, self.len)?,
            max_radius: read_f32(c, &self.max_radius, self.len)?,
        })
    }
}
