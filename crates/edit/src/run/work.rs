//! What a run will cost: the work it does and the memory it needs, shown (and checked) before it starts.

use diffusion::device::Precision;
use serde::Serialize;
use splat::GaussianScene;

use crate::fit::LPIPS_CACHE_BYTES;
use crate::sampler::EditModel;

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
    pub memory_bytes: u64,
    /// GPU memory the run needs on its device (`None` on the CPU).
    pub gpu_memory_bytes: Option<u64>,
    /// Views per UNet call.
    pub view_batch: usize,
}

impl WorkPlan {
    pub fn describe(&self) -> String {
        let gpu = self.gpu_memory_bytes.map_or(String::new(), |b| {
            format!(", GPU memory ≈ {:.1} GB", b as f64 / 1e9)
        });
        let batch = match self.view_batch {
            1 => "batch 6".to_string(),
            n => format!("batch 6 per view, {n} views per call"),
        };
        format!(
            "work: {} views × {} iterations: {} UNet passes ({batch}), {} renders, {} lifting passes, {} fitting steps; \
             memory needed ≈ {:.1} GB{gpu}",
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

/// Most views one UNet call takes when the choice is automatic.
pub const MAX_AUTO_VIEW_BATCH: usize = 8;

/// GPU memory the automatic view batch may give the UNet's activations. wgpu cannot report free memory
/// (gfx-rs/wgpu#2447), so this is a fixed share that leaves room for SD-1.5-sized weights, the scene and
/// the display on a 12 GB card; `--view-batch` overrides it either way.
pub const AUTO_VIEW_BATCH_GPU_BYTES: u64 = 6_000_000_000;

/// Views per UNet call: the job's choice, else 1 on the CPU (one view's batch of six already keeps every
/// core busy, and a larger batch only adds memory) and on a GPU the most views, up to
/// [`MAX_AUTO_VIEW_BATCH`] and the number of views, whose hooked call's activations fit in
/// [`AUTO_VIEW_BATCH_GPU_BYTES`] (a third of the device's memory where the backend states it) and whose
/// largest buffer fits the device's largest buffer.
pub fn view_batch(job: &EditJob, model: &EditModel, views: usize) -> usize {
    if let Some(n) = job.view_batch {
        return n.max(1);
    }
    let Some(gpu) = model.compute.networks() else {
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
    let max_buffer = gpu.context().limits.max_buffer_bytes;
    // With a stated memory size (some backends report one), a third of it; else a fixed share.
    let budget = gpu
        .context()
        .limits
        .memory_bytes
        .map_or(AUTO_VIEW_BATCH_GPU_BYTES, |m| m / 3);
    let fits = |n: usize| {
        (n * largest) as u64 <= max_buffer
            && config
                .activation_estimate(6 * n, lh, lw, 77, true)
                .is_ok_and(|e| e.total() as u64 <= budget)
    };
    (1..=MAX_AUTO_VIEW_BATCH.min(views.max(1)))
        .rev()
        .find(|&n| fits(n))
        .unwrap_or(1)
}

/// Counts the work of a run and estimates its peak memory.
pub fn work_plan(
    job: &EditJob,
    model: &EditModel,
    scene: &GaussianScene,
    cameras: usize,
) -> WorkPlan {
    let v = cameras.min(job.max_views);
    let view_batch = view_batch(job, model, v);
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
    // On a GPU: the networks' weights (f16 or f32 copies in the device cache), one hooked UNet call of
    // `view_batch` views (diffusion's documented upper bound; flash self-attention keeps no probability
    // matrix), the fit's device state (scene, gradients, two Adam moments, anchor snapshot) and the one
    // ECM fit alive at a time, one lifting's sums and one frame with CCM's channels.
    let gpu_memory_bytes = model.compute.networks().map(|gpu| {
        let weight_bytes = match gpu.precision() {
            Precision::F16 => model.parameters * 2,
            Precision::F32 => model.parameters * 4,
        };
        let (lh, lw) = ((h / f) as usize, (w / f) as usize);
        let activations = model
            .unet
            .config()
            .activation_estimate(6 * view_batch, lh, lw, 77, true)
            .map_or(unet, |e| e.total() as u64);
        let frame = w * h * 4 * (3 + 1 + 1 + 3 * heads * 8);
        weight_bytes + activations + params * 10 + n * 4 * (3 * heads * 8 + 1) + frame + 100_000_000
    });
    WorkPlan {
        views: v,
        iterations: job.iterations,
        unet_calls,
        renders,
        fit_steps,
        lifts,
        memory_bytes,
        gpu_memory_bytes,
        view_batch,
    }
}

const LPIPS_BUDGET: u64 = LPIPS_CACHE_BYTES as u64;

/// Memory available to a new run (Linux `MemAvailable`), if known.
pub fn available_memory() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}
