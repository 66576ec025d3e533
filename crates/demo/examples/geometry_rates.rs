//! What the editing fit's geometry rates do to a demo edit's outline: refits the demo scene to a demo
//! run's guidance images (both iterations, 300 steps each, as `vcedit demo`) with the position, scale and
//! rotation rates at 1 (the reference), 0.1 (`--keep-shape`'s) and 0, with the opacity's at 0.1 too,
//! without densification, and at twice the guidance's resolution (Lanczos-upsampled targets), then scores
//! each result with the oracle at the edit's resolution and at 4× it (docs/demo-model.md has the table).
//!
//! cargo run --release -p vcedit-demo --example geometry_rates -- RUN_DIR [PAIR]

mod support;

use std::path::PathBuf;

use demo::run::{demo_scene, DemoOptions};
use demo::world::{Oracle, OracleSettings};
use edit::fit::{ImageLoss, TrainSettings};
use splat::cameras::to_working_resolution;
use splat::{Camera, Image, SplatDevice};
use support::{edit_trainer, guidance};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let run = PathBuf::from(args.first().ok_or("usage: geometry_rates RUN [PAIR]")?);
    let mut opts = DemoOptions::new(PathBuf::from("unused"), PathBuf::from("unused"));
    opts.pair = args.get(1).map_or(Ok(0), |p| p.parse())?;
    let scene = demo_scene(&opts)?;
    let oracle = Oracle::new(&scene.source, &scene.target, OracleSettings::default())?;
    let rounds = [
        guidance(&run.join("iter_0/guidance"))?,
        guidance(&run.join("iter_1/guidance"))?,
    ];
    let scaled = |f: u32| -> Vec<Camera> {
        scene
            .cameras
            .iter()
            .map(|c| to_working_resolution(c, c.width * f, c.height * f))
            .collect()
    };
    // (name, geometry rate, opacity rate, densify, fit resolution factor)
    let variants = [
        ("reference rates", 1.0, 1.0, true, 1),
        ("geometry at 0.1x", 0.1, 1.0, true, 1),
        ("geometry frozen", 0.0, 1.0, true, 1),
        ("geometry+opacity 0.1x", 0.1, 0.1, true, 1),
        ("no densification", 1.0, 1.0, false, 1),
        ("fit at 2x resolution", 1.0, 1.0, true, 2),
    ];
    for (name, rate, opacity, densify, factor) in variants {
        let mut trainer = edit_trainer(&scene, TrainSettings::new(600), densify);
        trainer.set_geometry_rate(rate);
        trainer.state.adam.group_lr_scale[splat::train::optim::Group::Opacity.index()] = opacity;
        let cams = scaled(factor);
        for (k, images) in rounds.iter().enumerate() {
            let targets: Vec<Image> = images
                .iter()
                .map(|i| i.resize(i.width * factor, i.height * factor))
                .collect();
            trainer.fit(
                &cams,
                &targets,
                300,
                &ImageLoss::dssim(),
                7 + k as u64,
                &mut |_| {},
            )?;
        }
        let mut line = format!("{name:<22}");
        for f in [1, 4] {
            let view = scaled(f);
            let renders =
                SplatDevice::Cpu.render_images(trainer.scene(), &view, scene.source.background)?;
            let s = oracle.score(&view, &renders)?;
            line += &format!(
                "  {}²: IoU {:.3}, outside {:.4}, colour {:.3}",
                view[0].width,
                s.silhouette_iou.unwrap_or(f64::NAN),
                s.outside_change.unwrap_or(f64::NAN),
                s.color_fidelity.unwrap_or(f64::NAN),
            );
        }
        println!("{line}");
    }
    Ok(())
}
