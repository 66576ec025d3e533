//! Renders for fits that change only the appearance (opacities and colours) of a scene. ECM's mini fits
//! keep the means, scales and rotations (`EcmParams::Appearance`, hundreds of steps over the same views),
//! so each camera's projected geometry and depth order are the same at every step: [`FrozenView`] keeps
//! them for one camera, [`FrozenGeometry`] one per view of a fit. A render from them is the same, bit for
//! bit, as [`super::render`]; only the opacity-dependent extents, the colours and the tile lists are made
//! again, the lists by dropping the Gaussians too faint to draw from the kept lists of all those on
//! screen (no sorting, no scattering).

use super::cpu::{dispatch, Kernel};
use super::project::{project_appearance, project_geometry, CameraR, Splat};
use super::tiles::DepthOrder;
use super::{raster, Forward, Params, RenderOutput, RenderSettings, PROJECT_CHUNK};
use crate::cameras::Camera;
use crate::scene::GaussianScene;
use rayon::prelude::*;

/// One camera's projection of a scene's geometry (see the module documentation).
pub struct FrozenView {
    camera: Camera,
    /// Per Gaussian: mean, conic, depth, radius and tiles (radius 0: culled by its geometry).
    shapes: Vec<Splat<f32>>,
    /// Per Gaussian: the diagonal of the dilated 2D covariance (for the opacity-dependent extents).
    cov_diag: Vec<[f32; 2]>,
    order: DepthOrder,
}

impl FrozenView {
    /// Projects the geometry of `scene` for `camera`.
    ///
    /// # Panics
    /// As [`super::render`] does, on an inconsistent scene or an image too large to tile.
    pub fn new(scene: &GaussianScene, camera: &Camera) -> Self {
        let params = Params::from_scene(scene);
        let cam = CameraR::<f32>::new(camera);
        let (tx, ty) = cam.tiles();
        assert!(
            tx <= u16::MAX as u32 && ty <= u16::MAX as u32,
            "image too large: {}x{}",
            camera.width,
            camera.height
        );
        let n = params.len();
        let mut shapes = vec![Splat::default(); n];
        let mut cov_diag = vec![[0.0f32; 2]; n];
        shapes
            .par_chunks_mut(PROJECT_CHUNK)
            .zip(cov_diag.par_chunks_mut(PROJECT_CHUNK))
            .enumerate()
            .for_each(|(c, (shapes, cov_diag))| {
                dispatch(GeometryChunk {
                    params: &params,
                    cam: &cam,
                    start: c * PROJECT_CHUNK,
                    shapes,
                    cov_diag,
                })
            });
        let order = DepthOrder::new(&shapes, tx, ty);
        Self {
            camera: camera.clone(),
            shapes,
            cov_diag,
            order,
        }
    }

    pub fn camera(&self) -> &Camera {
        &self.camera
    }

    /// Bytes this view holds.
    pub fn bytes(&self) -> usize {
        self.shapes.len() * (std::mem::size_of::<Splat<f32>>() + std::mem::size_of::<[f32; 2]>())
            + self.order.bytes()
    }

    /// Bytes a view of `gaussians` Gaussians is assumed to hold before it is made (the tile lists of
    /// every Gaussian on screen: 4 tiles each assumed).
    pub fn memory_bytes_for(gaussians: usize) -> usize {
        gaussians
            * (std::mem::size_of::<Splat<f32>>()
                + std::mem::size_of::<[f32; 2]>()
                + DepthOrder::ENTRY_BYTES)
    }

    /// Renders `scene`, which must have the geometry this view was made from (its opacities and colours
    /// may differ): the same output as [`super::render`] without extra channels.
    ///
    /// # Panics
    /// When `scene` has another number of Gaussians (a programming error).
    pub fn render(&self, scene: &GaussianScene, settings: &RenderSettings) -> RenderOutput {
        let params = Params::from_scene(scene);
        assert_eq!(
            params.len(),
            self.shapes.len(),
            "scene of another size than its frozen view"
        );
        let cam = CameraR::<f32>::new(&self.camera);
        let mut splats = vec![Splat::default(); params.len()];
        splats
            .par_chunks_mut(PROJECT_CHUNK)
            .enumerate()
            .for_each(|(c, chunk)| {
                dispatch(AppearanceChunk {
                    params: &params,
                    cam: &cam,
                    view: self,
                    start: c * PROJECT_CHUNK,
                    chunk,
                })
            });
        let bins = self.order.bin(&splats);
        let raster = raster::rasterize(
            &splats,
            &bins,
            self.camera.width,
            self.camera.height,
            settings.background,
            None,
            None,
        );
        let fwd = Forward {
            splats,
            bins,
            raster,
        };
        RenderOutput::new(&self.camera, fwd, 0)
    }
}

