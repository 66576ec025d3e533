//! The files an edit writes: per iteration the source renders, the guidance images and (first iteration)
//! the per-word attention maps; at the end the edited scene, before/after renders, mask images, a
//! turntable GIF, metrics, `run.json` and `report.html`.

use std::path::{Path, PathBuf};

use serde::Serialize;
use splat::render::{render, Frame, RenderSettings};
use splat::{Camera, GaussianScene, Image};

use crate::eval::metrics::{self, MetricsError, WarpSettings};
use crate::ledger::WorkLedger;
use crate::present::gif::{write_gif, GifOptions};
use crate::present::report::{
    self, IterationInfo, MetricsSummary, ReportData, ReportOptions, StageTiming, ViewPair,
    WordImage,
};
use crate::present::viewer::{self, InitialView, ViewerOptions, ViewerScene};
use crate::present::viz;
use crate::sampler::{EditPlan, ViewState};

use super::estimate::Estimate;
use super::job::{io_err, EditJob, EditResult, IterationTimes, Progress, RunError};
use super::masks::render_mask;
use super::shape::ShapeDecision;

/// Where the main outputs went.
pub struct Written {
    pub scene: PathBuf,
    pub report: PathBuf,
    pub metrics: MetricsSummary,
}

/// Describes the inputs for the report and run.json.
pub struct RunInputs<'a> {
    pub scene: &'a str,
    pub cameras: &'a str,
    pub model: &'a str,
    pub loss: String,
    pub notes: Vec<String>,
    /// The time estimate printed before the run, if one was made (kept beside the measured timings).
    pub estimate: Option<Estimate>,
}

fn metrics_err(e: MetricsError) -> RunError {
    RunError::Input(e.to_string())
}

/// The folder of iteration `iteration`'s images (counted from 0).
pub(super) fn iteration_dir_name(iteration: usize) -> String {
    format!("iter_{iteration}")
}

/// Path of a guidance image.
fn guidance_path(out: &Path, iteration: usize, view: usize) -> PathBuf {
    out.join(iteration_dir_name(iteration))
        .join("guidance")
        .join(format!("view_{view:03}.png"))
}

/// Path of a source render (what the iteration edited).
fn source_path(out: &Path, iteration: usize, view: usize) -> PathBuf {
    out.join(iteration_dir_name(iteration))
        .join("source")
        .join(format!("view_{view:03}.png"))
}

/// Writes one iteration's source renders and guidance images.
pub(super) fn write_iteration(
    out: &Path,
    iteration: usize,
    sources: &[Image],
    guidance: &[Image],
) -> Result<(), RunError> {
    for (v, (source, img)) in sources.iter().zip(guidance).enumerate() {
        let p = guidance_path(out, iteration, v);
        img.save_png(&p)?;
        let p = source_path(out, iteration, v);
        source.save_png(&p)?;
    }
    Ok(())
}

/// The guidance images of the first `iterations` iterations, read back (a resumed run reports them too).
pub(super) fn read_guidance(
    out: &Path,
    iterations: usize,
    views: usize,
) -> Result<Vec<Vec<Image>>, RunError> {
    (0..iterations)
        .map(|k| {
            (0..views)
                .map(|v| {
                    let p = guidance_path(out, k, v);
                    Image::load(&p).map_err(|e| io_err(&p, e))
                })
                .collect()
        })
        .collect()
}

/// Writes the per-word attention heat maps of `view` (edited with `plan`) at `size` (width, height) under
/// `out/attention/`; returns (word, file name) per word.
pub(super) fn write_word_maps(
    out: &Path,
    plan: &EditPlan,
    view: &ViewState,
    size: (u32, u32),
) -> Result<Vec<(String, String)>, RunError> {
    let (w, h) = size;
    let maps = viz::word_maps(
        &view.controller.blend_store()?,
        plan.blend_size,
        &plan.target_tokens,
        (h as usize, w as usize),
    )?;
    let mut listing = Vec::with_capacity(maps.len());
    for (i, m) in maps.iter().enumerate() {
        let file = format!("attn_{i:02}_{}.png", viz::file_safe(&m.word));
        let p = out.join("attention").join(&file);
        viz::heat_image(&m.map, w, h).save_png(&p)?;
        listing.push((m.word.clone(), file));
    }
    Ok(listing)
}

