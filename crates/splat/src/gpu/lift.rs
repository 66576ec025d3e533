//! Lifting 2D maps onto Gaussians on the GPU, as [`crate::lift`] does on the CPU: per view the scene is
//! projected and binned as for rendering, then one kernel walks every pixel (laid out as the raster
//! forward) and adds its map values to the Gaussians it hits.

use super::{arg, project_and_bin, GpuContext, GpuError, GpuScene, TILE};
use crate::lift::Lifted;
use crate::{Camera, GaussianScene};
use ::gpu::cubecl::prelude::*;
use ::gpu::cubecl::server::Handle;
use ::gpu::gpu_call;
use ::gpu::prims::{read_f32, read_u32, upload_f32, zeros32};

/// Lifts per-view maps (`maps[v]` is H*W*C for `cameras[v]`) onto the Gaussians of `scene`.
///
/// # Panics
/// When `maps` and `cameras` differ in length or a map has the wrong size (programming errors).
/// The tests' entry (all views at once); callers lift view by view with [`GpuLiftAccumulator`].
#[cfg(test)]
pub fn lift(
    ctx: &GpuContext,
    scene: &GaussianScene,
    cameras: &[Camera],
    maps: &[&[f32]],
    channels: usize,
) -> Result<Lifted, GpuError> {
    let ppu = super::forward_pixels_per_unit(ctx);
    lift_with(ctx, scene, cameras, maps, channels, ppu)
}

/// [`lift`] with `ppu` pixels per unit (same counts; sums up to the order of float additions).
#[cfg(test)]
pub(super) fn lift_with(
    ctx: &GpuContext,
    scene: &GaussianScene,
    cameras: &[Camera],
    maps: &[&[f32]],
    channels: usize,
    ppu: u32,
) -> Result<Lifted, GpuError> {
    assert_eq!(cameras.len(), maps.len(), "one map per camera");
    let mut acc = GpuLiftAccumulator::with_layout(ctx, scene, channels, ppu);
    for (cam, map) in cameras.iter().zip(maps) {
        acc.add_view(ctx, cam, map)?;
    }
    acc.finish(ctx)
}

/// Lifting one view at a time (the GPU twin of [`crate::lift::LiftAccumulator`]): the scene and the
/// per-Gaussian sums stay on the device, so only one view's map is ever held on the host.
pub struct GpuLiftAccumulator {
    scene: GpuScene,
    n: usize,
    channels: usize,
    sums: Handle,
    counts: Handle,
    /// Pixels per unit of the accumulation kernel (laid out as the raster forward).
    ppu: u32,
}

impl GpuLiftAccumulator {
    /// Uploads `scene` with zeroed sums for `channels` channels.
    pub fn new(ctx: &GpuContext, scene: &GaussianScene, channels: usize) -> Self {
        Self::with_layout(ctx, scene, channels, super::forward_pixels_per_unit(ctx))
    }

    fn with_layout(ctx: &GpuContext, scene: &GaussianScene, channels: usize, ppu: u32) -> Self {
        let n = scene.len();
        Self {
            ppu,
            scene: GpuScene::upload(ctx, scene),
            n,
            channels,
            sums: zeros32(&ctx.client, n * channels),
            counts: zeros32(&ctx.client, n),
        }
    }

    /// Adds `map` (H*W*C) seen from `cam`.
    ///
    /// # Panics
    /// When the map has the wrong size (a programming error).
    pub fn add_view(
        &mut self,
        ctx: &GpuContext,
        cam: &Camera,
        map: &[f32],
    ) -> Result<(), GpuError> {
        let c = &ctx.client;
        let (n, channels, ppu) = (self.n, self.channels, self.ppu);
        let npix = (cam.width * cam.height) as usize;
        assert_eq!(map.len(), npix * channels, "map must be H*W*C");
        if npix == 0 || n == 0 {
            return Ok(());
        }
        gpu_call(|| {
            let b = project_and_bin(ctx, &self.scene, cam)?;
            if b.intersections == 0 {
                return Ok(());
            }
            let map = upload_f32(c, map);
            let num_tiles = (b.tiles_x * b.tiles_y) as usize;
            super::raster::lift_accumulate::launch(
                c,
                CubeCount::new_2d(b.tiles_x, b.tiles_y),
                CubeDim::new_2d(TILE, TILE / ppu),
                arg(&b.splats, super::SPLAT_F * n),
                arg(&b.ids, b.intersections),
                arg(&b.tile_start, num_tiles),
                arg(&b.tile_end, num_tiles),
                arg(&map, npix * channels),
                cam.width,
                cam.height,
                b.tiles_x,
                arg(&self.sums, n * channels),
                arg(&self.counts, n),
                channels as u32,
                ppu,
            );
            Ok(())
        })
    }

    /// The per-Gaussian averages and hit counts, read back.
    pub fn finish(self, ctx: &GpuContext) -> Result<Lifted, GpuError> {
        let c = &ctx.client;
        let (n, channels) = (self.n, self.channels);
        gpu_call(|| {
            let counts: Vec<f32> = read_u32(c, &self.counts, n)?
                .into_iter()
                .map(|k| k as f32)
                .collect();
            let mut values = read_f32(c, &self.sums, n * channels)?;
            if channels > 0 {
                for (row, &k) in values.chunks_mut(channels).zip(&counts) {
                    let inv = 1.0 / (k + 1e-7);
                    for v in row {
                        *v *= inv;
                    }
                }
            }
            Ok(Lifted { values, counts })
        })
    }
}
