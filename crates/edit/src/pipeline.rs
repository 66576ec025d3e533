//! The VcEdit editing loop: render → edit all views jointly → fit, repeated; with checkpoints, outputs and
//! a report.
//!
//! Iteration k (algorithm.md §0): render the V selected views of the current scene (black background), edit
//! them jointly with the multi-view sampler (iteration 0: source → target; later iterations: target →
//! target, re-editing the current renders), then fit the scene to those guidance images for `fit_steps`
//! single-view steps. Every iteration ends with an atomic checkpoint, so `--resume` continues after an
//! interruption and gives the same result as an uninterrupted run: all randomness of iteration k is derived
//! from (seed, k), never from a stream that an interruption would cut.

use std::path::{Path, PathBuf};
use std::time::Instant;

use rand::seq::SliceRandom;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use splat::render::{render, ExtraChannels, RenderSettings};
use splat::{Camera, GaussianScene, Image};

use crate::infedit::{EditPlan, EditPrompts, InfEditSettings};
use crate::masks::{self, Box3};
use crate::model::EditModel;
use crate::multiview::{ConsistencySettings, MultiView, Stage, StageTimes};
use crate::noise::SeededNoise;
use crate::train::{EcmFitter, EcmScope, EditTrainer, ImageLoss, TrainSettings};
use crate::viz;

/// How the views' guidance images are produced.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum GuidanceMode {
    /// VcEdit: all views edited jointly, with the consistency modules that are enabled.
    Joint,
    /// Every view edited on its own by InfEdit, with the same seed per view (as the reference re-seeds
    /// before every call): the inconsistent guidance of per-view editors.
    PerView,
}

/// Where the editable region comes from.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum MaskSource {
    /// The whole scene is editable.
    None,
    /// Gaussians whose centres lie in a box.
    Box { min: [f32; 3], max: [f32; 3] },
    /// Per-view mask images (white = editable) named after the cameras.
    Dir(PathBuf),
    /// The source prompt's attention to this word, lifted onto the Gaussians.
    Word(String),
    /// One flag per Gaussian, given by the caller (e.g. the demo's object labels).
    Given(#[serde(serialize_with = "count_editable", deserialize_with = "no_given")] Vec<bool>),
}

/// run.json shows how many Gaussians a given mask selects, not the flags themselves.
fn count_editable<S: serde::Serializer>(mask: &[bool], s: S) -> Result<S::Ok, S::Error> {
    s.serialize_str(&format!(
        "{} of {} Gaussians",
        mask.iter().filter(|&&m| m).count(),
        mask.len()
    ))
}

fn no_given<'de, D: serde::Deserializer<'de>>(_: D) -> Result<Vec<bool>, D::Error> {
    Err(serde::de::Error::custom(
        "a given mask cannot be read back from JSON",
    ))
}

/// Everything an edit run is configured with (written to run.json).
#[derive(Clone, Debug, Serialize)]
pub struct EditJob {
    pub prompts: EditPrompts,
    pub infedit: InfEditSettings,
    pub consistency: ConsistencySettings,
    pub guidance: GuidanceMode,
    pub iterations: usize,
    pub fit_steps: usize,
    pub max_views: usize,
    pub seed: u64,
    pub mask: MaskSource,
    pub mask_threshold: f32,
    pub ecm_scope: EcmScope,
    pub train: TrainSettings,
    /// Working resolution (width, height).
    pub size: (u32, u32),
    /// Background of every render (the reference uses black).
    pub background: [f32; 3],
}

/// Progress reporting: stages with a known amount of work.
pub trait Progress {
    /// A new stage with `total` units of work.
    fn stage(&mut self, name: &str, total: u64);
    /// `n` units of the current stage are done.
    fn advance(&mut self, n: u64);
    /// A line for the run's log.
    fn log(&mut self, line: &str);
}

/// A [`Progress`] that ignores everything (tests).
pub struct Quiet;

