//! `vcedit bench NAME [ARGS]`: measurements of this machine (crates/bench), in the one binary a machine
//! without a Rust toolchain can be given (tools/gpu-check carries it to borrowed GPU machines).

use anyhow::Result;

#[derive(clap::Args)]
#[command(
    about = "Measure this machine: GPU adapter, matrix products, UNet, codecs, text encoder, splatting; check a GPU against the CPU",
    after_help = "Each measurement is one `RESULT {json}` line on stdout; the first call (kernel compilation)\nis reported apart from the warm ones. Every bench's options are in its module's documentation\n(crates/bench/src/NAME.rs).\n\nExamples:\n  vcedit bench device --require-hardware\n  vcedit bench matmul --precisions f32,f16\n  vcedit bench unet --device gpu --batches 1,6 --hooks none,device\n  vcedit bench unet --model ./LCM_Dreamshaper_v7 --device gpu --batches 6\n  vcedit bench codec --model ./LCM_Dreamshaper_v7 --size 512 --device gpu\n  vcedit bench text --device gpu\n  vcedit bench lpips --device gpu --sizes 512\n  vcedit bench lift --device gpu --views 8 --size 512\n  vcedit bench render gpu n=125k size=512 device=gpu\n  vcedit bench check --device cuda --fixtures ./fixtures"
)]
pub struct Args {
    /// Which bench.
    #[arg(value_parser = clap::builder::PossibleValuesParser::new(bench::NAMES))]
    pub name: String,
    /// The bench's own options (see its documentation).
    #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
    pub args: Vec<String>,
}

pub fn run(args: Args) -> Result<()> {
    let reexec = ["bench".to_string(), args.name.clone()];
    bench::run(&args.name, &args.args, &reexec)?;
    Ok(())
}
