//! Latent Consistency Model scheduler (diffusers' `LCMScheduler`).
//!
//! diffusers changed how LCM picks its inference timesteps between releases; both behaviours are here,
//! named after the release they reproduce:
//! - [`LcmVariant::Diffusers022`] (the release VcEdit pins): take the `original_inference_steps` training
//!   timesteps `k·c − 1`, walk them backwards with a stride of `⌊len/steps⌋`, keep the first `steps`
//!   (15 steps: 999, 939, 879, …, 219, 159). Its `step` also re-noises after the last step.
//! - [`LcmVariant::Current`] (diffusers ≥ 0.23): pick indices `⌊linspace(0, len, steps, endpoint=False)⌋`
//!   of the reversed training timesteps (15 steps: 999, 939, 879, 799, 739, …, 139, 79); no noise after
//!   the last step.

use candle_core::Tensor;
use serde::Deserialize;

use super::{
    clip_or_threshold, predict_original, BetaParams, BetaSchedule, NoiseSchedule, PredictionType,
    SchedulerError, TimestepSpacing,
};

/// Which diffusers release's LCM behaviour to reproduce.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum LcmVariant {
    /// diffusers 0.22.0, pinned by VcEdit: the reference schedule and the default for editing.
    #[default]
    Diffusers022,
    /// Current diffusers.
    Current,
}

impl std::str::FromStr for LcmVariant {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "diffusers022" | "0.22" | "reference" => Ok(LcmVariant::Diffusers022),
            "current" => Ok(LcmVariant::Current),
            other => Err(format!(
                "unknown LCM schedule {other:?} (expected \"diffusers022\" or \"current\")"
            )),
        }
    }
}

