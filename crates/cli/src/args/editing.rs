//! Options shared by `vcedit edit-image` and `vcedit edit`: the model, prompts and InfEdit's knobs.

use std::path::{Path, PathBuf};

use anyhow::Context;
use diffusion::tokenizer::ClipTokenizer;
use edit::sampler::{EditModel, EditPlan, EditPrompts, InfEditSettings};

use super::parse::{finite, fraction, positive, whole};
use super::WorkingSize;

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
    /// Diffusion model folder (diffusers layout, or a hub-cache `models--org--name` folder / snapshot);
    /// `demo` (when no such folder exists here) is the small demo model built into vcedit.
    #[arg(long, value_name = "DIR")]
    pub model: PathBuf,
    /// Use TAESD from this folder as the latent codec instead of the model's VAE (faster, approximate).
    #[arg(long, value_name = "DIR")]
    pub taesd: Option<PathBuf>,
}

impl ModelArgs {
    /// The model folder: `--model` itself, or the built-in demo model for `--model demo`.
    pub fn folder(&self) -> anyhow::Result<PathBuf> {
        model_folder(&self.model)
    }
}

/// `dir`, or the built-in demo model when `dir` is the word `demo` and no such folder exists here.
pub fn model_folder(dir: &Path) -> anyhow::Result<PathBuf> {
    if dir == Path::new(DEMO_MODEL_NAME) && !dir.exists() {
        crate::embedded::demo_model()
    } else {
        Ok(dir.to_path_buf())
    }
}

/// The `--model` value that names the built-in demo model.
pub const DEMO_MODEL_NAME: &str = "demo";

