//! One whole edit iteration of the demo, timed stage by stage, on the CPU and on the GPU: render the views,
//! edit them together (InfEdit with CCM, ECM and the consistent blend), fit the scene to the edits.
//!
//! `cargo bench -p vcedit-demo --bench iteration [-- --devices cpu,gpu --views 4 --size 128 --steps 15
//! --fit-steps 300 --view-batch N --precision f16|f32]`
//!
//! Uses the demo model of this checkout (`models/demo`) and the demo's procedural scene, so it needs no
//! files. `gpu` takes the adapter `VCEDIT_DEVICE` rules pick (a software one such as lavapipe only when
//! named: `--devices cpu,gpu` counts as naming it). Prints a table and one `RESULT {json}` line per device.

use std::path::PathBuf;
use std::time::Instant;

use demo::run::{demo_job, demo_scene, load_model, DemoOptions, Variant};
use diffusion::device::Precision;
use edit::compute::Compute;
use edit::fit::ImageLoss;
use edit::run::{run_edit, IterationTimes, Quiet};

mod support;
use support::{arg_value, number};

fn main() {
    // As the `vcedit` binary does (edit and demo run with it).
    diffusion::runtime::tune_allocator();
    let args: Vec<String> = std::env::args().collect();
    let devices = arg_value(&args, "--devices").unwrap_or_else(|| "cpu,gpu".into());
    let precision: Precision = arg_value(&args, "--precision")
        .unwrap_or_else(|| "f16".into())
        .parse()
        .expect("--precision f16|f32");
    let model_dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../models/demo");
    let work = tempfile::tempdir().expect("a temporary folder");
    let mut opts = DemoOptions::new(model_dir.clone(), work.path().to_path_buf());
    opts.views = number(&args, "--views", 4);
    opts.size = number(&args, "--size", 128) as u32;
    opts.steps = number(&args, "--steps", 15);
    opts.fit_steps = number(&args, "--fit-steps", 300);
    opts.iterations = 1;
    let view_batch = arg_value(&args, "--view-batch").map(|v| v.parse().expect("--view-batch N"));
    let scene = demo_scene(&opts).expect("the demo scene builds");
    eprintln!(
        "iteration bench: {} Gaussians, {} views at {}², {} steps, {} fit steps",
        scene.built.scene.len(),
        opts.views,
        opts.size,
        opts.steps,
        opts.fit_steps
    );

    let mut rows = Vec::new();
    for device in devices.split(',') {
        let ctx = match device {
            "cpu" => None,
            "gpu" => match gpu::open(gpu::DeviceChoice::Gpu) {
                Ok(Some(ctx)) => Some(ctx),
                Ok(None) | Err(_) => {
                    eprintln!("SKIP gpu: no GPU adapter found");
                    continue;
                }
            },
            other => panic!("--devices takes cpu and/or gpu, not {other}"),
        };
        let name = ctx
            .as_ref()
            .map_or_else(|| "CPU".to_string(), |c| c.adapter.clone());
        let model = load_model(&model_dir)
            .expect("the demo model loads")
            .on(Compute::on(ctx, precision));
        let mut job = demo_job(&opts, &scene, Variant::Full);
        job.view_batch = view_batch;
        let out = work.path().join(device);
        let start = Instant::now();
        let result = run_edit(
            &job,
            &model,
            &ImageLoss::dssim(),
            &scene.built.scene,
            &scene.cameras,
            &out,
            false,
            &mut Quiet,
        )
        .expect("the edit runs");
        let wall = start.elapsed().as_secs_f64();
        let t: IterationTimes = result.times[0].clone();
        let s = &t.sampler;
        println!(
            "RESULT {{\"what\":\"edit_iteration\",\"device\":\"{name}\",\"views\":{},\"size\":{},\"steps\":{},\"fit_steps\":{},\
             \"render\":{:.2},\"encode\":{:.2},\"unet\":{:.2},\"ccm\":{:.2},\"ecm\":{:.2},\"blend\":{:.2},\"decode\":{:.2},\"fit\":{:.2},\"total\":{:.2},\"wall\":{wall:.2}}}",
            opts.views, opts.size, opts.steps, opts.fit_steps,
            t.render, s.encode, s.unet, s.ccm, s.ecm, s.blend, s.decode, t.fit, t.total()
        );
        rows.push((name, t, wall));
    }
    println!("\n| device | render | encode | UNet | CCM | ECM | blend | decode | fit | iteration | wall |");
    println!("|---|---|---|---|---|---|---|---|---|---|---|");
    for (name, t, wall) in rows {
        let s = &t.sampler;
        println!(
            "| {name} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {wall:.1} |",
            t.render, s.encode, s.unet, s.ccm, s.ecm, s.blend, s.decode, t.fit, t.total()
        );
    }
}
