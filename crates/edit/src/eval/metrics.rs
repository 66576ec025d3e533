//! Evaluation metrics that need no network weights.
//!
//! - [`multiview_consistency`]: how well a set of per-view images (guidance images of one editing step, or
//!   the final renders) agree with each other on the scene's surface. Each view is warped into its nearest
//!   cameras with the depth rendered from the scene geometry, and the photometric error is measured on the
//!   pixels both cameras see (inside the image, opaque, and not occluded). This is the "cross-view error"
//!   used to compare per-view guidance with VcEdit's consistent guidance.
//! - [`preservation`]: PSNR and SSIM between source and edited renders, optionally restricted to the pixels
//!   outside the editable region (where an edit should change nothing).
//!
//! All images are RGB in [0, 1] (extra channels are ignored); errors are per channel, averaged.

// `!(a > b)` is deliberate: it also rejects NaN. Index loops over 3-element arrays read like the formulas.
#![allow(clippy::neg_cmp_op_on_partial_ord, clippy::needless_range_loop)]

use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use splat::render::Frame;
use splat::train::loss::{ssim_blur, SSIM_C1, SSIM_C2};
use splat::{Camera, Image};

/// PSNR reported for a zero error, so reports stay finite (and JSON-serialisable).
pub const PSNR_CAP_DB: f64 = 100.0;

/// Errors from bad inputs (programming or file mix-ups), each naming the view and the problem.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum MetricsError {
    #[error("metrics: {0}")]
    Mismatch(String),
}

/// PSNR in dB of a mean squared error on [0, 1] data, capped at [`PSNR_CAP_DB`].
pub fn capped_psnr_from_mse(mse: f64) -> f64 {
    if mse.is_nan() {
        return 0.0;
    }
    if mse <= 10f64.powf(-PSNR_CAP_DB / 10.0) {
        PSNR_CAP_DB
    } else {
        splat::train::loss::psnr_from_mse(mse)
    }
}

// ---------------------------------------------------------------------------------------------------------
// Multi-view consistency
// ---------------------------------------------------------------------------------------------------------

/// The scene geometry seen from one camera: its rendered depth and alpha.
#[derive(Clone, Copy, Debug)]
pub struct ViewGeometry<'a> {
    pub camera: &'a Camera,
    /// H*W expected depth Σ z·α·T, as the renderer outputs it (not divided by alpha).
    pub depth: &'a [f32],
    /// H*W accumulated opacity.
    pub alpha: &'a [f32],
}

impl<'a> ViewGeometry<'a> {
    /// The geometry of a render of `camera`.
    pub fn from_render(camera: &'a Camera, render: &'a Frame) -> Self {
        Self {
            camera,
            depth: &render.depth,
            alpha: &render.alpha,
        }
    }
}

/// Options of [`multiview_consistency`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct WarpSettings {
    /// Neighbouring cameras each view is warped into.
    pub neighbours: usize,
    /// A pixel belongs to the surface when its alpha exceeds this (in both views).
    pub alpha_threshold: f32,
    /// Occlusion test: the target view's depth must agree with the warped point's depth within this
    /// fraction of it.
    pub depth_tolerance: f32,
    /// Cameras whose viewing directions differ by more than this (degrees) are never neighbours.
    pub max_angle_deg: f64,
}

impl Default for WarpSettings {
    fn default() -> Self {
        Self {
            neighbours: 3,
            alpha_threshold: 0.5,
            depth_tolerance: 0.03,
            max_angle_deg: 90.0,
        }
    }
}

/// Totals over all evaluated pairs.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ConsistencySummary {
    /// Mean absolute error per channel over all co-visible pixels of all pairs; `None` when no pixel was
    /// co-visible.
    pub mean_abs_error: Option<f64>,
    /// PSNR (dB) of the same pixels' mean squared error, capped at [`PSNR_CAP_DB`].
    pub psnr: Option<f64>,
    /// Directed pairs (view → neighbour) evaluated.
    pub pairs: usize,
    /// Co-visible pixels / opaque source pixels, over all pairs.
    pub covisible_fraction: f64,
    pub covisible_pixels: u64,
}

/// One directed pair: pixels of `from` warped into `to`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PairConsistency {
    pub from: usize,
    pub to: usize,
    pub covisible_pixels: u64,
    pub covisible_fraction: f64,
    pub mean_abs_error: Option<f64>,
}

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ConsistencyReport {
    #[serde(flatten)]
    pub summary: ConsistencySummary,
    pub per_pair: Vec<PairConsistency>,
}

fn forward_axis(c: &Camera) -> [f64; 3] {
    // The camera's z axis in world coordinates is the third row of the world-to-camera rotation.
    c.rotation[2]
}

fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

