//! `vcedit model ...`: inspect Stable Diffusion model folders.

use std::path::PathBuf;

use anyhow::Result;
use diffusion::model_check::{check_model, CheckDepth};

#[derive(clap::Args)]
#[command(about = "Inspect a Stable Diffusion model folder")]
pub struct Args {
    #[command(subcommand)]
    pub command: ModelCommand,
}

#[derive(clap::Subcommand)]
pub enum ModelCommand {
    /// Check that a model folder is complete and loads; print its components, sizes and scheduler.
    #[command(
        after_help = "DIR is a diffusers folder (model_index.json, unet/, vae/, text_encoder/, tokenizer/, scheduler/)\n\
                      or a Hugging Face hub cache entry (models--org--name, or one of its snapshots/<rev>).\n\n\
                      Examples:\n  vcedit model check ~/models/LCM_Dreamshaper_v7\n  \
                      vcedit model check \\\n      ~/.cache/huggingface/hub/models--SimianLuo--LCM_Dreamshaper_v7\n  \
                      vcedit model check ~/models/sd15 --headers-only   # no weights read, instant"
    )]
    Check(CheckArgs),
}

#[derive(clap::Args)]
pub struct CheckArgs {
    /// The model folder (`demo`: the small demo model built into vcedit).
    pub dir: PathBuf,
    /// Only check files, configs and safetensors headers; do not build the models.
    #[arg(long)]
    pub headers_only: bool,
}

pub fn run(args: Args) -> Result<()> {
    match args.command {
        ModelCommand::Check(a) => check(a),
    }
}

fn check(args: CheckArgs) -> Result<()> {
    let depth = if args.headers_only {
        CheckDepth::HeadersOnly
    } else {
        CheckDepth::Load
    };
    // The library error already names the folder and lists every problem on one line.
    let dir = crate::args::editing::model_folder(&args.dir)?;
    let report = check_model(&dir, depth)?;
    crate::out!("{report}");
    Ok(())
}
