//! AdamW with gradient clipping and an exponential moving average of the weights, both with named,
//! checkpointable state.
//!
//! candle_nn's `AdamW` keeps its moments private, so a resumed run could not continue with them; this one
//! exposes every moment as a named tensor. Parameters are visited in name order, so runs are reproducible.

use std::collections::HashMap;

use candle_core::backprop::GradStore;
use candle_core::{Result, Tensor, Var};
use candle_nn::VarMap;
use serde::{Deserialize, Serialize};

/// AdamW hyper-parameters (the learning rate is passed per step, so schedules live outside).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AdamSettings {
    pub beta1: f64,
    pub beta2: f64,
    pub eps: f64,
    /// Decoupled weight decay, applied to matrices and kernels only (not to biases, norms or embeddings'
    /// 1-D parameters).
    pub weight_decay: f64,
    /// Gradients are scaled down so their global L2 norm is at most this (`None`: no clipping).
    pub clip_norm: Option<f64>,
}

impl Default for AdamSettings {
    fn default() -> Self {
        Self {
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
            weight_decay: 0.01,
            clip_norm: Some(1.0),
        }
    }
}

/// The trainable parameters of a `VarMap`, sorted by name.
pub fn named_vars(varmap: &VarMap) -> Vec<(String, Var)> {
    let mut vars: Vec<(String, Var)> = varmap
        .data()
        .lock()
        .expect("varmap lock")
        .iter()
        .map(|(k, v)| (k.clone(), v.clone()))
        .collect();
    vars.sort_by(|a, b| a.0.cmp(&b.0));
    vars
}

pub struct AdamW {
    params: Vec<(String, Var)>,
    first: Vec<Tensor>,
    second: Vec<Tensor>,
    /// Updates done so far (bias correction uses it).
    pub steps: u64,
    pub settings: AdamSettings,
}

impl AdamW {
    pub fn new(varmap: &VarMap, settings: AdamSettings) -> Result<Self> {
        let params = named_vars(varmap);
        let zeros = |(_, v): &(String, Var)| v.as_tensor().zeros_like();
        Ok(Self {
            first: params.iter().map(zeros).collect::<Result<_>>()?,
            second: params.iter().map(zeros).collect::<Result<_>>()?,
            params,
            steps: 0,
            settings,
        })
    }

    /// One update with learning rate `lr`. Returns the global gradient norm before clipping (NaN or
    /// infinite norms skip the update, so one bad batch cannot destroy the weights).
    pub fn step(&mut self, grads: &GradStore, lr: f64) -> Result<f64> {
        let mut sq = 0f64;
        for (_, var) in &self.params {
            if let Some(g) = grads.get(var.as_tensor()) {
                sq += g.sqr()?.sum_all()?.to_scalar::<f32>()? as f64;
            }
        }
        let norm = sq.sqrt();
        if !norm.is_finite() {
            return Ok(norm);
        }
        let scale = match self.settings.clip_norm {
            Some(max) if norm > max => max / norm,
            _ => 1.0,
        };
        self.steps += 1;
        let s = &self.settings;
        let t = self.steps as i32;
        let (c1, c2) = (1.0 - s.beta1.powi(t), 1.0 - s.beta2.powi(t));
        for (k, (_, var)) in self.params.iter().enumerate() {
            let Some(g) = grads.get(var.as_tensor()) else {
                continue;
            };
            let g = (g * scale)?;
            // Moments must not track ops either, or they would chain every step's graph (see `Ema`).
            let g = g.detach();
            self.first[k] = ((&self.first[k] * s.beta1)? + (&g * (1.0 - s.beta1))?)?.detach();
            self.second[k] =
                ((&self.second[k] * s.beta2)? + (g.sqr()? * (1.0 - s.beta2))?)?.detach();
            let m_hat = (&self.first[k] / c1)?;
            let v_hat = (&self.second[k] / c2)?;
            let update = (m_hat / (v_hat.sqrt()? + s.eps)?)?;
            let w = var.as_tensor().detach();
            let decayed = if w.rank() >= 2 && s.weight_decay > 0.0 {
                (w * (1.0 - lr * s.weight_decay))?
            } else {
                w.clone()
            };
            var.set(&(decayed - (update * lr)?)?)?;
        }
        Ok(norm)
    }

    /// Moments as named tensors (`adam.m.<name>`, `adam.v.<name>`).
    pub fn state(&self) -> HashMap<String, Tensor> {
        let mut out = HashMap::new();
        for (k, (name, _)) in self.params.iter().enumerate() {
            out.insert(format!("adam.m.{name}"), self.first[k].clone());
            out.insert(format!("adam.v.{name}"), self.second[k].clone());
        }
        out
    }

