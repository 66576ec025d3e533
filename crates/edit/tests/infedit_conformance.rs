//! The InfEdit sampler against the Python reference (tools/make_infedit_fixtures.py) on the tiny LCM model:
//! the same noise, every step's latents and predictions within 1e-4.

use std::path::PathBuf;

use candle_core::{Device, Tensor};
use edit::sampler::{
    EditModel, EditPlan, EditPrompts, InfEditSettings, NoiseSource, RecordedNoise,
};

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../fixtures")
}

fn max_abs(a: &Tensor, b: &Tensor) -> f32 {
    a.sub(b)
        .unwrap()
        .abs()
        .unwrap()
        .flatten_all()
        .unwrap()
        .max(0)
        .unwrap()
        .to_scalar::<f32>()
        .unwrap()
}

#[derive(serde::Deserialize)]
struct Case {
    name: String,
    source: String,
    target: String,
    target_blend: String,
    #[serde(default)]
    source_blend: String,
    steps: usize,
    guidance_source: f64,
    guidance_target: f64,
    cross: f64,
    #[serde(rename = "self")]
    self_replace: f64,
    thresh_e: f64,
    thresh_m: f64,
    eta: f64,
    strength: Option<f64>,
    timesteps: Vec<usize>,
}

#[test]
fn infedit_matches_the_reference_every_step() {
    let model = EditModel::load(&root().join("models/tiny-lcm"), None).unwrap();
    let cases: Vec<Case> =
        serde_json::from_str(&std::fs::read_to_string(root().join("infedit/cases.json")).unwrap())
            .unwrap();
    assert!(cases.len() >= 5);
    for case in cases {
        let fx = candle_core::safetensors::load(
            root().join(format!("infedit/{}.safetensors", case.name)),
            &Device::Cpu,
        )
        .unwrap();
        let prompts = EditPrompts {
            source: case.source.clone(),
            target: case.target.clone(),
            target_blend: case.target_blend.clone(),
            source_blend: case.source_blend.clone(),
            ..Default::default()
        };
        let settings = InfEditSettings {
            steps: case.steps,
            guidance_source: case.guidance_source,
            guidance_target: case.guidance_target,
            cross_replace: case.cross,
            self_replace: case.self_replace,
            thresh_e: case.thresh_e,
            thresh_m: case.thresh_m,
            eta: case.eta,
            denoise_strength: case.strength,
            ..Default::default()
        };
        let image = &fx["image"];
        let (_, _, h, w) = image.dims4().unwrap();
        let plan = EditPlan::new(&model, &prompts, &settings, (w, h)).unwrap();
        assert_eq!(plan.timesteps, case.timesteps, "{}", case.name);
        let alphas: Vec<f32> = fx["alphas"].to_vec1().unwrap();
        assert_eq!(
            plan.alignment.alphas, alphas,
            "{}: alignment alphas",
            case.name
        );
        let alpha_e: Vec<f32> = fx["alpha_e"].to_vec1().unwrap();
        assert_eq!(
            plan.alignment.alpha_e, alpha_e,
            "{}: blend-word indicator",
            case.name
        );

        let mut noises = Vec::new();
        while let Some(n) = fx.get(&format!("noise{}", noises.len())) {
            noises.push(n.clone());
        }
        let mut noise = RecordedNoise::new(noises);
        let x0 = model.encode(image, &mut noise).unwrap();
        let init = noise.sample(&plan.latent_shape()).unwrap();
        let mut view = plan.initial_state(x0, &init).unwrap();
        let mut worst = 0f32;
        for i in 0..plan.timesteps.len() {
            let eps = plan.predict(&model, &mut view, i).unwrap();
            view.controller.end_step();
            let n = noise.sample(&plan.latent_shape()).unwrap();
            plan.update(&mut view, i, &eps, &n).unwrap();
            if i > 0 {
                plan.local_blend(&mut view, i).unwrap();
            }
            let ours = [
                ("z_s", &view.z_s),
                ("z_t", &view.z_t),
                ("z_m", &view.z_m),
                ("pred_t", view.pred_t.as_ref().unwrap()),
                ("pred_m", view.pred_m.as_ref().unwrap()),
            ];
            for (key, t) in ours {
                let want = &fx[&format!("step{i}_{key}")];
                let err = max_abs(t, want);
                worst = worst.max(err);
                assert!(
                    err <= 1e-4,
                    "{} step {i} {key}: max abs error {err}",
                    case.name
                );
            }
        }
        eprintln!("{}: worst latent error {worst:e}", case.name);
        assert_eq!(noise.remaining(), 0, "{}: noise left over", case.name);
        let decoded = model
            .decode(view.pred_t.as_ref().unwrap())
            .unwrap()
            .affine(0.5, 0.5)
            .unwrap()
            .clamp(0f32, 1f32)
            .unwrap();
        let err = max_abs(&decoded, &fx["decoded"]);
        // x̂0 at the last step carries float noise of ~1e-5 that the random tiny VAE amplifies; the latents
        // above are the conformance target, this only checks the decode path end to end.
        assert!(
            err <= 1e-3,
            "{}: decoded image max abs error {err}",
            case.name
        );
    }
}