fn rel(out: &Path, p: &Path) -> PathBuf {
    p.strip_prefix(out)
        .map(Path::to_path_buf)
        .unwrap_or_else(|_| p.to_path_buf())
}

/// Side-by-side frame: `a` | `b`.
fn side_by_side(a: &Image, b: &Image) -> Image {
    let (w, h) = (a.width as usize, a.height as usize);
    let mut data = Vec::with_capacity(2 * w * h * 3);
    for y in 0..h {
        data.extend_from_slice(&a.data[y * w * 3..(y + 1) * w * 3]);
        data.extend_from_slice(&b.data[y * w * 3..(y + 1) * w * 3]);
    }
    Image::from_data(2 * w as u32, h as u32, 3, data)
}

/// Writes the outputs of a finished run into `out` and returns the main paths.
pub fn write_outputs(
    out: &Path,
    job: &EditJob,
    inputs: &RunInputs<'_>,
    source: &GaussianScene,
    cameras: &[Camera],
    result: &EditResult,
    progress: &mut dyn Progress,
) -> Result<Written, RunError> {
    let cams: Vec<Camera> = result.views.iter().map(|&i| cameras[i].clone()).collect();
    let settings = RenderSettings {
        background: job.background,
    };

    progress.stage("writing outputs", (2 * cams.len() + 24) as u64);
    let scene_path = out.join("edited.ply");
    splat::ply::write_ply(&scene_path, &result.scene).map_err(|e| io_err(&scene_path, e))?;

    // Before/after renders (with depth and alpha for the metrics).
    let before: Vec<Frame> = cams
        .iter()
        .map(|c| render(source, c, &settings, None).into_frame())
        .collect();
    let after: Vec<Frame> = cams
        .iter()
        .map(|c| render(&result.scene, c, &settings, None).into_frame())
        .collect();
    let mut pairs = Vec::new();
    for (v, (b, a)) in before.iter().zip(&after).enumerate() {
        let pb = out.join("before").join(format!("view_{v:03}.png"));
        let pa = out.join("after").join(format!("view_{v:03}.png"));
        b.rgb_image().save_png(&pb)?;
        a.rgb_image().save_png(&pa)?;
        pairs.push(ViewPair {
            name: cams[v].name.clone(),
            before: rel(out, &pb),
            after: rel(out, &pa),
        });
        progress.advance(2);
    }

    // The editable mask as images (white = editable).
    let mut mask_paths = Vec::new();
    let mut mask_maps = Vec::new();
    if let Some(mask) = &result.mask {
        for (v, c) in cams.iter().enumerate() {
            let m = render_mask(source, mask, c);
            let p = out.join("mask").join(format!("view_{v:03}.png"));
            viz::mask_image(&m, c.width, c.height).save_png(&p)?;
            mask_paths.push(rel(out, &p));
            mask_maps.push(m);
        }
    }

    // What the views look at: the edited region when there is a mask, else where the cameras converge.
    let target = result
        .mask
        .as_deref()
        .and_then(|m| masked_centre(source, m))
        .or_else(|| splat::cameras::orbit::focus_point(cameras));

    // Turntable: before | after, circling the target at the views' own distance and elevation; around the
    // whole scene's bounds when they do not converge.
    let turntable = {
        let size = job.size.0.min(256);
        let orbit = target
            .and_then(|t| splat::cameras::orbit::orbit_like(cameras, t, 24, size, size))
            .unwrap_or_else(|| {
                let (lo, hi) =
                    splat::cameras::robust_bounds(source, 0.01).unwrap_or(([-1.0; 3], [1.0; 3]));
                splat::cameras::orbit_cameras(lo, hi, 24, size, size)
            });
        let frames: Vec<Image> = orbit
            .iter()
            .map(|c| {
                let b = render(source, c, &settings, None).rgb_image();
                let a = render(&result.scene, c, &settings, None).rgb_image();
                side_by_side(&b, &a)
            })
            .collect();
        progress.advance(24);
        let p = out.join("turntable.gif");
        write_gif(&p, &frames, &GifOptions::default()).map_err(|e| io_err(&p, e))?;
        rel(out, &p)
    };

    // Metrics.
    let cs = WarpSettings::default();
    let source_consistency = metrics::render_consistency(&cams, &before, &cs)
        .map_err(metrics_err)?
        .summary;
    let final_consistency = metrics::render_consistency(&cams, &after, &cs)
        .map_err(metrics_err)?
        .summary;
    let b_imgs: Vec<Image> = before.iter().map(|r| r.rgb_image()).collect();
    let a_imgs: Vec<Image> = after.iter().map(|r| r.rgb_image()).collect();
    let b_refs: Vec<&Image> = b_imgs.iter().collect();
    let a_refs: Vec<&Image> = a_imgs.iter().collect();
    let whole = metrics::preservation(&b_refs, &a_refs, None).map_err(metrics_err)?;
    let mask_refs: Vec<&[f32]> = mask_maps.iter().map(|m| m.as_slice()).collect();
    let mask_refs = (!mask_refs.is_empty()).then_some(&mask_refs[..]);
    let outside = match mask_refs {
        Some(refs) => {
            Some(metrics::preservation(&b_refs, &a_refs, Some(refs)).map_err(metrics_err)?)
        }
        None => None,
    };
    let changed_fraction =
        metrics::changed_fraction(&b_refs, &a_refs, mask_refs).map_err(metrics_err)?;
    let metrics = MetricsSummary {
        source_consistency: Some(source_consistency),
        guidance_consistency: result.guidance_consistency.last().cloned().flatten(),
        final_consistency: Some(final_consistency),
        preservation_outside_mask: outside,
        preservation_whole: Some(whole),
        changed_fraction,
        clip: None,
        extra: Default::default(),
    };

    // Iterations for the report.
    let iterations: Vec<IterationInfo> = (0..result.guidance.len())
        .map(|k| IterationInfo {
            index: k,
            source_prompt: Some(if k == 0 {
                job.prompts.source.clone()
            } else {
                job.prompts.target.clone()
            }),
            guidance: (0..cams.len())
                .map(|v| rel(out, &guidance_path(out, k, v)))
                .collect(),
            renders: Vec::new(),
            guidance_consistency: result.guidance_consistency.get(k).cloned().flatten(),
            seconds: result.times.get(k).map(IterationTimes::total),
            geometry_rate: result.shape.get(k).map(|s| s.geometry_rate),
            footprint_change: result.shape.get(k).and_then(|s| s.footprint_change),
        })
        .collect();
    let mut timings = Vec::new();
    let sum = |f: &dyn Fn(&IterationTimes) -> f64| result.times.iter().map(f).sum::<f64>();
    for (name, v) in [
        ("render", sum(&|t| t.render)),
        ("encode", sum(&|t| t.sampler.encode)),
        ("CCM", sum(&|t| t.sampler.ccm)),
        ("UNet passes", sum(&|t| t.sampler.unet)),
        ("ECM", sum(&|t| t.sampler.ecm)),
        ("blend-map consistency", sum(&|t| t.sampler.blend)),
        ("decode", sum(&|t| t.sampler.decode)),
        ("fit", sum(&|t| t.fit)),
    ] {
        timings.push(StageTiming {
            stage: name.into(),
            seconds: v,
        });
    }
    let settings_json = serde_json::to_value(job).unwrap_or_default();
    let mut notes = inputs.notes.clone();
    notes.push(format!("fit loss: {}", inputs.loss));
    if let Some(k) = result.resumed_from {
        notes.push(format!("resumed after iteration {k}"));
    }
    if let Some(e) = &inputs.estimate {
        notes.push(format!("estimated before the run: {}", e.describe()));
    }
    let mut work = WorkLedger::default();
    for t in &result.times {
        work.add(&t.work);
    }
    notes.push(format!("work done: {}", work.describe()));
    let data = ReportData {
        title: format!("vcedit: {} → {}", job.prompts.source, job.prompts.target),
        source_prompt: job.prompts.source.clone(),
        target_prompt: job.prompts.target.clone(),
        scene: Some(inputs.scene.to_string()),
        cameras: Some(inputs.cameras.to_string()),
        edited_scene: Some(rel(out, &scene_path)),
        settings: settings_json.clone(),
        notes,
        views: pairs,
        iterations,
        attention: result
            .word_maps
            .iter()
            .map(|(w, p)| WordImage {
                word: w.clone(),
                path: rel(out, p),
            })
            .collect(),
        masks: mask_paths,
        metrics: metrics.clone(),
        runs: Vec::new(),
        timings: timings.clone(),
        turntable: Some(turntable),
    };
    // The interactive viewer starts at the first edited view and turns around the same target.
    let viewer = viewer::viewer_html(
        &[
            ViewerScene {
                label: "before",
                scene: source,
            },
            ViewerScene {
                label: "after",
                scene: &result.scene,
            },
        ],
        &InitialView::from_cameras(&cams, source, target),
        &ViewerOptions {
            background: job.background,
            ..Default::default()
        },
    );
    let report_path =
        report::write_report_with_viewer(out, &data, &ReportOptions::default(), &viewer)
            .map_err(|e| io_err(out, e))?;

    #[derive(Serialize)]
    struct RunJson<'a> {
        vcedit_version: &'static str,
        model: &'a str,
        scene: &'a str,
        cameras: &'a str,
        views: &'a [usize],
        gaussians_before: usize,
        gaussians_after: usize,
        settings: serde_json::Value,
        loss: &'a str,
        metrics: &'a MetricsSummary,
        timings: &'a [StageTiming],
        iterations: &'a [IterationTimes],
        /// Per iteration: whether its fit kept the editable region's geometry, and why.
        shape: &'a [ShapeDecision],
        #[serde(skip_serializing_if = "Option::is_none")]
        estimate: Option<&'a Estimate>,
        /// Units of work per stage, all iterations together (each iteration's are in `iterations`).
        work: &'a WorkLedger,
    }
    let run = RunJson {
        vcedit_version: env!("CARGO_PKG_VERSION"),
        model: inputs.model,
        scene: inputs.scene,
        cameras: inputs.cameras,
        views: &result.views,
        gaussians_before: source.len(),
        gaussians_after: result.scene.len(),
        settings: settings_json,
        loss: &inputs.loss,
        metrics: &metrics,
        timings: &timings,
        iterations: &result.times,
        shape: &result.shape,
        estimate: inputs.estimate.as_ref(),
        work: &work,
    };
    let p = out.join("run.json");
    files::atomic_write(&p, &serde_json::to_vec_pretty(&run).expect("serialisable"))
        .map_err(|e| io_err(&p, e))?;
    Ok(Written {
        scene: scene_path,
        report: report_path,
        metrics,
    })
}

/// Per-axis median position of the masked Gaussians (robust to a few stray ones).
fn masked_centre(scene: &GaussianScene, mask: &[bool]) -> Option<[f64; 3]> {
    let picked: Vec<&[f32]> = scene
        .means
        .chunks_exact(3)
        .zip(mask)
        .filter_map(|(p, &m)| m.then_some(p))
        .collect();
    if picked.is_empty() {
        return None;
    }
    Some(std::array::from_fn(|a| {
        let mut v: Vec<f32> = picked.iter().map(|p| p[a]).collect();
        let mid = v.len() / 2;
        f64::from(*v.select_nth_unstable_by(mid, f32::total_cmp).1)
    }))
}
