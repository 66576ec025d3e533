//! An oracle for edit fidelity that needs no CLIP: the world is procedural, so for every camera we know
//! exactly which pixels show the edited object and what colour each should have before and after the edit.
//!
//! For a source spec, a target spec with the same geometry (only colours/pattern changed), cameras, and
//! images of an edited result, [`Oracle::score`] reports:
//!
//! - **fidelity** (layout-aware): over the main object's patterned pixels where the source and target
//!   renders differ clearly (the target colour is at least `min_contrast` CIELAB units from every source
//!   colour within `tolerance_px` pixels, and vice versa), the fraction whose edited colour is closer to
//!   the target render than to the source render. Distances are taken to the best match within
//!   `tolerance_px` pixels, so a pattern edge off by a pixel is not punished; ties count one half.
//!   Optionally the target pattern's phase is searched (`phase_steps`), since a caption fixes the pattern
//!   family but not where the stripes start: the best phase for all views together is kept, which still
//!   rewards edits that agree across views and punishes ones that do not.
//! - **colour fidelity** (layout-free): over the same object pixels, each edited colour is matched to the
//!   nearest of the source and target pattern colours (only when clearly nearer to it than to any other,
//!   so blends at pattern edges abstain); the fraction matched to a target-only colour among those
//!   matched to a colour that changed.
//! - **preservation**: PSNR between the edited images and the source renders outside the main object
//!   (its coverage dilated by `margin_px`), i.e. the table, floor and background.
//! - **shape**: the object's silhouette against the ideal edit's (IoU), and the change outside it. A
//!   pixel belongs to the silhouette when its colour differs from the *backdrop* (the scene rendered
//!   without the main object) by `silhouette_contrast` CIELAB units; the ideal edit (the target rendered)
//!   is classified by the same rule, so where the object's colour happens to match what is behind it both
//!   silhouettes leave the pixel out alike. The outside change counts pixels beyond the `margin_px`
//!   dilation whose colour moved more than `outside_change` (any channel, 0–1) from the source render,
//!   per pixel of the object (coverage ≥ 0.5): a colour edit should leave both at 1 and 0. The **outline
//!   IoU** compares the same silhouettes with the holes they enclose filled: it tells an outline that moved
//!   (both scores fall) from a part inside it whose colour came to match what is behind (only the
//!   silhouette IoU falls: a washed-out stripe, a face that took the floor's colour).
//!
//! 3DGS renders carry no lighting, so colours are compared directly (CIELAB, so distances follow what the
//! eye sees); expected images come from the same renderer as the edited ones.

use super::build::{
    build_scene, BuildSettings, BuiltScene, Slot, LABEL_CHANNELS, MAIN, OBJECT_IDS,
};
use super::palette::srgb_to_lab;
use super::pattern::PatternKind;
use super::spec::SceneSpec;
use super::WorldError;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use splat::render::{render, ExtraChannels, RenderSettings};
use splat::{Camera, Image};

/// Label of pixels no Gaussian covers (alpha < 0.5).
pub const BACKGROUND: u8 = u8::MAX;

/// Per-pixel labels of a view, from the Gaussian labels composited like colours.
#[derive(Clone, Debug, PartialEq)]
pub struct LabelImage {
    pub width: u32,
    pub height: u32,
    /// Object id ([`MAIN`], [`super::build::SUPPORT`], [`super::build::FLOOR`]) with the largest weight,
    /// or [`BACKGROUND`].
    pub object: Vec<u8>,
    /// [`Slot`] (as u8) with the largest weight, or [`BACKGROUND`].
    pub slot: Vec<u8>,
    /// H*W*3 weights of the object ids (they sum to the pixel's alpha).
    pub object_weights: Vec<f32>,
    /// H*W*3 weights of the slots (first, second, fixed).
    pub slot_weights: Vec<f32>,
    pub alpha: Vec<f32>,
}

/// Renders the label image of a built scene.
pub fn render_labels(built: &BuiltScene, camera: &Camera) -> LabelImage {
    let channels = built.label_channels();
    let out = render(
        &built.scene,
        camera,
        &RenderSettings::default(),
        Some(ExtraChannels {
            values: &channels,
            channels: LABEL_CHANNELS,
        }),
    );
    let npix = out.alpha.len();
    let mut object = vec![BACKGROUND; npix];
    let mut slot = vec![BACKGROUND; npix];
    let mut object_weights = Vec::with_capacity(npix * OBJECT_IDS);
    let mut slot_weights = Vec::with_capacity(npix * 3);
    let argmax = |w: &[f32]| {
        (0..w.len())
            .max_by(|&a, &b| w[a].total_cmp(&w[b]))
            .unwrap_or(0) as u8
    };
    for (p, px) in out.extra.chunks_exact(LABEL_CHANNELS).enumerate() {
        let (objects, slots) = px.split_at(OBJECT_IDS);
        object_weights.extend_from_slice(objects);
        slot_weights.extend_from_slice(slots);
        if out.alpha[p] >= 0.5 {
            object[p] = argmax(objects);
            slot[p] = argmax(slots);
        }
    }
    LabelImage {
        width: out.width,
        height: out.height,
        object,
        slot,
        object_weights,
        slot_weights,
        alpha: out.into_frame().alpha,
    }
}

