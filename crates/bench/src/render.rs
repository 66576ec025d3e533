//! Renderer benchmarks: forward and forward+backward at 256² and 512² with 30k, 125k and 500k Gaussians,
//! plus the real playbot-31k scene when the shared assets are present (or `--scene PLY`).
//!
//! `vcedit bench render` (add `quick` for one size, `stages` for a per-stage breakdown, `channels` for
//! extra-channel rendering and lifting with 24..300 channels).
//!
//! `gpu`: forward, backward, a full fit step (render, L1 + D-SSIM, backward, Adam, densification
//! statistics) and ECM's appearance step (the same with the geometry's rates at 0 and its projection
//! kept, no statistics; on the GPU 10 steps per wait for the device, as a fit queues them) beside the CPU, at 125k and 1M Gaussians, 512² and 1920x1080; `gpu
//! quick`: 30k at 512². Filters select cases: `n=125k,1m size=512,1080p device=cpu,gpu
//! stage=forward,backward,step,appearance runs=3 sh=3`, e.g. `gpu n=1m size=1080p device=gpu runs=1` (lavapipe
//! binds at most 128 MiB per buffer: 1M Gaussians need `sh=2` there). One `RESULT` line per
//! measurement, then a markdown table. Scenes: [`crate::scenes`].

use splat::cameras::orbit::look_at;
use splat::lift::lift;
use splat::render::{
    profile_stages, render, render_backward, render_backward_appearance, ExtraChannels, FrozenView,
    OutputGrads, RenderSettings,
};
use splat::{Camera, GaussianScene};
use std::time::{Duration, Instant};

use crate::scenes::{ball_scene, ball_scene_with_degree, camera, camera_wh};
use crate::{arg_value, cpu_seconds, has_flag, load_average, report, BenchError, Result};

fn median(mut v: Vec<Duration>) -> Duration {
    v.sort();
    v[v.len() / 2]
}

fn bench(label: &str, scene: &GaussianScene, cam: &Camera, runs: usize, stages: bool) {
    let settings = RenderSettings::default();
    let npix = (cam.width * cam.height) as usize;
    let grad: Vec<f32> = (0..3 * npix)
        .map(|i| ((i % 7) as f32 - 3.0) * 0.01)
        .collect();
    let grads = OutputGrads::rgb_only(&grad);
    // Warm-up (page faults, thread pool).
    let out = render(scene, cam, &settings, None);
    let _ = render_backward(scene, cam, &settings, None, &out, &grads);
    let (mut fwd, mut bwd) = (vec![], vec![]);
    let mut isects = 0;
    let cpu_start = cpu_seconds();
    for _ in 0..runs {
        let t = Instant::now();
        let out = render(scene, cam, &settings, None);
        fwd.push(t.elapsed());
        isects = out.tile_intersections();
        let t = Instant::now();
        let g = render_backward(scene, cam, &settings, None, &out, &grads);
        bwd.push(t.elapsed());
        std::hint::black_box(g);
    }
    let cpu = format!("{:.1} ms", (cpu_seconds() - cpu_start) * 1e3 / runs as f64);
    let (f, b) = (median(fwd), median(bwd));
    println!(
        "{label:<14} {:>4}x{:<4} forward {:>7.1} ms  backward {:>7.1} ms  fwd+bwd {:>7.1} ms  (CPU per fwd+bwd {cpu}; {} tile entries)",
        cam.width,
        cam.height,
        f.as_secs_f64() * 1e3,
        b.as_secs_f64() * 1e3,
        (f + b).as_secs_f64() * 1e3,
        isects
    );
    if stages {
        let mut acc: Vec<(&str, Vec<Duration>)> = vec![];
        for _ in 0..runs {
            for (i, (name, d)) in profile_stages(scene, cam, &settings)
                .into_iter()
                .enumerate()
            {
                if acc.len() <= i {
                    acc.push((name, vec![]));
                }
                acc[i].1.push(d);
            }
        }
        // The minimum over runs: the least disturbed by other processes.
        let parts: Vec<String> = acc
            .into_iter()
            .map(|(n, d)| format!("{n} {:.1}", d.iter().min().unwrap().as_secs_f64() * 1e3))
            .collect();
        println!("{:<14}   stages (min ms): {}", "", parts.join(", "));
    }
}

