//! DDIM scheduler (diffusers' `DDIMScheduler`), with η and caller-provided noise.

use candle_core::Tensor;
use serde::Deserialize;

use super::{
    clip_or_threshold, epsilon_from, predict_original, BetaParams, BetaSchedule, NoiseSchedule,
    PredictionType, SchedulerError, TimestepSpacing,
};

fn d_num_train() -> usize {
    1000
}
fn d_beta_start() -> f64 {
    0.0001
}
fn d_beta_end() -> f64 {
    0.02
}
fn d_beta_schedule() -> BetaSchedule {
    BetaSchedule::Linear
}
fn d_true() -> bool {
    true
}
fn d_one() -> f64 {
    1.0
}
fn d_epsilon() -> PredictionType {
    PredictionType::Epsilon
}
fn d_ratio() -> f64 {
    0.995
}
fn d_leading() -> TimestepSpacing {
    TimestepSpacing::Leading
}

/// `scheduler_config.json` of a `DDIMScheduler`; defaults are diffusers' (note `clip_sample` defaults
/// to true there, SD configs set it false).
#[derive(Debug, Clone, Deserialize)]
pub struct DdimConfig {
    #[serde(default = "d_num_train")]
    pub num_train_timesteps: usize,
    #[serde(default = "d_beta_start")]
    pub beta_start: f64,
    #[serde(default = "d_beta_end")]
    pub beta_end: f64,
    #[serde(default = "d_beta_schedule")]
    pub beta_schedule: BetaSchedule,
    #[serde(default)]
    pub trained_betas: Option<Vec<f64>>,
    #[serde(default = "d_true")]
    pub clip_sample: bool,
    #[serde(default = "d_true")]
    pub set_alpha_to_one: bool,
    #[serde(default)]
    pub steps_offset: usize,
    #[serde(default = "d_epsilon")]
    pub prediction_type: PredictionType,
    #[serde(default)]
    pub thresholding: bool,
    #[serde(default = "d_ratio")]
    pub dynamic_thresholding_ratio: f64,
    #[serde(default = "d_one")]
    pub clip_sample_range: f64,
    #[serde(default = "d_one")]
    pub sample_max_value: f64,
    #[serde(default = "d_leading")]
    pub timestep_spacing: TimestepSpacing,
    #[serde(default)]
    pub rescale_betas_zero_snr: bool,
}

impl Default for DdimConfig {
    fn default() -> Self {
        serde_json::from_str("{}").expect("all DDIM config keys have defaults")
    }
}

/// Result of one DDIM step.
#[derive(Debug, Clone)]
pub struct DdimStepOutput {
    pub prev_sample: Tensor,
    pub pred_original_sample: Tensor,
}

#[derive(Debug, Clone)]
pub struct DdimScheduler {
    config: DdimConfig,
    schedule: NoiseSchedule,
    timesteps: Vec<usize>,
}

impl DdimScheduler {
    pub fn new(config: DdimConfig) -> Result<Self, SchedulerError> {
        let schedule = NoiseSchedule::new(&BetaParams {
            num_train_timesteps: config.num_train_timesteps,
            beta_start: config.beta_start,
            beta_end: config.beta_end,
            beta_schedule: config.beta_schedule,
            trained_betas: config.trained_betas.as_deref(),
            rescale_betas_zero_snr: config.rescale_betas_zero_snr,
            set_alpha_to_one: config.set_alpha_to_one,
        })?;
        Ok(DdimScheduler {
            config,
            schedule,
            timesteps: Vec::new(),
        })
    }

    pub fn config(&self) -> &DdimConfig {
        &self.config
    }

    pub fn noise_schedule(&self) -> &NoiseSchedule {
        &self.schedule
    }

    pub fn timesteps(&self) -> &[usize] {
        &self.timesteps
    }

    /// Selects the inference timesteps per `timestep_spacing`, reproducing numpy's float arithmetic.
    pub fn set_timesteps(
        &mut self,
        num_inference_steps: usize,
    ) -> Result<&[usize], SchedulerError> {
        let n = self.config.num_train_timesteps;
        if num_inference_steps == 0 || num_inference_steps > n {
            return Err(SchedulerError::Usage(format!(
                "num_inference_steps {num_inference_steps} must be in 1..={n}"
            )));
        }
        let steps = num_inference_steps;
        let raw: Vec<i64> = match self.config.timestep_spacing {
            TimestepSpacing::Linspace => {
                // np.linspace(0, n-1, steps): i·((n-1)/(steps-1)), last value exactly n-1; then round.
                let mut v: Vec<i64> = if steps == 1 {
                    vec![0]
                } else {
                    let step = (n - 1) as f64 / (steps - 1) as f64;
                    let mut v: Vec<i64> = (0..steps)
                        .map(|i| (i as f64 * step).round_ties_even() as i64)
                        .collect();
                    v[steps - 1] = (n - 1) as i64;
                    v
                };
                v.reverse();
                v
            }
            TimestepSpacing::Leading => {
                let ratio = n / steps;
                (0..steps)
                    .rev()
                    .map(|i| (i * ratio + self.config.steps_offset) as i64)
                    .collect()
            }
            TimestepSpacing::Trailing => {
                // np.round(np.arange(n, 0, -ratio)) - 1, with numpy's arange fill (start + i·delta, where
                // delta is the difference of the first two values).
                let ratio = n as f64 / steps as f64;
                let len = ((0.0 - n as f64) / -ratio).ceil() as usize;
                let first = n as f64;
                let second = first + -ratio;
                let delta = second - first;
                (0..len)
                    .map(|i| {
                        let v = match i {
                            0 => first,
                            1 => second,
                            _ => first + i as f64 * delta,
                        };
                        v.round_ties_even() as i64 - 1
                    })
                    .collect()
            }
        };
        let mut timesteps = Vec::with_capacity(raw.len());
        for t in raw {
            if t < 0 || t as usize >= n {
                return Err(SchedulerError::Invalid(format!(
                    "timestep {t} from {num_inference_steps} steps with steps_offset {} is outside 0..{n}",
                    self.config.steps_offset
                )));
            }
            timesteps.push(t as usize);
        }
        self.timesteps = timesteps;
        Ok(&self.timesteps)
    }