/// Knobs of the oracle.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct OracleSettings {
    /// Misalignment tolerated, pixels (radius of the neighbourhood searched for the best match).
    pub tolerance_px: u32,
    /// Smallest CIELAB distance between source and target colour for a pixel to count.
    pub min_contrast: f32,
    /// Smallest coverage by the main object's patterned parts for a pixel to count (excludes silhouettes).
    pub min_coverage: f32,
    /// Dilation of the object mask excluded from preservation, pixels.
    pub margin_px: u32,
    /// Phase candidates per axis for the target pattern (1 = the target spec's exact layout only).
    pub phase_steps: u32,
    /// Smallest CIELAB distance from the backdrop for a pixel to be part of the object's silhouette.
    pub silhouette_contrast: f32,
    /// Smallest change (largest channel difference, 0–1) that counts a pixel outside the object as changed.
    pub outside_change: f32,
    /// Density of the scenes the oracle renders.
    pub build: BuildSettings,
}

impl Default for OracleSettings {
    fn default() -> Self {
        Self {
            tolerance_px: 1,
            min_contrast: 20.0,
            min_coverage: 0.9,
            margin_px: 2,
            phase_steps: 1,
            silhouette_contrast: 20.0,
            outside_change: 0.1,
            build: BuildSettings::default(),
        }
    }
}

/// Scores of one view.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ViewScore {
    /// Layout-aware fidelity; `None` when no pixel of this view is informative.
    pub fidelity: Option<f64>,
    pub informative_pixels: usize,
    /// Layout-free colour fidelity; `None` when no pixel matched a changed colour.
    pub color_fidelity: Option<f64>,
    pub color_votes: usize,
    /// PSNR outside the object, dB (capped at 100).
    pub preservation_psnr: f64,
    pub outside_pixels: usize,
    /// Silhouette IoU against the ideal edit's; `None` when neither silhouette has a pixel.
    pub silhouette_iou: Option<f64>,
    /// The same with each silhouette's enclosed holes filled (the outline alone).
    pub outline_iou: Option<f64>,
    /// Changed pixels beyond the margin per object pixel; `None` when the object covers no pixel.
    pub outside_change: Option<f64>,
}

/// Scores of a set of views (pooled over pixels of all views).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EditScore {
    pub fidelity: Option<f64>,
    pub color_fidelity: Option<f64>,
    pub preservation_psnr: f64,
    /// Silhouette IoU against the ideal edit's (pooled over views).
    pub silhouette_iou: Option<f64>,
    /// Outline IoU (silhouettes with their holes filled; pooled over views).
    pub outline_iou: Option<f64>,
    /// Changed pixels beyond the margin per object pixel (pooled over views).
    pub outside_change: Option<f64>,
    /// Offset added to the target pattern's phase that matched best (zero without phase search).
    pub phase_offset: [f32; 2],
    pub per_view: Vec<ViewScore>,
}

/// Expected appearance of one view.
#[derive(Clone, Debug)]
pub struct ExpectedView {
    /// Render of the source spec.
    pub source: Image,
    /// Render of the target spec.
    pub target: Image,
    /// H*W coverage by the main object.
    pub main: Vec<f32>,
    /// H*W coverage by the main object's patterned parts.
    pub patterned: Vec<f32>,
}

/// The oracle for one source → target edit.
pub struct Oracle {
    source: SceneSpec,
    target: SceneSpec,
    built: BuiltScene,
    /// The source scene without its main object: what each silhouette is told apart from.
    backdrop: splat::GaussianScene,
    settings: OracleSettings,
}

const PSNR_CAP: f64 = 100.0;

impl Oracle {
    /// Fails when the target does not share the source's geometry.
    pub fn new(
        source: &SceneSpec,
        target: &SceneSpec,
        settings: OracleSettings,
    ) -> Result<Self, WorldError> {
        if !source.same_geometry(target) {
            return Err(WorldError::Incompatible(format!(
                "oracle: \"{}\" and \"{}\" differ in more than colour and pattern",
                source.caption(),
                target.caption()
            )));
        }
        let built = build_scene(source, &settings.build);
        let mut backdrop = built.scene.clone();
        let keep: Vec<bool> = built.labels.object.iter().map(|&o| o != MAIN).collect();
        backdrop.retain(&keep);
        Ok(Self {
            source: source.clone(),
            target: target.clone(),
            built,
            backdrop,
            settings,
        })
    }

    /// Target specs to try: the target itself, or its pattern at every phase offset of the search grid.
    fn candidates(&self) -> Vec<([f32; 2], SceneSpec)> {
        let steps = self.settings.phase_steps.max(1);
        if steps == 1 || self.target.main.pattern.kind == PatternKind::Solid {
            return vec![([0.0; 2], self.target.clone())];
        }
        let mut out = Vec::new();
        for i in 0..steps {
            for j in 0..steps {
                let offset = [i as f32 / steps as f32, j as f32 / steps as f32];
                let mut spec = self.target.clone();
                spec.main.pattern.phase[0] += offset[0];
                spec.main.pattern.phase[1] += offset[1];
                out.push((offset, spec));
            }
        }
        out
    }