    /// Restores moments saved by [`Self::state`] (and the step count, kept by the caller).
    pub fn load_state(&mut self, tensors: &HashMap<String, Tensor>, steps: u64) -> Result<()> {
        for (k, (name, var)) in self.params.iter().enumerate() {
            for (prefix, slot) in [
                ("adam.m", &mut self.first[k]),
                ("adam.v", &mut self.second[k]),
            ] {
                *slot = saved_like(tensors, &format!("{prefix}.{name}"), var)?;
            }
        }
        self.steps = steps;
        Ok(())
    }
}

/// Exponential moving average of the parameters (what gets exported: smoother than the last iterate).
pub struct Ema {
    params: Vec<(String, Var)>,
    shadow: Vec<Tensor>,
    pub max_decay: f64,
}

impl Ema {
    pub fn new(varmap: &VarMap, max_decay: f64) -> Result<Self> {
        let params = named_vars(varmap);
        let shadow = params
            .iter()
            .map(|(_, v)| v.as_tensor().detach().copy())
            .collect::<Result<_>>()?;
        Ok(Self {
            params,
            shadow,
            max_decay,
        })
    }

    /// Blends the current parameters in after update number `step` (1-based); the decay ramps up as
    /// (1 + step) / (10 + step) so early, random weights are forgotten quickly.
    pub fn update(&mut self, step: u64) -> Result<()> {
        let decay = self
            .max_decay
            .min((1.0 + step as f64) / (10.0 + step as f64));
        for (k, (_, var)) in self.params.iter().enumerate() {
            // Detached: a variable's products are tracked, and each shadow would keep the previous one
            // (and a copy of the weights) alive through its backprop graph — tens of MB per step.
            let w = var.as_tensor().detach();
            self.shadow[k] = ((&self.shadow[k] * decay)? + (w * (1.0 - decay))?)?.detach();
        }
        Ok(())
    }

    /// The averaged weights by parameter name.
    pub fn weights(&self) -> HashMap<String, Tensor> {
        self.params
            .iter()
            .zip(&self.shadow)
            .map(|((name, _), t)| (name.clone(), t.clone()))
            .collect()
    }

    /// Named as `ema.<name>` for checkpoints.
    pub fn state(&self) -> HashMap<String, Tensor> {
        self.weights()
            .into_iter()
            .map(|(k, v)| (format!("ema.{k}"), v))
            .collect()
    }

    pub fn load_state(&mut self, tensors: &HashMap<String, Tensor>) -> Result<()> {
        for (k, (name, var)) in self.params.iter().enumerate() {
            self.shadow[k] = saved_like(tensors, &format!("ema.{name}"), var)?;
        }
        Ok(())
    }
}

/// The checkpoint tensor `key`, which must have the shape of `var`.
fn saved_like(tensors: &HashMap<String, Tensor>, key: &str, var: &Var) -> Result<Tensor> {
    let t = tensors
        .get(key)
        .ok_or_else(|| candle_core::Error::Msg(format!("checkpoint lacks {key}")))?;
    if t.dims() != var.dims() {
        candle_core::bail!(
            "checkpoint {key} has shape {:?}, expected {:?}",
            t.dims(),
            var.dims()
        );
    }
    Ok(t.clone())
}

