//! What a run will cost: the work it does and the memory it needs, shown (and checked) before it starts.

use serde::Serialize;
use splat::GaussianScene;

use crate::consistency::EcmParams;
use crate::fit::LPIPS_CACHE_BYTES;
use crate::ledger::WorkLedger;
use crate::sampler::{EditModel, DEFAULT_STORE_MAX_TOKENS};

use super::estimate::{worth_calibrating, Calibration, Estimate, PlannedCounts};
use super::job::{EditJob, GuidanceMode};

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
    /// Cross-attention layers a CCM step records (maps of at most 32² queries).
    pub ccm_layers: usize,
    pub memory_bytes: u64,
    /// GPU memory the run needs on its device (`None` on the CPU).
    pub gpu_memory_bytes: Option<u64>,
    /// The GPU's free memory when it was opened, where its driver reports it (NVIDIA, AMD).
    pub gpu_free_bytes: Option<u64>,
    /// Views per UNet call.
    pub view_batch: usize,
    /// How long the run will take, where it was calibrated ([`super::calibrate`]).
    pub estimate: Option<Estimate>,
    /// The units of work per stage the run will do (its `run.json` counts what it did).
    pub work: WorkLedger,
}

impl WorkPlan {
    /// The counts the time estimate scales its unit costs by.
    pub fn counts(&self) -> PlannedCounts {
        PlannedCounts {
            unet_calls: self.unet_calls,
            view_batch: self.view_batch,
            unet_samples: self.work.total().unet_samples,
            renders: self.renders,
            fit_steps: self.fit_steps,
            lifts: self.lifts,
        }
    }

    /// Whether the run is long enough to be worth timing its unit costs first.
    pub fn worth_calibrating(&self) -> bool {
        worth_calibrating(self.unet_calls)
    }

    /// Sets the run's time estimate from its unit costs measured here ([`super::calibrate`]).
    pub fn set_estimate(&mut self, calibration: Calibration) -> Estimate {
        let estimate = Estimate::new(&self.counts(), calibration);
        self.estimate = Some(estimate);
        estimate
    }

    pub fn describe(&self) -> String {
        let gpu = self.gpu_memory_bytes.map_or(String::new(), |b| {
            let free = self.gpu_free_bytes.map_or(String::new(), |f| {
                format!(" of {:.1} GB free", f as f64 / 1e9)
            });
            format!(", GPU memory ≈ {:.1} GB{free}", b as f64 / 1e9)
        });
        // Up to six samples a view (three branches, with and without the prompt): `BatchLayout` leaves
        // out those nobody reads.
        let batch = match self.view_batch {
            1 => "≤ 6 samples a view".to_string(),
            n => format!("≤ 6 samples a view, {n} views per call"),
        };
        use crate::present::count;
        let time = self
            .estimate
            .map_or(String::new(), |e| format!("\n      {}", e.describe()));
        // Lines within 80 columns for the sizes runs have.
        format!(
            "work: {} × {}: {} ({batch}),\n      {}, {}, {}; memory needed ≈ {:.1} GB{gpu}{time}",
            count(self.views, "view", "views"),
            count(self.iterations, "iteration", "iterations"),
            count(self.unet_calls, "UNet pass", "UNet passes"),
            count(self.renders, "render", "renders"),
            count(self.lifts, "lifting pass", "lifting passes"),
            count(self.fit_steps, "fitting step", "fitting steps"),
            self.memory_bytes as f64 / 1e9
        )
    }
}

/// Most views one UNet call takes when the choice is automatic.
pub const MAX_AUTO_VIEW_BATCH: usize = 8;

/// GPU memory the automatic view batch may give the UNet's activations where the GPU's free memory is
/// unknown (wgpu cannot report it, gfx-rs/wgpu#2447; NVIDIA and AMD cards report it through their
/// drivers, see `gpu::GpuLimits::free_bytes_at_open`): a fixed share that leaves room for SD-1.5-sized
/// weights, the scene and the display on a 12 GB card. `--view-batch` overrides it either way.
pub const AUTO_VIEW_BATCH_GPU_BYTES: u64 = 6_000_000_000;