fn d_num_train() -> usize {
    1000
}
fn d_beta_start() -> f64 {
    0.00085
}
fn d_beta_end() -> f64 {
    0.012
}
fn d_beta_schedule() -> BetaSchedule {
    BetaSchedule::ScaledLinear
}
fn d_original_steps() -> usize {
    50
}
fn d_one() -> f64 {
    1.0
}
fn d_true() -> bool {
    true
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
fn d_timestep_scaling() -> f64 {
    10.0
}

/// `scheduler_config.json` of an `LCMScheduler`; defaults are diffusers'.
#[derive(Debug, Clone, Deserialize)]
pub struct LcmConfig {
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
    #[serde(default = "d_original_steps")]
    pub original_inference_steps: usize,
    #[serde(default)]
    pub clip_sample: bool,
    #[serde(default = "d_one")]
    pub clip_sample_range: f64,
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
    pub sample_max_value: f64,
    /// Present in configs but unused by LCM's own timestep selection.
    #[serde(default = "d_leading")]
    pub timestep_spacing: TimestepSpacing,
    #[serde(default = "d_timestep_scaling")]
    pub timestep_scaling: f64,
    #[serde(default)]
    pub rescale_betas_zero_snr: bool,
}

impl Default for LcmConfig {
    fn default() -> Self {
        serde_json::from_str("{}").expect("all LCM config keys have defaults")
    }
}

/// Result of one LCM step.
#[derive(Debug, Clone)]
pub struct LcmStepOutput {
    /// The sample for the next timestep (re-noised `denoised`).
    pub prev_sample: Tensor,
    /// The consistency function's estimate of x0 (what the final image is decoded from).
    pub denoised: Tensor,
}

#[derive(Debug, Clone)]
pub struct LcmScheduler {
    config: LcmConfig,
    variant: LcmVariant,
    schedule: NoiseSchedule,
    timesteps: Vec<usize>,
}

impl LcmScheduler {
    pub fn new(config: LcmConfig, variant: LcmVariant) -> Result<Self, SchedulerError> {
        let schedule = NoiseSchedule::new(&BetaParams {
            num_train_timesteps: config.num_train_timesteps,
            beta_start: config.beta_start,
            beta_end: config.beta_end,
            beta_schedule: config.beta_schedule,
            trained_betas: config.trained_betas.as_deref(),
            rescale_betas_zero_snr: config.rescale_betas_zero_snr,
            set_alpha_to_one: config.set_alpha_to_one,
        })?;
        if config.original_inference_steps == 0 {
            return Err(SchedulerError::Invalid(
                "original_inference_steps is 0".into(),
            ));
        }
        Ok(LcmScheduler {
            config,
            variant,
            schedule,
            timesteps: Vec::new(),
        })
    }

    pub fn config(&self) -> &LcmConfig {
        &self.config
    }

    pub fn variant(&self) -> LcmVariant {
        self.variant
    }

    pub fn noise_schedule(&self) -> &NoiseSchedule {
        &self.schedule
    }

    /// The selected timesteps, descending (empty before [`Self::set_timesteps`]).
    pub fn timesteps(&self) -> &[usize] {
        &self.timesteps
    }

    /// Selects `num_inference_steps` timesteps from the LCM training schedule of
    /// `original_inference_steps` (config value when `None`); `strength` < 1 keeps only the lower part of
    /// that schedule (image-to-image).
    pub fn set_timesteps(
        &mut self,
        num_inference_steps: usize,
        original_inference_steps: Option<usize>,
        strength: f64,
    ) -> Result<&[usize], SchedulerError> {
        let n_train = self.config.num_train_timesteps;
        let original = original_inference_steps.unwrap_or(self.config.original_inference_steps);
        let usage = |m: String| Err(SchedulerError::Usage(m));
        if num_inference_steps == 0 {
            return usage("num_inference_steps must be at least 1".into());
        }
        if num_inference_steps > n_train {
            return usage(format!(
                "num_inference_steps {num_inference_steps} exceeds num_train_timesteps {n_train}"
            ));
        }
        if original == 0 || original > n_train {
            return usage(format!(
                "original_inference_steps {original} must be in 1..={n_train}"
            ));
        }
        if num_inference_steps > original {
            return usage(format!(
                "num_inference_steps {num_inference_steps} exceeds original_inference_steps {original}: \
                 LCM picks its steps from that schedule"
            ));
        }
        if !(strength > 0.0 && strength <= 1.0) {
            return usage(format!("strength {strength} must be in (0, 1]"));
        }
        let c = n_train / original;
        // Python's int() truncates toward zero, as does the cast.
        let count = (original as f64 * strength) as usize;
        // Training timesteps k·c − 1 for k = 1..=count, ascending.
        let origin: Vec<usize> = (1..=count).map(|k| k * c - 1).collect();
        let skip = origin.len() / num_inference_steps;
        if skip == 0 {
            return usage(format!(
                "original_inference_steps × strength = {} is smaller than num_inference_steps {num_inference_steps}",
                origin.len()
            ));
        }
        self.timesteps = match self.variant {
            LcmVariant::Diffusers022 => origin
                .iter()
                .rev()
                .step_by(skip)
                .take(num_inference_steps)
                .copied()
                .collect(),
            LcmVariant::Current => {
                let reversed: Vec<usize> = origin.iter().rev().copied().collect();
                // numpy: arange(num) * (len / num), floored.
                let stride = reversed.len() as f64 / num_inference_steps as f64;
                (0..num_inference_steps)
                    .map(|i| {
                        reversed[((i as f64 * stride).floor() as usize).min(reversed.len() - 1)]
                    })
                    .collect()
            }
        };
        Ok(&self.timesteps)
    }

    /// ᾱ_t.
    pub fn alpha_cumprod(&self, t: usize) -> Result<f64, SchedulerError> {
        self.schedule.checked_alpha(t)
    }

    /// ᾱ of the timestep after step `step_index`: the next selected timestep, or the step's own timestep
    /// after the last step (LCM's rule, unlike DDIM's `final_alpha_cumprod`).
    pub fn prev_alpha_cumprod(&self, step_index: usize) -> Result<f64, SchedulerError> {
        let t = self.timestep_at(step_index)?;
        let prev = self.timesteps.get(step_index + 1).copied().unwrap_or(t);
        self.schedule.checked_alpha(prev)
    }

    /// The boundary-condition scalings (c_skip, c_out) at timestep `t`: with σ_data = 0.5 and
    /// s = t·timestep_scaling, c_skip = σ²/(s² + σ²) and c_out = s/√(s² + σ²). diffusers 0.22 always used
    /// t/0.1 (i.e. a scaling of 10).
    pub fn boundary_scalings(&self, t: usize) -> (f64, f64) {
        let sigma_data = 0.5f64;
        let scaled = match self.variant {
            LcmVariant::Diffusers022 => t as f64 / 0.1,
            LcmVariant::Current => t as f64 * self.config.timestep_scaling,
        };
        let denom = scaled * scaled + sigma_data * sigma_data;
        (sigma_data * sigma_data / denom, scaled / denom.sqrt())
    }

    /// x̂0 predicted from the model output at timestep `t` (before the boundary condition), clipped or
    /// thresholded as the config says.
    pub fn predict_original(
        &self,
        model_output: &Tensor,
        sample: &Tensor,
        t: usize,
    ) -> Result<Tensor, SchedulerError> {
        let alpha = self.schedule.checked_alpha(t)?;
        let x0 = predict_original(self.config.prediction_type, model_output, sample, alpha)?;
        Ok(clip_or_threshold(
            x0,
            self.config.thresholding,
            self.config.dynamic_thresholding_ratio,
            self.config.sample_max_value,
            self.config.clip_sample,
            self.config.clip_sample_range,
        )?)
    }

    /// Whether step `step_index` re-noises (and so needs a noise tensor).
    pub fn step_needs_noise(&self, step_index: usize) -> bool {
        match self.variant {
            LcmVariant::Diffusers022 => self.timesteps.len() > 1,
            LcmVariant::Current => step_index + 1 != self.timesteps.len(),
        }
    }

    /// One LCM step at `timesteps[step_index]`: denoised = c_out·x̂0 + c_skip·sample, then
    /// prev = √ᾱ_prev·denoised + √(1−ᾱ_prev)·noise when the step re-noises (else prev = denoised).
    pub fn step(
        &self,
        step_index: usize,
        model_output: &Tensor,
        sample: &Tensor,
        noise: Option<&Tensor>,
    ) -> Result<LcmStepOutput, SchedulerError> {
        let t = self.timestep_at(step_index)?;
        let x0 = self.predict_original(model_output, sample, t)?;
        let (c_skip, c_out) = self.boundary_scalings(t);
        let denoised = ((x0 * c_out)? + (sample * c_skip)?)?;
        let prev_sample = if self.step_needs_noise(step_index) {
            let noise = noise.ok_or_else(|| {
                SchedulerError::Usage(format!(
                    "LCM step {step_index} (t = {t}) re-noises and needs a noise tensor"
                ))
            })?;
            let a_prev = self.prev_alpha_cumprod(step_index)?;
            ((&denoised * a_prev.sqrt())? + (noise * (1.0 - a_prev).sqrt())?)?
        } else {
            denoised.clone()
        };
        Ok(LcmStepOutput {
            prev_sample,
            denoised,
        })
    }

    /// The index of timestep `t` in the schedule, as diffusers finds it for the first `step` call (the
    /// second occurrence if `t` appears twice).
    pub fn index_of(&self, t: usize) -> Option<usize> {
        let mut hits = self
            .timesteps
            .iter()
            .enumerate()
            .filter(|(_, &s)| s == t)
            .map(|(i, _)| i);
        let first = hits.next()?;
        Some(hits.next().unwrap_or(first))
    }

    fn timestep_at(&self, step_index: usize) -> Result<usize, SchedulerError> {
        self.timesteps.get(step_index).copied().ok_or_else(|| {
            SchedulerError::Usage(format!(
                "step index {step_index} is outside the {} selected timesteps (call set_timesteps first)",
                self.timesteps.len()
            ))
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scheduler(variant: LcmVariant) -> LcmScheduler {
        let config = LcmConfig {
            steps_offset: 1,
            ..LcmConfig::default()
        };
        LcmScheduler::new(config, variant).unwrap()
    }

    #[test]
    fn fifteen_steps_match_both_releases() {
        let mut old = scheduler(LcmVariant::Diffusers022);
        let expected_old: Vec<usize> = (0..15).map(|i| 999 - 60 * i).collect();
        assert_eq!(
            old.set_timesteps(15, None, 1.0).unwrap(),
            expected_old.as_slice()
        );
        let mut new = scheduler(LcmVariant::Current);
        let ts = new.set_timesteps(15, None, 1.0).unwrap().to_vec();
        assert_eq!(&ts[..4], &[999, 939, 879, 799]);
        assert_eq!(&ts[13..], &[139, 79]);
    }

    #[test]
    fn boundary_scalings_vanish_at_zero_and_saturate_late() {
        let s = scheduler(LcmVariant::Current);
        assert_eq!(s.boundary_scalings(0), (1.0, 0.0));
        let (skip, out) = s.boundary_scalings(999);
        assert!(skip < 1e-6 && (out - 1.0).abs() < 1e-6);
    }

    #[test]
    fn invalid_requests_are_errors() {
        let mut s = scheduler(LcmVariant::Diffusers022);
        assert!(s.set_timesteps(0, None, 1.0).is_err());
        assert!(s.set_timesteps(51, None, 1.0).is_err());
        assert!(s.set_timesteps(10, None, 0.1).is_err());
        assert!(s
            .step(
                0,
                &Tensor::zeros(1, candle_core::DType::F32, &candle_core::Device::Cpu).unwrap(),
                &Tensor::zeros(1, candle_core::DType::F32, &candle_core::Device::Cpu).unwrap(),
                None
            )
            .is_err());
    }

    #[test]
    fn step_without_noise_is_refused_when_it_renoises() {
        let mut s = scheduler(LcmVariant::Current);
        s.set_timesteps(2, None, 1.0).unwrap();
        let x = Tensor::ones(4, candle_core::DType::F32, &candle_core::Device::Cpu).unwrap();
        assert!(s.step(0, &x, &x, None).is_err());
        // The last step of the current variant returns the denoised sample itself.
        let out = s.step(1, &x, &x, None).unwrap();
        assert_eq!(
            out.prev_sample.to_vec1::<f32>().unwrap(),
            out.denoised.to_vec1::<f32>().unwrap()
        );
    }
}