/// For each camera, up to `k` neighbours, best first. The score adds the centre distance (in units of the
/// median nearest-centre distance, so it does not depend on the scene scale) and 1 − cos of the angle
/// between viewing directions; cameras looking more than `max_angle_deg` away are excluded.
pub fn nearest_cameras(cameras: &[&Camera], k: usize, max_angle_deg: f64) -> Vec<Vec<usize>> {
    let n = cameras.len();
    let centres: Vec<[f64; 3]> = cameras.iter().map(|c| c.center()).collect();
    let dirs: Vec<[f64; 3]> = cameras.iter().map(|c| forward_axis(c)).collect();
    let mut nearest: Vec<f64> = (0..n)
        .filter_map(|i| {
            (0..n)
                .filter(|&j| j != i)
                .map(|j| dist(centres[i], centres[j]))
                .filter(|d| *d > 0.0)
                .min_by(f64::total_cmp)
        })
        .collect();
    nearest.sort_by(f64::total_cmp);
    let scale = nearest.get(nearest.len() / 2).copied().unwrap_or(1.0);
    let scale = if scale > 0.0 && scale.is_finite() {
        scale
    } else {
        1.0
    };
    let min_cos = max_angle_deg.to_radians().cos();
    (0..n)
        .map(|i| {
            let mut cands: Vec<(f64, usize)> = (0..n)
                .filter(|&j| j != i)
                .filter_map(|j| {
                    let cos =
                        dirs[i][0] * dirs[j][0] + dirs[i][1] * dirs[j][1] + dirs[i][2] * dirs[j][2];
                    let score = dist(centres[i], centres[j]) / scale + (1.0 - cos);
                    (cos >= min_cos - 1e-12 && score.is_finite()).then_some((score, j))
                })
                .collect();
            cands.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
            cands.into_iter().take(k).map(|(_, j)| j).collect()
        })
        .collect()
}

/// Sums of one directed pair.
#[derive(Default, Clone, Copy)]
struct PairSums {
    opaque: u64,
    covisible: u64,
    abs: f64,
    sq: f64,
}

/// Warps the opaque pixels of view `from` into view `to` and accumulates the photometric differences on
/// the co-visible ones.
fn warp_pair(
    img_from: &Image,
    from: &ViewGeometry,
    region: Option<&[f32]>,
    img_to: &Image,
    to: &ViewGeometry,
    settings: &WarpSettings,
) -> PairSums {
    let (a, b) = (from.camera, to.camera);
    // X_to = M X_from + o with M = R_b R_aᵀ, o = t_b − M t_a (camera-to-camera transform).
    let mut m = [[0.0f64; 3]; 3];
    for r in 0..3 {
        for c in 0..3 {
            m[r][c] = (0..3).map(|k| b.rotation[r][k] * a.rotation[c][k]).sum();
        }
    }
    let o: [f64; 3] = std::array::from_fn(|r| {
        b.translation[r] - (0..3).map(|c| m[r][c] * a.translation[c]).sum::<f64>()
    });
    let (wa, ha) = (a.width as usize, a.height as usize);
    let (wb, hb) = (b.width as usize, b.height as usize);
    let (ca, cb) = (img_from.channels as usize, img_to.channels as usize);
    let thr = settings.alpha_threshold;
    let tol = settings.depth_tolerance as f64;

    (0..ha)
        .into_par_iter()
        .map(|y| {
            let mut s = PairSums::default();
            let ny = (y as f64 + 0.5 - a.cy) / a.fy;
            for x in 0..wa {
                let p = y * wa + x;
                let alpha = from.alpha[p];
                if !(alpha > thr) || region.is_some_and(|r| !(r[p] >= MASK_THRESHOLD)) {
                    continue;
                }
                let z = from.depth[p] as f64 / alpha as f64;
                if !(z > 0.0) || !z.is_finite() {
                    continue;
                }
                s.opaque += 1;
                let nx = (x as f64 + 0.5 - a.cx) / a.fx;
                let pa = [nx * z, ny * z, z];
                let q: [f64; 3] = std::array::from_fn(|r| {
                    m[r][0] * pa[0] + m[r][1] * pa[1] + m[r][2] * pa[2] + o[r]
                });
                if !(q[2] > 1e-9) {
                    continue;
                }
                let u = b.fx * q[0] / q[2] + b.cx;
                let v = b.fy * q[1] / q[2] + b.cy;
                if !(u >= 0.0 && v >= 0.0 && u < wb as f64 && v < hb as f64) {
                    continue;
                }
                // Bilinear taps around the continuous pixel index (centres at +0.5), clamped at the border.
                let (fx, fy) = ((u - 0.5).max(0.0), (v - 0.5).max(0.0));
                let (x0, y0) = ((fx as usize).min(wb - 1), (fy as usize).min(hb - 1));
                let (x1, y1) = ((x0 + 1).min(wb - 1), (y0 + 1).min(hb - 1));
                let (tx, ty) = (fx - x0 as f64, fy - y0 as f64);
                let taps = [
                    (y0 * wb + x0, (1.0 - tx) * (1.0 - ty)),
                    (y0 * wb + x1, tx * (1.0 - ty)),
                    (y1 * wb + x0, (1.0 - tx) * ty),
                    (y1 * wb + x1, tx * ty),
                ];
                // Every tap that contributes must see the same surface: opaque and at the warped depth.
                let visible = taps.iter().all(|&(i, w)| {
                    if w <= 1e-9 {
                        return true;
                    }
                    let al = to.alpha[i];
                    al > thr && {
                        let d = to.depth[i] as f64 / al as f64;
                        (d - q[2]).abs() <= tol * q[2]
                    }
                });
                if !visible {
                    continue;
                }
                s.covisible += 1;
                let src = &img_from.data[p * ca..p * ca + 3];
                let mut abs = 0.0;
                let mut sq = 0.0;
                for c in 0..3 {
                    let sampled: f64 = taps
                        .iter()
                        .map(|&(i, w)| w * img_to.data[i * cb + c] as f64)
                        .sum();
                    let d = src[c] as f64 - sampled;
                    abs += d.abs();
                    sq += d * d;
                }
                s.abs += abs / 3.0;
                s.sq += sq / 3.0;
            }
            s
        })
        // Rows are summed in order: rayon's `reduce` pairs partial sums as its threads split the work,
        // which differs from run to run on a busy machine, and float sums depend on their order (the same
        // scene scored twice differed in the last bit of its mean error).
        .collect::<Vec<_>>()
        .into_iter()
        .fold(PairSums::default(), |x, y| PairSums {
            opaque: x.opaque + y.opaque,
            covisible: x.covisible + y.covisible,
            abs: x.abs + y.abs,
            sq: x.sq + y.sq,
        })
}

