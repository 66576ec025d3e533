//! Views whose geometry is kept on the device, for fits that move only the opacities and colours (ECM's
//! appearance fits): the host twin of [`crate::render::FrozenGeometry`].
//!
//! On the device a Gaussian's tile rectangle is its 3σ extent, whatever its opacity; the opacity only
//! decides whether it is binned at all (at least 1/255, not NaN), and the raster kernels skip a
//! Gaussian under 1/255 at every pixel before they touch any state. So a view's projection and tile
//! lists, made once with the opacity test left out, serve every later step: a step rewrites the
//! opacities and colours (one kernel) and rasterises; its backward skips the geometry's part. No
//! sort, no scan, no pair emission, and no read back (the full pass reads the pair count to size its
//! buffers: a wait for the device at every step). Renders and gradients are the full pass's, up to
//! the order in which the backward's atomics add (the tests compare them).
//!
//! The caller keeps the geometry as it was (the device-resident trainer forgets the views before a
//! step whose geometry rates are not 0); a view is made again when its camera changes.

use super::project::{self, CAM_F, INFO_U, SPLAT_F};
use super::{
    arg, forward_pixels_per_unit, project_and_bin, rasterise, rasterise_images, Binned, GpuContext,
    GpuError, GpuFrame, GpuScene, PairImage,
};
use crate::cameras::Camera;
use crate::render::{RenderSettings, TILE};
use ::gpu::gpu_call;
use ::gpu::prims::{empty32, grid};

/// One view's slot.
enum Slot {
    /// Not asked for yet (or forgotten).
    Empty,
    Kept(Box<KeptView>),
    /// Over the budget: the view renders the ordinary way.
    Refused,
}

/// A view's projection and tile lists, the camera they were made for, and their device bytes.
struct KeptView {
    camera: Camera,
    bins: Binned,
    bytes: usize,
}

/// The kept views of one fit (or of one scene's lifting rounds), within a memory budget.
pub struct GpuFrozenGeometry {
    views: Vec<Slot>,
    /// Whether the tile lists hold the Gaussians under 1/255 opacity too: for fits, whose opacities
    /// move; not for a scene whose opacities stay (lifting), where they would only be skipped.
    keep_faint: bool,
    /// The number of Gaussians the views were made for.
    len: usize,
    bytes: usize,
    budget: usize,
}

impl Default for GpuFrozenGeometry {
    fn default() -> Self {
        Self::with_budget(crate::render::FrozenGeometry::DEFAULT_BUDGET)
    }
}

impl GpuFrozenGeometry {
    /// Views for a fit that moves the opacities and colours, kept while their device bytes
    /// ([`Self::view_bytes`]) stay within `budget`.
    pub fn with_budget(budget: usize) -> Self {
        Self {
            keep_faint: true,
            views: Vec::new(),
            len: 0,
            bytes: 0,
            budget,
        }
    }

    /// Device bytes of a kept view of `n` Gaussians with `pairs` tile intersections, `width`×`height`.
    pub fn view_bytes(n: usize, pairs: usize, width: u32, height: u32) -> usize {
        let tiles = (width.div_ceil(TILE) * height.div_ceil(TILE)) as usize;
        4 * ((SPLAT_F + INFO_U) * n + pairs + 2 * tiles + CAM_F)
    }

    /// Views of a scene whose opacities stay as they are (every round of a lifting session), within
    /// `budget`: their tile lists are the ordinary render's.
    pub fn fixed_opacities(budget: usize) -> Self {
        Self {
            keep_faint: false,
            ..Self::with_budget(budget)
        }
    }

    /// Forgets every view (the geometry is about to change).
    pub fn clear(&mut self) {
        self.views.clear();
        self.bytes = 0;
    }

    /// Bytes the kept views hold on the device.
    #[cfg(test)]
    pub(crate) fn bytes(&self) -> usize {
        self.bytes
    }