    /// The timestep DDIM steps to from `t`: t − n_train/steps (may be negative: then ᾱ = final).
    pub fn prev_timestep(&self, t: usize) -> i64 {
        let stride = self.config.num_train_timesteps / self.timesteps.len().max(1);
        t as i64 - stride as i64
    }

    /// ᾱ at a possibly negative previous timestep.
    pub fn alpha_cumprod_or_final(&self, t: i64) -> f64 {
        if t >= 0 {
            self.schedule
                .alpha_cumprod(t as usize)
                .unwrap_or(self.schedule.final_alpha_cumprod)
        } else {
            self.schedule.final_alpha_cumprod
        }
    }

    /// One DDIM step from timestep `t` with stochasticity `eta` (0 = deterministic); `variance_noise` is
    /// required when `eta > 0`.
    pub fn step(
        &self,
        model_output: &Tensor,
        t: usize,
        sample: &Tensor,
        eta: f64,
        use_clipped_model_output: bool,
        variance_noise: Option<&Tensor>,
    ) -> Result<DdimStepOutput, SchedulerError> {
        if self.timesteps.is_empty() {
            return Err(SchedulerError::Usage(
                "DDIM step before set_timesteps".into(),
            ));
        }
        let alpha_t = self.schedule.checked_alpha(t)?;
        let prev_t = self.prev_timestep(t);
        let alpha_prev = self.alpha_cumprod_or_final(prev_t);
        let beta_t = 1.0 - alpha_t;
        let prediction = self.config.prediction_type;
        let x0 = predict_original(prediction, model_output, sample, alpha_t)?;
        let mut eps = epsilon_from(prediction, model_output, sample, &x0, alpha_t)?;
        let x0 = clip_or_threshold(
            x0,
            self.config.thresholding,
            self.config.dynamic_thresholding_ratio,
            self.config.sample_max_value,
            self.config.clip_sample,
            self.config.clip_sample_range,
        )?;
        let variance = ((1.0 - alpha_prev) / beta_t) * (1.0 - alpha_t / alpha_prev);
        let std_dev = eta * variance.sqrt();
        if use_clipped_model_output {
            eps = ((sample - (&x0 * alpha_t.sqrt())?)? / beta_t.sqrt())?;
        }
        let direction = (eps * (1.0 - alpha_prev - std_dev * std_dev).max(0.0).sqrt())?;
        let mut prev = ((&x0 * alpha_prev.sqrt())? + direction)?;
        if eta > 0.0 {
            let noise = variance_noise.ok_or_else(|| {
                SchedulerError::Usage(format!("DDIM step with eta {eta} needs a noise tensor"))
            })?;
            prev = (prev + (noise * std_dev)?)?;
        }
        Ok(DdimStepOutput {
            prev_sample: prev,
            pred_original_sample: x0,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn with_spacing(spacing: TimestepSpacing, offset: usize) -> DdimScheduler {
        DdimScheduler::new(DdimConfig {
            timestep_spacing: spacing,
            steps_offset: offset,
            ..DdimConfig::default()
        })
        .unwrap()
    }

    #[test]
    fn spacings_follow_diffusers_formulas() {
        let mut s = with_spacing(TimestepSpacing::Leading, 1);
        assert_eq!(s.set_timesteps(4).unwrap(), &[751, 501, 251, 1]);
        let mut s = with_spacing(TimestepSpacing::Trailing, 0);
        assert_eq!(s.set_timesteps(4).unwrap(), &[999, 749, 499, 249]);
        let mut s = with_spacing(TimestepSpacing::Linspace, 0);
        assert_eq!(s.set_timesteps(4).unwrap(), &[999, 666, 333, 0]);
    }

    #[test]
    fn deterministic_step_with_exact_noise_prediction_recovers_x0() {
        let dev = candle_core::Device::Cpu;
        let mut s = DdimScheduler::new(DdimConfig {
            clip_sample: false,
            ..DdimConfig::default()
        })
        .unwrap();
        s.set_timesteps(10).unwrap();
        let x0 = Tensor::new(&[0.3f32, -0.2, 0.7], &dev).unwrap();
        let eps = Tensor::new(&[1.0f32, -0.5, 0.1], &dev).unwrap();
        let t = s.timesteps()[0];
        let xt = s.noise_schedule().add_noise(&x0, &eps, t).unwrap();
        let out = s.step(&eps, t, &xt, 0.0, false, None).unwrap();
        let got = out.pred_original_sample.to_vec1::<f32>().unwrap();
        for (g, e) in got.iter().zip([0.3f32, -0.2, 0.7]) {
            assert!((g - e).abs() < 1e-4, "{got:?}");
        }
        // The next sample is the same x0 noised to the previous timestep with the same noise.
        let expected = s
            .noise_schedule()
            .add_noise(&x0, &eps, t - 100)
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        let prev = out.prev_sample.to_vec1::<f32>().unwrap();
        for (g, e) in prev.iter().zip(expected) {
            assert!((g - e).abs() < 1e-4);
        }
        assert!(s.step(&eps, t, &xt, 1.0, false, None).is_err());
    }
}