    /// Per-Gaussian extra channels: main indicator, patterned indicator, then RGB under each candidate.
    fn channels(
        &self,
        candidates: &[([f32; 2], SceneSpec)],
    ) -> Result<(Vec<f32>, usize), WorldError> {
        let n = self.built.len();
        let c = 2 + 3 * candidates.len();
        let colors: Vec<Vec<f32>> = candidates
            .iter()
            .map(|(_, spec)| self.built.colors_for(spec))
            .collect::<Result<_, _>>()?;
        let mut values = vec![0.0; n * c];
        for (i, px) in values.chunks_exact_mut(c).enumerate() {
            let main = self.built.labels.object[i] == MAIN;
            px[0] = main as u8 as f32;
            px[1] = (main && self.built.labels.slot[i] != Slot::Fixed) as u8 as f32;
            for (k, col) in colors.iter().enumerate() {
                px[2 + 3 * k..5 + 3 * k].copy_from_slice(&col[3 * i..3 * i + 3]);
            }
        }
        Ok((values, c))
    }

    /// The expected source and target renders of a view, with the object coverage.
    pub fn expected(&self, camera: &Camera) -> Result<ExpectedView, WorldError> {
        let candidates = vec![([0.0; 2], self.target.clone())];
        let (values, c) = self.channels(&candidates)?;
        let r = self.render_view(camera, &values, c);
        Ok(ExpectedView {
            source: Image::from_data(r.width, r.height, 3, r.source),
            target: Image::from_data(
                r.width,
                r.height,
                3,
                r.targets.into_iter().next().unwrap_or_default(),
            ),
            main: r.main,
            patterned: r.patterned,
        })
    }

    fn render_view(&self, camera: &Camera, values: &[f32], c: usize) -> RenderedView {
        let bg = self.source.background;
        let out = render(
            &self.built.scene,
            camera,
            &RenderSettings { background: bg },
            Some(ExtraChannels {
                values,
                channels: c,
            }),
        );
        let backdrop = render(
            &self.backdrop,
            camera,
            &RenderSettings { background: bg },
            None,
        )
        .into_frame()
        .rgb;
        let npix = out.alpha.len();
        let ncand = (c - 2) / 3;
        let mut main = Vec::with_capacity(npix);
        let mut patterned = Vec::with_capacity(npix);
        let mut targets = vec![Vec::with_capacity(3 * npix); ncand];
        for (p, px) in out.extra.chunks_exact(c).enumerate() {
            main.push(px[0]);
            patterned.push(px[1]);
            let t = 1.0 - out.alpha[p];
            for (k, target) in targets.iter_mut().enumerate() {
                for ch in 0..3 {
                    target.push(px[2 + 3 * k + ch] + t * bg[ch]);
                }
            }
        }
        RenderedView {
            width: out.width,
            height: out.height,
            source: out.into_frame().rgb,
            backdrop,
            targets,
            main,
            patterned,
        }
    }

    /// Scores images of an edited result seen from `cameras` (one image per camera, same size, RGB or
    /// RGBA; alpha is ignored).
    pub fn score(&self, cameras: &[Camera], images: &[Image]) -> Result<EditScore, WorldError> {
        check_images(cameras, images)?;
        let candidates = self.candidates();
        let (values, c) = self.channels(&candidates)?;
        let colour_sets = ColourSets::new(&self.source, &self.target);
        let views: Vec<Vec<ViewTally>> = cameras
            .par_iter()
            .zip(images.par_iter())
            .map(|(cam, img)| {
                let r = self.render_view(cam, &values, c);
                self.tally(&r, img, &colour_sets)
            })
            .collect();
        // Best candidate over all views together.
        let best = (0..candidates.len())
            .max_by(|&a, &b| {
                let score = |k: usize| {
                    let (votes, n) = views.iter().fold((0.0, 0usize), |acc, v| {
                        (acc.0 + v[k].votes, acc.1 + v[k].informative)
                    });
                    if n == 0 {
                        0.0
                    } else {
                        votes / n as f64
                    }
                };
                // On equal scores prefer the earlier candidate (the exact target layout comes first).
                score(a).total_cmp(&score(b)).then(b.cmp(&a))
            })
            .unwrap_or(0);
        let per_view: Vec<ViewScore> = views.iter().map(|v| v[best].score()).collect();
        let mut total = ViewTally::default();
        for v in &views {
            total.add(&v[best]);
        }
        let pooled = total.score();
        Ok(EditScore {
            fidelity: pooled.fidelity,
            color_fidelity: pooled.color_fidelity,
            preservation_psnr: pooled.preservation_psnr,
            silhouette_iou: pooled.silhouette_iou,
            outline_iou: pooled.outline_iou,
            outside_change: pooled.outside_change,
            phase_offset: candidates[best].0,
            per_view,
        })
    }

