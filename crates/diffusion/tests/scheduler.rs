//! LCM (both diffusers releases) and DDIM against the real diffusers code, recorded by
//! tools/make_sched_fixtures.py.

use std::collections::HashMap;

use candle_core::{Device, Tensor};
use diffusion::scheduler::{DdimConfig, DdimScheduler, LcmConfig, LcmScheduler, LcmVariant};
use serde::Deserialize;
use testkit::paths::repo;

mod common;
use common::max_abs_diff;

#[derive(Deserialize)]
struct Reference {
    lcm: HashMap<String, LcmEntry>,
    ddim: HashMap<String, DdimEntry>,
    add_noise_timesteps: Vec<usize>,
}

#[derive(Deserialize)]
struct LcmEntry {
    config: serde_json::Value,
    variants: HashMap<String, LcmVariantRecord>,
}

#[derive(Deserialize)]
struct LcmVariantRecord {
    final_alpha_cumprod: f64,
    timesteps: Vec<TimestepCase>,
    scalings: Vec<Scaling>,
    loops: HashMap<String, Loop>,
}

#[derive(Deserialize)]
struct TimestepCase {
    steps: usize,
    #[serde(default = "one")]
    strength: f64,
    #[serde(default)]
    original_inference_steps: Option<usize>,
    timesteps: Option<Vec<usize>>,
}

fn one() -> f64 {
    1.0
}

#[derive(Deserialize)]
struct Scaling {
    t: usize,
    c_skip: f64,
    c_out: f64,
}

#[derive(Deserialize)]
struct Loop {
    key: Option<String>,
    timesteps: Vec<usize>,
    #[serde(default)]
    eta: f64,
    #[serde(default)]
    use_clipped_model_output: bool,
}

#[derive(Deserialize)]
struct DdimEntry {
    config: serde_json::Value,
    final_alpha_cumprod: f64,
    timesteps: Vec<TimestepCase>,
    loops: HashMap<String, Loop>,
}

struct Fixtures {
    reference: Reference,
    tensors: HashMap<String, Tensor>,
}

fn fixtures() -> Fixtures {
    let dir = repo().join("fixtures/sched");
    let reference =
        serde_json::from_str(&std::fs::read_to_string(dir.join("reference.json")).unwrap())
            .unwrap();
    let tensors =
        candle_core::safetensors::load(dir.join("steps.safetensors"), &Device::Cpu).unwrap();
    Fixtures { reference, tensors }
}

fn variant(name: &str) -> LcmVariant {
    match name {
        "diffusers022" => LcmVariant::Diffusers022,
        "current" => LcmVariant::Current,
        other => panic!("unknown variant {other}"),
    }
}

fn check_alphas(name: &str, alphas: &[f64], fx: &Fixtures) {
    let expected = fx.tensors[&format!("alphas/{name}")]
        .to_vec1::<f32>()
        .unwrap();
    assert_eq!(alphas.len(), expected.len(), "{name}");
    let mut exact = 0;
    for (i, (a, e)) in alphas.iter().zip(&expected).enumerate() {
        let e = *e as f64;
        exact += (*a as f32 == e as f32) as usize;
        assert!(
            (a - e).abs() <= 1e-6 * e + 1e-9,
            "{name}: alphas_cumprod[{i}] = {a:e}, expected {e:e}"
        );
    }
    println!(
        "{name}: {exact} of {} alphas_cumprod bit-exact",
        expected.len()
    );
}

#[test]
fn lcm_schedules_timesteps_and_scalings_match_both_releases() {
    let fx = fixtures();
    for (name, entry) in &fx.reference.lcm {
        let config: LcmConfig = serde_json::from_value(entry.config.clone()).unwrap();
        for (vname, rec) in &entry.variants {
            let mut s = LcmScheduler::new(config.clone(), variant(vname)).unwrap();
            check_alphas(name, &s.noise_schedule().alphas_cumprod, &fx);
            assert_eq!(
                s.noise_schedule().final_alpha_cumprod as f32,
                rec.final_alpha_cumprod as f32
            );
            for case in &rec.timesteps {
                let got = s
                    .set_timesteps(case.steps, case.original_inference_steps, case.strength)
                    .map(|t| t.to_vec())
                    .ok();
                assert_eq!(
                    got, case.timesteps,
                    "{name}/{vname}: {} steps, strength {}, original {:?}",
                    case.steps, case.strength, case.original_inference_steps
                );
            }
            for sc in &rec.scalings {
                let (c_skip, c_out) = s.boundary_scalings(sc.t);
                assert!(
                    (c_skip - sc.c_skip).abs() <= 1e-6 * sc.c_skip.abs().max(1e-3),
                    "{name}/{vname} t={}",
                    sc.t
                );
                assert!(
                    (c_out - sc.c_out).abs() <= 1e-6,
                    "{name}/{vname} t={}",
                    sc.t
                );
            }
        }
    }
}

