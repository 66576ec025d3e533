//! Diffusion schedulers (LCM and DDIM) reproducing diffusers' arithmetic.
//!
//! Noise schedules are computed the way diffusers computes them in torch: betas in f32 (including
//! `torch.linspace`'s two-sided formula), cumulative products accumulated in f64 and stored as f32, so
//! `alphas_cumprod` matches the reference bit for bit. Timestep selection reproduces numpy's float
//! arithmetic (`linspace`, `arange`, round-half-to-even).
//!
//! Steps take their noise as an argument: callers own the random number generator (VcEdit shares one
//! noise tensor across views and branches).

mod ddim;
mod lcm;

use std::path::{Path, PathBuf};

use candle_core::Tensor;
use serde::Deserialize;

pub use ddim::{DdimConfig, DdimScheduler, DdimStepOutput};
pub use lcm::{LcmConfig, LcmScheduler, LcmStepOutput, LcmVariant};

/// Errors from scheduler configuration and stepping.
#[derive(Debug, thiserror::Error)]
pub enum SchedulerError {
    #[error("{}: {message}", .path.display())]
    Config { path: PathBuf, message: String },
    #[error("{}: {source}", .path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("scheduler config: {0}")]
    Invalid(String),
    #[error("{0}")]
    Usage(String),
    #[error(transparent)]
    Candle(#[from] candle_core::Error),
}

/// `beta_schedule` of the config.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BetaSchedule {
    Linear,
    ScaledLinear,
    #[serde(rename = "squaredcos_cap_v2")]
    SquaredcosCapV2,
}

/// `prediction_type` of the config: what the UNet predicts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PredictionType {
    Epsilon,
    Sample,
    VPrediction,
}

/// `timestep_spacing` of the config (used by DDIM; LCM has its own selection).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TimestepSpacing {
    Leading,
    Trailing,
    Linspace,
}

/// The training noise schedule: ᾱ_t for t in 0..num_train_timesteps.
#[derive(Debug, Clone, PartialEq)]
pub struct NoiseSchedule {
    /// ᾱ_t, f32 values held in f64.
    pub alphas_cumprod: Vec<f64>,
    /// ᾱ used after the last step: 1 with `set_alpha_to_one`, else ᾱ_0.
    pub final_alpha_cumprod: f64,
}

/// The beta-related keys shared by all scheduler configs.
pub struct BetaParams<'a> {
    pub num_train_timesteps: usize,
    pub beta_start: f64,
    pub beta_end: f64,
    pub beta_schedule: BetaSchedule,
    pub trained_betas: Option<&'a [f64]>,
    pub rescale_betas_zero_snr: bool,
    pub set_alpha_to_one: bool,
}

/// The most training timesteps a schedule may have.
pub const MAX_TRAIN_TIMESTEPS: usize = 100_000;

impl NoiseSchedule {
    pub fn new(p: &BetaParams) -> Result<Self, SchedulerError> {
        let n = p.num_train_timesteps;
        if n == 0 {
            return Err(SchedulerError::Invalid("num_train_timesteps is 0".into()));
        }
        // Stable Diffusion trains with 1000; the schedule holds one value per step, so an absurd count
        // (a damaged config) would ask for gigabytes.
        if n > MAX_TRAIN_TIMESTEPS {
            return Err(SchedulerError::Invalid(format!(
                "num_train_timesteps is {n}; at most {MAX_TRAIN_TIMESTEPS} are supported (Stable \
                 Diffusion uses 1000)"
            )));
        }
        let mut betas: Vec<f32> = match (p.trained_betas, p.beta_schedule) {
            (Some(trained), _) => {
                if trained.len() != n {
                    return Err(SchedulerError::Invalid(format!(
                        "trained_betas has {} values, num_train_timesteps is {n}",
                        trained.len()
                    )));
                }
                trained.iter().map(|&b| b as f32).collect()
            }
            (None, BetaSchedule::Linear) => {
                torch_linspace_f32(p.beta_start as f32, p.beta_end as f32, n)
            }
            (None, BetaSchedule::ScaledLinear) => {
                torch_linspace_f32(p.beta_start.sqrt() as f32, p.beta_end.sqrt() as f32, n)
                    .into_iter()
                    .map(|b| b * b)
                    .collect()
            }
            (None, BetaSchedule::SquaredcosCapV2) => cosine_betas(n),
        };
        // Every β_t must be a probability below 1 (ᾱ_t = Π(1 − β) then falls from 1 towards 0); anything
        // else, e.g. `beta_start 5, beta_end -1`, gives negative or NaN ᾱ and black images, not an error.
        if let Some((t, b)) = betas
            .iter()
            .enumerate()
            .find(|(_, b)| !(0.0..1.0).contains(*b))
        {
            return Err(SchedulerError::Invalid(format!(
                "the beta schedule gives beta_{t} = {b}, outside [0, 1) (check beta_start, beta_end, \
                 beta_schedule and trained_betas)"
            )));
        }
        if p.rescale_betas_zero_snr {
            betas = rescale_zero_terminal_snr(&betas);
        }
        let mut acc = 1.0f64;
        let alphas_cumprod: Vec<f64> = betas
            .iter()
            .map(|&b| {
                // torch: alphas in f32, cumprod accumulated in double, stored as f32.
                acc *= (1.0f32 - b) as f64;
                acc as f32 as f64
            })
            .collect();
        let final_alpha_cumprod = if p.set_alpha_to_one {
            1.0
        } else {
            alphas_cumprod[0]
        };
        Ok(NoiseSchedule {
            alphas_cumprod,
            final_alpha_cumprod,
        })
    }