/// Forward render with C extra channels (as the editor renders attention maps) and lifting C-channel
/// maps from 4 views.
fn bench_channels(scene: &GaussianScene, size: u32, channels: usize) {
    let cam = camera(size);
    let settings = RenderSettings::default();
    let values: Vec<f32> = (0..scene.len() * channels)
        .map(|i| (i % 13) as f32 / 13.0)
        .collect();
    let extra = ExtraChannels {
        values: &values,
        channels,
    };
    let _ = render(scene, &cam, &settings, Some(extra));
    let runs = 3;
    let mut times = vec![];
    for _ in 0..runs {
        let t = Instant::now();
        std::hint::black_box(render(scene, &cam, &settings, Some(extra)));
        times.push(t.elapsed());
    }
    let fwd = median(times);
    let views: Vec<Camera> = (0..4)
        .map(|k| {
            let a = k as f64 * 1.3;
            let focal = size as f64 / 2.0 / (25f64.to_radians()).tan();
            look_at(
                format!("v{k}"),
                [2.9 * a.sin(), -0.6, -2.9 * a.cos()],
                [0.0; 3],
                [0.0, -1.0, 0.0],
                size,
                size,
                focal,
            )
        })
        .collect();
    let maps: Vec<Vec<f32>> = (0..4)
        .map(|k| {
            (0..(size * size) as usize * channels)
                .map(|i| ((i + k) % 7) as f32)
                .collect()
        })
        .collect();
    let map_refs: Vec<&[f32]> = maps.iter().map(|m| &m[..]).collect();
    let t = Instant::now();
    std::hint::black_box(lift(scene, &views, &map_refs, channels));
    let lifted = t.elapsed();
    println!(
        "ball {}k {size}x{size}, {channels} extra channels: forward {:.1} ms; lifting 4 views: {:.1} ms",
        scene.len() / 1000,
        fwd.as_secs_f64() * 1e3,
        lifted.as_secs_f64() * 1e3
    );
}

/// One measured case of the `gpu` matrix.
#[derive(Clone, Copy, Debug)]
struct Case {
    gaussians: usize,
    width: u32,
    height: u32,
}

impl Case {
    fn size_label(&self) -> String {
        match (self.width, self.height) {
            (1920, 1080) => "1080p".into(),
            (w, h) if w == h => format!("{w}²"),
            (w, h) => format!("{w}x{h}"),
        }
    }

    fn count_label(&self) -> String {
        match self.gaussians {
            n if n >= 1_000_000 && n.is_multiple_of(1_000_000) => format!("{}M", n / 1_000_000),
            n => format!("{}k", n / 1000),
        }
    }
}

/// Timings of one case on one device; `None` = stage not selected.
#[derive(Default)]
struct Timings {
    forward: Option<Duration>,
    backward: Option<Duration>,
    step: Option<Duration>,
    appearance: Option<Duration>,
}

/// What the command line selects: `n=125k,1m size=512,1080p device=cpu,gpu
/// stage=forward,backward,step,appearance runs=N sh=D` (each optional; comma-separated values; `sh`: the scenes' SH degree, 3 by default).
struct Selection {
    counts: Vec<usize>,
    sizes: Vec<(u32, u32)>,
    cpu: bool,
    gpu: bool,
    stages: [bool; 4],
    runs: Option<usize>,
    sh_degree: u32,
}

const STAGES: [&str; 4] = ["forward", "backward", "step", "appearance"];

fn parse_count(s: &str) -> Option<usize> {
    let s = s.to_ascii_lowercase();
    if let Some(k) = s.strip_suffix('k') {
        k.parse::<usize>().ok().map(|v| v * 1000)
    } else if let Some(m) = s.strip_suffix('m') {
        m.parse::<usize>().ok().map(|v| v * 1_000_000)
    } else {
        s.parse().ok()
    }
}

fn parse_size(s: &str) -> Option<(u32, u32)> {
    match s.to_ascii_lowercase().as_str() {
        "1080p" => Some((1920, 1080)),
        "720p" => Some((1280, 720)),
        s => match s.split_once('x') {
            Some((w, h)) => Some((w.parse().ok()?, h.parse().ok()?)),
            None => s.parse().ok().map(|v| (v, v)),
        },
    }
}

