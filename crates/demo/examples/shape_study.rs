//! Where does a demo edit lose the object's shape? Fits the demo scene with the editing fit (mask,
//! anchors, densification as in `vcedit demo`) to several target sets and scores each result's shape with
//! the oracle: the ideal edit, the ideal edit through the model's autoencoder, and (given a demo run
//! folder) that run's guidance images of each iteration.
//!
//! cargo run --release -p vcedit-demo --example shape_study -- MODEL_DIR [RUN_DIR or ""] [PAIR]

mod support;

use std::path::PathBuf;

use demo::run::{codec_round_trip, demo_scene, load_model, DemoOptions};
use demo::world::{Oracle, OracleSettings};
use edit::fit::{ImageLoss, TrainSettings};
use edit::sampler::SeededNoise;
use splat::render::{render, RenderSettings};
use splat::{Camera, GaussianScene, Image};
use support::{edit_trainer, guidance};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    diffusion::runtime::tune_allocator();
    let args: Vec<String> = std::env::args().skip(1).collect();
    let model_dir = PathBuf::from(
        args.first()
            .ok_or("usage: shape_study MODEL [RUN] [PAIR]")?,
    );
    let run_dir = args.get(1).filter(|s| !s.is_empty()).map(PathBuf::from);
    let mut opts = DemoOptions::new(model_dir.clone(), PathBuf::from("unused"));
    opts.pair = args.get(2).map_or(Ok(0), |p| p.parse())?;
    let scene = demo_scene(&opts)?;
    let model = load_model(&model_dir)?;
    let oracle = Oracle::new(&scene.source, &scene.target, OracleSettings::default())?;
    let settings = RenderSettings {
        background: scene.source.background,
    };
    let render_all = |s: &GaussianScene, cams: &[Camera]| -> Vec<Image> {
        cams.iter()
            .map(|c| render(s, c, &settings, None).rgb_image())
            .collect()
    };
    let mut target = scene.built.clone();
    target.recolor(&scene.target)?;
    let ideal = render_all(&target.scene, &scene.cameras);
    let score = |name: &str, images: &[Image]| -> Result<(), Box<dyn std::error::Error>> {
        let s = oracle.score(&scene.cameras, images)?;
        println!(
            "{name:<44} IoU {:.3}  outside change {:.4}  preservation {:.1} dB",
            s.silhouette_iou.unwrap_or(f64::NAN),
            s.outside_change.unwrap_or(f64::NAN),
            s.preservation_psnr
        );
        Ok(())
    };
    // Codec-error cancellation: the source render plus what decoding changed between the source and the
    // edit (both round trips drawn with the same noise, as the sampler's two branches share z0).
    let source = render_all(&scene.built.scene, &scene.cameras);
    let round_trip = |images: &[Image]| codec_round_trip(&model, images, &mut SeededNoise::new(0));
    let (src_codec, codec) = (round_trip(&source)?, round_trip(&ideal)?);
    score("ideal edit", &ideal)?;
    score("ideal edit through the autoencoder", &codec)?;
    let cancelled: Vec<Image> = source
        .iter()
        .zip(src_codec.iter().zip(&codec))
        .map(|(s, (sc, tc))| {
            let mut out = s.clone();
            for (i, v) in out.data.iter_mut().enumerate() {
                *v = (*v + tc.data[i] - sc.data[i]).clamp(0.0, 1.0);
            }
            out
        })
        .collect();
    score("source + (codec(ideal) - codec(source))", &cancelled)?;
    let fit = |name: &str,
               targets: &[Image],
               steps: usize,
               densify: bool,
               anchor: bool|
     -> Result<(), Box<dyn std::error::Error>> {
        let mut settings = TrainSettings::new(600);
        settings.anchor = anchor;
        let mut trainer = edit_trainer(&scene, settings, densify);
        trainer.fit(
            &scene.cameras,
            targets,
            steps,
            &ImageLoss::dssim(),
            7,
            &mut |_| {},
        )?;
        let n = trainer.scene().len();
        score(
            &format!(
                "fit {steps} to {name}{}{} ({n} G)",
                if densify { "" } else { ", no densify" },
                if anchor { "" } else { ", no anchor" }
            ),
            &render_all(trainer.scene(), &scene.cameras),
        )
    };
    fit("ideal", &ideal, 600, true, true)?;
    fit("cancelled codec ideal", &cancelled, 600, true, true)?;
    fit("codec ideal", &codec, 600, true, true)?;
    fit("codec ideal", &codec, 600, false, true)?;
    if let Some(run) = run_dir {
        for k in 0.. {
            let dir = run.join(format!("iter_{k}")).join("guidance");
            if !dir.is_dir() {
                break;
            }
            let images = guidance(&dir)?;
            if images.len() != scene.cameras.len() {
                println!("iteration {k}: {} guidance images, skipped", images.len());
                continue;
            }
            score(&format!("guidance of iteration {}", k + 1), &images)?;
            fit(&format!("guidance {}", k + 1), &images, 600, true, true)?;
            fit(&format!("guidance {}", k + 1), &images, 600, false, true)?;
        }
    }
    Ok(())
}