/// The geometry of the Gaussians from `start` on (compiled for AVX2+FMA as well, as the projection is).
struct GeometryChunk<'a> {
    params: &'a Params<'a, f32>,
    cam: &'a CameraR<f32>,
    start: usize,
    shapes: &'a mut [Splat<f32>],
    cov_diag: &'a mut [[f32; 2]],
}

impl Kernel for GeometryChunk<'_> {
    type Output = ();

    #[inline(always)]
    fn run<const SIMD: bool>(self) {
        for (j, (shape, diag)) in self
            .shapes
            .iter_mut()
            .zip(self.cov_diag.iter_mut())
            .enumerate()
        {
            if let Some(s) = project_geometry(self.params, self.start + j, self.cam) {
                *shape = s.splat;
                *diag = s.cov_diag;
            }
        }
    }
}

/// Opacities, extents and colours of the Gaussians from `start` on, from their kept geometry.
struct AppearanceChunk<'a> {
    params: &'a Params<'a, f32>,
    cam: &'a CameraR<f32>,
    view: &'a FrozenView,
    start: usize,
    chunk: &'a mut [Splat<f32>],
}

impl Kernel for AppearanceChunk<'_> {
    type Output = ();

    #[inline(always)]
    fn run<const SIMD: bool>(self) {
        for (j, out) in self.chunk.iter_mut().enumerate() {
            let i = self.start + j;
            let shape = &self.view.shapes[i];
            if shape.radius > 0 {
                *out = project_appearance(
                    self.params,
                    i,
                    self.cam,
                    shape,
                    self.view.cov_diag[i],
                    true,
                );
            }
        }
    }
}

/// The [`FrozenView`]s of a fit's views, made on first use and kept while the scene's geometry (means,
/// scales, rotations, compared bit for bit) and each view's camera stay the same, within a memory budget.
pub struct FrozenGeometry {
    /// Bit patterns of the means, log-scales and rotations the views were made from.
    geometry: Vec<u32>,
    views: Vec<Option<FrozenView>>,
    bytes: usize,
    budget: usize,
}

impl Default for FrozenGeometry {
    fn default() -> Self {
        Self::with_budget(Self::DEFAULT_BUDGET)
    }
}

impl FrozenGeometry {
    /// 1 GiB: the demo's 16 views of 23k Gaussians take 32 MiB; a 1M-Gaussian scene keeps 12 views.
    pub const DEFAULT_BUDGET: usize = 1 << 30;

    /// Views are kept while their bytes ([`FrozenView::memory_bytes_for`]) stay within `budget`.
    pub fn with_budget(budget: usize) -> Self {
        Self {
            geometry: Vec::new(),
            views: Vec::new(),
            bytes: 0,
            budget,
        }
    }

    /// View `v` of `scene` from `camera`: the kept one when the geometry and the camera are those it was
    /// made from, else a new one when the budget allows it, else `None` (render without one).
    pub fn view(
        &mut self,
        scene: &GaussianScene,
        camera: &Camera,
        v: usize,
    ) -> Option<&FrozenView> {
        let same_geometry = self.geometry.len() == 10 * scene.len()
            && geometry_bits(scene).eq(self.geometry.iter().copied());
        if !same_geometry {
            self.views.clear();
            self.bytes = 0;
            self.geometry.clear();
            self.geometry.extend(geometry_bits(scene));
        }
        if self.views.len() <= v {
            self.views.resize_with(v + 1, || None);
        }
        let kept = matches!(&self.views[v], Some(view) if view.camera == *camera);
        if !kept {
            if let Some(old) = self.views[v].take() {
                self.bytes -= old.bytes();
            }
            if self.bytes + FrozenView::memory_bytes_for(scene.len()) > self.budget {
                return None;
            }
            let view = FrozenView::new(scene, camera);
            self.bytes += view.bytes();
            self.views[v] = Some(view);
        }
        self.views[v].as_ref()
    }
}