    pub fn num_train_timesteps(&self) -> usize {
        self.alphas_cumprod.len()
    }

    /// ᾱ_t; `None` for t past the training range.
    pub fn alpha_cumprod(&self, t: usize) -> Option<f64> {
        self.alphas_cumprod.get(t).copied()
    }

    /// √ᾱ_t·x0 + √(1−ᾱ_t)·noise, as diffusers' `add_noise` for one timestep.
    pub fn add_noise(
        &self,
        original: &Tensor,
        noise: &Tensor,
        t: usize,
    ) -> Result<Tensor, SchedulerError> {
        let a = self.checked_alpha(t)?;
        Ok(((original * a.sqrt())? + (noise * (1.0 - a).sqrt())?)?)
    }

    fn checked_alpha(&self, t: usize) -> Result<f64, SchedulerError> {
        self.alpha_cumprod(t).ok_or_else(|| {
            SchedulerError::Usage(format!(
                "timestep {t} is outside the training range 0..{}",
                self.alphas_cumprod.len()
            ))
        })
    }
}

/// `torch.linspace` in f32 as its CPU kernel computes it: the first half counts up from `start`, the
/// second half down from `end`, each value one fused multiply-add (checked bit-exact against torch).
fn torch_linspace_f32(start: f32, end: f32, steps: usize) -> Vec<f32> {
    if steps == 1 {
        return vec![start];
    }
    let step = (end - start) / (steps - 1) as f32;
    let halfway = steps / 2;
    (0..steps)
        .map(|i| {
            if i < halfway {
                step.mul_add(i as f32, start)
            } else {
                (-step).mul_add((steps - i - 1) as f32, end)
            }
        })
        .collect()
}

/// Betas of the "squaredcos_cap_v2" (improved DDPM cosine) schedule, in f64 then stored as f32.
fn cosine_betas(n: usize) -> Vec<f32> {
    let alpha_bar = |t: f64| {
        ((t + 0.008) / 1.008 * std::f64::consts::PI / 2.0)
            .cos()
            .powi(2)
    };
    (0..n)
        .map(|i| {
            let t1 = i as f64 / n as f64;
            let t2 = (i + 1) as f64 / n as f64;
            (1.0 - alpha_bar(t2) / alpha_bar(t1)).min(0.999) as f32
        })
        .collect()
}

/// Rescales betas so the last timestep has zero SNR (Lin et al. 2023, Algorithm 1), in f32 like torch.
fn rescale_zero_terminal_snr(betas: &[f32]) -> Vec<f32> {
    let mut acc = 1.0f64;
    let mut sqrt_bar: Vec<f32> = betas
        .iter()
        .map(|&b| {
            acc *= (1.0f32 - b) as f64;
            (acc as f32).sqrt()
        })
        .collect();
    let first = sqrt_bar[0];
    let last = sqrt_bar[sqrt_bar.len() - 1];
    let scale = first / (first - last);
    for v in &mut sqrt_bar {
        *v -= last;
        *v *= scale;
    }
    let bar: Vec<f32> = sqrt_bar.iter().map(|v| v * v).collect();
    let mut out = Vec::with_capacity(bar.len());
    out.push(1.0 - bar[0]);
    for i in 1..bar.len() {
        out.push(1.0 - bar[i] / bar[i - 1]);
    }
    out
}