impl Selection {
    fn parse(args: &[String], quick: bool) -> std::result::Result<Self, String> {
        let mut sel = Self {
            counts: if quick {
                vec![30_000]
            } else {
                vec![125_000, 1_000_000]
            },
            sizes: if quick {
                vec![(512, 512)]
            } else {
                vec![(512, 512), (1920, 1080)]
            },
            cpu: true,
            gpu: true,
            stages: [true; 4],
            runs: None,
            sh_degree: 3,
        };
        for a in args {
            let Some((key, value)) = a.split_once('=') else {
                continue;
            };
            let values: Vec<&str> = value.split(',').filter(|v| !v.is_empty()).collect();
            let bad = || format!("bad filter '{a}'");
            match key {
                "n" => {
                    sel.counts = values
                        .iter()
                        .map(|v| parse_count(v))
                        .collect::<Option<_>>()
                        .ok_or_else(bad)?
                }
                "size" => {
                    sel.sizes = values
                        .iter()
                        .map(|v| parse_size(v))
                        .collect::<Option<_>>()
                        .ok_or_else(bad)?
                }
                "device" => {
                    sel.cpu = values.contains(&"cpu");
                    sel.gpu = values.contains(&"gpu");
                }
                "stage" => {
                    sel.stages = STAGES.map(|s| values.contains(&s));
                }
                "runs" => sel.runs = Some(value.parse().map_err(|_| bad())?),
                "sh" => {
                    sel.sh_degree = value.parse().map_err(|_| bad())?;
                    if sel.sh_degree > 3 {
                        return Err(bad());
                    }
                }
                _ => {
                    return Err(format!(
                        "unknown filter '{key}' (n, size, device, stage, runs, sh)"
                    ))
                }
            }
        }
        Ok(sel)
    }

    /// Runs per measurement: a few for the small cases, fewer where one run takes seconds.
    fn runs(&self, case: &Case, software_gpu: bool) -> usize {
        if let Some(r) = self.runs {
            return r.max(1);
        }
        let small = case.gaussians <= 125_000 && case.width * case.height <= 512 * 512;
        match (small, software_gpu) {
            (true, false) => 5,
            (true, true) | (false, false) => 3,
            (false, true) => 1,
        }
    }
}

/// Prints one machine-readable line per measurement.
fn report_line(
    device: &str,
    case: &Case,
    stage: &str,
    times: &[Duration],
    extra: serde_json::Value,
) {
    let ms = |d: Duration| (d.as_secs_f64() * 1e5).round() / 1e2;
    let min = times.iter().min().copied().unwrap_or_default();
    let mut fields = serde_json::json!({
        "bench": "render",
        "device": device,
        "gaussians": case.gaussians,
        "width": case.width,
        "height": case.height,
        "stage": stage,
        "runs": times.len(),
        "median_ms": ms(median(times.to_vec())),
        "min_ms": ms(min),
        "load": load_average(),
    });
    if let (Some(map), serde_json::Value::Object(more)) = (fields.as_object_mut(), extra) {
        map.extend(more);
    }
    report(fields);
}