fn check_view(k: usize, image: &Image, g: &ViewGeometry) -> Result<(), MetricsError> {
    let (w, h) = (g.camera.width, g.camera.height);
    let n = (w * h) as usize;
    if image.width != w || image.height != h {
        return Err(MetricsError::Mismatch(format!(
            "view {k}: image is {}x{}, camera {w}x{h}",
            image.width, image.height
        )));
    }
    if image.channels < 3 {
        return Err(MetricsError::Mismatch(format!(
            "view {k}: image has {} channels, need RGB",
            image.channels
        )));
    }
    if g.depth.len() != n || g.alpha.len() != n {
        return Err(MetricsError::Mismatch(format!(
            "view {k}: depth/alpha have {}/{} values, camera has {n} pixels",
            g.depth.len(),
            g.alpha.len()
        )));
    }
    Ok(())
}

/// Multi-view photometric consistency of `images` (one per view) on the surface described by `geometry`
/// (the scene rendered from the same cameras). See the module docs; errors are pooled over all co-visible
/// pixels of all directed pairs.
pub fn multiview_consistency(
    images: &[&Image],
    geometry: &[ViewGeometry],
    settings: &WarpSettings,
) -> Result<ConsistencyReport, MetricsError> {
    consistency_impl(images, geometry, None, settings)
}

/// [`multiview_consistency`] restricted to a region: only pixels whose `regions[view]` value is at least
/// [`MASK_THRESHOLD`] are warped (their partners in the neighbour may lie anywhere). Used to measure the
/// edited part of a scene alone, where per-view editing differs; outside it the local blend keeps the
/// source and the error there is mostly the autoencoder's.
pub fn multiview_consistency_in(
    images: &[&Image],
    geometry: &[ViewGeometry],
    regions: &[&[f32]],
    settings: &WarpSettings,
) -> Result<ConsistencyReport, MetricsError> {
    if regions.len() != geometry.len() {
        return Err(MetricsError::Mismatch(format!(
            "{} regions for {} views",
            regions.len(),
            geometry.len()
        )));
    }
    for (k, (r, g)) in regions.iter().zip(geometry).enumerate() {
        if r.len() != g.alpha.len() {
            return Err(MetricsError::Mismatch(format!(
                "view {k}: region has {} values, camera has {} pixels",
                r.len(),
                g.alpha.len()
            )));
        }
    }
    consistency_impl(images, geometry, Some(regions), settings)
}

fn consistency_impl(
    images: &[&Image],
    geometry: &[ViewGeometry],
    regions: Option<&[&[f32]]>,
    settings: &WarpSettings,
) -> Result<ConsistencyReport, MetricsError> {
    if images.len() != geometry.len() {
        return Err(MetricsError::Mismatch(format!(
            "{} images for {} views",
            images.len(),
            geometry.len()
        )));
    }
    for (k, (img, g)) in images.iter().zip(geometry).enumerate() {
        check_view(k, img, g)?;
    }
    let cams: Vec<&Camera> = geometry.iter().map(|g| g.camera).collect();
    let neighbours = nearest_cameras(&cams, settings.neighbours, settings.max_angle_deg);
    let pairs: Vec<(usize, usize)> = neighbours
        .iter()
        .enumerate()
        .flat_map(|(i, ns)| ns.iter().map(move |&j| (i, j)))
        .collect();
    let sums: Vec<PairSums> = pairs
        .iter()
        .map(|&(i, j)| {
            let region = regions.map(|r| r[i]);
            warp_pair(
                images[i],
                &geometry[i],
                region,
                images[j],
                &geometry[j],
                settings,
            )
        })
        .collect();
    let mut total = PairSums::default();
    let mut per_pair = Vec::with_capacity(pairs.len());
    for (&(from, to), s) in pairs.iter().zip(&sums) {
        total.opaque += s.opaque;
        total.covisible += s.covisible;
        total.abs += s.abs;
        total.sq += s.sq;
        per_pair.push(PairConsistency {
            from,
            to,
            covisible_pixels: s.covisible,
            covisible_fraction: ratio(s.covisible, s.opaque),
            mean_abs_error: (s.covisible > 0).then(|| s.abs / s.covisible as f64),
        });
    }
    let n = total.covisible as f64;
    Ok(ConsistencyReport {
        summary: ConsistencySummary {
            mean_abs_error: (total.covisible > 0).then(|| total.abs / n),
            psnr: (total.covisible > 0).then(|| capped_psnr_from_mse(total.sq / n)),
            pairs: pairs.len(),
            covisible_fraction: ratio(total.covisible, total.opaque),
            covisible_pixels: total.covisible,
        },
        per_pair,
    })
}

fn ratio(a: u64, b: u64) -> f64 {
    if b == 0 {
        0.0
    } else {
        a as f64 / b as f64
    }
}