/// x̂0 from the model output, for each prediction type.
pub(crate) fn predict_original(
    prediction: PredictionType,
    model_output: &Tensor,
    sample: &Tensor,
    alpha_prod_t: f64,
) -> Result<Tensor, candle_core::Error> {
    let beta_prod_t = 1.0 - alpha_prod_t;
    match prediction {
        PredictionType::Epsilon => {
            (sample - (model_output * beta_prod_t.sqrt())?)? / alpha_prod_t.sqrt()
        }
        PredictionType::Sample => Ok(model_output.clone()),
        PredictionType::VPrediction => {
            (sample * alpha_prod_t.sqrt())? - (model_output * beta_prod_t.sqrt())?
        }
    }
}

/// ε implied by x̂0 and the sample.
pub(crate) fn epsilon_from(
    prediction: PredictionType,
    model_output: &Tensor,
    sample: &Tensor,
    pred_original: &Tensor,
    alpha_prod_t: f64,
) -> Result<Tensor, candle_core::Error> {
    let beta_prod_t = 1.0 - alpha_prod_t;
    match prediction {
        PredictionType::Epsilon => Ok(model_output.clone()),
        PredictionType::Sample => {
            (sample - (pred_original * alpha_prod_t.sqrt())?)? / beta_prod_t.sqrt()
        }
        PredictionType::VPrediction => {
            (model_output * alpha_prod_t.sqrt())? + (sample * beta_prod_t.sqrt())?
        }
    }
}

/// Clip or dynamically threshold x̂0 as the config asks.
pub(crate) fn clip_or_threshold(
    x0: Tensor,
    thresholding: bool,
    ratio: f64,
    max_value: f64,
    clip_sample: bool,
    clip_range: f64,
) -> Result<Tensor, candle_core::Error> {
    if thresholding {
        dynamic_threshold(&x0, ratio, max_value)
    } else if clip_sample {
        x0.clamp(-clip_range, clip_range)
    } else {
        Ok(x0)
    }
}

/// Imagen's dynamic thresholding: per batch item, s = quantile(|x|, ratio) clamped to [1, max];
/// x ← clamp(x, −s, s)/s. The quantile interpolates linearly like `torch.quantile`.
fn dynamic_threshold(
    x0: &Tensor,
    ratio: f64,
    max_value: f64,
) -> Result<Tensor, candle_core::Error> {
    let dtype = x0.dtype();
    let dims = x0.dims().to_vec();
    let batch = dims.first().copied().unwrap_or(1);
    let flat = x0.to_dtype(candle_core::DType::F32)?.reshape((batch, ()))?;
    let rows = flat.to_vec2::<f32>()?;
    let mut out = Vec::with_capacity(rows.len() * rows.first().map_or(0, Vec::len));
    for row in rows {
        let mut abs: Vec<f32> = row.iter().map(|v| v.abs()).collect();
        abs.sort_by(f32::total_cmp);
        let pos = ratio * (abs.len().saturating_sub(1)) as f64;
        let lo = pos.floor() as usize;
        let hi = pos.ceil() as usize;
        let frac = pos - lo as f64;
        let q = abs[lo] as f64 + (abs[hi] as f64 - abs[lo] as f64) * frac;
        let s = q.clamp(1.0, max_value) as f32;
        out.extend(row.iter().map(|v| v.clamp(-s, s) / s));
    }
    Tensor::from_vec(out, dims, x0.device())?.to_dtype(dtype)
}

/// Either scheduler, chosen by the config's `_class_name`.
#[derive(Debug, Clone)]
pub enum Scheduler {
    Lcm(LcmScheduler),
    Ddim(DdimScheduler),
}

impl Scheduler {
    /// Reads `scheduler_config.json`; LCM configs use `lcm_variant`'s behaviour.
    pub fn from_config_file(path: &Path, lcm_variant: LcmVariant) -> Result<Self, SchedulerError> {
        let text = std::fs::read_to_string(path).map_err(|source| SchedulerError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let value: serde_json::Value =
            serde_json::from_str(&text).map_err(|e| SchedulerError::Config {
                path: path.to_path_buf(),
                message: format!("invalid JSON: {e}"),
            })?;
        let class = value
            .get("_class_name")
            .and_then(|v| v.as_str())
            .unwrap_or("")
            .to_string();
        let config_err = |e: String| SchedulerError::Config {
            path: path.to_path_buf(),
            message: e,
        };
        match class.as_str() {
            "LCMScheduler" => {
                let config: LcmConfig =
                    serde_json::from_value(value).map_err(|e| config_err(e.to_string()))?;
                Ok(Scheduler::Lcm(
                    LcmScheduler::new(config, lcm_variant)
                        .map_err(|e| config_err(e.to_string()))?,
                ))
            }
            "DDIMScheduler" => {
                let config: DdimConfig =
                    serde_json::from_value(value).map_err(|e| config_err(e.to_string()))?;
                Ok(Scheduler::Ddim(
                    DdimScheduler::new(config).map_err(|e| config_err(e.to_string()))?,
                ))
            }
            other => Err(config_err(format!(
                "scheduler class {other:?} is not supported (LCMScheduler or DDIMScheduler)"
            ))),
        }
    }

    pub fn class_name(&self) -> &'static str {
        match self {
            Scheduler::Lcm(_) => "LCMScheduler",
            Scheduler::Ddim(_) => "DDIMScheduler",
        }
    }