/// CPU: forward, backward and one fit step (render, L1 + D-SSIM, backward, Adam, densification stats).
fn measure_cpu(scene: &GaussianScene, case: &Case, runs: usize, stages: [bool; 4]) -> Timings {
    use splat::train::loss::l1_dssim;
    use splat::train::optim::LearningRates;
    use splat::train::{RenderedView, TrainState};
    let cam = camera_wh(case.width, case.height);
    let settings = RenderSettings::default();
    let npix = (cam.width * cam.height) as usize;
    let grad = pattern_grad(npix);
    let grads = OutputGrads::rgb_only(&grad);
    let mut out = Timings::default();
    let mut fwd = vec![];
    let mut bwd = vec![];
    let frame = render(scene, &cam, &settings, None);
    if stages[0] || stages[1] {
        for _ in 0..runs {
            let t = Instant::now();
            let frame = std::hint::black_box(render(scene, &cam, &settings, None));
            fwd.push(t.elapsed());
            if stages[1] {
                let t = Instant::now();
                std::hint::black_box(render_backward(
                    scene, &cam, &settings, None, &frame, &grads,
                ));
                bwd.push(t.elapsed());
            }
        }
        let isects = serde_json::json!({"intersections": frame.tile_intersections()});
        if stages[0] {
            report_line("cpu", case, "forward", &fwd, isects.clone());
            out.forward = Some(median(fwd));
        }
        if stages[1] {
            report_line("cpu", case, "backward", &bwd, isects);
            out.backward = Some(median(bwd));
        }
    }
    if stages[2] {
        let target = pattern_target(npix);
        let mut state = TrainState::new(scene.clone(), LearningRates::inria(30_000), 3.0);
        let (w, h) = (cam.width as usize, cam.height as usize);
        let mut steps = vec![];
        for _ in 0..runs {
            let t = Instant::now();
            let frame = render(&state.scene, &cam, &settings, None);
            let loss = l1_dssim(&frame.rgb, &target, w, h, 3, 0.2);
            let g = render_backward(
                &state.scene,
                &cam,
                &settings,
                None,
                &frame,
                &OutputGrads::rgb_only(&loss.grad),
            );
            state.step(&g);
            state
                .stats
                .add(&RenderedView::new(&g, &frame.radii, &cam), 1);
            steps.push(t.elapsed());
        }
        report_line("cpu", case, "step", &steps, serde_json::Value::Null);
        out.step = Some(median(steps));
    }
    if stages[3] {
        let target = pattern_target(npix);
        let mut state = appearance_state(scene);
        let (w, h) = (cam.width as usize, cam.height as usize);
        let t = Instant::now();
        let view = FrozenView::new(scene, &cam);
        let keep_ms = t.elapsed().as_secs_f64() * 1e3;
        let mut steps = vec![];
        for _ in 0..runs {
            let t = Instant::now();
            let frame = view.render(&state.scene, &settings);
            let loss = l1_dssim(&frame.rgb, &target, w, h, 3, 0.2);
            let g = render_backward_appearance(
                &state.scene,
                &cam,
                &settings,
                &frame,
                &OutputGrads::rgb_only(&loss.grad),
            );
            state.step(&g);
            steps.push(t.elapsed());
        }
        report_line(
            "cpu",
            case,
            "appearance",
            &steps,
            serde_json::json!({"keep_ms": keep_ms}),
        );
        out.appearance = Some(median(steps));
    }
    out
}

/// Steps per wait for the device in the GPU's appearance-step runs.
const APPEARANCE_BATCH: usize = 10;

/// A fit state whose means, scales and rotations have rate 0, as ECM's appearance fits.
fn appearance_state(scene: &GaussianScene) -> splat::train::TrainState {
    use splat::train::optim::{Group, LearningRates};
    let mut state = splat::train::TrainState::new(scene.clone(), LearningRates::inria(30_000), 3.0);
    for g in [Group::Means, Group::LogScales, Group::Quats] {
        state.adam.group_lr_scale[g.index()] = 0.0;
    }
    state
}

/// A fixed dL/d rgb for the backward benches.
fn pattern_grad(npix: usize) -> Vec<f32> {
    (0..3 * npix)
        .map(|i| ((i % 7) as f32 - 3.0) * 0.01)
        .collect()
}

/// A fixed target image for the fit-step benches.
fn pattern_target(npix: usize) -> Vec<f32> {
    (0..3 * npix).map(|i| (i % 11) as f32 / 10.0).collect()
}