    /// The ideal edit's silhouette and the edited image's (CIELAB pixels), each told apart from the
    /// backdrop by the same rule.
    fn silhouettes(&self, r: &RenderedView, edited: &[[f32; 3]]) -> (Vec<bool>, Vec<bool>) {
        let contrast = self.settings.silhouette_contrast;
        (0..edited.len())
            .map(|p| {
                let behind = lab_at(&r.backdrop, p);
                (
                    dist(lab_at(&r.targets[0], p), behind) > contrast,
                    dist(edited[p], behind) > contrast,
                )
            })
            .unzip()
    }

    /// Where the silhouettes of an edited view and of the ideal edit disagree, as an RGB image: white where
    /// both see the object, red where only the ideal edit does (a part lost, or taken the colour of what is
    /// behind it), blue where only the edited view does (a halo, or a kept part recoloured). For finding
    /// what lowers a shape score (`cargo run --release -p vcedit-demo --example silhouette_maps`).
    pub fn silhouette_map(&self, camera: &Camera, image: &Image) -> Result<Image, WorldError> {
        check_images(std::slice::from_ref(camera), std::slice::from_ref(image))?;
        let candidates = vec![([0.0; 2], self.target.clone())];
        let (values, c) = self.channels(&candidates)?;
        let r = self.render_view(camera, &values, c);
        let (ideal, edited) = self.silhouettes(&r, &lab_pixels(image));
        let data = ideal
            .iter()
            .zip(&edited)
            .flat_map(|(&i, &e)| match (i, e) {
                (true, true) => [1.0, 1.0, 1.0],
                (true, false) => [1.0, 0.0, 0.0],
                (false, true) => [0.0, 0.0, 1.0],
                (false, false) => [0.0; 3],
            })
            .collect();
        Ok(Image::from_data(r.width, r.height, 3, data))
    }

    /// Vote counts of one view for every candidate.
    fn tally(&self, r: &RenderedView, img: &Image, sets: &ColourSets) -> Vec<ViewTally> {
        let (w, h) = (r.width as usize, r.height as usize);
        let npix = w * h;
        let ch = img.channels as usize;
        let edited = lab_pixels(img);
        let source: Vec<[f32; 3]> = (0..npix).map(|p| lab_at(&r.source, p)).collect();
        let counted: Vec<bool> = r
            .main
            .iter()
            .zip(&r.patterned)
            .map(|(&m, &pat)| m >= self.settings.min_coverage && pat >= self.settings.min_coverage)
            .collect();

        // Preservation and colour votes do not depend on the candidate.
        let mut base = ViewTally::default();
        let margin = self.settings.margin_px as i64;
        for y in 0..h as i64 {
            for x in 0..w as i64 {
                let near_object = (-margin..=margin).any(|dy| {
                    (-margin..=margin).any(|dx| {
                        let (xx, yy) = (x + dx, y + dy);
                        xx >= 0
                            && yy >= 0
                            && xx < w as i64
                            && yy < h as i64
                            && r.main[yy as usize * w + xx as usize] > 0.02
                    })
                });
                if !near_object {
                    let p = y as usize * w + x as usize;
                    base.outside += 1;
                    let mut largest = 0.0f32;
                    for k in 0..3 {
                        let d = img.data[ch * p + k].clamp(0.0, 1.0)
                            - r.source[3 * p + k].clamp(0.0, 1.0);
                        base.squared_error += (d as f64) * (d as f64);
                        largest = largest.max(d.abs());
                    }
                    base.outside_changed += (largest > self.settings.outside_change) as usize;
                }
            }
        }
        // Silhouettes: the edited image's and the ideal edit's (the exact target layout; every
        // candidate shares its geometry), each told apart from the backdrop by the same rule.
        let (ideal, edited_object) = self.silhouettes(r, &edited);
        for p in 0..npix {
            base.silhouette_both += (ideal[p] && edited_object[p]) as usize;
            base.silhouette_either += (ideal[p] || edited_object[p]) as usize;
            base.object_pixels += (r.main[p] >= 0.5) as usize;
        }
        let (ideal, edited_object) = (fill_holes(&ideal, w, h), fill_holes(&edited_object, w, h));
        for p in 0..npix {
            base.outline_both += (ideal[p] && edited_object[p]) as usize;
            base.outline_either += (ideal[p] || edited_object[p]) as usize;
        }
        for p in (0..npix).filter(|&p| counted[p]) {
            match sets.nearest(edited[p]) {
                Some(true) => {
                    base.color_target += 1;
                }
                Some(false) => {
                    base.color_source += 1;
                }
                None => {}
            }
        }

        let tol = self.settings.tolerance_px as i64;
        r.targets
            .iter()
            .map(|target| {
                let target: Vec<[f32; 3]> = (0..npix).map(|p| lab_at(target, p)).collect();
                let mut t = base.clone();
                for p in (0..npix).filter(|&p| counted[p]) {
                    let (x, y) = ((p % w) as i64, (p / w) as i64);
                    let mut d_target = f32::INFINITY;
                    let mut d_source = f32::INFINITY;
                    // A pixel only tells source from target when its expected target colour appears
                    // nowhere near it in the source render and vice versa; otherwise a shift by the
                    // tolerance would explain either.
                    let mut separable = true;
                    for yy in (y - tol).max(0)..=(y + tol).min(h as i64 - 1) {
                        for xx in (x - tol).max(0)..=(x + tol).min(w as i64 - 1) {
                            let q = yy as usize * w + xx as usize;
                            separable &= dist(target[p], source[q]) >= self.settings.min_contrast
                                && dist(source[p], target[q]) >= self.settings.min_contrast;
                            d_target = d_target.min(dist(edited[p], target[q]));
                            d_source = d_source.min(dist(edited[p], source[q]));
                        }
                    }
                    if !separable {
                        continue;
                    }
                    t.informative += 1;
                    t.votes += if (d_target - d_source).abs() < 1.0 {
                        0.5
                    } else if d_target < d_source {
                        1.0
                    } else {
                        0.0
                    };
                }
                t
            })
            .collect()
    }
}

