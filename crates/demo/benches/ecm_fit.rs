//! ECM's two appearance fits on the CPU, shaped as in `vcedit demo`: the demo's procedural scene (~23k
//! Gaussians, its object mask), 16 views at 128², the target and layout fits side by side
//! (`SceneFitter::fit_pair`) to targets whose object changed colour.
//!
//! `cargo bench -p vcedit-demo --bench ecm_fit [-- --views 16 --size 128 --steps 96 --runs 1 --single]`
//!
//! `--steps`: Adam steps of each fit (the demo's fits take 576); `--single`: one fit instead of the pair.
//! Prints the wall and process CPU time per fit step and a fingerprint of the fitted scenes' colours and
//! opacities, so two builds can be checked for bit-identical fits.

use std::path::PathBuf;
use std::time::Instant;

use demo::run::{demo_job, demo_scene, DemoOptions, Variant};
use edit::consistency::{EcmFitter, EcmSettings, SceneFitter};
use edit::fit::{EditTrainer, ImageLoss};
use edit::run::scene_extent;
use splat::{GaussianScene, SplatDevice};

mod support;
use support::number;

/// Process CPU seconds (user + system) so far.
fn cpu_seconds() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    // Fields after the command's closing parenthesis; utime and stime are the 12th and 13th of them.
    let rest = stat.rsplit_once(')').map_or("", |(_, r)| r);
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks = |i: usize| f.get(i).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
    (ticks(11) + ticks(12)) / 100.0
}

/// FNV-1a over the bit patterns of the fitted colours and opacities.
fn fingerprint(scenes: &[GaussianScene]) -> u64 {
    let mut h = 0xcbf2_9ce4_8422_2325u64;
    for s in scenes {
        for v in s.sh.iter().chain(&s.opacity_logits) {
            for b in v.to_bits().to_le_bytes() {
                h = (h ^ b as u64).wrapping_mul(0x0100_0000_01b3);
            }
        }
    }
    h
}

fn main() {
    diffusion::runtime::tune_allocator();
    let args: Vec<String> = std::env::args().collect();
    let model_dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../models/demo");
    let mut opts = DemoOptions::new(model_dir, std::env::temp_dir());
    opts.views = number(&args, "--views", 16);
    opts.size = number(&args, "--size", 128) as u32;
    let steps = number(&args, "--steps", 96);
    let runs = number(&args, "--runs", 1);
    let single = args.iter().any(|a| a == "--single");
    let scene = demo_scene(&opts).expect("the demo scene builds");
    let job = demo_job(&opts, &scene, Variant::Full);
    let source = &scene.built.scene;
    let cams = &scene.cameras;
    let trainer = EditTrainer::new(
        source,
        Some(scene.mask.clone()),
        job.train.clone(),
        scene_extent(cams),
        job.background,
    );
    // Targets: the object's colours rotated (R → G → B → R), and a darker copy for the second fit.
    let mut shifted = source.clone();
    let k3 = 3 * shifted.sh_coeffs();
    for (i, sh) in shifted.sh.chunks_exact_mut(k3).enumerate() {
        if scene.mask[i] {
            sh[..3].rotate_left(1);
        }
    }
    let device = SplatDevice::Cpu;
    let targets = device
        .render_images(&shifted, cams, job.background)
        .expect("renders");
    let layouts: Vec<splat::Image> = targets
        .iter()
        .map(|t| {
            let mut t = t.clone();
            t.data.iter_mut().for_each(|v| *v *= 0.8);
            t
        })
        .collect();
    let ecm = EcmSettings {
        min_steps: steps,
        ..job.consistency.ecm.clone()
    };
    let loss = ImageLoss::dssim();
    let fitter = EcmFitter::new(&trainer, &loss, &ecm);
    let (epochs, _) = ecm.schedule(cams.len());
    let fit_steps = epochs * cams.len() * if single { 1 } else { 2 };
    eprintln!(
        "ECM fit probe: {} Gaussians ({} in the mask), {} views at {}², {} fit steps per run, {} threads",
        source.len(),
        scene.mask.iter().filter(|&&m| m).count(),
        cams.len(),
        opts.size,
        fit_steps,
        rayon::current_num_threads()
    );
    for run in 0..runs {
        let (wall, cpu) = (Instant::now(), cpu_seconds());
        let fitted: Vec<GaussianScene> = if single {
            vec![fitter.fit(source, cams, &targets, 7).expect("fits")]
        } else {
            fitter
                .fit_pair(source, cams, [&targets, &layouts], 7)
                .expect("fits")
                .into()
        };
        let (wall, cpu) = (wall.elapsed().as_secs_f64(), cpu_seconds() - cpu);
        println!(
            "RESULT {{\"what\":\"ecm_fit\",\"run\":{run},\"pair\":{},\"fit_steps\":{fit_steps},\"wall_s\":{wall:.3},\"cpu_s\":{cpu:.2},\"ms_per_step\":{:.3},\"cpu_ms_per_step\":{:.3},\"fingerprint\":\"{:016x}\"}}",
            !single,
            wall * 1e3 / fit_steps as f64,
            cpu * 1e3 / fit_steps as f64,
            fingerprint(&fitted)
        );
    }
}