/// Learning rate at `step` of `total`: linear warm-up over `warmup` steps, then cosine decay to
/// `final_fraction` of `peak`.
pub fn learning_rate(step: u64, total: u64, warmup: u64, peak: f64, final_fraction: f64) -> f64 {
    if step < warmup {
        return peak * (step + 1) as f64 / warmup as f64;
    }
    let span = total.saturating_sub(warmup).max(1) as f64;
    let progress = ((step - warmup) as f64 / span).min(1.0);
    let cosine = 0.5 * (1.0 + (std::f64::consts::PI * progress).cos());
    peak * (final_fraction + (1.0 - final_fraction) * cosine)
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Device};
    use candle_nn::VarBuilder;

    fn quadratic_problem() -> (VarMap, Var, Tensor) {
        let vm = VarMap::new();
        let vb = VarBuilder::from_varmap(&vm, DType::F32, &Device::Cpu);
        let w = vb
            .get_with_hints((2, 3), "w", candle_nn::Init::Const(0.0))
            .unwrap();
        let target = Tensor::new(&[[1f32, -2.0, 3.0], [0.5, 0.0, -1.0]], &Device::Cpu).unwrap();
        let var = vm.data().lock().unwrap()["w"].clone();
        assert_eq!(w.dims(), var.dims());
        (vm, var, target)
    }

    #[test]
    fn adamw_minimises_a_quadratic_and_resumes_exactly() {
        let settings = AdamSettings {
            weight_decay: 0.0,
            clip_norm: None,
            ..Default::default()
        };
        let loss = |var: &Var, target: &Tensor| {
            (var.as_tensor() - target)
                .unwrap()
                .sqr()
                .unwrap()
                .sum_all()
                .unwrap()
        };
        let (vm, var, target) = quadratic_problem();
        let mut opt = AdamW::new(&vm, settings.clone()).unwrap();
        let first = loss(&var, &target).to_scalar::<f32>().unwrap();
        for _ in 0..300 {
            let grads = loss(&var, &target).backward().unwrap();
            opt.step(&grads, 0.05).unwrap();
        }
        let last = loss(&var, &target).to_scalar::<f32>().unwrap();
        assert!(last < 1e-3 * first, "{first} -> {last}");

        // Resume: 10 steps straight equal 5 steps, save, restore into a fresh optimiser, 5 more steps.
        let run = |split: bool| -> Vec<f32> {
            let (vm, var, target) = quadratic_problem();
            let mut opt = AdamW::new(&vm, settings.clone()).unwrap();
            for i in 0..10 {
                if split && i == 5 {
                    let state = opt.state();
                    let weights = var.as_tensor().copy().unwrap();
                    opt = AdamW::new(&vm, settings.clone()).unwrap();
                    var.set(&weights).unwrap();
                    opt.load_state(&state, 5).unwrap();
                }
                let grads = loss(&var, &target).backward().unwrap();
                opt.step(&grads, 0.1).unwrap();
            }
            var.as_tensor().flatten_all().unwrap().to_vec1().unwrap()
        };
        assert_eq!(run(false), run(true));
    }

    #[test]
    fn clipping_bounds_the_step_and_nan_gradients_are_skipped() {
        let (vm, var, _) = quadratic_problem();
        let mut opt = AdamW::new(&vm, AdamSettings::default()).unwrap();
        let huge = (var.as_tensor() * 1e6).unwrap().sum_all().unwrap();
        let norm = opt.step(&huge.backward().unwrap(), 0.1).unwrap();
        assert!(norm > 1e6);
        let nan = (var.as_tensor() * f64::NAN).unwrap().sum_all().unwrap();
        let before = var
            .as_tensor()
            .flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        let norm = opt.step(&nan.backward().unwrap(), 0.1).unwrap();
        assert!(norm.is_nan());
        assert_eq!(
            var.as_tensor()
                .flatten_all()
                .unwrap()
                .to_vec1::<f32>()
                .unwrap(),
            before
        );
        assert_eq!(opt.steps, 1);
    }

    #[test]
    fn ema_tracks_the_weights() {
        let (vm, var, _) = quadratic_problem();
        let mut ema = Ema::new(&vm, 0.9).unwrap();
        var.set(&Tensor::ones((2, 3), DType::F32, &Device::Cpu).unwrap())
            .unwrap();
        for step in 1..=200 {
            ema.update(step).unwrap();
        }
        let w = ema.weights()["w"]
            .flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        assert!(w.iter().all(|&v| (v - 1.0).abs() < 1e-3), "{w:?}");
    }

    /// The optimiser's and the average's tensors must carry no backprop graph: a tracked shadow keeps
    /// every previous step alive (this once grew a training run by ~40 MB per step until it was killed).
    #[test]
    fn state_tensors_do_not_track_ops() {
        let (vm, var, target) = quadratic_problem();
        let mut opt = AdamW::new(&vm, AdamSettings::default()).unwrap();
        let mut ema = Ema::new(&vm, 0.99).unwrap();
        for step in 1..=3 {
            let loss = (var.as_tensor() - &target)
                .unwrap()
                .sqr()
                .unwrap()
                .sum_all()
                .unwrap();
            opt.step(&loss.backward().unwrap(), 0.1).unwrap();
            ema.update(step).unwrap();
        }
        for (name, t) in opt.state().iter().chain(ema.state().iter()) {
            assert!(!t.track_op(), "{name} tracks ops");
        }
    }

    #[test]
    fn schedule_warms_up_then_decays() {
        assert!((learning_rate(0, 100, 10, 1.0, 0.1) - 0.1).abs() < 1e-12);
        assert!((learning_rate(9, 100, 10, 1.0, 0.1) - 1.0).abs() < 1e-12);
        assert!((learning_rate(100, 100, 10, 1.0, 0.1) - 0.1).abs() < 1e-12);
        let mid = learning_rate(55, 100, 10, 1.0, 0.1);
        assert!((mid - 0.55).abs() < 1e-9, "{mid}");
    }
}
