//! Where does a demo edit lose its shape scores? Writes, for every view of a demo run's final renders, the
//! oracle's silhouette disagreement map (white: both silhouettes; red: only the ideal edit's, i.e. a part
//! lost or coloured like what is behind it; blue: only the edit's, i.e. a halo or a kept part recoloured),
//! the ideal edit beside it, and prints the shape scores.
//!
//! cargo run --release -p vcedit-demo --example silhouette_maps -- RUN_DIR [PAIR] [OUT_DIR]
//! (the run made by `vcedit demo --pair PAIR --out RUN_DIR` with the default settings)

use std::path::PathBuf;

use demo::run::{demo_scene, DemoOptions};
use demo::world::{Oracle, OracleSettings};
use splat::SplatDevice;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let run = PathBuf::from(
        args.first()
            .ok_or("usage: silhouette_maps RUN [PAIR] [OUT]")?,
    );
    let mut opts = DemoOptions::new(PathBuf::from("unused"), PathBuf::from("unused"));
    opts.pair = args.get(1).map_or(Ok(0), |p| p.parse())?;
    let out = args
        .get(2)
        .map_or_else(|| run.join("silhouettes"), PathBuf::from);
    std::fs::create_dir_all(&out)?;
    let scene = demo_scene(&opts)?;
    let edited = splat::read_scene(&run.join("edited.ply"))?;
    let oracle = Oracle::new(&scene.source, &scene.target, OracleSettings::default())?;
    let renders =
        SplatDevice::Cpu.render_images(&edited, &scene.cameras, scene.source.background)?;
    for (k, (cam, img)) in scene.cameras.iter().zip(&renders).enumerate() {
        oracle
            .silhouette_map(cam, img)?
            .save_png(&out.join(format!("view_{k:03}.png")))?;
        oracle
            .expected(cam)?
            .target
            .save_png(&out.join(format!("ideal_{k:03}.png")))?;
    }
    let score = oracle.score(&scene.cameras, &renders)?;
    let f = |v: Option<f64>| v.map_or("–".to_string(), |v| format!("{v:.3}"));
    println!(
        "silhouette IoU {}, outline IoU {}, outside change {}; maps in {}",
        f(score.silhouette_iou),
        f(score.outline_iou),
        f(score.outside_change),
        out.display()
    );
    Ok(())
}
