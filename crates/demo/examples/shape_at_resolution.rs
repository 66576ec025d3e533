//! Does a demo edit's outline hold up closer than the edit saw it? Scores a demo run's `edited.ply` with
//! the oracle at the edit's resolution and at `SCALE` times it (same cameras, intrinsics scaled): Gaussians
//! stretched along the outline are sub-pixel at 128² and show as a fringe when the scene is viewed larger
//! (the report's 3D viewer), which the shape scores at the edit's resolution cannot see.
//!
//! cargo run --release -p vcedit-demo --example shape_at_resolution -- RUN_DIR [PAIR] [SCALE]
//! (the run made by `vcedit demo --pair PAIR --out RUN_DIR` with the default settings)

use std::path::PathBuf;

use demo::run::{demo_scene, DemoOptions};
use demo::world::{Oracle, OracleSettings};
use splat::cameras::to_working_resolution;
use splat::{Camera, SplatDevice};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let run = PathBuf::from(
        args.first()
            .ok_or("usage: shape_at_resolution RUN [PAIR] [SCALE]")?,
    );
    let mut opts = DemoOptions::new(PathBuf::from("unused"), PathBuf::from("unused"));
    opts.pair = args.get(1).map_or(Ok(0), |p| p.parse())?;
    let scale: u32 = args.get(2).map_or(Ok(4), |s| s.parse())?;
    let scene = demo_scene(&opts)?;
    let edited = splat::read_scene(&run.join("edited.ply"))?;
    let oracle = Oracle::new(&scene.source, &scene.target, OracleSettings::default())?;
    for factor in [1, scale] {
        let cams: Vec<Camera> = scene
            .cameras
            .iter()
            .map(|c| to_working_resolution(c, c.width * factor, c.height * factor))
            .collect();
        let renders = SplatDevice::Cpu.render_images(&edited, &cams, scene.source.background)?;
        let score = oracle.score(&cams, &renders)?;
        let f = |v: Option<f64>| v.map_or("–".to_string(), |v| format!("{v:.3}"));
        println!(
            "{}x{}: silhouette IoU {}, outside change {}, colour fidelity {}, layout fidelity {}",
            cams[0].width,
            cams[0].height,
            f(score.silhouette_iou),
            f(score.outside_change),
            f(score.color_fidelity),
            f(score.fidelity)
        );
    }
    Ok(())
}
