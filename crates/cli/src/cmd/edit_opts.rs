//! Options shared by `vcedit edit-image` and `vcedit edit`: the model, prompts and InfEdit's knobs.

use std::path::PathBuf;

use anyhow::{bail, Context};
use edit::sampler::{EditPrompts, InfEditSettings};

/// Which LCM timestep selection to use.
#[derive(Clone, Copy, Debug, clap::ValueEnum)]
pub enum LcmSchedule {
    /// diffusers 0.22 (what VcEdit pins): 999, 939, ..., 159 for 15 steps.
    #[value(name = "diffusers-0.22")]
    Diffusers022,
    /// Current diffusers: 999, 939, 879, 799, ..., 79 for 15 steps.
    Current,
}

#[derive(clap::Args, Debug, Clone)]
pub struct ModelArgs {
    /// Diffusion model folder (diffusers layout, or a hub-cache `models--org--name` folder / snapshot).
    #[arg(long, value_name = "DIR")]
    pub model: PathBuf,
    /// Use TAESD from this folder as the latent codec instead of the model's VAE (faster, approximate).
    #[arg(long, value_name = "DIR")]
    pub taesd: Option<PathBuf>,
}

#[derive(clap::Args, Debug, Clone)]
pub struct PromptArgs {
    /// What the input shows, e.g. "a man".
    #[arg(long)]
    pub source: String,
    /// What it should show, e.g. "a clown".
    #[arg(long)]
    pub target: String,
    /// Words of the target prompt marking the region the edit may change (local blend).
    /// Default: the whole target prompt. An empty string disables the local blend.
    #[arg(long, value_name = "WORDS")]
    pub blend_words: Option<String>,
    /// Words present in both prompts whose regions are kept from the source.
    #[arg(long, value_name = "WORDS", default_value = "")]
    pub keep_words: String,
    /// Unconditional text of the target branch (negative prompt).
    #[arg(long, default_value = "")]
    pub negative: String,
}

impl PromptArgs {
    pub fn prompts(&self) -> EditPrompts {
        EditPrompts {
            source: self.source.clone(),
            target: self.target.clone(),
            target_blend: self
                .blend_words
                .clone()
                .unwrap_or_else(|| self.target.clone()),
            source_blend: self.keep_words.clone(),
            positive: String::new(),
            negative: self.negative.clone(),
        }
    }
}

#[derive(clap::Args, Debug, Clone)]
pub struct SamplerArgs {
    /// Working resolution: N for NxN or WxH (multiples of 64 for SD 1.x models).
    #[arg(long, default_value = "512", value_name = "N|WxH")]
    pub size: String,
    /// LCM steps.
    #[arg(long, default_value_t = 15)]
    pub steps: usize,
    /// Classifier-free guidance scale of the target branch.
    #[arg(long, default_value_t = 2.0)]
    pub guidance_scale: f64,
    /// Guidance scale of the source and layout branches.
    #[arg(long, default_value_t = 1.0)]
    pub guidance_scale_source: f64,
    /// Fraction of steps whose target cross-attention is taken from the source.
    #[arg(long = "cross", default_value_t = 0.7, value_name = "FRACTION")]
    pub cross_replace: f64,
    /// Fraction of steps using the source's self-attention queries/keys.
    #[arg(long = "self", default_value_t = 0.3, value_name = "FRACTION")]
    pub self_replace: f64,
    /// Local-blend threshold of the target words.
    #[arg(long, default_value_t = 0.6)]
    pub thresh_e: f64,
    /// Local-blend threshold of the kept words.
    #[arg(long, default_value_t = 0.6)]
    pub thresh_m: f64,
    /// DDCM eta (1 = LCM-style re-noising).
    #[arg(long, default_value_t = 1.0)]
    pub eta: f64,
    /// Start from the noised source instead of pure noise, keeping this fraction of the steps.
    #[arg(long, value_name = "0..1")]
    pub strength: Option<f64>,
    /// LCM timestep selection.
    #[arg(long, value_enum, default_value = "diffusers-0.22")]
    pub lcm_schedule: LcmSchedule,
    /// Random seed.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

impl SamplerArgs {
    pub fn settings(&self) -> anyhow::Result<InfEditSettings> {
        for (name, v) in [
            ("--cross", self.cross_replace),
            ("--self", self.self_replace),
        ] {
            if !(0.0..=1.0).contains(&v) {
                bail!("{name} {v} must be between 0 and 1");
            }
        }
        for (name, v) in [
            ("--guidance-scale", self.guidance_scale),
            ("--guidance-scale-source", self.guidance_scale_source),
            ("--eta", self.eta),
        ] {
            if !v.is_finite() || v < 0.0 {
                bail!("{name} {v} must be a non-negative number");
            }
        }
        if self.eta > 1.0 {
            bail!("--eta {} must be at most 1", self.eta);
        }
        if self.guidance_scale <= 1.0 {
            bail!(
                "--guidance-scale {} must be above 1 (the sampler needs classifier-free guidance on the target)",
                self.guidance_scale
            );
        }
        if self.steps == 0 {
            bail!("--steps must be at least 1");
        }
        Ok(InfEditSettings {
            steps: self.steps,
            guidance_source: self.guidance_scale_source,
            guidance_target: self.guidance_scale,
            cross_replace: self.cross_replace,
            self_replace: self.self_replace,
            thresh_e: self.thresh_e,
            thresh_m: self.thresh_m,
            eta: self.eta,
            denoise_strength: self.strength,
            lcm_variant: match self.lcm_schedule {
                LcmSchedule::Diffusers022 => diffusion::scheduler::LcmVariant::Diffusers022,
                LcmSchedule::Current => diffusion::scheduler::LcmVariant::Current,
            },
            ..InfEditSettings::default()
        })
    }

    /// (width, height) from `--size`.
    pub fn size(&self) -> anyhow::Result<(u32, u32)> {
        parse_size(&self.size)
    }
}

/// Parses "512" or "640x512".
pub fn parse_size(s: &str) -> anyhow::Result<(u32, u32)> {
    let parse = |v: &str| {
        v.trim()
            .parse::<u32>()
            .with_context(|| format!("--size {s}: expected N or WxH"))
    };
    let (w, h) = match s.split_once(['x', 'X']) {
        Some((w, h)) => (parse(w)?, parse(h)?),
        None => {
            let n = parse(s)?;
            (n, n)
        }
    };
    if w == 0 || h == 0 || w > 8192 || h > 8192 {
        bail!("--size {s}: width and height must be between 1 and 8192");
    }
    Ok((w, h))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_parse() {
        assert_eq!(parse_size("512").unwrap(), (512, 512));
        assert_eq!(parse_size("640x384").unwrap(), (640, 384));
        assert!(parse_size("0").is_err());
        assert!(parse_size("abc").is_err());
    }
}