/// CIELAB of pixel `p` of an RGB buffer.
fn lab_at(rgb: &[f32], p: usize) -> [f32; 3] {
    srgb_to_lab([rgb[3 * p], rgb[3 * p + 1], rgb[3 * p + 2]])
}

/// CIELAB of every pixel of an RGB or RGBA image (alpha ignored).
fn lab_pixels(img: &Image) -> Vec<[f32; 3]> {
    img.data
        .chunks_exact(img.channels as usize)
        .map(|px| srgb_to_lab([px[0], px[1], px[2]]))
        .collect()
}

/// Fails unless there is one RGB(A) image per camera, at its size.
fn check_images(cameras: &[Camera], images: &[Image]) -> Result<(), WorldError> {
    if cameras.len() != images.len() {
        return Err(WorldError::Input(format!(
            "oracle: {} cameras but {} images",
            cameras.len(),
            images.len()
        )));
    }
    for (k, (cam, img)) in cameras.iter().zip(images).enumerate() {
        if (cam.width, cam.height) != (img.width, img.height) || img.channels < 3 {
            return Err(WorldError::Input(format!(
                "oracle: image {k} is {}x{}x{}, camera {} expects {}x{} RGB",
                img.width, img.height, img.channels, cam.name, cam.width, cam.height
            )));
        }
    }
    Ok(())
}

/// Scores an edit in one call (see [`Oracle`]).
pub fn score_edit(
    source: &SceneSpec,
    target: &SceneSpec,
    cameras: &[Camera],
    images: &[Image],
    settings: OracleSettings,
) -> Result<EditScore, WorldError> {
    Oracle::new(source, target, settings)?.score(cameras, images)
}

struct RenderedView {
    width: u32,
    height: u32,
    source: Vec<f32>,
    /// RGB of the scene without its main object.
    backdrop: Vec<f32>,
    targets: Vec<Vec<f32>>,
    main: Vec<f32>,
    patterned: Vec<f32>,
}

#[derive(Clone, Debug, Default)]
struct ViewTally {
    votes: f64,
    informative: usize,
    color_target: usize,
    color_source: usize,
    squared_error: f64,
    outside: usize,
    outside_changed: usize,
    silhouette_both: usize,
    silhouette_either: usize,
    outline_both: usize,
    outline_either: usize,
    object_pixels: usize,
}

impl ViewTally {
    fn add(&mut self, o: &ViewTally) {
        self.votes += o.votes;
        self.informative += o.informative;
        self.color_target += o.color_target;
        self.color_source += o.color_source;
        self.squared_error += o.squared_error;
        self.outside += o.outside;
        self.outside_changed += o.outside_changed;
        self.silhouette_both += o.silhouette_both;
        self.silhouette_either += o.silhouette_either;
        self.outline_both += o.outline_both;
        self.outline_either += o.outline_either;
        self.object_pixels += o.object_pixels;
    }

    fn score(&self) -> ViewScore {
        let color_votes = self.color_target + self.color_source;
        let mse = self.squared_error / (3 * self.outside.max(1)) as f64;
        ViewScore {
            fidelity: (self.informative > 0).then(|| self.votes / self.informative as f64),
            informative_pixels: self.informative,
            color_fidelity: (color_votes > 0)
                .then(|| self.color_target as f64 / color_votes as f64),
            color_votes,
            preservation_psnr: if mse > 0.0 {
                (10.0 * (1.0 / mse).log10()).min(PSNR_CAP)
            } else {
                PSNR_CAP
            },
            outside_pixels: self.outside,
            silhouette_iou: (self.silhouette_either > 0)
                .then(|| self.silhouette_both as f64 / self.silhouette_either as f64),
            outline_iou: (self.outline_either > 0)
                .then(|| self.outline_both as f64 / self.outline_either as f64),
            outside_change: (self.object_pixels > 0)
                .then(|| self.outside_changed as f64 / self.object_pixels as f64),
        }
    }
}

/// The pattern colours of source and target, for the layout-free colour vote.
struct ColourSets {
    /// (Lab, is a target colour, is a source colour)
    colours: Vec<([f32; 3], bool, bool)>,
}

