//! CCM's 2D → 3D → 2D round (`SplatDevice::lift_and_render_back`): per-view maps on a coarse grid with
//! many channels (SD 1.5's small cross-attention layers: 16² maps, 3 branches × 8 heads × the prompt's
//! real tokens) resampled to the render resolution, lifted onto a scene over every view and rendered back.
//! Beside it, the same round as it ran before the resampling moved onto the device (`host`): each view's
//! full-resolution map resampled on the host, uploaded, and rendered back in full. At 512² and 144
//! channels that map is 150 MB per view and layer. And a later round of one `LiftSession` (the scene
//! uploaded and each view projected and binned by an earlier round), as CCM's later layers run.
//!
//! `vcedit bench lift [--gaussians 31000] [--views 8] [--size 512] [--grid 16] [--channels 144]
//! [--runs 3] [--device cpu|gpu|auto]` (a GPU opens as an edit opens it: the networks' compiler).

use splat::lift::{resample, MapGrid, Resample};
use splat::render::{ExtraChannels, RenderSettings};
use splat::{Camera, GaussianScene, GpuError, SplatDevice};

use crate::scenes::{ball_scene_with_degree, camera};
use crate::{arg_parsed, arg_value, report, sync, BenchError, Result, Timed};

/// A smooth map per view with values in [0, 1], different per channel and view.
pub(crate) fn map(grid: &MapGrid, view: usize) -> Vec<f32> {
    (0..grid.len())
        .map(|i| 0.5 + 0.5 * ((i as f32) * 0.37 + view as f32).sin())
        .collect()
}

/// `views` cameras around the ball, all at `size`².
pub(crate) fn cameras(views: usize, size: u32) -> Vec<Camera> {
    let base = camera(size);
    (0..views)
        .map(|v| {
            let yaw = v as f64 * std::f64::consts::TAU / views as f64;
            let (s, c) = yaw.sin_cos();
            let centre = base.center();
            let eye = [
                c * centre[0] - s * centre[2],
                centre[1],
                s * centre[0] + c * centre[2],
            ];
            splat::cameras::orbit::look_at(
                format!("v{v}"),
                eye,
                [0.0; 3],
                [0.0, -1.0, 0.0],
                size,
                size,
                base.fx,
            )
        })
        .collect()
}

/// The round as it ran before: host resampling, full-resolution maps up and down the bus.
fn host_round(
    device: &SplatDevice,
    scene: &GaussianScene,
    cams: &[Camera],
    grid: &MapGrid,
) -> std::result::Result<f32, GpuError> {
    let native = (grid.height, grid.width);
    let full = |c: &Camera| (c.height as usize, c.width as usize);
    let mut lift = device.lifter(scene, grid.channels);
    for (v, cam) in cams.iter().enumerate() {
        lift.add_view(
            cam,
            &resample(&map(grid, v), native, full(cam), grid.channels, grid.up),
        )?;
    }
    let lifted = lift.finish()?;
    let extra = ExtraChannels {
        values: &lifted.values,
        channels: grid.channels,
    };
    let mut total = 0.0;
    device.for_each_render::<GpuError>(
        scene,
        cams,
        &RenderSettings::default(),
        Some(extra),
        &mut |v, frame| {
            let back = resample(
                &frame.extra,
                full(&cams[v]),
                native,
                grid.channels,
                grid.down,
            );
            total += back.iter().sum::<f32>();
            Ok(())
        },
    )?;
    Ok(total)
}

/// The round through the device seam.
fn device_round(
    device: &SplatDevice,
    scene: &GaussianScene,
    cams: &[Camera],
    grid: &MapGrid,
) -> std::result::Result<f32, GpuError> {
    let mut total = 0.0;
    device.lift_and_render_back::<GpuError>(
        scene,
        cams,
        grid,
        &mut |v| Ok(map(grid, v)),
        &mut |_, back| {
            total += back.iter().sum::<f32>();
            Ok(())
        },
    )?;
    Ok(total)
}