/// Consistency of renders of a scene with themselves (images = the renders' colours, geometry = their
/// depth and alpha): what the final renders of an edited scene are measured with.
pub fn render_consistency(
    cameras: &[Camera],
    renders: &[Frame],
    settings: &WarpSettings,
) -> Result<ConsistencyReport, MetricsError> {
    if cameras.len() != renders.len() {
        return Err(MetricsError::Mismatch(format!(
            "{} renders for {} cameras",
            renders.len(),
            cameras.len()
        )));
    }
    let images: Vec<Image> = renders.iter().map(|r| r.rgb_image()).collect();
    let geometry: Vec<ViewGeometry> = cameras
        .iter()
        .zip(renders)
        .map(|(c, r)| ViewGeometry::from_render(c, r))
        .collect();
    multiview_consistency(&images.iter().collect::<Vec<_>>(), &geometry, settings)
}

// ---------------------------------------------------------------------------------------------------------
// Preservation (PSNR / SSIM, optionally outside a mask)
// ---------------------------------------------------------------------------------------------------------

/// A mask value at or above this marks an editable pixel; below it the pixel is "outside".
pub const MASK_THRESHOLD: f32 = 0.5;

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PreservationReport {
    /// PSNR (dB) of the mean squared error over the evaluated pixels of all views (capped at
    /// [`PSNR_CAP_DB`]); `None` when no pixel is evaluated (everything editable).
    pub psnr: Option<f64>,
    /// Mean SSIM over the evaluated pixels of all views; `None` likewise.
    pub ssim: Option<f64>,
    /// Evaluated pixels (per view, not per channel), all views together.
    pub pixels: u64,
    /// Evaluated pixels / all pixels.
    pub fraction: f64,
    pub views: usize,
}

/// Per view: (squared-error sum over channels, SSIM sum over channels, evaluated pixels).
fn preservation_view(a: &Image, b: &Image, outside: &[bool]) -> (f64, f64, u64) {
    let (w, h) = (a.width as usize, a.height as usize);
    let n = w * h;
    let (ca, cb) = (a.channels as usize, b.channels as usize);
    let count = outside.iter().filter(|&&o| o).count() as u64;
    if count == 0 {
        return (0.0, 0.0, 0);
    }
    let m: Vec<f64> = outside.iter().map(|&o| if o { 1.0 } else { 0.0 }).collect();
    let wsum = ssim_blur(&m, w, h);
    let (mut sq, mut ssim) = (0.0, 0.0);
    for c in 0..3 {
        let x: Vec<f64> = (0..n).map(|i| a.data[i * ca + c] as f64).collect();
        let y: Vec<f64> = (0..n).map(|i| b.data[i * cb + c] as f64).collect();
        // Window statistics restricted to outside pixels: blur(m·f) / blur(m).
        let maps: Vec<Vec<f64>> = [
            (0..n).map(|i| m[i] * x[i]).collect::<Vec<f64>>(),
            (0..n).map(|i| m[i] * y[i]).collect(),
            (0..n).map(|i| m[i] * x[i] * x[i]).collect(),
            (0..n).map(|i| m[i] * y[i] * y[i]).collect(),
            (0..n).map(|i| m[i] * x[i] * y[i]).collect(),
        ]
        .iter()
        .map(|map| ssim_blur(map, w, h))
        .collect();
        for i in 0..n {
            if !outside[i] {
                continue;
            }
            let d = x[i] - y[i];
            sq += d * d;
            let ws = wsum[i];
            let (mx, my) = (maps[0][i] / ws, maps[1][i] / ws);
            let vx = maps[2][i] / ws - mx * mx;
            let vy = maps[3][i] / ws - my * my;
            let cxy = maps[4][i] / ws - mx * my;
            ssim += ((2.0 * mx * my + SSIM_C1) * (2.0 * cxy + SSIM_C2))
                / ((mx * mx + my * my + SSIM_C1) * (vx + vy + SSIM_C2));
        }
    }
    (sq, ssim, count)
}

/// Checks that `source` and `edited` pair up view by view (equal sizes, RGB) with one mask per view when
/// given; returns the pixels of all views.
fn check_pairs(
    source: &[&Image],
    edited: &[&Image],
    edit_mask: Option<&[&[f32]]>,
) -> Result<u64, MetricsError> {
    if source.len() != edited.len() {
        return Err(MetricsError::Mismatch(format!(
            "{} source images vs {} edited images",
            source.len(),
            edited.len()
        )));
    }
    if let Some(m) = edit_mask {
        if m.len() != source.len() {
            return Err(MetricsError::Mismatch(format!(
                "{} masks for {} views",
                m.len(),
                source.len()
            )));
        }
    }
    let mut total_pixels = 0u64;
    for (k, (a, b)) in source.iter().zip(edited).enumerate() {
        if (a.width, a.height) != (b.width, b.height) || a.channels < 3 || b.channels < 3 {
            return Err(MetricsError::Mismatch(format!(
                "view {k}: source {}x{}x{} vs edited {}x{}x{} (need equal sizes, RGB)",
                a.width, a.height, a.channels, b.width, b.height, b.channels
            )));
        }
        let n = (a.width * a.height) as usize;
        if let Some(m) = edit_mask {
            if m[k].len() != n {
                return Err(MetricsError::Mismatch(format!(
                    "view {k}: mask has {} values for {n} pixels",
                    m[k].len()
                )));
            }
        }
        total_pixels += n as u64;
    }
    Ok(total_pixels)
}

/// A pixel whose colour moved by more than this (on a 0–1 scale, in any channel) counts as changed.
pub const CHANGE_TOLERANCE: f32 = 0.1;