impl ColourSets {
    fn new(source: &SceneSpec, target: &SceneSpec) -> Self {
        let used = |s: &SceneSpec| {
            let n = if s.main.pattern.kind.uses_second_color() {
                2
            } else {
                1
            };
            s.main.colors[..n].to_vec()
        };
        let (src, tgt) = (used(source), used(target));
        let mut colours = Vec::new();
        for c in &src {
            colours.push((
                srgb_to_lab(c.rgb),
                tgt.iter().any(|t| t.name == c.name),
                true,
            ));
        }
        for c in &tgt {
            if !src.iter().any(|s| s.name == c.name) {
                colours.push((srgb_to_lab(c.rgb), true, false));
            }
        }
        Self { colours }
    }

    /// `Some(true)` when the nearest colour is target-only, `Some(false)` when source-only, `None` when
    /// it is shared.
    fn nearest(&self, lab: [f32; 3]) -> Option<bool> {
        let mut ranked: Vec<(f32, bool, bool)> = self
            .colours
            .iter()
            .map(|&(c, t, s)| (dist(lab, c), t, s))
            .collect();
        ranked.sort_by(|a, b| a.0.total_cmp(&b.0));
        let &(nearest, is_target, is_source) = ranked.first()?;
        // Blends of two pattern colours (pattern edges, blur) match neither clearly: no vote.
        if ranked.get(1).is_some_and(|second| nearest > 0.5 * second.0) {
            return None;
        }
        match (is_target, is_source) {
            (true, false) => Some(true),
            (false, true) => Some(false),
            _ => None,
        }
    }
}

/// `mask` with every region of unset pixels that does not reach the image border set: a silhouette's
/// outline and all it encloses (4-connected flood fill of the outside from the border).
fn fill_holes(mask: &[bool], w: usize, h: usize) -> Vec<bool> {
    let mut outside = vec![false; mask.len()];
    let mut stack: Vec<usize> = (0..w)
        .flat_map(|x| [x, (h - 1) * w + x])
        .chain((0..h).flat_map(|y| [y * w, y * w + w - 1]))
        .filter(|&p| !mask[p])
        .collect();
    while let Some(p) = stack.pop() {
        if outside[p] || mask[p] {
            continue;
        }
        outside[p] = true;
        let (x, y) = (p % w, p / w);
        if x > 0 {
            stack.push(p - 1);
        }
        if x + 1 < w {
            stack.push(p + 1);
        }
        if y > 0 {
            stack.push(p - w);
        }
        if y + 1 < h {
            stack.push(p + w);
        }
    }
    outside.iter().map(|&o| !o).collect()
}