    pub fn noise_schedule(&self) -> &NoiseSchedule {
        match self {
            Scheduler::Lcm(s) => s.noise_schedule(),
            Scheduler::Ddim(s) => s.noise_schedule(),
        }
    }

    pub fn num_train_timesteps(&self) -> usize {
        self.noise_schedule().num_train_timesteps()
    }

    pub fn prediction_type(&self) -> PredictionType {
        match self {
            Scheduler::Lcm(s) => s.config().prediction_type,
            Scheduler::Ddim(s) => s.config().prediction_type,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn linspace_is_exact_at_both_ends() {
        let v = torch_linspace_f32(0.1, 0.7, 7);
        assert_eq!(v[0], 0.1);
        assert_eq!(v[6], 0.7);
        assert_eq!(torch_linspace_f32(2.0, 3.0, 1), vec![2.0]);
    }

    #[test]
    fn betas_outside_zero_one_are_refused() {
        let params = |start, end| BetaParams {
            num_train_timesteps: 10,
            beta_start: start,
            beta_end: end,
            beta_schedule: BetaSchedule::Linear,
            trained_betas: None,
            rescale_betas_zero_snr: false,
            set_alpha_to_one: true,
        };
        let e = NoiseSchedule::new(&params(5.0, -1.0))
            .unwrap_err()
            .to_string();
        assert!(e.contains("beta_0 = 5") && e.contains("beta_start"), "{e}");
        assert!(NoiseSchedule::new(&params(0.1, f64::NAN)).is_err());
        assert!(NoiseSchedule::new(&params(0.0001, 0.02)).is_ok());
    }

    #[test]
    fn cumprod_decreases_and_final_alpha_follows_flag() {
        let params = |one| BetaParams {
            num_train_timesteps: 1000,
            beta_start: 0.00085,
            beta_end: 0.012,
            beta_schedule: BetaSchedule::ScaledLinear,
            trained_betas: None,
            rescale_betas_zero_snr: false,
            set_alpha_to_one: one,
        };
        let s = NoiseSchedule::new(&params(true)).unwrap();
        assert!(s.alphas_cumprod.windows(2).all(|w| w[1] < w[0]));
        assert_eq!(s.final_alpha_cumprod, 1.0);
        let s2 = NoiseSchedule::new(&params(false)).unwrap();
        assert_eq!(s2.final_alpha_cumprod, s2.alphas_cumprod[0]);
        assert!((s.alphas_cumprod[0] - (1.0 - 0.00085)).abs() < 1e-7);
    }

    #[test]
    fn zero_snr_rescale_ends_at_zero_and_keeps_first() {
        let betas = torch_linspace_f32(0.0001, 0.02, 1000);
        let rescaled = rescale_zero_terminal_snr(&betas);
        assert!(
            (rescaled[999] - 1.0).abs() < 1e-6,
            "last beta must be 1 (ᾱ_T = 0)"
        );
        assert!((rescaled[0] - betas[0]).abs() < 1e-6);
    }

    #[test]
    fn dynamic_threshold_scales_by_quantile() {
        let x = Tensor::new(&[[0.5f32, -4.0, 2.0, 1.0]], &candle_core::Device::Cpu).unwrap();
        // |x| sorted: 0.5 1 2 4; quantile 0.5 -> 1.5; clamp to max 3 -> 1.5.
        let y = dynamic_threshold(&x, 0.5, 3.0)
            .unwrap()
            .to_vec2::<f32>()
            .unwrap();
        let expected = [0.5 / 1.5, -1.0, 1.0, 1.0 / 1.5];
        for (a, b) in y[0].iter().zip(expected) {
            assert!((a - b).abs() < 1e-6, "{y:?}");
        }
    }
}