#[test]
fn lcm_steps_match_both_releases() {
    let fx = fixtures();
    let mut checked = 0;
    for entry in fx.reference.lcm.values() {
        let config: LcmConfig = serde_json::from_value(entry.config.clone()).unwrap();
        for (vname, rec) in &entry.variants {
            for (steps, lp) in &rec.loops {
                let key = lp.key.as_ref().unwrap();
                let mut s = LcmScheduler::new(config.clone(), variant(vname)).unwrap();
                s.set_timesteps(steps.parse().unwrap(), None, 1.0).unwrap();
                assert_eq!(s.timesteps(), lp.timesteps.as_slice());
                let mut sample = fx.tensors[&format!("{key}/sample")].clone();
                for i in 0..lp.timesteps.len() {
                    let t = |n: &str| &fx.tensors[&format!("{key}/{i}/{n}")];
                    assert_eq!(s.index_of(lp.timesteps[i]), Some(i));
                    let out = s
                        .step(i, t("model_output"), &sample, Some(t("noise")))
                        .unwrap();
                    let e1 = max_abs_diff(&out.denoised, t("denoised"));
                    let e2 = max_abs_diff(&out.prev_sample, t("prev_sample"));
                    assert!(
                        e1 <= 1e-5 && e2 <= 1e-5,
                        "{key} step {i}: denoised {e1:e}, prev {e2:e}"
                    );
                    // Continue from the reference so errors cannot compound.
                    sample = t("prev_sample").clone();
                    checked += 1;
                }
            }
        }
    }
    assert!(checked >= 40, "only {checked} steps checked");
}

#[test]
fn ddim_timesteps_and_steps_match_diffusers() {
    let fx = fixtures();
    for (name, entry) in &fx.reference.ddim {
        let config: DdimConfig = serde_json::from_value(entry.config.clone()).unwrap();
        let mut s = DdimScheduler::new(config.clone()).unwrap();
        check_alphas(name, &s.noise_schedule().alphas_cumprod, &fx);
        assert_eq!(
            s.noise_schedule().final_alpha_cumprod as f32,
            entry.final_alpha_cumprod as f32
        );
        let n_train = config.num_train_timesteps;
        for case in &entry.timesteps {
            let got = s.set_timesteps(case.steps).map(|t| t.to_vec()).ok();
            // diffusers accepts a schedule reaching past the last training timestep (1000 steps with
            // steps_offset 1) and fails later indexing alphas_cumprod; we refuse it up front.
            let expected = case
                .timesteps
                .clone()
                .filter(|ts| ts.iter().all(|&t| t < n_train));
            assert_eq!(got, expected, "{name}: {} steps", case.steps);
        }
        for (key, lp) in &entry.loops {
            let mut s = DdimScheduler::new(config.clone()).unwrap();
            s.set_timesteps(lp.timesteps.len()).unwrap();
            assert_eq!(s.timesteps(), lp.timesteps.as_slice());
            let mut sample = fx.tensors[&format!("{key}/sample")].clone();
            for (i, &ts) in lp.timesteps.iter().enumerate() {
                let t = |n: &str| &fx.tensors[&format!("{key}/{i}/{n}")];
                let noise = (lp.eta > 0.0).then(|| t("noise"));
                let out = s
                    .step(
                        t("model_output"),
                        ts,
                        &sample,
                        lp.eta,
                        lp.use_clipped_model_output,
                        noise,
                    )
                    .unwrap();
                let e1 = max_abs_diff(&out.pred_original_sample, t("pred_original_sample"));
                let e2 = max_abs_diff(&out.prev_sample, t("prev_sample"));
                assert!(
                    e1 <= 1e-4 && e2 <= 1e-5,
                    "{key} step {i}: x0 {e1:e}, prev {e2:e}"
                );
                sample = t("prev_sample").clone();
            }
        }
    }
}

#[test]
fn add_noise_matches_diffusers() {
    let fx = fixtures();
    let config: LcmConfig =
        serde_json::from_value(fx.reference.lcm["lcm_sd"].config.clone()).unwrap();
    let s = LcmScheduler::new(config, LcmVariant::Current).unwrap();
    for &t in &fx.reference.add_noise_timesteps {
        let got = s
            .noise_schedule()
            .add_noise(
                &fx.tensors["add_noise/x0"],
                &fx.tensors["add_noise/noise"],
                t,
            )
            .unwrap();
        let err = max_abs_diff(&got, &fx.tensors[&format!("add_noise/{t}")]);
        assert!(err <= 1e-6, "t={t}: {err:e}");
    }
}

#[test]
fn model_folder_schedulers_load_by_class_name() {
    use diffusion::scheduler::Scheduler;
    let lcm = Scheduler::from_config_file(
        &repo().join("fixtures/models/tiny-lcm/scheduler/scheduler_config.json"),
        LcmVariant::default(),
    )
    .unwrap();
    assert_eq!(lcm.class_name(), "LCMScheduler");
    let ddim = Scheduler::from_config_file(
        &repo().join("fixtures/models/tiny-ip2p/scheduler/scheduler_config.json"),
        LcmVariant::default(),
    )
    .unwrap();
    assert_eq!(ddim.class_name(), "DDIMScheduler");
    assert_eq!(
        ddim.noise_schedule().final_alpha_cumprod,
        ddim.noise_schedule().alphas_cumprod[0]
    );
}