/// GPU: the same three stages with the scene, frame, target and optimiser state on the device. Times
/// include waiting for the device (each stage ends with a sync); the forward reads one 4-byte count.
fn measure_gpu(
    ctx: &gpu::GpuContext,
    scene: &GaussianScene,
    case: &Case,
    runs: usize,
    stages: [bool; 4],
) -> std::result::Result<Timings, gpu::GpuError> {
    use splat::stages::{
        render_backward_device, render_device, DeviceTrainer, GpuOutputGrads, GpuScene,
    };
    use splat::train::optim::LearningRates;
    use splat::train::TrainState;
    let cam = camera_wh(case.width, case.height);
    let settings = RenderSettings::default();
    let npix = (cam.width * cam.height) as usize;
    let sync = || gpu::cubecl::future::block_on(ctx.client.sync()).map_err(gpu::server_error);
    let mut out = Timings::default();
    if stages[0] || stages[1] {
        let dev = GpuScene::upload(ctx, scene);
        let grad = gpu::prims::upload_f32(&ctx.client, &pattern_grad(npix));
        let grads = GpuOutputGrads::rgb_only(&grad);
        // Warm-up: kernel compilation, timed apart.
        let t = Instant::now();
        let frame = render_device(ctx, &dev, &cam, &settings, None)?;
        sync()?;
        let first_forward = t.elapsed();
        let t = Instant::now();
        if stages[1] {
            render_backward_device(ctx, &dev, &settings, None, &frame, &grads)?;
        }
        sync()?;
        let first_backward = t.elapsed();
        let isects = |first: Duration| serde_json::json!({"intersections": frame.intersections, "first_ms": first.as_secs_f64() * 1e3});
        let (extra_forward, extra_backward) = (isects(first_forward), isects(first_backward));
        drop(frame);
        let (mut fwd, mut bwd) = (vec![], vec![]);
        for _ in 0..runs {
            let t = Instant::now();
            let frame = render_device(ctx, &dev, &cam, &settings, None)?;
            sync()?;
            fwd.push(t.elapsed());
            if stages[1] {
                let t = Instant::now();
                let g = render_backward_device(ctx, &dev, &settings, None, &frame, &grads)?;
                sync()?;
                bwd.push(t.elapsed());
                std::hint::black_box(g);
            }
        }
        if stages[0] {
            report_line("gpu", case, "forward", &fwd, extra_forward);
            out.forward = Some(median(fwd));
        }
        if stages[1] {
            report_line("gpu", case, "backward", &bwd, extra_backward);
            out.backward = Some(median(bwd));
        }
    }
    if stages[2] {
        let mut state = TrainState::new(scene.clone(), LearningRates::inria(30_000), 3.0);
        let mut trainer = DeviceTrainer::upload(ctx, &state);
        let target = gpu::prims::upload_f32(&ctx.client, &pattern_target(npix));
        let t = Instant::now();
        trainer.step(ctx, &mut state.adam, &cam, &target, &settings, 0.2, true)?;
        sync()?;
        let first_step = t.elapsed();
        let mut steps = vec![];
        for _ in 0..runs {
            let t = Instant::now();
            std::hint::black_box(trainer.step(
                ctx,
                &mut state.adam,
                &cam,
                &target,
                &settings,
                0.2,
                true,
            )?);
            sync()?;
            steps.push(t.elapsed());
        }
        report_line(
            "gpu",
            case,
            "step",
            &steps,
            serde_json::json!({"first_ms": first_step.as_secs_f64() * 1e3}),
        );
        out.step = Some(median(steps));
    }
    if stages[3] {
        let mut state = appearance_state(scene);
        let mut trainer = DeviceTrainer::upload(ctx, &state);
        trainer.freeze_geometry();
        let target = gpu::prims::upload_f32(&ctx.client, &pattern_target(npix));
        // A kept view's step reads nothing back, so steps queue on the device as in a fit: each run
        // times `APPEARANCE_BATCH` steps and one wait, per step.
        let mut steps_then_sync = |state: &mut TrainState, count: usize| {
            let t = Instant::now();
            for _ in 0..count {
                trainer.step(ctx, &mut state.adam, &cam, &target, &settings, 0.2, false)?;
            }
            sync()?;
            Ok::<_, gpu::GpuError>(t.elapsed() / count as u32)
        };
        // The first step compiles and keeps the view's projection and tile lists.
        let first_step = steps_then_sync(&mut state, 1)?;
        let mut steps = vec![];
        for _ in 0..runs {
            steps.push(steps_then_sync(&mut state, APPEARANCE_BATCH)?);
        }
        report_line(
            "gpu",
            case,
            "appearance",
            &steps,
            serde_json::json!({"first_ms": first_step.as_secs_f64() * 1e3, "steps_per_sync": APPEARANCE_BATCH}),
        );
        out.appearance = Some(median(steps));
    }
    Ok(out)
}