/// The means, log-scales and rotations of `scene` as bit patterns (so -0 differs from 0 and NaN equals
/// itself: the kept views are used only for exactly the geometry they were made from).
fn geometry_bits(scene: &GaussianScene) -> impl Iterator<Item = u32> + '_ {
    scene
        .means
        .iter()
        .chain(&scene.log_scales)
        .chain(&scene.quats)
        .map(|v| v.to_bits())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::gpu::tests::{camera, random_scene};
    use crate::render::{render, render_backward, render_backward_appearance, OutputGrads};

    fn bits(v: &[f32]) -> Vec<u32> {
        v.iter().map(|x| x.to_bits()).collect()
    }

    /// The frozen view's render and the appearance backward pass are bit-identical to the full ones,
    /// after the opacities and colours move (some opacities below 1/255, one NaN).
    #[test]
    fn frozen_render_and_backward_match_the_full_pass_bit_for_bit() {
        for degree in 0..=3 {
            let mut scene = random_scene(600, degree, 11 + degree as u64);
            let cam = camera(70, 52);
            let settings = RenderSettings {
                background: [0.2, 0.5, 0.9],
            };
            let view = FrozenView::new(&scene, &cam);
            for round in 0..3 {
                if round > 0 {
                    for (i, o) in scene.opacity_logits.iter_mut().enumerate() {
                        *o += ((i * 7 + round) % 13) as f32 * 0.4 - 2.6;
                    }
                    for (i, c) in scene.sh.iter_mut().enumerate() {
                        *c += ((i * 5 + round) % 11) as f32 * 0.05 - 0.25;
                    }
                    scene.opacity_logits[round] = -9.0;
                    scene.opacity_logits[3 + round] = f32::NAN;
                }
                let full = render(&scene, &cam, &settings, None);
                let kept = view.render(&scene, &settings);
                assert_eq!(
                    bits(&full.rgb),
                    bits(&kept.rgb),
                    "degree {degree} round {round}"
                );
                assert_eq!(bits(&full.alpha), bits(&kept.alpha));
                assert_eq!(full.radii, kept.radii);
                assert_eq!(full.state.bins.ids, kept.state.bins.ids);
                let grad: Vec<f32> = full.rgb.iter().map(|v| v - 0.4).collect();
                let out_grads = OutputGrads::rgb_only(&grad);
                let g = render_backward(&scene, &cam, &settings, None, &full, &out_grads);
                let a = render_backward_appearance(&scene, &cam, &settings, &kept, &out_grads);
                assert!(g.opacity_logits.iter().any(|v| *v != 0.0));
                assert_eq!(bits(&g.opacity_logits), bits(&a.opacity_logits));
                assert_eq!(bits(&g.sh), bits(&a.sh));
                assert_eq!(g.means2d, a.means2d);
                assert!(a
                    .means
                    .iter()
                    .chain(&a.log_scales)
                    .chain(&a.quats)
                    .all(|v| *v == 0.0));
            }
        }
    }

    /// Views are kept across calls, made again when the geometry or the camera changes, and not made
    /// beyond the budget.
    #[test]
    fn views_are_kept_while_geometry_and_camera_stay() {
        let mut scene = random_scene(300, 1, 5);
        let (a, b) = (camera(40, 30), camera(48, 32));
        let one_view = FrozenView::memory_bytes_for(scene.len());
        let mut frozen = FrozenGeometry::with_budget(2 * one_view);
        let first = frozen.view(&scene, &a, 0).unwrap() as *const FrozenView;
        scene.sh[0] += 1.0;
        scene.opacity_logits[0] -= 1.0;
        assert_eq!(
            frozen.view(&scene, &a, 0).unwrap() as *const _,
            first,
            "appearance changes keep it"
        );
        assert!(frozen.view(&scene, &b, 1).is_some());
        assert!(frozen.view(&scene, &a, 2).is_none(), "over the budget");
        // Another camera for view 1 replaces it (within the budget).
        assert_eq!(frozen.view(&scene, &a, 1).unwrap().camera(), &a);
        scene.means[4] += 1e-3;
        let moved = frozen.view(&scene, &a, 0).unwrap();
        let full = render(&scene, &a, &RenderSettings::default(), None);
        let kept = moved.render(&scene, &RenderSettings::default());
        assert_eq!(
            bits(&full.rgb),
            bits(&kept.rgb),
            "a moved mean makes the view again"
        );
    }
}
