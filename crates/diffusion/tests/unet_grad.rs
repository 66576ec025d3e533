//! The UNet is differentiable: with its weights as `Var`s the composite (training) path runs, agrees with
//! the fused inference path, and gives gradients that match finite differences.

use std::path::PathBuf;

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::{VarBuilder, VarMap};
use diffusion::unet::{UNet2DConditionModel, UNetConfig};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

fn unet_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../fixtures/models/tiny-lcm/unet")
}

/// Seeded standard-normal tensor, so the test is deterministic.
fn randn(rng: &mut ChaCha8Rng, shape: &[usize], dtype: DType) -> Tensor {
    let n = shape.iter().product();
    let data: Vec<f32> = (0..n).map(|_| StandardNormal.sample(rng)).collect();
    let t = Tensor::from_vec(data, shape, &Device::Cpu).unwrap();
    t.to_dtype(dtype).unwrap()
}

fn max_abs(t: &Tensor) -> f64 {
    let t = t.abs().unwrap().flatten_all().unwrap().max(0).unwrap();
    t.to_dtype(DType::F64).unwrap().to_scalar::<f64>().unwrap()
}

fn scalar(t: &Tensor) -> f64 {
    t.to_dtype(DType::F64).unwrap().to_scalar::<f64>().unwrap()
}

#[test]
fn gradients_flow_to_every_parameter_and_match_finite_differences() {
    let dev = Device::Cpu;
    let dir = unet_dir();
    let config_path = dir.join("config.json");
    let weights = dir.join("diffusion_pytorch_model.safetensors");
    let config = UNetConfig::from_json(&std::fs::read_to_string(&config_path).unwrap()).unwrap();
    let frozen =
        UNet2DConditionModel::from_files(&config_path, std::slice::from_ref(&weights)).unwrap();

    // The trainable copy runs in f64 so finite differences are not drowned by f32 rounding.
    let varmap = VarMap::new();
    let vb = VarBuilder::from_varmap(&varmap, DType::F64, &dev);
    let trainable = UNet2DConditionModel::load(&config, vb).unwrap();
    let stored = candle_core::safetensors::load(&weights, &dev).unwrap();
    let vars = varmap.data().lock().unwrap().clone();
    assert_eq!(
        vars.len(),
        stored.len(),
        "every stored tensor becomes a variable"
    );
    for (name, var) in &vars {
        var.set(&stored[name].to_dtype(DType::F64).unwrap())
            .unwrap();
    }

    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let timesteps = Tensor::new(&[700f32, 120.0], &dev).unwrap();
    let sample = randn(&mut rng, &[2, 4, 8, 8], DType::F32);
    let context = randn(&mut rng, &[2, 7, 32], DType::F32);
    let cond = randn(&mut rng, &[2, 16], DType::F32);
    let fast = frozen
        .forward(&sample, &timesteps, &context, Some(&cond), None)
        .unwrap();

    let f64_of = |t: &Tensor| t.to_dtype(DType::F64).unwrap();
    let (sample, context, cond) = (f64_of(&sample), f64_of(&context), f64_of(&cond));
    let run = || {
        let out = trainable.forward(&sample, &timesteps, &context, Some(&cond), None);
        out.unwrap()
    };
    let out = run();
    let gap = max_abs(&(&fast.to_dtype(DType::F64).unwrap() - &out).unwrap());
    assert!(
        gap < 1e-4,
        "training path differs from inference path by {gap}"
    );

    let weight_of_output = randn(&mut rng, out.dims(), DType::F64);
    let loss_of = |out: &Tensor| (out * &weight_of_output).unwrap().sum_all().unwrap();
    let grads = loss_of(&out).backward().unwrap();

    let mut without_gradient = Vec::new();
    for (name, var) in &vars {
        let norm = grads.get(var.as_tensor()).map(max_abs).unwrap_or(0.0);
        if norm <= 0.0 || !norm.is_finite() {
            without_gradient.push(name.clone());
        }
    }
    assert!(
        without_gradient.is_empty(),
        "no gradient for {without_gradient:?}"
    );

    // Directional finite differences through a conv, an attention projection (softmax), a layer norm
    // and the LCM condition projection.
    for name in [
        "conv_in.weight",
        "mid_block.attentions.0.transformer_blocks.0.attn1.to_q.weight",
        "down_blocks.1.attentions.0.transformer_blocks.0.norm3.weight",
        "time_embedding.cond_proj.weight",
    ] {
        let var: &Var = &vars[name];
        let original = var.as_tensor().copy().unwrap();
        let direction = randn(&mut rng, original.dims(), DType::F64);
        let gradient = grads.get(var.as_tensor()).unwrap();
        let analytic = scalar(&(gradient * &direction).unwrap().sum_all().unwrap());
        let eps = 1e-4;
        let loss_at = |sign: f64| -> f64 {
            let shifted = (&original + (&direction * (sign * eps)).unwrap()).unwrap();
            var.set(&shifted).unwrap();
            scalar(&loss_of(&run()))
        };
        let numeric = (loss_at(1.0) - loss_at(-1.0)) / (2.0 * eps);
        var.set(&original).unwrap();
        let rel = (numeric - analytic).abs() / analytic.abs().max(1e-3);
        println!("{name}: analytic {analytic:.6} numeric {numeric:.6} rel {rel:.2e}");
        assert!(
            rel < 1e-3,
            "{name}: gradient {analytic} vs finite difference {numeric}"
        );
    }
}