fn dist(a: [f32; 3], b: [f32; 3]) -> f32 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::world::build::{FLOOR, SUPPORT};
    use crate::world::dataset::{render_view, ring_views};
    use crate::world::spec::GeneratorSettings;

    fn renders(spec: &SceneSpec, cams: &[Camera]) -> Vec<Image> {
        let built = build_scene(spec, &BuildSettings::default());
        cams.iter().map(|c| render_view(&built, c)).collect()
    }

    fn shifted(img: &Image, dx: i64) -> Image {
        let mut out = img.clone();
        let w = img.width as i64;
        for y in 0..img.height as usize {
            for x in 0..w {
                let sx = (x - dx).clamp(0, w - 1);
                let (d, s) = (
                    (y * w as usize + x as usize) * 3,
                    (y * w as usize + sx as usize) * 3,
                );
                out.data[d..d + 3].copy_from_slice(&img.data[s..s + 3]);
            }
        }
        out
    }

    #[test]
    fn source_scores_zero_and_target_scores_one() {
        let gen = GeneratorSettings::default();
        for (src, tgt) in [
            ("a red sphere", "a blue sphere"),
            (
                "a red striped vase on a table",
                "a green striped vase on a table",
            ),
            ("a yellow checkered cube", "a purple checkered cube"),
            (
                "an orange dotted mushroom",
                "an orange and blue dotted mushroom",
            ),
        ] {
            let source = SceneSpec::from_caption(src, 21, &gen).unwrap();
            let target = source.with_caption(tgt).unwrap();
            let cams = ring_views(&source, 3, 64, 64, 25.0, 10.0);
            let oracle = Oracle::new(&source, &target, OracleSettings::default()).unwrap();
            let s = oracle.score(&cams, &renders(&source, &cams)).unwrap();
            let t = oracle.score(&cams, &renders(&target, &cams)).unwrap();
            let (sf, tf) = (s.fidelity.unwrap(), t.fidelity.unwrap());
            assert!(sf < 0.05, "{src} -> {tgt}: source fidelity {sf}");
            assert!(tf > 0.95, "{src} -> {tgt}: target fidelity {tf}");
            assert!(
                s.color_fidelity.unwrap() < 0.05 && t.color_fidelity.unwrap() > 0.95,
                "{s:?} {t:?}"
            );
            // Only the object changed: outside it, both match the source.
            assert_eq!(s.preservation_psnr, PSNR_CAP);
            assert!(t.preservation_psnr > 40.0, "{}", t.preservation_psnr);
            assert!(s.per_view.iter().all(|v| v.informative_pixels > 50));
            // The ideal edit has the ideal silhouette; the source's is the same outline in other
            // colours, told apart from the same backdrop.
            assert_eq!(t.silhouette_iou, Some(1.0));
            assert_eq!(t.outside_change, Some(0.0));
            assert!(s.silhouette_iou.unwrap() > 0.97, "{src}: {s:?}");
            assert_eq!(s.outside_change, Some(0.0));
        }
    }

    #[test]
    fn a_halo_around_the_object_lowers_the_shape_scores() {
        let gen = GeneratorSettings::default();
        let source = SceneSpec::from_caption("a red sphere", 3, &gen).unwrap();
        let target = source.with_caption("a blue sphere").unwrap();
        let cams = ring_views(&source, 2, 64, 64, 25.0, 15.0);
        let oracle = Oracle::new(&source, &target, OracleSettings::default()).unwrap();
        let haloed: Vec<Image> = cams
            .iter()
            .map(|cam| {
                let e = oracle.expected(cam).unwrap();
                let mut img = e.target.clone();
                let (w, h) = (img.width as i64, img.height as i64);
                let object = |x: i64, y: i64| {
                    x >= 0 && y >= 0 && x < w && y < h && e.main[(y * w + x) as usize] >= 0.5
                };
                // A soft blue rim up to 4 px wide around the outline.
                for y in 0..h {
                    for x in 0..w {
                        let near = (-4..=4).any(|dy| (-4..=4).any(|dx| object(x + dx, y + dy)));
                        if near && !object(x, y) {
                            let px = &mut img.data[3 * (y * w + x) as usize..][..3];
                            for (v, blue) in px.iter_mut().zip([0.1, 0.2, 0.9]) {
                                *v = 0.4 * *v + 0.6 * blue;
                            }
                        }
                    }
                }
                img
            })
            .collect();
        let halo = oracle.score(&cams, &haloed).unwrap();
        assert!(halo.silhouette_iou.unwrap() < 0.9, "{halo:?}");
        assert!(halo.outline_iou.unwrap() < 0.9, "{halo:?}");
        assert!(halo.outside_change.unwrap() > 0.05, "{halo:?}");
        // A one-pixel shift keeps the outline's shape: IoU stays high, nothing far outside changes.
        let moved: Vec<Image> = renders(&target, &cams)
            .iter()
            .map(|i| shifted(i, 1))
            .collect();
        let m = oracle.score(&cams, &moved).unwrap();
        assert!(m.silhouette_iou.unwrap() > 0.9, "{m:?}");
    }

    #[test]
    fn a_part_that_takes_the_backdrops_colour_keeps_the_outline() {
        let gen = GeneratorSettings::default();
        let source = SceneSpec::from_caption("a red sphere", 3, &gen).unwrap();
        let target = source.with_caption("a blue sphere").unwrap();
        let cams = ring_views(&source, 2, 64, 64, 25.0, 15.0);
        let oracle = Oracle::new(&source, &target, OracleSettings::default()).unwrap();
        let settings = RenderSettings {
            background: source.background,
        };
        let holed: Vec<Image> = cams
            .iter()
            .map(|cam| {
                let e = oracle.expected(cam).unwrap();
                let behind = render(&oracle.backdrop, cam, &settings, None)
                    .into_frame()
                    .rgb;
                let mut img = e.target.clone();
                let w = img.width as usize;
                let inside = |p: usize| {
                    let (x, y) = ((p % w) as i64, (p / w) as i64);
                    (-4..=4).all(|d: i64| {
                        [(x + d, y), (x, y + d)].iter().all(|&(xx, yy)| {
                            xx >= 0
                                && yy >= 0
                                && (xx as usize) < w
                                && (yy as usize) < img.height as usize
                                && e.main[yy as usize * w + xx as usize] >= 0.5
                        })
                    })
                };
                // The object's inner part (4 px in from its outline) shows what is behind it.
                for p in (0..w * img.height as usize).filter(|&p| inside(p)) {
                    img.data[3 * p..3 * p + 3].copy_from_slice(&behind[3 * p..3 * p + 3]);
                }
                img
            })
            .collect();
        let s = oracle.score(&cams, &holed).unwrap();
        assert!(s.silhouette_iou.unwrap() < 0.7, "{s:?}");
        assert!(s.outline_iou.unwrap() > 0.99, "{s:?}");
        let t = oracle.score(&cams, &renders(&target, &cams)).unwrap();
        assert_eq!(t.outline_iou, Some(1.0));
        // The map shows the lost inner part in red (only the ideal edit sees it), and nothing in blue.
        let count =
            |img: &Image, rgb: [f32; 3]| img.data.chunks_exact(3).filter(|p| *p == rgb).count();
        let map = oracle.silhouette_map(&cams[0], &holed[0]).unwrap();
        assert!(count(&map, [1.0, 0.0, 0.0]) > 100, "no red");
        assert_eq!(count(&map, [0.0, 0.0, 1.0]), 0);
        let ideal = oracle
            .silhouette_map(&cams[0], &renders(&target, &cams[..1])[0])
            .unwrap();
        assert_eq!(
            count(&ideal, [1.0, 0.0, 0.0]) + count(&ideal, [0.0, 0.0, 1.0]),
            0
        );
    }

    #[test]
    fn fill_holes_fills_what_the_border_cannot_reach() {
        #[rustfmt::skip]
        let ring = [
            false, false, false, false, false,
            false, true,  true,  true,  false,
            false, true,  false, true,  false,
            false, true,  true,  false, false,
            false, false, false, false, false,
        ];
        let filled = fill_holes(&ring, 5, 5);
        // The centre is enclosed; the gap at (3, 3) opens the ring's corner to the outside, but the
        // centre's 4-neighbours are all set, so it stays enclosed.
        assert!(filled[12]);
        assert!(!filled[18] && !filled[0]);
        assert_eq!(filled.iter().filter(|&&v| v).count(), 8);
    }

    #[test]
    fn small_misalignment_and_outside_damage_are_told_apart() {
        let gen = GeneratorSettings::default();
        let source = SceneSpec::from_caption("a red striped cylinder", 4, &gen).unwrap();
        let target = source.with_caption("a blue striped cylinder").unwrap();
        let cams = ring_views(&source, 2, 64, 64, 20.0, 0.0);
        let oracle = Oracle::new(&source, &target, OracleSettings::default()).unwrap();
        let moved: Vec<Image> = renders(&target, &cams)
            .iter()
            .map(|i| shifted(i, 1))
            .collect();
        let s = oracle.score(&cams, &moved).unwrap();
        assert!(s.fidelity.unwrap() > 0.9, "{s:?}");
        // Shifting the whole image also moves the floor's tiles: preservation drops but stays finite.
        assert!(s.preservation_psnr < 60.0);
        // Painting the background changes preservation only.
        let mut painted = renders(&target, &cams);
        for img in &mut painted {
            for v in img.data[..64 * 3 * 4].iter_mut() {
                *v = 1.0 - *v;
            }
        }
        let p = oracle.score(&cams, &painted).unwrap();
        assert!(p.fidelity.unwrap() > 0.95);
        assert!(p.preservation_psnr < 30.0, "{}", p.preservation_psnr);
    }

    #[test]
    fn phase_search_accepts_a_shifted_pattern_but_not_the_source() {
        let gen = GeneratorSettings::default();
        let source = SceneSpec::from_caption("a red striped sphere", 8, &gen).unwrap();
        let target = source.with_caption("a red dotted sphere").unwrap();
        let mut elsewhere = target.clone();
        elsewhere.main.pattern.phase[0] += 0.5;
        elsewhere.main.pattern.phase[1] += 0.5;
        let cams = ring_views(&source, 3, 64, 64, 25.0, 0.0);
        let images = renders(&elsewhere, &cams);
        let exact = Oracle::new(&source, &target, OracleSettings::default()).unwrap();
        let searched = Oracle::new(
            &source,
            &target,
            OracleSettings {
                phase_steps: 4,
                ..Default::default()
            },
        )
        .unwrap();
        let e = exact.score(&cams, &images).unwrap().fidelity.unwrap();
        let s = searched.score(&cams, &images).unwrap();
        assert!(
            e < 0.8,
            "exact layout should see the shifted dots as wrong: {e}"
        );
        assert!(s.fidelity.unwrap() > 0.95, "{s:?}");
        assert_eq!(s.phase_offset, [0.5, 0.5]);
        let src = searched.score(&cams, &renders(&source, &cams)).unwrap();
        assert!(src.fidelity.unwrap() < 0.5, "{src:?}");
    }

    #[test]
    fn label_image_and_input_errors() {
        let gen = GeneratorSettings::default();
        let spec = SceneSpec::from_caption("a green cube on a table", 2, &gen).unwrap();
        let built = build_scene(&spec, &BuildSettings::default());
        let cam = &ring_views(&spec, 1, 64, 64, 30.0, 0.0)[0];
        let labels = render_labels(&built, cam);
        let at = |x: usize, y: usize| labels.object[y * 64 + x];
        assert_eq!(at(32, 18), MAIN, "the cube is above the centre");
        assert_eq!(at(32, 48), SUPPORT, "the table below it");
        assert_eq!(at(1, 62), FLOOR);
        assert_eq!(at(1, 1), BACKGROUND);
        assert_eq!(labels.slot[18 * 64 + 32], Slot::First as u8);
        for p in 0..64 * 64 {
            let sum: f32 = labels.object_weights[3 * p..3 * p + 3].iter().sum();
            assert!((sum - labels.alpha[p]).abs() < 1e-3);
        }
        let other = SceneSpec::from_caption("a green cube on a table", 3, &gen).unwrap();
        assert!(Oracle::new(&spec, &other, OracleSettings::default()).is_err());
        let oracle = Oracle::new(
            &spec,
            &spec.with_caption("a red cube on a table").unwrap(),
            OracleSettings::default(),
        )
        .unwrap();
        assert!(oracle.score(std::slice::from_ref(cam), &[]).is_err());
        assert!(oracle
            .score(std::slice::from_ref(cam), &[Image::new(32, 32, 3)])
            .is_err());
        let expected = oracle.expected(cam).unwrap();
        assert_eq!(expected.source, render_view(&built, cam));
    }
}
