//! Renderer benchmarks: forward and forward+backward at 256² and 512² with 30k, 125k and 500k Gaussians,
//! plus the real playbot-31k scene when the shared assets are present.
//!
//! Run: `cargo bench -p vcedit-splat --bench render` (add `-- quick` for one size, `-- stages` for a
//! per-stage breakdown, `-- gpu` for the GPU renderer at 125k 512² beside the CPU (`-- gpu quick`: 30k), `-- channels` for extra-channel rendering and lifting with 24..300 channels). Synthetic scenes fill a unit ball the way trained scenes fill their volume:
//! log-normal, anisotropic scales around the typical neighbour spacing, random rotations, opacities
//! spread over (0, 1) with many near-opaque Gaussians, and SH degree 3.

use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal};
use splat::cameras::orbit::look_at;
use splat::lift::lift;
use splat::render::{
    profile_stages, render, render_backward, ExtraChannels, OutputGrads, RenderSettings,
};
use splat::{Camera, GaussianScene};
use std::time::{Duration, Instant};

fn ball_scene(n: usize, seed: u64) -> GaussianScene {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let normal = Normal::new(0.0f32, 1.0).unwrap();
    // Typical spacing of n points in the unit ball; scales are log-normal around half of it.
    let spacing = (4.19f32 / n as f32).cbrt();
    let mut s = GaussianScene::new(3);
    for _ in 0..n {
        let dir: [f32; 3] = std::array::from_fn(|_| normal.sample(&mut rng));
        let len = (dir[0] * dir[0] + dir[1] * dir[1] + dir[2] * dir[2])
            .sqrt()
            .max(1e-6);
        let r = rng.gen::<f32>().cbrt();
        s.means.extend(dir.map(|v| v / len * r));
        let base = (0.5 * spacing).ln() + 0.5 * normal.sample(&mut rng);
        for _ in 0..3 {
            s.log_scales.push(base + 0.4 * normal.sample(&mut rng));
        }
        s.quats.extend((0..4).map(|_| normal.sample(&mut rng)));
        s.opacity_logits.push(1.0 + 2.0 * normal.sample(&mut rng));
        for k in 0..16 {
            for _ in 0..3 {
                s.sh.push(if k == 0 {
                    normal.sample(&mut rng)
                } else {
                    0.1 * normal.sample(&mut rng)
                });
            }
        }
    }
    s
}

fn camera(size: u32) -> Camera {
    // 50° field of view from distance 3: the ball fills most of the frame.
    let focal = size as f64 / 2.0 / (25f64.to_radians()).tan();
    look_at(
        "bench".into(),
        [0.6, -0.8, -2.8],
        [0.0; 3],
        [0.0, -1.0, 0.0],
        size,
        size,
        focal,
    )
}

/// CPU time (user + system) consumed so far by this process, from /proc (Linux; None elsewhere). On a
/// busy machine this is a steadier measure than wall time: wall ≈ CPU / threads on an idle machine.
fn process_cpu_time() -> Option<Duration> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // Fields after the parenthesised command name; utime and stime are fields 14 and 15.
    let rest = &stat[stat.rfind(')')? + 2..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks: u64 = f.get(11)?.parse::<u64>().ok()? + f.get(12)?.parse::<u64>().ok()?;
    Some(Duration::from_secs_f64(ticks as f64 / 100.0))
}

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
    let grads = OutputGrads {
        rgb: &grad,
        alpha: None,
        depth: None,
        extra: None,
    };
    // Warm-up (page faults, thread pool).
    let out = render(scene, cam, &settings, None);
    let _ = render_backward(scene, cam, &settings, None, &out, &grads);
    let (mut fwd, mut bwd) = (vec![], vec![]);
    let mut isects = 0;
    let cpu_start = process_cpu_time();
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
    let cpu = match (cpu_start, process_cpu_time()) {
        (Some(a), Some(b)) => format!("{:.1} ms", (b - a).as_secs_f64() * 1e3 / runs as f64),
        _ => "n/a".into(),
    };
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

/// Forward and backward on the GPU with the scene and frame on the device (the timings include waiting
/// for the device; the only host read is the pair count inside the forward).
fn bench_gpu(ctx: &gpu::GpuContext, label: &str, scene: &GaussianScene, cam: &Camera, runs: usize) {
    use splat::gpu::{render_backward_device, render_device, GpuOutputGrads, GpuScene};
    let settings = RenderSettings::default();
    let npix = (cam.width * cam.height) as usize;
    let grad: Vec<f32> = (0..3 * npix)
        .map(|i| ((i % 7) as f32 - 3.0) * 0.01)
        .collect();
    let dev = GpuScene::upload(ctx, scene);
    let grad = gpu::prims::upload_f32(&ctx.client, &grad);
    let sync = || gpu::cubecl::future::block_on(ctx.client.sync()).expect("device failed");
    let grads = GpuOutputGrads {
        rgb: &grad,
        alpha: None,
        depth: None,
        extra: None,
    };
    // Warm-up: kernel compilation.
    let frame = render_device(ctx, &dev, cam, &settings, None).expect("forward");
    render_backward_device(ctx, &dev, &settings, None, &frame, &grads).expect("backward");
    sync();
    let (mut fwd, mut bwd) = (vec![], vec![]);
    let mut isects = 0;
    for _ in 0..runs {
        let t = Instant::now();
        let frame = render_device(ctx, &dev, cam, &settings, None).expect("forward");
        sync();
        fwd.push(t.elapsed());
        isects = frame.intersections;
        let t = Instant::now();
        let g =
            render_backward_device(ctx, &dev, &settings, None, &frame, &grads).expect("backward");
        sync();
        bwd.push(t.elapsed());
        std::hint::black_box(g);
    }
    let (f, b) = (median(fwd), median(bwd));
    println!(
        "{label:<14} {:>4}x{:<4} GPU forward {:>7.1} ms  backward {:>7.1} ms  fwd+bwd {:>7.1} ms  ({} tile entries)",
        cam.width,
        cam.height,
        f.as_secs_f64() * 1e3,
        b.as_secs_f64() * 1e3,
        (f + b).as_secs_f64() * 1e3,
        isects
    );
}

/// `-- gpu`: the GPU renderer (any adapter, software ones included) beside the CPU one.
fn main_gpu(quick: bool) {
    let ctx = match gpu::open(gpu::DeviceChoice::Gpu) {
        Ok(Some(ctx)) => ctx,
        Ok(None) | Err(_) => {
            println!("SKIP gpu: no GPU adapter");
            return;
        }
    };
    println!("GPU: {}", ctx.describe());
    let counts: &[usize] = if quick { &[30_000] } else { &[125_000] };
    for &n in counts {
        let scene = ball_scene(n, 1);
        let cam = camera(512);
        let label = format!("ball {}k", n / 1000);
        bench_gpu(&ctx, &label, &scene, &cam, 3);
        bench(&label, &scene, &cam, 3, false);
    }
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let quick = args.iter().any(|a| a == "quick");
    if args.iter().any(|a| a == "gpu") {
        return main_gpu(quick);
    }
    if args.iter().any(|a| a == "channels") {
        let scene = ball_scene(125_000, 1);
        for channels in [24, 96, 300] {
            bench_channels(&scene, 512, channels);
        }
        return;
    }
    let stages = args.iter().any(|a| a == "stages");
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
    let playbot = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../../shared/assets/scenes/playbot-31k.ply");
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
}