/// Views per UNet call: the job's choice, else 1 on the CPU (one view's batch of six already keeps every
/// core busy, and a larger batch only adds memory) and on a GPU the most views, up to
/// [`MAX_AUTO_VIEW_BATCH`] and the number of views, whose hooked call's activations fit in the GPU's
/// free memory less what the run keeps there besides ([`gpu_state_bytes`]); where the free memory is
/// unknown, in a third of the device's stated memory or else [`AUTO_VIEW_BATCH_GPU_BYTES`]. One call's
/// largest buffer must also fit the device's largest buffer.
pub fn view_batch(job: &EditJob, model: &EditModel, scene: &GaussianScene, views: usize) -> usize {
    if let Some(n) = job.view_batch {
        return n.max(1);
    }
    let Some(limits) = model.compute.gpu_limits() else {
        return 1;
    };
    let f = model.downscale();
    let (lh, lw) = (job.size.1 as usize / f, job.size.0 as usize / f);
    let config = model.unet.config();
    // The largest single buffer of one view's call: the first level's GEGLU projection (8 × its width
    // per token) or a cross-attention map (heads × 77 per token), for six branches. Convolutions block
    // their own im2col buffers. A batch must keep it within the device's largest buffer.
    let width = config.block_out_channels.first().copied().unwrap_or(320);
    let largest = 6 * lh * lw * (8 * width).max(8 * 77) * 4;
    let budget = match (limits.free_bytes_at_open, limits.memory_bytes) {
        (Some(free), _) => free.saturating_sub(gpu_state_bytes(job, model, scene, views)),
        (None, Some(stated)) => stated / 3,
        (None, None) => AUTO_VIEW_BATCH_GPU_BYTES,
    };
    let fits = |n: usize| {
        (n * largest) as u64 <= limits.max_buffer_bytes
            && config
                .activation_estimate(6 * n, lh, lw, 77, true)
                .is_ok_and(|e| e.total() as u64 <= budget)
    };
    (1..=MAX_AUTO_VIEW_BATCH.min(views.max(1)))
        .rev()
        .find(|&n| fits(n))
        .unwrap_or(1)
}

/// Attention heads assumed for the stores and lifting sums (SD 1.5's 8).
const HEADS: u64 = 8;

/// GPU memory a run keeps besides one UNet call's activations: the networks' weights (f16 or f32 copies
/// in the device cache), the fit's device state (scene, gradients, two Adam moments, anchor snapshot)
/// and ECM's fits (one alive at a time, or both where its appearance fits step together: a second copy
/// and each step's splat records of both), one lifting's sums and one frame with CCM's channels, the
/// views ECM's fits (shared by a pair) and the lifting session keep (`views` of them at most), plus 100
/// MB of pools and small buffers. 0 on the CPU.
pub fn gpu_state_bytes(
    job: &EditJob,
    model: &EditModel,
    scene: &GaussianScene,
    views: usize,
) -> u64 {
    let Some(weight_bytes) = model.compute.gpu_weight_bytes(model.parameters) else {
        return 0;
    };
    let (w, h) = (job.size.0 as u64, job.size.1 as u64);
    let n = scene.len() as u64;
    let lift_channels = widest_lift_round(job, model) as u64;
    let frame = w * h * 4 * (3 + 1 + 1 + lift_channels);
    // The views ECM's fit keeps, and those the sampler run's lifting session keeps (CCM, blend maps).
    let splat = model.compute.splat();
    let lifts = job.guidance == GuidanceMode::Joint
        && (!job.consistency.ccm_steps.is_empty() || job.consistency.blend_consistency);
    let kept_views = (u64::from(ecm_keeps_views(job)) + u64::from(lifts))
        * splat.kept_views_bytes(scene.len(), views, job.size.0, job.size.1);
    // The second copy of an appearance pair (`PairTrainer`): its parameters, gradients and moments.
    let ecm_pair = if ecm_keeps_views(job) {
        scene_param_bytes(scene) * 5
    } else {
        0
    };
    weight_bytes
        + scene_param_bytes(scene) * 10
        + ecm_pair
        + n * 4 * (lift_channels + 1)
        + frame
        + kept_views
        + 100_000_000
}

/// The recorded layers' map sizes and layer counts (one CCM lifting round each; see
/// `UNetConfig::cross_attention_grids`): none for a config the UNet cannot resolve.
fn ccm_grids(job: &EditJob, model: &EditModel) -> Vec<((usize, usize), usize)> {
    let f = model.downscale();
    let latent_size = (job.size.1 as usize / f, job.size.0 as usize / f);
    model
        .unet
        .config()
        .cross_attention_grids(latent_size.0, latent_size.1, DEFAULT_STORE_MAX_TOKENS)
        .unwrap_or_default()
}