    /// View `v` of `scene` from `camera`: the kept one when the camera is the one it was made from,
    /// else a new one when the budget allows it, else `None` (render the ordinary way).
    pub(crate) fn view(
        &mut self,
        ctx: &GpuContext,
        scene: &GpuScene,
        camera: &Camera,
        v: usize,
    ) -> Result<Option<&Binned>, GpuError> {
        if scene.len != self.len {
            self.clear();
            self.len = scene.len;
        }
        if self.views.len() <= v {
            self.views.resize_with(v + 1, || Slot::Empty);
        }
        match &self.views[v] {
            Slot::Kept(kept) if kept.camera == *camera => {}
            Slot::Refused => return Ok(None),
            slot => {
                if let Slot::Kept(kept) = slot {
                    self.bytes -= kept.bytes;
                }
                self.views[v] = Slot::Empty;
                // Refused before anything is made when even the pair-free part does not fit.
                let least = Self::view_bytes(scene.len, 0, camera.width, camera.height);
                if self.bytes + least > self.budget {
                    self.views[v] = Slot::Refused;
                    return Ok(None);
                }
                let bins = gpu_call(|| project_and_bin(ctx, scene, camera, self.keep_faint))?;
                let bytes =
                    Self::view_bytes(scene.len, bins.intersections, camera.width, camera.height);
                if self.bytes + bytes > self.budget {
                    self.views[v] = Slot::Refused;
                    return Ok(None);
                }
                self.bytes += bytes;
                self.views[v] = Slot::Kept(Box::new(KeptView {
                    camera: camera.clone(),
                    bins,
                    bytes,
                }));
            }
        }
        match &self.views[v] {
            Slot::Kept(kept) => Ok(Some(&kept.bins)),
            _ => unreachable!("view {v} was just kept"),
        }
    }
}

/// Renders a kept view with the scene's current opacities and colours; the frame's backward
/// ([`super::render_backward_device`]) gives the opacity and SH gradients, the geometry's as 0.
pub(crate) fn render_kept(
    ctx: &GpuContext,
    scene: &GpuScene,
    bins: &Binned,
    settings: &RenderSettings,
) -> Result<GpuFrame, GpuError> {
    let ppu = forward_pixels_per_unit(ctx, 0);
    gpu_call(|| {
        let n = scene.len;
        if n > 0 {
            let (count, dim) = grid(n);
            project::project_appearance::launch(
                &ctx.client,
                count,
                dim,
                arg(&scene.means, 3 * n),
                arg(&scene.opacity_logits, n),
                arg(&scene.sh, 3 * crate::scene::sh_coeffs(scene.sh_degree) * n),
                arg(&bins.cam, CAM_F),
                n as u32,
                arg(&bins.splats, SPLAT_F * n),
                arg(&bins.info, INFO_U * n),
                scene.sh_degree,
            );
        }
        Ok(rasterise(ctx, n, bins.clone(), settings, None, ppu, false))
    })
}