/// `-- gpu [quick] [filters]`: forward, backward and a full fit step of the GPU renderer (any adapter,
/// software ones included) beside the CPU one, for 125k and 1M Gaussians at 512² and 1080p (`quick`: 30k
/// at 512²). Filters: see [`Selection`]. Prints one `BENCH {json}` line per measurement, then a markdown
/// table of medians.
fn main_gpu(args: &[String], quick: bool) -> Result<()> {
    let sel = Selection::parse(args, quick).map_err(BenchError::new)?;
    let ctx = if sel.gpu {
        match gpu::open_for(gpu::DeviceChoice::Gpu, gpu::Workload::Splatting) {
            Ok(Some(ctx)) => Some(ctx),
            // Asked for the GPU alone: its absence is the answer, an error (with the reason).
            Err(e) if !sel.cpu => return Err(e.into()),
            Ok(None) if !sel.cpu => return Err(BenchError::new("no GPU adapter")),
            Ok(None) | Err(_) => {
                println!("SKIP gpu: no GPU adapter");
                None
            }
        }
    } else {
        None
    };
    if let Some(ctx) = &ctx {
        println!("GPU: {}", ctx.describe());
    }
    println!(
        "CPU: {} rayon threads; load average {}",
        rayon::current_num_threads(),
        load_average().map_or("n/a".into(), |l| format!("{l:.2}"))
    );
    let mut rows = vec![];
    for &n in &sel.counts {
        let scene = ball_scene_with_degree(n, 1, sel.sh_degree);
        for &(width, height) in &sel.sizes {
            let case = Case {
                gaussians: n,
                width,
                height,
            };
            if let Some(ctx) = &ctx {
                let runs = sel.runs(&case, ctx.software);
                match measure_gpu(ctx, &scene, &case, runs, sel.stages) {
                    Ok(t) => rows.push((case, "GPU", runs, t)),
                    Err(e) => {
                        println!("SKIP gpu {} {}: {e}", case.count_label(), case.size_label())
                    }
                }
            }
            if sel.cpu {
                let runs = sel.runs(&case, false);
                let t = measure_cpu(&scene, &case, runs, sel.stages);
                rows.push((case, "CPU", runs, t));
            }
        }
    }
    let device = ctx.as_ref().map_or("no GPU".into(), |c| c.describe());
    println!(
        "\nGPU = {device}; SH degree {}; medians in ms (runs in brackets).\n",
        sel.sh_degree
    );
    println!(
        "| Gaussians | size | device | forward | backward | fwd+bwd | fit step | appearance step |"
    );
    println!("| --- | --- | --- | --- | --- | --- | --- | --- |");
    let ms =
        |d: Option<Duration>| d.map_or("–".into(), |d| format!("{:.1}", d.as_secs_f64() * 1e3));
    for (case, dev, runs, t) in rows {
        let both = t.forward.zip(t.backward).map(|(f, b)| f + b);
        println!(
            "| {} | {} | {dev} ({runs}) | {} | {} | {} | {} | {} |",
            case.count_label(),
            case.size_label(),
            ms(t.forward),
            ms(t.backward),
            ms(both),
            ms(t.step),
            ms(t.appearance)
        );
    }
    Ok(())
}

pub fn main(args: &[String]) -> Result<()> {
    let quick = has_flag(args, "quick");
    if has_flag(args, "gpu") {
        return main_gpu(args, quick);
    }
    if has_flag(args, "channels") {
        let scene = ball_scene(125_000, 1);
        for channels in [24, 96, 300] {
            bench_channels(&scene, 512, channels);
        }
        return Ok(());
    }
    let stages = has_flag(args, "stages");
    println!("rayon threads: {}", rayon::current_num_threads());
    let counts: &[usize] = if quick {
        &[125_000]
    } else {
        &[30_000, 125_000, 500_000]
    };
    let sizes: &[u32] = if quick { &[512] } else { &[256, 512] };
    for &n in counts {
        let scene = ball_scene(n, 1);
        for &size in sizes {
            let runs = if n >= 500_000 { 3 } else { 7 };
            bench(
                &format!("ball {}k", n / 1000),
                &scene,
                &camera(size),
                runs,
                stages,
            );
        }
    }
    let playbot = arg_value(args, "--scene").map_or_else(
        || {
            std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("../../../shared/assets/scenes/playbot-31k.ply")
        },
        std::path::PathBuf::from,
    );
    match splat::ply::read_ply(&playbot) {
        Ok(scene) => {
            for &size in sizes {
                let focal = size as f64 / 2.0 / (25f64.to_radians()).tan();
                let cam = look_at(
                    "playbot".into(),
                    [0.0, -1.2, -3.0],
                    [0.0, -0.5, 0.0],
                    [0.0, -1.0, 0.0],
                    size,
                    size,
                    focal,
                );
                bench("playbot-31k", &scene, &cam, 7, stages);
            }
        }
        Err(e) => println!("SKIP playbot-31k: {e}"),
    }
    Ok(())
}