/// Channels of the run's widest lifting round: CCM's largest map size, all its layers stacked
/// (3 branches × heads × tokens each; 8 tokens assumed), or the blend maps' few. Kept as small as
/// the blend maps' when CCM is off.
fn widest_lift_round(job: &EditJob, model: &EditModel) -> usize {
    let ccm = job.guidance == GuidanceMode::Joint && !job.consistency.ccm_steps.is_empty();
    match ccm_grids(job, model)
        .iter()
        .map(|&(_, layers)| layers)
        .max()
    {
        Some(layers) if ccm => layers * 3 * HEADS as usize * 8,
        _ => 3,
    }
}

/// Whether the run's ECM fits are appearance-only, and so keep each view's projection
/// (`Trainer::freeze_geometry`).
fn ecm_keeps_views(job: &EditJob) -> bool {
    job.guidance == GuidanceMode::Joint
        && !job.consistency.ecm.steps.is_empty()
        && job.consistency.ecm.params == EcmParams::Appearance
}

/// The scene's trainable parameters in bytes (position, scale, rotation, opacity, SH).
fn scene_param_bytes(scene: &GaussianScene) -> u64 {
    let k = 3 * ((scene.sh_degree + 1) * (scene.sh_degree + 1)) as u64;
    scene.len() as u64 * (11 + k) * 4
}

/// Activation bytes of one hooked UNet call on `views` views (six latent rows each: three branches,
/// conditional and unconditional) of `latent` (height, width) pixels: the config's documented upper bound,
/// or roughly 40 activations of the first block's width when the config cannot be resolved.
fn unet_call_bytes(model: &EditModel, views: usize, latent: (usize, usize)) -> u64 {
    let config = model.unet.config();
    config
        .activation_estimate(6 * views, latent.0, latent.1, 77, true)
        .map_or_else(
            |_| rough_unet_call_bytes(model, views, latent),
            |e| e.total() as u64,
        )
}

/// The rough form of [`unet_call_bytes`].
fn rough_unet_call_bytes(model: &EditModel, views: usize, latent: (usize, usize)) -> u64 {
    let width = model
        .unet
        .config()
        .block_out_channels
        .first()
        .copied()
        .unwrap_or(320);
    (6 * views * latent.0 * latent.1 * width * 4 * 40) as u64
}

