//! A tiny demo-model training run end to end: losses fall, the folder loads with the editor's loader and
//! runs an InfEdit step, sampling works, and a resumed run continues where the first stopped.

use demo::train::{train, Event, TrainConfig, TrainOptions};
use edit::sampler::{edit_image, EditModel, EditPlan, EditPrompts, InfEditSettings, SeededNoise};

fn run(out: &std::path::Path, config: &TrainConfig) -> (demo::train::TrainSummary, Vec<String>) {
    let mut stages = Vec::new();
    let summary = train(out, config, &TrainOptions::default(), &mut |e| {
        if let Event::Stage { name, .. } = e {
            stages.push(name.to_string());
        }
    })
    .unwrap();
    (summary, stages)
}

fn mean_loss(summary: &demo::train::TrainSummary, stage: &str, first: bool) -> f64 {
    let mut it = summary
        .state
        .loss_history
        .iter()
        .filter(|(s, _, _)| s == stage);
    let entry = if first { it.next() } else { it.next_back() };
    entry.unwrap().2
}

#[test]
fn tiny_training_run_learns_saves_loads_edits_and_resumes() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("model");
    let mut config = TrainConfig::tiny();
    config.codec.steps = 200;
    config.unet.steps = 200;
    let (summary, stages) = run(&out, &config);
    assert_eq!(stages, ["render", "codec", "encode", "unet"]);

    // Losses are recorded every 100 steps; the second window is clearly below the first (a tiny codec on
    // 48 images: ~0.27 -> ~0.22).
    let (c0, c1) = (
        mean_loss(&summary, "codec", true),
        mean_loss(&summary, "codec", false),
    );
    assert!(c1 < 0.9 * c0, "codec L1 {c0} -> {c1}");
    let (u0, u1) = (
        mean_loss(&summary, "unet", true),
        mean_loss(&summary, "unet", false),
    );
    assert!(u1 < u0, "unet mse {u0} -> {u1}");
    let scaling = summary.state.scaling_factor.unwrap();
    assert!(scaling.is_finite() && scaling > 0.0);

    // The folder is a diffusers pipeline the editor loads unchanged.
    for f in [
        "model_index.json",
        "README.md",
        "scheduler/scheduler_config.json",
        "tokenizer/vocab.json",
        "tokenizer/merges.txt",
        "text_encoder/config.json",
        "text_encoder/model.safetensors",
        "unet/config.json",
        "unet/diffusion_pytorch_model.safetensors",
        "vae/config.json",
        "vae/diffusion_pytorch_model.safetensors",
    ] {
        assert!(out.join(f).is_file(), "{f} missing");
    }
    let model = EditModel::load(&out, None).unwrap();
    assert_eq!(model.downscale(), 8);
    let size = config.image_size as usize;
    let settings = InfEditSettings {
        steps: 2,
        ..Default::default()
    };
    let prompts = EditPrompts::new("a red sphere", "a blue sphere");
    let plan = EditPlan::new(&model, &prompts, &settings, (size, size)).unwrap();
    let image = candle_core::Tensor::zeros(
        (1, 3, size, size),
        candle_core::DType::F32,
        &candle_core::Device::Cpu,
    )
    .unwrap();
    let outcome = edit_image(&model, &plan, &image, &mut SeededNoise::new(0), &mut |_| {}).unwrap();
    let _ = outcome;

    let images = demo::sample::generate(
        &model,
        &["a red sphere".to_string(), "a blue cube".to_string()],
        &demo::sample::SampleSettings {
            steps: 3,
            ..Default::default()
        },
    )
    .unwrap();
    assert_eq!(images.len(), 2);
    assert_eq!(
        (images[0].width as usize, images[0].height as usize),
        (size, size)
    );
    assert!(images[0]
        .data
        .iter()
        .all(|v| v.is_finite() && (0.0..=1.0).contains(v)));

    // Rerunning the same command does no work; more UNet steps continue from the checkpoint.
    let (again, stages) = run(&out, &config);
    assert!(stages.is_empty(), "{stages:?}");
    assert_eq!(again.state.unet_step, 200);
    config.unet.steps = 220;
    let (more, stages) = run(&out, &config);
    assert_eq!(stages, ["unet"]);
    assert_eq!(more.state.unet_step, 220);
    assert_eq!(more.state.codec_step, 200);

    // Training further from the exported model (`--init`): its codec is kept, the UNet starts trained
    // (its first loss window well below the scratch run's), and other samples can be drawn (seed).
    let tuned = dir.path().join("tuned");
    let mut tune = config.clone();
    tune.seed += 1;
    tune.unet.steps = 100;
    let options = TrainOptions {
        init: Some(out.clone()),
        ..Default::default()
    };
    let mut stages = Vec::new();
    let summary = train(&tuned, &tune, &options, &mut |e| {
        if let Event::Stage { name, .. } = e {
            stages.push(name.to_string());
        }
    })
    .unwrap();
    assert_eq!(stages, ["render", "encode", "unet"]);
    assert_eq!(summary.state.scaling_factor, Some(scaling));
    let vae = |dir: &std::path::Path| {
        std::fs::read(dir.join("vae/diffusion_pytorch_model.safetensors")).unwrap()
    };
    assert_eq!(vae(&tuned), vae(&out));
    let first = mean_loss(&summary, "unet", true);
    assert!(
        first < 0.8 * u0,
        "fine-tune starts at {first}, scratch at {u0}"
    );
    EditModel::load(&tuned, None).unwrap();
    let readme = std::fs::read_to_string(tuned.join("README.md")).unwrap();
    assert!(readme.contains("codec taken from"), "{readme}");

    // A model of another architecture is refused, naming the file.
    let mut wider = tune.clone();
    wider.unet.block_out_channels[0] *= 2;
    let err = train(&dir.path().join("wider"), &wider, &options, &mut |_| {})
        .err()
        .unwrap()
        .to_string();
    assert!(
        err.contains("unet/diffusion_pytorch_model.safetensors") && err.contains("architecture"),
        "{err}"
    );

    // A different architecture refuses the old checkpoints.
    config.unet.lr *= 2.0;
    let err = train(&out, &config, &TrainOptions::default(), &mut |_| {})
        .err()
        .unwrap();
    assert!(
        err.to_string().contains("different training config"),
        "{err}"
    );
}