#[derive(clap::Args, Debug, Clone)]
pub struct PromptArgs {
    /// What the input shows, e.g. "a man".
    #[arg(long, visible_alias = "source-prompt")]
    pub source: String,
    /// What it should show, e.g. "a clown".
    #[arg(long, visible_alias = "target-prompt")]
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

/// Refuses a word of `words` (the value of `option`) that is not a word of `prompt` (`which` prompt):
/// its tokens must appear, in order, among the prompt's. A misspelt word would otherwise silently change
/// the edit (an unknown blend word turns the local blend off).
pub fn check_words_in(
    tokenizer: &ClipTokenizer,
    option: &str,
    words: &str,
    which: &str,
    prompt: &str,
) -> anyhow::Result<()> {
    let prompt_ids = tokenizer.tokenize(prompt);
    for word in words.split_whitespace() {
        let ids = tokenizer.tokenize(word);
        // Punctuation alone ("," in "a, b") has tokens too; a word with none cannot mark anything.
        let found = !ids.is_empty() && prompt_ids.windows(ids.len()).any(|w| w == ids.as_slice());
        if !found {
            // A value that does not fit another option's value: a usage error (exit code 2).
            crate::usage!("{option}: '{word}' is not a word of the {which} prompt '{prompt}'");
        }
    }
    Ok(())
}

impl PromptArgs {
    /// Checks every prompt-word option against its prompt (`mask_word` against the source prompt), before
    /// any work.
    pub fn check_words(
        &self,
        tokenizer: &ClipTokenizer,
        mask_word: Option<&str>,
    ) -> anyhow::Result<()> {
        if let Some(words) = &self.blend_words {
            check_words_in(tokenizer, "--blend-words", words, "target", &self.target)?;
        }
        check_words_in(
            tokenizer,
            "--keep-words",
            &self.keep_words,
            "source",
            &self.source,
        )?;
        check_words_in(
            tokenizer,
            "--keep-words",
            &self.keep_words,
            "target",
            &self.target,
        )?;
        if let Some(word) = mask_word {
            if word.trim().is_empty() {
                crate::usage!(
                    "--mask-word is empty; give a word of the source prompt '{}'",
                    self.source
                );
            }
            check_words_in(tokenizer, "--mask-word", word, "source", &self.source)?;
        }
        Ok(())
    }

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
    #[command(flatten)]
    pub size: WorkingSize,
    /// LCM steps.
    #[arg(long, default_value_t = 15, value_parser = positive::<usize>, allow_negative_numbers = true)]
    pub steps: usize,
    /// Classifier-free guidance scale of the target branch (above 1).
    #[arg(long, default_value_t = 2.0, value_parser = finite::<f64>, allow_negative_numbers = true)]
    pub guidance_scale: f64,
    /// Guidance scale of the source and layout branches.
    #[arg(long, default_value_t = 1.0, value_parser = finite::<f64>, allow_negative_numbers = true)]
    pub guidance_scale_source: f64,
    /// Fraction of steps whose target cross-attention is taken from the source.
    #[arg(
        long = "cross",
        default_value_t = 0.7,
        value_name = "FRACTION",
        value_parser = fraction::<f64>,
        allow_negative_numbers = true
    )]
    pub cross_replace: f64,
    /// Fraction of steps using the source's self-attention queries/keys.
    #[arg(
        long = "self",
        default_value_t = 0.3,
        value_name = "FRACTION",
        value_parser = fraction::<f64>,
        allow_negative_numbers = true
    )]
    pub self_replace: f64,
    /// Local-blend threshold of the target words, from 0 to 1.
    #[arg(long, default_value_t = 0.6, value_parser = fraction::<f64>, allow_negative_numbers = true)]
    pub thresh_e: f64,
    /// Local-blend threshold of the kept words, from 0 to 1.
    #[arg(long, default_value_t = 0.6, value_parser = fraction::<f64>, allow_negative_numbers = true)]
    pub thresh_m: f64,
    /// DDCM eta, from 0 to 1 (1 = LCM-style re-noising).
    #[arg(long, default_value_t = 1.0, value_parser = fraction::<f64>, allow_negative_numbers = true)]
    pub eta: f64,
    /// Start from the noised source instead of pure noise, keeping this fraction of the steps.
    #[arg(
        long,
        value_name = "0..1",
        value_parser = fraction::<f64>,
        allow_negative_numbers = true
    )]
    pub strength: Option<f64>,
    /// UNet level whose cross-attention maps drive the local blend and CCM (0 = the latents'
    /// resolution, each level halves it); default: the coarsest with cross-attention (SD 1.x's 16×16
    /// maps at 512²). The built-in demo model's words localize at level 1.
    #[arg(long, value_name = "LEVEL", value_parser = whole::<usize>, allow_negative_numbers = true)]
    pub blend_level: Option<usize>,
    /// LCM timestep selection.
    #[arg(long, value_enum, default_value = "diffusers-0.22")]
    pub lcm_schedule: LcmSchedule,
    /// Random seed.
    #[arg(long, default_value_t = 0, value_parser = whole::<u64>, allow_negative_numbers = true)]
    pub seed: u64,
}

impl SamplerArgs {
    /// The sampler's settings; the checks here are the ones a single option's parser cannot make.
    pub fn settings(&self) -> anyhow::Result<InfEditSettings> {
        if self.guidance_scale_source < 0.0 {
            crate::usage!(
                "--guidance-scale-source {} must be a non-negative number",
                self.guidance_scale_source
            );
        }
        if self.guidance_scale <= 1.0 {
            crate::usage!(
                "--guidance-scale {} must be above 1 (the sampler needs classifier-free guidance on the target)",
                self.guidance_scale
            );
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
            blend_level: self.blend_level,
            lcm_variant: match self.lcm_schedule {
                LcmSchedule::Diffusers022 => diffusion::scheduler::LcmVariant::Diffusers022,
                LcmSchedule::Current => diffusion::scheduler::LcmVariant::Current,
            },
            ..InfEditSettings::default()
        })
    }

    /// (width, height) from `--size`.
    pub fn size(&self) -> (u32, u32) {
        self.size.size
    }

    /// Whether `model` works at `--size` (each model has its own multiple) and has cross-attention at
    /// `--blend-level`, before any work.
    pub fn check_model(&self, model: &EditModel) -> anyhow::Result<()> {
        let (w, h) = self.size();
        EditPlan::check_size(model, (w as usize, h as usize)).context("--size")?;
        EditPlan::check_blend_level(model, self.blend_level).context("--blend-level")
    }
}