/// How much an edit changed where it may act: the fraction of pixels (inside the mask, or of whole images
/// without one) whose colour moved by more than [`CHANGE_TOLERANCE`] in some channel, over all views.
/// A fit's noise moves pixels by a few hundredths; an edit moves its region by tenths. `None` when no
/// pixel is inside the mask.
pub fn changed_fraction(
    source: &[&Image],
    edited: &[&Image],
    edit_mask: Option<&[&[f32]]>,
) -> Result<Option<f64>, MetricsError> {
    check_pairs(source, edited, edit_mask)?;
    let (changed, counted) = (0..source.len())
        .into_par_iter()
        .map(|k| {
            let (a, b) = (source[k], edited[k]);
            let (ca, cb) = (a.channels as usize, b.channels as usize);
            let n = (a.width * a.height) as usize;
            let mut out = (0u64, 0u64);
            for p in 0..n {
                // NaN counts as editable, as in `preservation`.
                if edit_mask.is_some_and(|m| m[k][p] < MASK_THRESHOLD) {
                    continue;
                }
                out.1 += 1;
                let moved = (0..3)
                    .any(|c| (a.data[p * ca + c] - b.data[p * cb + c]).abs() > CHANGE_TOLERANCE);
                out.0 += u64::from(moved);
            }
            out
        })
        .reduce(|| (0, 0), |x, y| (x.0 + y.0, x.1 + y.1));
    Ok((counted > 0).then(|| changed as f64 / counted as f64))
}

