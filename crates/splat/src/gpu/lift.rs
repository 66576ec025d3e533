//! Lifting 2D maps onto Gaussians on the GPU, as [`crate::lift`] does on the CPU: per view the scene is
//! projected and binned as for rendering, then one kernel walks every pixel (laid out as the raster
//! forward) and adds its map values to the Gaussians it hits.

use super::{arg, project_and_bin, GpuContext, GpuError, GpuScene, TILE};
use crate::lift::Lifted;
use crate::{Camera, GaussianScene};
use ::gpu::cubecl::prelude::*;
use ::gpu::gpu_call;
use ::gpu::prims::{read_f32, read_u32, upload_f32, zeros32};

/// Lifts per-view maps (`maps[v]` is H*W*C for `cameras[v]`) onto the Gaussians of `scene`.
///
/// # Panics
/// When `maps` and `cameras` differ in length or a map has the wrong size (programming errors).
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
pub(super) fn lift_with(
    ctx: &GpuContext,
    scene: &GaussianScene,
    cameras: &[Camera],
    maps: &[&[f32]],
    channels: usize,
    ppu: u32,
) -> Result<Lifted, GpuError> {
    assert_eq!(cameras.len(), maps.len(), "one map per camera");
    let c = &ctx.client;
    let n = scene.len();
    let dev = GpuScene::upload(ctx, scene);
    let sums = zeros32(c, n * channels);
    let counts = zeros32(c, n);
    gpu_call(|| {
        for (cam, map) in cameras.iter().zip(maps) {
            let npix = (cam.width * cam.height) as usize;
            assert_eq!(map.len(), npix * channels, "map must be H*W*C");
            if npix == 0 || n == 0 {
                continue;
            }
            let b = project_and_bin(ctx, &dev, cam)?;
            if b.intersections == 0 {
                continue;
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
                arg(&sums, n * channels),
                arg(&counts, n),
                channels as u32,
                ppu,
            );
        }
        let counts: Vec<f32> = read_u32(c, &counts, n)?
            .into_iter()
            .map(|k| k as f32)
            .collect();
        let mut values = read_f32(c, &sums, n * channels)?;
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