impl Progress for Quiet {
    fn stage(&mut self, _: &str, _: u64) {}
    fn advance(&mut self, _: u64) {}
    fn log(&mut self, _: &str) {}
}

#[derive(Debug, thiserror::Error)]
pub enum PipelineError {
    #[error("{0}")]
    Input(String),
    #[error("{}: {msg}", .path.display())]
    Io { path: PathBuf, msg: String },
    #[error(transparent)]
    Edit(#[from] crate::infedit::EditError),
    #[error(transparent)]
    MultiView(#[from] crate::multiview::MultiViewError),
    #[error(transparent)]
    Mask(#[from] masks::MaskError),
    #[error(transparent)]
    Train(#[from] crate::train::TrainError),
    #[error("{0}")]
    Candle(#[from] candle_core::Error),
}

fn io_err(path: &Path, e: impl std::fmt::Display) -> PipelineError {
    PipelineError::Io {
        path: path.to_path_buf(),
        msg: e.to_string(),
    }
}

/// A seeded sample of `min(n, max)` distinct camera indices, in ascending order.
pub fn select_views(n: usize, max: usize, seed: u64) -> Vec<usize> {
    let mut idx: Vec<usize> = (0..n).collect();
    if n > max {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        idx.shuffle(&mut rng);
        idx.truncate(max);
        idx.sort_unstable();
    }
    idx
}

/// A seed for one purpose of one iteration, independent of everything that ran before it.
pub fn derive_seed(seed: u64, iteration: usize, purpose: u64) -> u64 {
    // SplitMix64 of the combined value: well-mixed and stable across versions.
    let mut z = seed
        ^ (iteration as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ purpose.wrapping_mul(0xD1B5_4A32_D192_ED03);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

const PURPOSE_NOISE: u64 = 1;
const PURPOSE_FIT: u64 = 2;
const PURPOSE_ECM: u64 = 3;
const PURPOSE_MASK: u64 = 4;

/// Renders `scene` from every camera over `background` as RGB images.
pub fn render_views(scene: &GaussianScene, cameras: &[Camera], background: [f32; 3]) -> Vec<Image> {
    let settings = RenderSettings { background };
    cameras
        .iter()
        .map(|c| Image::from_data(c.width, c.height, 3, render(scene, c, &settings, None).rgb))
        .collect()
}

/// The editable mask rendered from a camera (1 where editable Gaussians cover the pixel).
pub fn render_mask(scene: &GaussianScene, mask: &[bool], camera: &Camera) -> Vec<f32> {
    let values: Vec<f32> = mask.iter().map(|&m| if m { 1.0 } else { 0.0 }).collect();
    let out = render(
        scene,
        camera,
        &RenderSettings::default(),
        Some(ExtraChannels {
            values: &values,
            channels: 1,
        }),
    );
    out.extra
}

/// The state saved after every iteration.
#[derive(Serialize, Deserialize)]
struct CheckpointMeta {
    /// Bumped when the format changes.
    version: u32,
    /// Iterations completed.
    iterations_done: usize,
    /// Indices of the edited views among the input cameras.
    views: Vec<usize>,
    /// Fingerprint of the settings that determine the result; resuming with others is refused.
    fingerprint: String,
    /// Editable Gaussians at the start (None = all).
    mask: Option<Vec<bool>>,
    times: Vec<IterationTimes>,
    guidance_consistency: Vec<Option<crate::metrics::ConsistencySummary>>,
    /// Per-word attention images of iteration 0: (word, file under `attention/`).
    attention: Vec<(String, String)>,
}

/// Wall-clock seconds per stage of one iteration.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct IterationTimes {
    pub render: f64,
    pub sampler: SamplerTimes,
    pub fit: f64,
}

/// [`StageTimes`] in a serialisable form.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct SamplerTimes {
    pub encode: f64,
    pub ccm: f64,
    pub unet: f64,
    pub ecm: f64,
    pub blend: f64,
    pub decode: f64,
}

impl From<&StageTimes> for SamplerTimes {
    fn from(t: &StageTimes) -> Self {
        Self {
            encode: t.encode,
            ccm: t.ccm,
            unet: t.unet,
            ecm: t.ecm,
            blend: t.blend,
            decode: t.decode,
        }
    }
}

/// What a finished run produced.
pub struct EditResult {
    pub scene: GaussianScene,
    /// Input-camera indices of the edited views.
    pub views: Vec<usize>,
    pub mask: Option<Vec<bool>>,
    /// Source renders of the first iteration (the scene before editing).
    pub before: Vec<Image>,
    /// Guidance images of every iteration.
    pub guidance: Vec<Vec<Image>>,
    pub times: Vec<IterationTimes>,
    /// Per-word attention heat maps of iteration 0 (first view), written under `out/attention/`.
    pub word_maps: Vec<(String, PathBuf)>,
    /// Multi-view consistency of each iteration's guidance (with that iteration's scene geometry).
    pub guidance_consistency: Vec<Option<crate::metrics::ConsistencySummary>>,
    /// Whether the run continued from a checkpoint.
    pub resumed_from: Option<usize>,
}

fn fingerprint(job: &EditJob, scene: &GaussianScene, cameras: &[Camera]) -> String {
    // Settings + input sizes; cheap and good enough to catch resuming into a different run.
    let settings = serde_json::to_string(job).unwrap_or_default();
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for b in settings
        .bytes()
        .chain(scene.len().to_le_bytes())
        .chain(cameras.len().to_le_bytes())
    {
        h ^= b as u64;
        h = h.wrapping_mul(0x100_0000_01b3);
    }
    for v in scene.means.iter().step_by(97) {
        h ^= v.to_bits() as u64;
        h = h.wrapping_mul(0x100_0000_01b3);
    }
    format!("{h:016x}")
}

fn checkpoint_dir(out: &Path) -> PathBuf {
    out.join("checkpoint")
}

fn save_checkpoint(
    out: &Path,
    meta: &CheckpointMeta,
    trainer: &EditTrainer,
) -> Result<(), PipelineError> {
    let scene = trainer.scene();
    let dir = checkpoint_dir(out);
    // Files of iteration k are written under their own names, then the meta file (the commit point).
    let k = meta.iterations_done;
    let scene_path = dir.join(format!("scene_{k}.ply"));
    splat::ply::write_ply(&scene_path, scene).map_err(|e| io_err(&scene_path, e))?;
    let state_path = dir.join(format!("trainer_{k}.safetensors"));
    trainer.save(&state_path)?;
    let meta_path = dir.join("checkpoint.json");
    let json = serde_json::to_vec_pretty(meta).expect("serialisable");
    splat::atomic_write(&meta_path, &json).map_err(|e| io_err(&meta_path, e))?;
    // Older iterations' files are no longer needed.
    if k > 0 {
        let _ = std::fs::remove_file(dir.join(format!("scene_{}.ply", k - 1)));
        let _ = std::fs::remove_file(dir.join(format!("trainer_{}.safetensors", k - 1)));
    }
    Ok(())
}

/// Runs an edit. `scene` and `cameras` (already at the working resolution) are the inputs; outputs go to
/// `out` (guidance images per iteration; the caller writes the final outputs). With `resume`, a
/// checkpoint in `out` is continued.
#[allow(clippy::too_many_arguments)]
pub fn run_edit(
    job: &EditJob,
    model: &EditModel,
    loss: &ImageLoss,
    scene: &GaussianScene,
    cameras: &[Camera],
    out: &Path,
    resume: bool,
    progress: &mut dyn Progress,
) -> Result<EditResult, PipelineError> {
    if cameras.is_empty() {
        return Err(PipelineError::Input("no cameras".into()));
    }
    if scene.is_empty() {
        return Err(PipelineError::Input("the scene has no Gaussians".into()));
    }
    let fp = fingerprint(job, scene, cameras);
    let views = select_views(cameras.len(), job.max_views, job.seed);
    let cams: Vec<Camera> = views.iter().map(|&i| cameras[i].clone()).collect();
    let extent = scene_extent(&cams);

    // Resume or start fresh.
    let meta_path = checkpoint_dir(out).join("checkpoint.json");
    let mut resumed_from = None;
    let (mut trainer, mut meta) = if resume && meta_path.is_file() {
        let text = std::fs::read_to_string(&meta_path).map_err(|e| io_err(&meta_path, e))?;
        let meta: CheckpointMeta =
            serde_json::from_str(&text).map_err(|e| io_err(&meta_path, e))?;
        if meta.fingerprint != fp || meta.version != 1 {
            return Err(PipelineError::Input(format!(
                "{}: the checkpoint belongs to a run with other inputs or settings; use another --out or drop --resume",
                meta_path.display()
            )));
        }
        let k = meta.iterations_done;
        let scene_path = checkpoint_dir(out).join(format!("scene_{k}.ply"));
        let saved = splat::ply::read_ply(&scene_path).map_err(|e| io_err(&scene_path, e))?;
        let trainer = EditTrainer::load(
            &checkpoint_dir(out).join(format!("trainer_{k}.safetensors")),
            &saved,
            job.train.clone(),
            extent,
        )?;
        resumed_from = Some(k);
        progress.log(&format!(
            "resuming after iteration {k} of {}",
            job.iterations
        ));
        (trainer, meta)
    } else {
        if resume {
            progress.log("no checkpoint to resume from; starting from the beginning");
        }
        let mask = compute_mask(job, model, scene, &cams, progress)?;
        let trainer = EditTrainer::new(scene, mask.clone(), job.train.clone(), extent);
        let meta = CheckpointMeta {
            version: 1,
            iterations_done: 0,
            views: views.clone(),
            fingerprint: fp,
            mask,
            times: vec![],
            guidance_consistency: vec![],
            attention: vec![],
        };
        (trainer, meta)
    };

    let mut guidance_all = Vec::new();
    let before = render_views(scene, &cams, job.background);
    let (w, h) = job.size;
    // Guidance of already completed iterations (for the report) from disk.
    for k in 0..meta.iterations_done {
        let mut imgs = Vec::new();
        for v in 0..cams.len() {
            let p = guidance_path(out, k, v);
            imgs.push(Image::load(&p).map_err(|e| io_err(&p, e))?);
        }
        guidance_all.push(imgs);
    }

    for k in meta.iterations_done..job.iterations {
        let mut times = IterationTimes::default();
        let t = Instant::now();
        progress.stage(
            &format!("iteration {}/{}: rendering", k + 1, job.iterations),
            cams.len() as u64,
        );
        let settings = RenderSettings {
            background: job.background,
        };
        let renders: Vec<splat::render::RenderOutput> = cams
            .iter()
            .map(|c| render(trainer.scene(), c, &settings, None))
            .collect();
        let sources: Vec<Image> = renders.iter().map(|r| r.rgb_image()).collect();
        progress.advance(cams.len() as u64);
        times.render = t.elapsed().as_secs_f64();

        // From the second iteration the source prompt is the target prompt (the scene already shows it).
        let mut prompts = job.prompts.clone();
        if k > 0 {
            prompts.source = prompts.target.clone();
        }
        let mut plan = EditPlan::new(model, &prompts, &job.infedit, (w as usize, h as usize))?;
        let consistency = match job.guidance {
            GuidanceMode::Joint => {
                plan.thresholds.dynamic_me = true;
                job.consistency.clone()
            }
            GuidanceMode::PerView => ConsistencySettings::none(),
        };
        let fitter = EcmFitter::new(&trainer, loss, job.ecm_scope);
        let mv = MultiView {
            model,
            plan: &plan,
            scene: trainer.scene(),
            cameras: &cams,
            consistency: &consistency,
            fitter: Some(&fitter),
            seed: derive_seed(job.seed, k, PURPOSE_ECM),
            background: job.background,
        };
        let steps = plan.timesteps.len() as u64;
        progress.stage(
            &format!(
                "iteration {}/{}: editing {} views",
                k + 1,
                job.iterations,
                cams.len()
            ),
            steps,
        );
        let mut noise = SeededNoise::new(derive_seed(job.seed, k, PURPOSE_NOISE));
        let outcome = mv.run(&sources, &mut noise, &mut |_, stage| {
            if stage == Stage::Unet {
                progress.advance(1);
            }
        })?;
        times.sampler = SamplerTimes::from(&outcome.times);
        let geometry: Vec<crate::metrics::ViewGeometry> = cams
            .iter()
            .zip(&renders)
            .map(|(c, r)| crate::metrics::ViewGeometry::from_render(c, r))
            .collect();
        let consistency = crate::metrics::multiview_consistency(
            &outcome.images.iter().collect::<Vec<_>>(),
            &geometry,
            &crate::metrics::ConsistencySettings::default(),
        )
        .ok()
        .map(|r| r.summary);
        meta.guidance_consistency.push(consistency);
        for (v, img) in outcome.images.iter().enumerate() {
            let p = guidance_path(out, k, v);
            img.save_png(&p).map_err(|e| io_err(&p, e))?;
            let p = out
                .join(format!("iter_{k}"))
                .join("source")
                .join(format!("view_{v:03}.png"));
            sources[v].save_png(&p).map_err(|e| io_err(&p, e))?;
        }
        if k == 0 {
            if let Some(first) = outcome.views.first() {
                let maps = viz::word_maps(
                    first.controller.blend_store(),
                    plan.blend_size,
                    &plan.target_tokens,
                    (h as usize, w as usize),
                )?;
                let listing: Vec<(String, String)> = maps
                    .iter()
                    .enumerate()
                    .map(|(i, m)| {
                        (
                            m.word.clone(),
                            format!("attn_{i:02}_{}.png", viz::file_safe(&m.word)),
                        )
                    })
                    .collect();
                for (m, (_, file)) in maps.iter().zip(&listing) {
                    let p = out.join("attention").join(file);
                    viz::heat_image(&m.map, w, h)
                        .save_png(&p)
                        .map_err(|e| io_err(&p, e))?;
                }
                meta.attention = listing;
            }
        }

        let t = Instant::now();
        progress.stage(
            &format!("iteration {}/{}: fitting", k + 1, job.iterations),
            job.fit_steps as u64,
        );
        drop(mv);
        drop(fitter);
        trainer.fit(
            &cams,
            &outcome.images,
            job.fit_steps,
            loss,
            derive_seed(job.seed, k, PURPOSE_FIT),
            &mut |n| progress.advance(n),
        )?;
        times.fit = t.elapsed().as_secs_f64();
        guidance_all.push(outcome.images);

        meta.iterations_done = k + 1;
        meta.times.push(times);
        save_checkpoint(out, &meta, &trainer)?;
        progress.log(&format!(
            "iteration {} done: {} Gaussians",
            k + 1,
            trainer.scene().len()
        ));
        // Stops the run here as a kill right after the checkpoint would (for testing resume).
        if std::env::var("VCEDIT_STOP_AFTER_ITERATION")
            .ok()
            .and_then(|v| v.parse::<usize>().ok())
            == Some(k + 1)
        {
            return Err(PipelineError::Input(format!(
                "stopped after iteration {} (VCEDIT_STOP_AFTER_ITERATION)",
                k + 1
            )));
        }
    }

    Ok(EditResult {
        scene: trainer.state.scene,
        views,
        mask: meta.mask.clone(),
        before,
        guidance: guidance_all,
        times: meta.times,
        word_maps: meta
            .attention
            .iter()
            .map(|(w, f)| (w.clone(), out.join("attention").join(f)))
            .collect(),
        guidance_consistency: meta.guidance_consistency,
        resumed_from,
    })
}

/// The work a run will do and the memory it needs, printed before it starts.
#[derive(Clone, Debug, Serialize)]
pub struct WorkPlan {
    pub views: usize,
    pub iterations: usize,
    /// UNet calls with a batch of 6 (3 branches × CFG), recording passes included.
    pub unet_calls: usize,
    /// Renders (forward only) and render+backward passes of the fits.
    pub renders: usize,
    pub fit_steps: usize,
    pub lifts: usize,
    pub memory_bytes: u64,
}

impl WorkPlan {
    pub fn describe(&self) -> String {
        format!(
            "work: {} views × {} iterations: {} UNet calls (batch 6), {} renders, {} lifting passes, {} fitting steps; \
             memory needed ≈ {:.1} GB",
            self.views,
            self.iterations,
            self.unet_calls,
            self.renders,
            self.lifts,
            self.fit_steps,
            self.memory_bytes as f64 / 1e9
        )
    }
}

/// Counts the work of a run and estimates its peak memory.
pub fn work_plan(
    job: &EditJob,
    model: &EditModel,
    scene: &GaussianScene,
    cameras: usize,
) -> WorkPlan {
    let v = cameras.min(job.max_views);
    let steps = job.infedit.steps;
    let (ccm, ecm, blend) = match job.guidance {
        GuidanceMode::Joint => (
            job.consistency.ccm_steps.len(),
            job.consistency.ecm_steps.len(),
            if job.consistency.blend_consistency {
                steps.saturating_sub(1)
            } else {
                0
            },
        ),
        GuidanceMode::PerView => (0, 0, 0),
    };
    let (epochs, _) = job.train.ecm_schedule(v);
    let cfg = &model.unet.config().block_out_channels;
    let unet_calls = job.iterations * v * (steps + ccm);
    // Attention layers recorded by CCM, at most one per transformer block: a generous 16.
    let ccm_layers = 16;
    let renders = job.iterations
        * (v + ecm * (2 * epochs * v + 2 * v) + blend * v + ccm * ccm_layers * v)
        + 2 * v
        + 48;
    let lifts = job.iterations * (blend * v + ccm * ccm_layers * v);
    let fit_steps = job.iterations * job.fit_steps;

    let (w, h) = (job.size.0 as u64, job.size.1 as u64);
    let f = model.downscale() as u64;
    let latent = (w / f) * (h / f);
    let weights = model.parameters * 4;
    // A batch-6 UNet pass: roughly 40 activations of the first block's width at latent resolution.
    let unet = 6 * latent * cfg.first().copied().unwrap_or(320) as u64 * 4 * 40;
    // Per view: latents and attention stores (blend layers, CCM records at most 32² queries × 77 tokens).
    let heads = 8u64;
    let per_view = 12 * latent * 4
        + 2 * heads * (latent / 16).max(1) * 77 * 4 * 5
        + if ccm > 0 {
            3 * heads * 1024 * 77 * 4 * 6
        } else {
            0
        };
    let images = v as u64 * w * h * 3 * 4 * 6;
    let n = scene.len() as u64;
    let k = 3 * ((scene.sh_degree + 1) * (scene.sh_degree + 1)) as u64;
    let params = n * (11 + k) * 4;
    // Editing state (params, grads, 2 moments, anchors) + two ECM copies; splits can grow the scene.
    let train = params * 5 * 3 / 2 + params * 4 * 2;
    // Lifting: per-thread sums of the widest map (CCM: 3 branches × heads × tokens).
    let threads = rayon::current_num_threads() as u64;
    let lift =
        n * 4 * threads * if ccm > 0 { 3 * heads * 8 } else { 3 } + w * h * 4 * 3 * heads * 8;
    let lpips = LPIPS_BUDGET.min(v as u64 * w * h * 4 * 128);
    let memory_bytes =
        weights + unet + v as u64 * per_view + images + train + lift + lpips + 300_000_000;
    WorkPlan {
        views: v,
        iterations: job.iterations,
        unet_calls,
        renders,
        fit_steps,
        lifts,
        memory_bytes,
    }
}

const LPIPS_BUDGET: u64 = crate::train::LPIPS_CACHE_BYTES as u64;

/// Memory available to a new run (Linux `MemAvailable`), if known.
pub fn available_memory() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

/// Path of a guidance image.
pub fn guidance_path(out: &Path, iteration: usize, view: usize) -> PathBuf {
    out.join(format!("iter_{iteration}"))
        .join("guidance")
        .join(format!("view_{view:03}.png"))
}

/// The INRIA trainer's scene extent: 1.1 × the largest distance of a camera centre from their mean.
pub fn scene_extent(cameras: &[Camera]) -> f32 {
    let n = cameras.len().max(1) as f64;
    let mut mean = [0.0f64; 3];
    for c in cameras {
        let p = c.center();
        for a in 0..3 {
            mean[a] += p[a] / n;
        }
    }
    let r = cameras
        .iter()
        .map(|c| {
            let p = c.center();
            ((p[0] - mean[0]).powi(2) + (p[1] - mean[1]).powi(2) + (p[2] - mean[2]).powi(2)).sqrt()
        })
        .fold(0.0f64, f64::max);
    (1.1 * r).max(1e-3) as f32
}

fn compute_mask(
    job: &EditJob,
    model: &EditModel,
    scene: &GaussianScene,
    cams: &[Camera],
    progress: &mut dyn Progress,
) -> Result<Option<Vec<bool>>, PipelineError> {
    let mask = match &job.mask {
        MaskSource::None => return Ok(None),
        MaskSource::Box { min, max } => masks::mask_from_box(
            scene,
            &Box3 {
                min: *min,
                max: *max,
            },
        ),
        MaskSource::Given(mask) => {
            if mask.len() != scene.len() {
                return Err(PipelineError::Input(format!(
                    "the mask has {} flags for {} Gaussians",
                    mask.len(),
                    scene.len()
                )));
            }
            mask.clone()
        }
        MaskSource::Dir(dir) => {
            let maps = masks::load_mask_images(dir, cams)?;
            masks::threshold(&masks::lift_maps(scene, cams, &maps), job.mask_threshold)
        }
        MaskSource::Word(word) => {
            progress.stage("mask: attention to the mask word", cams.len() as u64);
            let images = render_views(scene, cams, job.background);
            let (w, h) = job.size;
            let plan = EditPlan::new(model, &job.prompts, &job.infedit, (w as usize, h as usize))?;
            let mut noise = SeededNoise::new(derive_seed(job.seed, 0, PURPOSE_MASK));
            // A mid-schedule timestep: noisy enough for the UNet to attend by meaning, not by pixels.
            let t = plan.timesteps[plan.timesteps.len() / 2];
            let maps = masks::word_attention_maps(
                model,
                &images,
                &job.prompts.source,
                word,
                t,
                plan.blend_size,
                &mut noise,
            )?;
            progress.advance(cams.len() as u64);
            masks::threshold(&masks::lift_maps(scene, cams, &maps), job.mask_threshold)
        }
    };
    let n = mask.iter().filter(|&&m| m).count();
    progress.log(&format!("mask: {n} of {} Gaussians editable", mask.len()));
    if n == 0 {
        return Err(PipelineError::Input(
            "the mask selects no Gaussian; lower --mask-threshold or check the box / word / mask images".into(),
        ));
    }
    Ok(Some(mask))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn views_are_a_seeded_sorted_sample() {
        assert_eq!(select_views(5, 96, 0), vec![0, 1, 2, 3, 4]);
        let a = select_views(200, 10, 3);
        assert_eq!(a.len(), 10);
        assert!(a.windows(2).all(|w| w[0] < w[1]));
        assert_eq!(a, select_views(200, 10, 3));
        assert_ne!(a, select_views(200, 10, 4));
    }

    #[test]
    fn derived_seeds_differ_by_iteration_and_purpose() {
        let s = derive_seed(0, 0, 1);
        assert_ne!(s, derive_seed(0, 1, 1));
        assert_ne!(s, derive_seed(0, 0, 2));
        assert_eq!(s, derive_seed(0, 0, 1));
    }
}