/// Renders two fits of one scene in one launch sequence (ECM's target and layout fits): `scene` holds
/// both fits' Gaussians (the first fit's `0..n`, the second's `n..2n`), whose geometry is the same and
/// kept; image 0 is the first fit seen from `bins[0]`'s view, image 1 the second from `bins[1]`'s (the
/// same size; the views may be one). The kept views are only read, so one [`GpuFrozenGeometry`]
/// serves both fits. Each image is [`render_kept`]'s of its fit, bit for bit, and the frame's backward
/// ([`super::render_backward_device`]) gives both fits' opacity and SH gradients (2n records).
pub(crate) fn render_kept_pair(
    ctx: &GpuContext,
    scene: &GpuScene,
    bins: [&Binned; 2],
    settings: &RenderSettings,
) -> Result<GpuFrame, GpuError> {
    let [a, b] = bins;
    assert!(
        scene.len.is_multiple_of(2) && (a.width, a.height) == (b.width, b.height),
        "a pair renders two halves of a scene into two images of one size"
    );
    let ppu = forward_pixels_per_unit(ctx, 0);
    gpu_call(|| {
        let (all, n) = (scene.len, scene.len / 2);
        let c = &ctx.client;
        let splats = empty32(c, SPLAT_F * all);
        let info = empty32(c, INFO_U * all);
        if n > 0 {
            let (count, dim) = grid(all);
            project::project_appearance_pair::launch(
                c,
                count,
                dim,
                arg(&scene.means, 3 * all),
                arg(&scene.opacity_logits, all),
                arg(
                    &scene.sh,
                    3 * crate::scene::sh_coeffs(scene.sh_degree) * all,
                ),
                arg(&a.cam, CAM_F),
                arg(&a.splats, SPLAT_F * n),
                arg(&a.info, INFO_U * n),
                arg(&b.cam, CAM_F),
                arg(&b.splats, SPLAT_F * n),
                arg(&b.info, INFO_U * n),
                n as u32,
                arg(&splats, SPLAT_F * all),
                arg(&info, INFO_U * all),
                scene.sh_degree,
            );
        }
        let first = Binned {
            splats,
            info,
            ..a.clone()
        };
        let second = Some(PairImage::of(b, n));
        Ok(rasterise_images(
            ctx, all, first, second, settings, None, ppu, false, None,
        ))
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::gpu::tests::{bits, camera, max_rel, random_scene};
    use crate::render::gpu::{read_grads, render_backward_device, render_device, GpuOutputGrads};
    use crate::scene::GaussianScene;
    use ::gpu::prims::{read_f32, upload_f32};
    use ::gpu::testing::context_or_skip;

    /// Moves the opacities and colours as a fit would, with one opacity far below 1/255 and one NaN.
    fn move_appearance(scene: &mut GaussianScene, round: usize) {
        for (i, o) in scene.opacity_logits.iter_mut().enumerate() {
            *o += ((i * 7 + round) % 13) as f32 * 0.4 - 2.6;
        }
        for (i, c) in scene.sh.iter_mut().enumerate() {
            *c += ((i * 5 + round) % 11) as f32 * 0.05 - 0.25;
        }
        scene.opacity_logits[round] = -9.0;
        scene.opacity_logits[3 + round] = f32::NAN;
    }

    /// A kept view renders as the full pass, bit for bit, after the opacities and colours move (some
    /// opacities below 1/255, a NaN one, SH degrees 0-3), and its backward gives the full pass's
    /// opacity and SH gradients and zero for the geometry.
    #[test]
    fn kept_views_render_and_differentiate_as_the_full_pass() {
        let Some(ctx) = context_or_skip() else {
            return;
        };
        let settings = RenderSettings {
            background: [0.2, 0.5, 0.9],
        };
        for degree in 0..=3 {
            let mut scene = random_scene(500, degree, 11 + degree as u64);
            let cam = camera(70, 52);
            let npix = (cam.width * cam.height) as usize;
            let mut frozen = GpuFrozenGeometry::default();
            for round in 0..3 {
                if round > 0 {
                    move_appearance(&mut scene, round);
                }
                let dev = GpuScene::upload(&ctx, &scene);
                let full = render_device(&ctx, &dev, &cam, &settings, None).unwrap();
                let bins = frozen.view(&ctx, &dev, &cam, 0).unwrap().unwrap().clone();
                let kept = render_kept(&ctx, &dev, &bins, &settings).unwrap();
                let read = |h: &_, len| read_f32(&ctx.client, h, len).unwrap();
                let what = format!("degree {degree} round {round}");
                assert_eq!(
                    bits(&read(&full.rgb, 3 * npix)),
                    bits(&read(&kept.rgb, 3 * npix)),
                    "{what}"
                );
                assert_eq!(
                    bits(&read(&full.alpha, npix)),
                    bits(&read(&kept.alpha, npix)),
                    "{what}"
                );
                assert_eq!(
                    bits(&read(&full.depth, npix)),
                    bits(&read(&kept.depth, npix)),
                    "{what}"
                );
                // The kept lists hold the faint Gaussians too (from round 1 on there are some).
                assert!(kept.intersections >= full.intersections, "{what}");
                assert!(
                    round == 0 || kept.intersections > full.intersections,
                    "{what}"
                );
                let rgb = read(&full.rgb, 3 * npix);
                let grad = upload_f32(
                    &ctx.client,
                    &rgb.iter().map(|v| v - 0.4).collect::<Vec<_>>(),
                );
                let out = GpuOutputGrads::rgb_only(&grad);
                let n = scene.len();
                let g = render_backward_device(&ctx, &dev, &settings, None, &full, &out).unwrap();
                let g = read_grads(&ctx, &g, n, degree, None).unwrap();
                let a = render_backward_device(&ctx, &dev, &settings, None, &kept, &out).unwrap();
                let a = read_grads(&ctx, &a, n, degree, None).unwrap();
                assert!(g.opacity_logits.iter().any(|v| *v != 0.0));
                assert!(g.means.iter().any(|v| *v != 0.0));
                // The backward's atomics may add in another order: equal up to float rounding.
                for (name, got, want) in [
                    ("opacity", &a.opacity_logits, &g.opacity_logits),
                    ("sh", &a.sh, &g.sh),
                ] {
                    let e = max_rel(got, want);
                    assert!(e <= 1e-5, "{what}: {name} differs by {e:e}");
                    assert!(got.iter().all(|v| v.is_finite()), "{what}: {name}");
                }
                assert!(
                    a.means
                        .iter()
                        .chain(&a.log_scales)
                        .chain(&a.quats)
                        .all(|v| *v == 0.0),
                    "{what}: geometry gradients"
                );
            }
        }
    }

    /// Views are kept while the camera stays, made again when it changes, refused beyond the budget
    /// (before or after their pairs are counted), and forgotten for another scene size.
    #[test]
    fn views_are_kept_within_the_budget() {
        let Some(ctx) = context_or_skip() else {
            return;
        };
        let scene = random_scene(300, 1, 5);
        let dev = GpuScene::upload(&ctx, &scene);
        let (a, b) = (camera(40, 30), camera(48, 32));
        let mut frozen = GpuFrozenGeometry::default();
        let id = |bins: &Binned| bins.splats.memory.descriptor().id;
        let first = id(frozen.view(&ctx, &dev, &a, 0).unwrap().unwrap());
        let one_view = frozen.bytes();
        assert!(one_view > GpuFrozenGeometry::view_bytes(scene.len(), 0, a.width, a.height));
        let again = id(frozen.view(&ctx, &dev, &a, 0).unwrap().unwrap());
        assert_eq!(first, again, "kept, not made again");
        let pairs = frozen
            .view(&ctx, &dev, &b, 0)
            .unwrap()
            .unwrap()
            .intersections;
        assert_eq!(
            frozen.bytes(),
            GpuFrozenGeometry::view_bytes(scene.len(), pairs, b.width, b.height),
            "made again for the new camera, the old one's bytes returned"
        );
        frozen.view(&ctx, &dev, &a, 3).unwrap().unwrap();
        assert!(frozen.bytes() > one_view);

        // A budget of the pair-free part alone: made, counted, refused, and then never made again.
        let mut tight = GpuFrozenGeometry::with_budget(GpuFrozenGeometry::view_bytes(
            scene.len(),
            0,
            a.width,
            a.height,
        ));
        assert!(tight.view(&ctx, &dev, &a, 0).unwrap().is_none());
        assert!(tight.view(&ctx, &dev, &a, 0).unwrap().is_none());
        assert_eq!(tight.bytes(), 0);
        let mut none = GpuFrozenGeometry::with_budget(0);
        assert!(none.view(&ctx, &dev, &a, 0).unwrap().is_none());

        let smaller = GpuScene::upload(&ctx, &random_scene(100, 1, 6));
        frozen.view(&ctx, &smaller, &a, 0).unwrap().unwrap();
        assert!(frozen.bytes() < one_view, "the old scene's views forgotten");
    }

    /// Two halves of one scene (two fits' appearance on one geometry) render in one launch as each
    /// half alone from its own kept view, bit for bit, also when both images are of one view; the loss of
    /// both images is each image's loss, bit for bit; and the pair's backward gives each half its own
    /// frame's opacity and SH gradients (up to the atomics' order), the geometry's as 0.
    #[test]
    fn a_pair_renders_and_differentiates_as_each_half_alone() {
        use crate::train::gpu::{l1_dssim_images, l1_dssim_weighted, L1DssimWeights};
        let Some(ctx) = context_or_skip() else {
            return;
        };
        let settings = RenderSettings {
            background: [0.2, 0.5, 0.9],
        };
        let degree = 2;
        let mut halves = [random_scene(500, degree, 31), random_scene(500, degree, 31)];
        move_appearance(&mut halves[0], 1);
        move_appearance(&mut halves[1], 2);
        let n = halves[0].len();
        let mut both = halves[0].clone();
        both.means.extend_from_slice(&halves[1].means);
        both.log_scales.extend_from_slice(&halves[1].log_scales);
        both.quats.extend_from_slice(&halves[1].quats);
        both.opacity_logits
            .extend_from_slice(&halves[1].opacity_logits);
        both.sh.extend_from_slice(&halves[1].sh);
        let dev_both = GpuScene::upload(&ctx, &both);
        let first_half = GpuScene {
            len: n,
            sh_degree: degree,
            means: dev_both.means.clone(),
            log_scales: dev_both.log_scales.clone(),
            quats: dev_both.quats.clone(),
            opacity_logits: dev_both.opacity_logits.clone(),
            sh: dev_both.sh.clone(),
        };
        let dev_halves = halves.each_ref().map(|h| GpuScene::upload(&ctx, h));
        let (w, h) = (64, 48);
        let cams = [
            camera(w, h),
            crate::cameras::orbit::look_at(
                "u".into(),
                [1.2, 0.3, -2.6],
                [0.0, 0.0, 1.0],
                [0.0, -1.0, 0.0],
                w,
                h,
                0.8 * w as f64,
            ),
        ];
        let npix = (w * h) as usize;
        let targets: Vec<_> = (0..2)
            .map(|k| {
                let t: Vec<f32> = (0..3 * npix).map(|i| ((i + k) % 7) as f32 / 7.0).collect();
                upload_f32(&ctx.client, &t)
            })
            .collect();
        let weights = L1DssimWeights::new(10.0, 2.5);
        let read = |hd: &_, len| read_f32(&ctx.client, hd, len).unwrap();
        let mut shared = GpuFrozenGeometry::default();
        let mut own = [GpuFrozenGeometry::default(), GpuFrozenGeometry::default()];
        for views in [[0, 1], [1, 1], [1, 0]] {
            let bins = views.map(|v| {
                let kept = shared.view(&ctx, &first_half, &cams[v], v).unwrap();
                kept.unwrap().clone()
            });
            let pair = render_kept_pair(&ctx, &dev_both, [&bins[0], &bins[1]], &settings).unwrap();
            let pair_loss = l1_dssim_images(
                &ctx,
                &pair.rgb,
                &[&targets[0], &targets[1]],
                64,
                48,
                3,
                weights,
            )
            .unwrap();
            let g = render_backward_device(
                &ctx,
                &dev_both,
                &settings,
                None,
                &pair,
                &GpuOutputGrads::rgb_only(&pair_loss.grad),
            )
            .unwrap();
            let g = read_grads(&ctx, &g, 2 * n, degree, None).unwrap();
            let (rgb, alpha) = (read(&pair.rgb, 6 * npix), read(&pair.alpha, 2 * npix));
            let grad = read(&pair_loss.grad, 6 * npix);
            for k in 0..2 {
                let what = format!("views {views:?}, half {k}");
                let v = views[k];
                let mine = own[k].view(&ctx, &dev_halves[k], &cams[v], v).unwrap();
                let alone = render_kept(&ctx, &dev_halves[k], mine.unwrap(), &settings).unwrap();
                let image = k * 3 * npix..(k + 1) * 3 * npix;
                assert_eq!(
                    bits(&rgb[image.clone()]),
                    bits(&read(&alone.rgb, 3 * npix)),
                    "{what}"
                );
                assert_eq!(
                    bits(&alpha[k * npix..(k + 1) * npix]),
                    bits(&read(&alone.alpha, npix)),
                    "{what}"
                );
                let loss =
                    l1_dssim_weighted(&ctx, &alone.rgb, &targets[k], 64, 48, 3, weights).unwrap();
                assert_eq!(
                    bits(&grad[image]),
                    bits(&read(&loss.grad, 3 * npix)),
                    "{what}"
                );
                let a = render_backward_device(
                    &ctx,
                    &dev_halves[k],
                    &settings,
                    None,
                    &alone,
                    &GpuOutputGrads::rgb_only(&loss.grad),
                )
                .unwrap();
                let a = read_grads(&ctx, &a, n, degree, None).unwrap();
                let k_of = |v: &[f32], per: usize| v[k * per * n..(k + 1) * per * n].to_vec();
                let sh_per = 3 * crate::scene::sh_coeffs(degree);
                assert!(a.opacity_logits.iter().any(|v| *v != 0.0), "{what}");
                for (name, got, want) in [
                    ("opacity", k_of(&g.opacity_logits, 1), &a.opacity_logits),
                    ("sh", k_of(&g.sh, sh_per), &a.sh),
                ] {
                    let e = max_rel(&got, want);
                    assert!(e <= 1e-5, "{what}: {name} differs by {e:e}");
                }
            }
            assert!(
                g.means
                    .iter()
                    .chain(&g.log_scales)
                    .chain(&g.quats)
                    .all(|v| *v == 0.0),
                "views {views:?}: geometry gradients"
            );
        }
    }
}