/// PSNR and SSIM (11-tap Gaussian window, σ = 1.5, C1 = 0.01², C2 = 0.03²) of `edited` against `source`,
/// per view. With `edit_mask` (per view H*W, e.g. the editable mask rendered as an extra channel), only
/// pixels whose mask value is below [`MASK_THRESHOLD`] count, and the SSIM window statistics use only those
/// pixels (weights renormalised), so changes inside the editable region do not leak into the score. The
/// same renormalisation applies at the image border (instead of zero padding); away from borders and
/// masks this is the standard SSIM.
pub fn preservation(
    source: &[&Image],
    edited: &[&Image],
    edit_mask: Option<&[&[f32]]>,
) -> Result<PreservationReport, MetricsError> {
    let total_pixels = check_pairs(source, edited, edit_mask)?;
    let per_view: Vec<(f64, f64, u64)> = (0..source.len())
        .into_par_iter()
        .map(|k| {
            let n = (source[k].width * source[k].height) as usize;
            let outside: Vec<bool> = match edit_mask {
                // NaN counts as editable: never score pixels we know nothing about.
                Some(m) => m[k].iter().map(|&v| v < MASK_THRESHOLD).collect(),
                None => vec![true; n],
            };
            preservation_view(source[k], edited[k], &outside)
        })
        .collect();
    let pixels: u64 = per_view.iter().map(|v| v.2).sum();
    let sq: f64 = per_view.iter().map(|v| v.0).sum();
    let ssim: f64 = per_view.iter().map(|v| v.1).sum();
    let samples = 3.0 * pixels as f64;
    Ok(PreservationReport {
        psnr: (pixels > 0).then(|| capped_psnr_from_mse(sq / samples)),
        ssim: (pixels > 0).then(|| ssim / samples),
        pixels,
        fraction: ratio(pixels, total_pixels),
        views: source.len(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn changed_fraction_counts_pixels_that_moved_where_the_edit_may_act() {
        let grey = Image::from_data(4, 2, 3, vec![0.5; 24]);
        let mut edited = grey.clone();
        // Pixel 0 recoloured, pixel 1 nudged by less than the tolerance.
        edited.data[0] = 0.9;
        edited.data[3] = 0.55;
        let f = changed_fraction(&[&grey], &[&edited], None).unwrap();
        assert_eq!(f, Some(1.0 / 8.0));
        // Inside a mask of pixels 0 and 1 only: one of two changed.
        let mask = [1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        let f = changed_fraction(&[&grey], &[&edited], Some(&[&mask[..]])).unwrap();
        assert_eq!(f, Some(0.5));
        // An empty mask evaluates nothing; mismatched views are an error.
        assert_eq!(
            changed_fraction(&[&grey], &[&edited], Some(&[&[0.0; 8][..]])).unwrap(),
            None
        );
        assert!(changed_fraction(&[&grey], &[], None).is_err());
    }
    use splat::cameras::orbit::look_at;

    /// A smooth texture on the plane z = 0, values in [0.2, 0.8].
    fn texture(x: f64, y: f64) -> [f32; 3] {
        [
            (0.5 + 0.3 * (1.3 * x).sin() * (0.7 * y).cos()) as f32,
            (0.5 + 0.3 * (0.9 * x + 0.4 * y).cos()) as f32,
            (0.5 + 0.3 * (1.1 * y).sin()) as f32,
        ]
    }

    /// Image, depth and alpha of the textured square |x|, |y| ≤ `half` on z = 0 seen by `cam`, computed
    /// analytically per pixel centre; `occluder` optionally paints a nearer, differently coloured patch
    /// over the pixels whose plane point has x > occluder.0 (depth scaled by occluder.1).
    fn view_of_plane(
        cam: &Camera,
        half: f64,
        occluder: Option<(f64, f64)>,
    ) -> (Image, Vec<f32>, Vec<f32>) {
        let (w, h) = (cam.width as usize, cam.height as usize);
        let mut img = Image::new(cam.width, cam.height, 3);
        let mut depth = vec![0.0f32; w * h];
        let mut alpha = vec![0.0f32; w * h];
        let c = cam.center();
        for py in 0..h {
            for px in 0..w {
                // Ray direction in world: Rᵀ (normalised camera ray).
                let d_cam = [
                    (px as f64 + 0.5 - cam.cx) / cam.fx,
                    (py as f64 + 0.5 - cam.cy) / cam.fy,
                    1.0,
                ];
                let r = &cam.rotation;
                let d: [f64; 3] = std::array::from_fn(|a| {
                    r[0][a] * d_cam[0] + r[1][a] * d_cam[1] + r[2][a] * d_cam[2]
                });
                if d[2].abs() < 1e-12 {
                    continue;
                }
                let s = -c[2] / d[2]; // camera z of the hit, since d_cam.z = 1
                if s <= 0.0 {
                    continue;
                }
                let (x, y) = (c[0] + s * d[0], c[1] + s * d[1]);
                if x.abs() > half || y.abs() > half {
                    continue;
                }
                let i = py * w + px;
                let mut col = texture(x, y);
                let mut z = s;
                if let Some((x0, f)) = occluder {
                    if x > x0 {
                        col = [1.0, 0.0, 1.0];
                        z *= f;
                    }
                }
                img.data[3 * i..3 * i + 3].copy_from_slice(&col);
                depth[i] = z as f32;
                alpha[i] = 1.0;
            }
        }
        (img, depth, alpha)
    }

    fn two_cameras(size: u32) -> Vec<Camera> {
        let up = [0.0, 1.0, 0.0];
        vec![
            look_at(
                "a".into(),
                [-0.6, 0.2, 4.0],
                [0.0, 0.0, 0.0],
                up,
                size,
                size,
                size as f64,
            ),
            look_at(
                "b".into(),
                [0.7, -0.1, 3.6],
                [0.1, 0.0, 0.0],
                up,
                size,
                size,
                size as f64 * 0.9,
            ),
        ]
    }

    fn consistency_of(views: &[(Image, Vec<f32>, Vec<f32>)], cams: &[Camera]) -> ConsistencyReport {
        let geometry: Vec<ViewGeometry> = views
            .iter()
            .zip(cams)
            .map(|((_, d, a), c)| ViewGeometry {
                camera: c,
                depth: d,
                alpha: a,
            })
            .collect();
        let images: Vec<&Image> = views.iter().map(|v| &v.0).collect();
        multiview_consistency(&images, &geometry, &WarpSettings::default()).unwrap()
    }

    #[test]
    fn plane_seen_twice_is_consistent_and_a_brightened_view_reads_its_offset() {
        let cams = two_cameras(96);
        let views: Vec<_> = cams.iter().map(|c| view_of_plane(c, 1.5, None)).collect();
        let r = consistency_of(&views, &cams);
        assert_eq!(r.summary.pairs, 2);
        let base = r.summary.mean_abs_error.unwrap();
        assert!(base < 2e-3, "identical surface colours: error {base}");
        assert!(r.summary.covisible_fraction > 0.5, "{:?}", r.summary);

        let mut bright = views.clone();
        for v in &mut bright[1].0.data {
            *v += 0.1;
        }
        let r = consistency_of(&bright, &cams);
        let e = r.summary.mean_abs_error.unwrap();
        assert!((e - 0.1).abs() < 2e-3, "brightened by 0.1: error {e}");
        // Mean squared error is 0.01 up to resampling: 20 dB.
        assert!((r.summary.psnr.unwrap() - 20.0).abs() < 0.2);
        for p in &r.per_pair {
            assert!((p.mean_abs_error.unwrap() - 0.1).abs() < 2e-3);
        }
    }

    #[test]
    fn a_region_limits_the_warped_pixels() {
        let cams = two_cameras(96);
        let mut views: Vec<_> = cams.iter().map(|c| view_of_plane(c, 1.5, None)).collect();
        for v in &mut views[1].0.data {
            *v += 0.1;
        }
        let geometry: Vec<ViewGeometry> = views
            .iter()
            .zip(&cams)
            .map(|((_, d, a), c)| ViewGeometry {
                camera: c,
                depth: d,
                alpha: a,
            })
            .collect();
        let images: Vec<&Image> = views.iter().map(|v| &v.0).collect();
        let settings = WarpSettings::default();
        let all = multiview_consistency(&images, &geometry, &settings).unwrap();
        let n = 96 * 96;
        let (ones, zeros) = (vec![1.0f32; n], vec![0.0f32; n]);
        // A region covering everything changes nothing.
        let full =
            multiview_consistency_in(&images, &geometry, &[&ones, &ones], &settings).unwrap();
        assert_eq!(full, all);
        // Excluding view a's pixels leaves only the pair b → a, with the same error.
        let only_b =
            multiview_consistency_in(&images, &geometry, &[&zeros, &ones], &settings).unwrap();
        let b_to_a = all.per_pair.iter().find(|p| p.from == 1).unwrap();
        assert_eq!(only_b.summary.covisible_pixels, b_to_a.covisible_pixels);
        assert!((only_b.summary.mean_abs_error.unwrap() - 0.1).abs() < 2e-3);
        // Regions must match the views.
        assert!(multiview_consistency_in(&images, &geometry, &[&ones], &settings).is_err());
        assert!(
            multiview_consistency_in(&images, &geometry, &[&ones, &ones[..10]], &settings).is_err()
        );
    }

    #[test]
    fn occluded_pixels_are_not_compared() {
        let cams = two_cameras(96);
        let clean: Vec<_> = cams.iter().map(|c| view_of_plane(c, 1.5, None)).collect();
        let base = consistency_of(&clean, &cams);
        // View b sees a magenta occluder 30 % nearer over part of the plane: those pixels of a must not
        // be compared (wrong colour), so the error stays ~0 and fewer pixels are co-visible.
        let mut views = clean.clone();
        views[1] = view_of_plane(&cams[1], 1.5, Some((0.2, 0.7)));
        let r = consistency_of(&views, &cams);
        let a_to_b = r.per_pair.iter().find(|p| p.from == 0).unwrap();
        let base_a_to_b = base.per_pair.iter().find(|p| p.from == 0).unwrap();
        assert!(a_to_b.covisible_pixels < base_a_to_b.covisible_pixels * 3 / 4);
        assert!(a_to_b.mean_abs_error.unwrap() < 2e-3, "{a_to_b:?}");
        // Without the occlusion test the magenta would dominate.
        let loose = WarpSettings {
            depth_tolerance: 1.0,
            ..Default::default()
        };
        let geometry: Vec<ViewGeometry> = views
            .iter()
            .zip(&cams)
            .map(|((_, d, a), c)| ViewGeometry {
                camera: c,
                depth: d,
                alpha: a,
            })
            .collect();
        let images: Vec<&Image> = views.iter().map(|v| &v.0).collect();
        let r = multiview_consistency(&images, &geometry, &loose).unwrap();
        assert!(r.summary.mean_abs_error.unwrap() > 0.05);
    }

    #[test]
    fn nothing_covisible_gives_none() {
        let cams = two_cameras(16);
        let n = 16 * 16;
        let empty = vec![0.0f32; n];
        let img = Image::new(16, 16, 3);
        let geometry: Vec<ViewGeometry> = cams
            .iter()
            .map(|c| ViewGeometry {
                camera: c,
                depth: &empty,
                alpha: &empty,
            })
            .collect();
        let r = multiview_consistency(&[&img, &img], &geometry, &WarpSettings::default()).unwrap();
        assert_eq!(r.summary.mean_abs_error, None);
        assert_eq!(r.summary.psnr, None);
        assert_eq!(r.summary.covisible_fraction, 0.0);
        // Mismatched inputs are errors, not panics.
        let small = Image::new(8, 8, 3);
        assert!(
            multiview_consistency(&[&small, &img], &geometry, &WarpSettings::default()).is_err()
        );
        assert!(multiview_consistency(&[&img], &geometry, &WarpSettings::default()).is_err());
    }

    #[test]
    fn neighbours_follow_distance_and_direction() {
        // Eight cameras on a circle looking at the origin, plus one far away looking away.
        let up = [0.0, 1.0, 0.0];
        let mut cams: Vec<Camera> = (0..8)
            .map(|i| {
                let t = i as f64 * std::f64::consts::TAU / 8.0;
                look_at(
                    format!("{i}"),
                    [3.0 * t.cos(), 0.0, 3.0 * t.sin()],
                    [0.0; 3],
                    up,
                    8,
                    8,
                    8.0,
                )
            })
            .collect();
        cams.push(look_at(
            "away".into(),
            [3.2, 0.0, 0.2],
            [10.0, 0.0, 0.2],
            up,
            8,
            8,
            8.0,
        ));
        let refs: Vec<&Camera> = cams.iter().collect();
        let nn = nearest_cameras(&refs, 2, 90.0);
        let mut first: Vec<usize> = nn[0].clone();
        first.sort();
        assert_eq!(first, vec![1, 7]);
        let mut fourth = nn[4].clone();
        fourth.sort();
        assert_eq!(fourth, vec![3, 5]);
        // Camera 8 sits next to camera 0 but looks the other way: excluded.
        assert!(!nn[0].contains(&8));
        // It pairs with far-side cameras looking its way, never with its opposite-facing neighbours.
        assert!(nn[8].iter().all(|j| ![0, 1, 7].contains(j)), "{:?}", nn[8]);
        // Within 40° only camera 4 looks the same way.
        assert_eq!(nearest_cameras(&refs, 2, 40.0)[8], vec![4]);
    }

    fn noise_image(w: u32, h: u32, seed: u32) -> Image {
        let mut img = Image::new(w, h, 3);
        let mut s = seed.wrapping_mul(2654435761).wrapping_add(1);
        for v in &mut img.data {
            s ^= s << 13;
            s ^= s >> 17;
            s ^= s << 5;
            *v = 0.2 + 0.6 * (s % 1000) as f32 / 1000.0;
        }
        img
    }

    #[test]
    fn psnr_of_a_constant_offset_and_identity() {
        let a = noise_image(20, 14, 1);
        let mut b = a.clone();
        for v in &mut b.data {
            *v += 0.1;
        }
        let r = preservation(&[&a], &[&b], None).unwrap();
        assert!((r.psnr.unwrap() - 20.0).abs() < 1e-4);
        assert_eq!(r.pixels, 20 * 14);
        assert_eq!(r.fraction, 1.0);
        let same = preservation(&[&a, &b], &[&a, &b], None).unwrap();
        assert_eq!(same.psnr, Some(PSNR_CAP_DB));
        assert!((same.ssim.unwrap() - 1.0).abs() < 1e-12);
    }

    /// SSIM at pixel (x, y) straight from the definition: Gaussian-weighted statistics over the in-image
    /// part of the 11x11 window, renormalised.
    fn direct_ssim(a: &Image, b: &Image, x: usize, y: usize, c: usize) -> f64 {
        let (w, h) = (a.width as usize, a.height as usize);
        let g = splat::train::loss::ssim_window();
        let (mut sw, mut mx, mut my, mut xx, mut yy, mut xy) = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
        for dy in 0..11 {
            for dx in 0..11 {
                let (sx, sy) = (x as i64 + dx as i64 - 5, y as i64 + dy as i64 - 5);
                if sx < 0 || sy < 0 || sx >= w as i64 || sy >= h as i64 {
                    continue;
                }
                let wt = g[dx] * g[dy];
                let i = (sy as usize * w + sx as usize) * 3 + c;
                let (p, q) = (a.data[i] as f64, b.data[i] as f64);
                sw += wt;
                mx += wt * p;
                my += wt * q;
                xx += wt * p * p;
                yy += wt * q * q;
                xy += wt * p * q;
            }
        }
        let (mx, my) = (mx / sw, my / sw);
        let (vx, vy, cxy) = (xx / sw - mx * mx, yy / sw - my * my, xy / sw - mx * my);
        ((2.0 * mx * my + SSIM_C1) * (2.0 * cxy + SSIM_C2))
            / ((mx * mx + my * my + SSIM_C1) * (vx + vy + SSIM_C2))
    }

    /// The preservation SSIM's window statistics are splat's SSIM blur; they must stay, bit for bit, the
    /// direct zero-padded window sums this module computed before it used splat's.
    #[test]
    fn ssim_blur_is_the_direct_window_sum_bit_for_bit() {
        let g = splat::train::loss::ssim_window();
        let direct = |map: &[f64], w: usize, h: usize| -> Vec<f64> {
            let r = g.len() / 2;
            let mut tmp = vec![0.0; w * h];
            for y in 0..h {
                for x in 0..w {
                    let (lo, hi) = (x.saturating_sub(r), (x + r).min(w - 1));
                    tmp[y * w + x] = (lo..=hi).map(|k| g[k + r - x] * map[y * w + k]).sum();
                }
            }
            let mut out = vec![0.0; w * h];
            for y in 0..h {
                let (lo, hi) = (y.saturating_sub(r), (y + r).min(h - 1));
                for x in 0..w {
                    out[y * w + x] = (lo..=hi).map(|k| g[k + r - y] * tmp[k * w + x]).sum();
                }
            }
            out
        };
        for (w, h, seed) in [(23, 17, 1), (7, 30, 2), (64, 5, 3), (1, 1, 4)] {
            let img = noise_image(w, h, seed);
            let (w, h) = (w as usize, h as usize);
            // Masked products as preservation forms them (zeros outside).
            let map: Vec<f64> = (0..w * h)
                .map(|i| {
                    let v = img.data[3 * i] as f64 * img.data[3 * i + 1] as f64;
                    if i % 5 == 0 {
                        0.0
                    } else {
                        v
                    }
                })
                .collect();
            assert_eq!(ssim_blur(&map, w, h), direct(&map, w, h), "{w}x{h}");
        }
    }

    #[test]
    fn ssim_matches_the_definition() {
        let a = noise_image(23, 17, 2);
        let mut b = noise_image(23, 17, 3);
        for (p, q) in b.data.iter_mut().zip(&a.data) {
            *p = 0.7 * q + 0.3 * *p;
        }
        let r = preservation(&[&a], &[&b], None).unwrap();
        let mut sum = 0.0;
        for y in 0..17 {
            for x in 0..23 {
                for c in 0..3 {
                    sum += direct_ssim(&a, &b, x, y, c);
                }
            }
        }
        let want = sum / (23.0 * 17.0 * 3.0);
        assert!(
            (r.ssim.unwrap() - want).abs() < 1e-9,
            "{} vs {want}",
            r.ssim.unwrap()
        );
        assert!(want > 0.3 && want < 0.99);
    }

    #[test]
    fn changes_inside_the_mask_do_not_count() {
        let a = noise_image(30, 20, 4);
        let mut b = a.clone();
        let mut mask = vec![0.0f32; 30 * 20];
        for y in 5..15 {
            for x in 8..20 {
                mask[y * 30 + x] = 0.9;
                for c in 0..3 {
                    b.data[(y * 30 + x) * 3 + c] = 1.0 - b.data[(y * 30 + x) * 3 + c];
                }
            }
        }
        let masked = preservation(&[&a], &[&b], Some(&[&mask])).unwrap();
        assert_eq!(masked.psnr, Some(PSNR_CAP_DB));
        assert!((masked.ssim.unwrap() - 1.0).abs() < 1e-12);
        assert_eq!(masked.pixels, 30 * 20 - 10 * 12);
        let whole = preservation(&[&a], &[&b], None).unwrap();
        assert!(whole.psnr.unwrap() < 20.0 && whole.ssim.unwrap() < 0.9);
        // A change outside the mask is seen.
        let mut c = b.clone();
        c.data[0] += 0.5;
        let r = preservation(&[&a], &[&c], Some(&[&mask])).unwrap();
        assert!(r.psnr.unwrap() < 40.0 && r.ssim.unwrap() < 1.0);
    }

    #[test]
    fn everything_editable_reports_none() {
        let a = noise_image(8, 8, 5);
        let mask = vec![1.0f32; 64];
        let r = preservation(&[&a], &[&a], Some(&[&mask])).unwrap();
        assert_eq!((r.psnr, r.ssim, r.pixels), (None, None, 0));
        let nan = vec![f32::NAN; 64];
        assert_eq!(preservation(&[&a], &[&a], Some(&[&nan])).unwrap().pixels, 0);
        let short = vec![0.0f32; 10];
        assert!(preservation(&[&a], &[&a], Some(&[&short])).is_err());
        assert!(preservation(&[&a], &[], None).is_err());
    }
}