/// The memory of a single-image edit (`vcedit edit-image`) of `size` (width, height): host bytes and, on a
/// GPU, device bytes. The weights (held on the host either way) plus one hooked batch-6 UNet call (the
/// three branches, conditional and unconditional) where the networks run, and the image's buffers.
pub fn image_edit_memory(model: &EditModel, size: (u32, u32)) -> (u64, Option<u64>) {
    let (w, h) = (size.0 as u64, size.1 as u64);
    let f = model.downscale() as u64;
    let weights = model.parameters * 4;
    let unet = unet_call_bytes(model, 1, ((h / f) as usize, (w / f) as usize));
    // The input, the decoded outputs and the attention maps saved with the image, in f32.
    let images = w * h * 4 * 16;
    if model.compute.is_gpu() {
        (weights + images + 300_000_000, Some(weights + unet))
    } else {
        (weights + unet + images + 300_000_000, None)
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
    let view_batch = view_batch(job, model, scene, v);
    let steps = job.infedit.steps;
    let (ccm, ecm, blend) = match job.guidance {
        GuidanceMode::Joint => (
            job.consistency.ccm_steps.len(),
            job.consistency.ecm.steps.len(),
            if job.consistency.blend_consistency {
                steps.saturating_sub(1)
            } else {
                0
            },
        ),
        GuidanceMode::PerView => (0, 0, 0),
    };
    let (epochs, _) = job.consistency.ecm.schedule(v);
    let unet_calls = job.iterations * v * (steps + ccm);
    let f = model.downscale();
    let latent_size = (job.size.1 as usize / f, job.size.0 as usize / f);
    // The layers CCM lifts: those the attention store records, one lifting round per map size. A config
    // the UNet loaded resolves.
    let ccm_grids = ccm_grids(job, model);
    let ccm_layers: usize = ccm_grids.iter().map(|&(_, layers)| layers).sum();
    let ccm_rounds = ccm_grids.len();
    let renders = job.iterations
        * (v + ecm * (2 * epochs * v + 2 * v) + blend * v + ccm * ccm_rounds * v)
        + 2 * v
        + 48;
    // Lifting passes in units of the calibrated one-layer round: a stacked round does each layer's
    // channel work, sharing only the projection and traversal, so a layer still counts as one (an
    // overestimate by what the sharing saves).
    let lifts = job.iterations * (blend * v + ccm * ccm_layers * v);
    let fit_steps = job.iterations * job.fit_steps;
    let work = planned_work(job, v, view_batch, ccm_rounds);

    let (w, h) = (job.size.0 as u64, job.size.1 as u64);
    let latent = (latent_size.0 * latent_size.1) as u64;
    let weights = model.parameters * 4;
    // One view per UNet call on the host.
    let unet = rough_unet_call_bytes(model, 1, latent_size);
    // Per view: latents and attention stores (blend layers, CCM records at most 32² queries × 77 tokens).
    let heads = HEADS;
    let per_view = 12 * latent * 4
        + 2 * heads * (latent / 16).max(1) * 77 * 4 * 5
        + if ccm > 0 {
            3 * heads * 1024 * 77 * 4 * 6
        } else {
            0
        };
    let images = v as u64 * w * h * 3 * 4 * 6;
    let params = scene_param_bytes(scene);
    // Editing state (params, grads, 2 moments, anchors) + two ECM copies; splits can grow the scene.
    // Appearance-only ECM fits keep each view's projection, two fits at a time on the CPU (on a GPU
    // they are device memory: `gpu_state_bytes`).
    let splat = model.compute.splat();
    let frozen_views = if ecm_keeps_views(job) && splat.is_cpu() {
        2 * splat.kept_views_bytes(scene.len(), v, job.size.0, job.size.1)
    } else {
        0
    };
    let train = params * 5 * 3 / 2 + params * 4 * 2 + frozen_views;
    // Lifting on the CPU: the sums and render-back of its widest round, within splat's per-pass bound.
    let lift = if splat.is_cpu() {
        splat::cpu_lift_round_bytes(scene.len(), w * h, widest_lift_round(job, model))
    } else {
        0
    };
    let lpips = LPIPS_BUDGET.min(v as u64 * w * h * 4 * 128);
    let memory_bytes =
        weights + unet + v as u64 * per_view + images + train + lift + lpips + 300_000_000;
    // On a GPU: what the run keeps there (`gpu_state_bytes`) plus one hooked UNet call of `view_batch`
    // views (diffusion's documented upper bound, self-attention's score chunks included).
    let gpu_memory_bytes = model.compute.is_gpu().then(|| {
        gpu_state_bytes(job, model, scene, v) + unet_call_bytes(model, view_batch, latent_size)
    });
    let gpu_free_bytes = model.compute.gpu_free_bytes();
    WorkPlan {
        views: v,
        iterations: job.iterations,
        unet_calls,
        renders,
        fit_steps,
        lifts,
        ccm_layers,
        memory_bytes,
        gpu_memory_bytes,
        gpu_free_bytes,
        view_batch,
        estimate: None,
        work,
    }
}

/// The units of work of a run of `views` views, `view_batch` per UNet call, whose CCM steps lift in
/// `ccm_rounds` rounds (one per map size of the recorded layers): what
/// [`crate::consistency::MultiView::run`] and the editing loop count, less the map reads (their number and
/// size are known only when the UNet runs).
pub fn planned_work(
    job: &EditJob,
    views: usize,
    view_batch: usize,
    ccm_rounds: usize,
) -> WorkLedger {
    let mut w = WorkLedger::default();
    let joint = job.guidance == GuidanceMode::Joint;
    let c = &job.consistency;
    let calls = views.div_ceil(view_batch.max(1));
    let steps = job
        .infedit
        .start_steps()
        .map_or(0, |start| job.infedit.steps.saturating_sub(start));
    let samples = |i: usize, recording: bool| job.infedit.unet_samples(i, recording).unwrap_or(0);
    w.encode.vae_encodes = views;
    for i in 0..steps {
        w.unet.unet_calls += calls;
        w.unet.unet_samples += views * samples(i, false);
        if joint && c.ccm_steps.contains(&i) {
            w.ccm.unet_calls += calls;
            w.ccm.unet_samples += views * samples(i, true);
            w.ccm.lifting_rounds += ccm_rounds;
            w.ccm.render_backs += ccm_rounds * views;
        }
        if joint && c.ecm.steps.contains(&i) {
            let (epochs, _) = c.ecm.schedule(views);
            w.ecm.fit_steps += 2 * epochs * views;
            w.ecm.vae_decodes += 2 * views;
            w.ecm.vae_encodes += 2 * views;
        }
        if joint && c.blend_consistency && i > 0 {
            w.blend.lifting_rounds += 1;
            w.blend.render_backs += views;
        }
    }
    w.fit.fit_steps = job.fit_steps;
    let mut total = WorkLedger::default();
    for k in 0..job.iterations {
        let mut iteration = w.clone();
        // The decoded change needs the source latents decoded too.
        iteration.decode.vae_decodes = views * if job.delta_decode.applies(k) { 2 } else { 1 };
        total.add(&iteration);
    }
    total
}

const LPIPS_BUDGET: u64 = LPIPS_CACHE_BYTES as u64;

#[cfg(test)]
mod tests {
    use super::*;
    use crate::compute::Compute;
    use diffusion::device::Precision;

    fn job() -> EditJob {
        EditJob {
            max_views: 16,
            ..super::super::job::tests::job()
        }
    }

    /// With the card's free memory known, the automatic view batch is the most views whose call fits
    /// in it beside the run's other device memory, and the plan reports the free memory it checked.
    #[test]
    fn view_batch_follows_the_free_memory_the_card_reports() {
        let Some(mut ctx) = gpu::testing::context_or_skip() else {
            return;
        };
        let cpu = EditModel::load(&testkit::paths::tiny_lcm(), None).unwrap();
        let scene = GaussianScene::new(0);
        let job = job();
        let on = |free: Option<u64>, ctx: &mut gpu::GpuContext| {
            ctx.limits.free_bytes_at_open = free;
            EditModel::load(&testkit::paths::tiny_lcm(), None)
                .unwrap()
                .on(Compute::on(Some(ctx.clone()), Precision::F32))
        };
        let model = on(None, &mut ctx);
        let f = model.downscale();
        let (lh, lw) = (64 / f, 64 / f);
        let state = gpu_state_bytes(&job, &model, &scene, 16);
        let needs = |views: usize| {
            state
                + model
                    .unet
                    .config()
                    .activation_estimate(6 * views, lh, lw, 77, true)
                    .unwrap()
                    .total() as u64
        };
        assert!(state > 0 && needs(2) > needs(1));
        assert_eq!(gpu_state_bytes(&job, &cpu, &scene, 16), 0);

        let exactly_three = on(Some(needs(3)), &mut ctx);
        assert_eq!(view_batch(&job, &exactly_three, &scene, 16), 3);
        let just_short_of_three = on(Some(needs(3) - 1), &mut ctx);
        assert_eq!(view_batch(&job, &just_short_of_three, &scene, 16), 2);
        // Too little for even one view: one view per call, and the plan's check refuses the run.
        let too_little = on(Some(needs(1) - 1), &mut ctx);
        assert_eq!(view_batch(&job, &too_little, &scene, 16), 1);
        let plan = work_plan(&job, &too_little, &scene, 16);
        assert_eq!(plan.gpu_memory_bytes, Some(needs(1)));
        assert_eq!(plan.gpu_free_bytes, Some(needs(1) - 1));
        assert!(plan.describe().contains(" GB free"), "{}", plan.describe());
        // Plenty: as many views as the cap and the number of views allow.
        let plenty = on(Some(u64::MAX / 4), &mut ctx);
        assert_eq!(view_batch(&job, &plenty, &scene, 16), MAX_AUTO_VIEW_BATCH);
        assert_eq!(view_batch(&job, &plenty, &scene, 5), 5);
        // An explicit --view-batch and the CPU are not the budget's business.
        let fixed = EditJob {
            view_batch: Some(4),
            ..job.clone()
        };
        assert_eq!(view_batch(&fixed, &too_little, &scene, 16), 4);
        assert_eq!(view_batch(&job, &cpu, &scene, 16), 1);
        assert_eq!(work_plan(&job, &cpu, &scene, 16).gpu_free_bytes, None);
    }
}