pub fn main(args: &[String]) -> Result<()> {
    let gaussians: usize = arg_parsed(args, "--gaussians", 31_000)?;
    let views: usize = arg_parsed(args, "--views", 8)?;
    let size: u32 = arg_parsed(args, "--size", 512)?;
    let cells: usize = arg_parsed(args, "--grid", 16)?;
    let channels: usize = arg_parsed(args, "--channels", 144)?;
    let runs: usize = arg_parsed(args, "--runs", 3)?;
    let choice: gpu::DeviceChoice = arg_value(args, "--device")
        .unwrap_or_else(|| "cpu".into())
        .parse()?;
    if views == 0 || size == 0 || cells == 0 || channels == 0 {
        return Err(BenchError::new(
            "--views, --size, --grid and --channels must be positive",
        ));
    }
    let device = SplatDevice::from(gpu::open_for(choice, gpu::Workload::Networks)?);
    let on = match device.gpu() {
        Some(ctx) => ctx.describe(),
        None => format!("CPU, {} threads", rayon::current_num_threads()),
    };
    let grid = MapGrid {
        height: cells,
        width: cells,
        channels,
        up: Resample::Bilinear,
        down: Resample::Bilinear,
    };
    let scene = ball_scene_with_degree(gaussians, 1, 0);
    let cams = cameras(views, size);
    eprintln!(
        "lift bench: {gaussians} Gaussians, {views} views at {size}², {cells}² maps with {channels} channels, {on}"
    );
    let timed = |round: fn(&SplatDevice, &GaussianScene, &[Camera], &MapGrid) -> _| {
        Timed::measure(runs, || {
            let total = round(&device, &scene, &cams, &grid)?;
            if let Some(ctx) = device.gpu() {
                sync(ctx)?;
            }
            Ok(total)
        })
    };
    // Both rounds compute the same maps: a sum over them says so without keeping either.
    let (a, b) = (
        host_round(&device, &scene, &cams, &grid)?,
        device_round(&device, &scene, &cams, &grid)?,
    );
    if (a - b).abs() > 1e-3 * a.abs().max(1.0) {
        return Err(BenchError::new(format!(
            "the two rounds disagree: {a} against {b}"
        )));
    }
    for (what, round) in [
        ("host resampling", host_round as fn(&_, &_, &_, &_) -> _),
        ("device seam", device_round),
    ] {
        let t = timed(round)?;
        eprintln!(
            "  {what}: best {:.3} s, {:.1} ms per view (first call {:.3} s)",
            t.best().as_secs_f64(),
            1e3 * t.best().as_secs_f64() / views as f64,
            t.first.as_secs_f64()
        );
        report(t.json(serde_json::json!({
            "bench": "lift", "what": what, "device": on, "gaussians": gaussians, "views": views,
            "size": size, "grid": cells, "channels": channels,
        })));
    }
    // A later round of one session (CCM's second and later layers, the blend maps' later steps): the
    // scene uploaded and every view projected and binned by an earlier round.
    let mut session = device.lift_session(&scene, &cams);
    let mut session_round = || -> Result<f32> {
        let mut total = 0.0;
        session.lift_and_render_back::<GpuError>(
            &grid,
            &mut |v| Ok(map(&grid, v)),
            &mut |_, back| {
                total += back.iter().sum::<f32>();
                Ok(())
            },
        )?;
        if let Some(ctx) = device.gpu() {
            sync(ctx)?;
        }
        Ok(total)
    };
    let c = session_round()?;
    if (c - b).abs() > 1e-3 * b.abs().max(1.0) {
        return Err(BenchError::new(format!(
            "a session's round disagrees: {c} against {b}"
        )));
    }
    let t = Timed::measure(runs, &mut session_round)?;
    eprintln!(
        "  session, later round: best {:.3} s, {:.1} ms per view",
        t.best().as_secs_f64(),
        1e3 * t.best().as_secs_f64() / views as f64,
    );
    report(t.json(serde_json::json!({
        "bench": "lift", "what": "session, later round", "device": on, "gaussians": gaussians,
        "views": views, "size": size, "grid": cells, "channels": channels,
    })));
    Ok(())
}
