//! `vcedit bench NAME [ARGS]`: measurements of this machine (crates/bench), in the one binary a machine
//! without a Rust toolchain can be given (tools/gpu-check carries it to borrowed GPU machines).

use anyhow::Result;

#[derive(clap::Args)]
#[command(
    disable_help_flag = true,
    about = "Measure this machine: GPU adapter, matrix products, UNet, codecs, text encoder, splatting; check a GPU against the CPU",
    after_help = "Each measurement is one `RESULT {json}` line on stdout; the first call (kernel compilation)\nis reported apart from the warm ones. `vcedit bench NAME --help` says what a bench measures and\nlists its options.\n\nExamples:\n  vcedit bench device --require-hardware\n  vcedit bench matmul --precisions f32,f16\n  vcedit bench unet --device gpu --batches 1,6 --hooks none,device\n  vcedit bench unet --model ./LCM_Dreamshaper_v7 --device gpu --batches 6\n  vcedit bench codec --model ./LCM_Dreamshaper_v7 --size 512 --device gpu\n  vcedit bench text --device gpu\n  vcedit bench lpips --device gpu --sizes 512\n  vcedit bench lift --device gpu --views 8 --size 512\n  vcedit bench render gpu n=125k size=512 device=gpu\n  vcedit bench check --device cuda --fixtures ./fixtures"
)]
pub struct Args {
    /// Which bench.
    #[arg(value_parser = clap::builder::PossibleValuesParser::new(bench::NAMES))]
    pub name: Option<String>,
    /// The bench's own options (see `vcedit bench NAME --help`).
    #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
    pub args: Vec<String>,
    /// Print help; after NAME, that bench's own (what it measures, its options).
    #[arg(short = 'h', long)]
    pub help: bool,
}

pub fn run(args: Args) -> Result<()> {
    // `--help` after the bench's first own option arrives among its options.
    let help = args.help || args.args.iter().any(|a| a == "--help" || a == "-h");
    let Some(name) = args.name else {
        if help {
            print_bench_help()?;
            return Ok(());
        }
        crate::usage!(
            "which bench? one of {} (vcedit bench --help)",
            bench::NAMES.join(", ")
        );
    };
    if help {
        print!("{}", bench::help(&name).unwrap_or_default());
        return Ok(());
    }
    let reexec = ["bench".to_string(), name.clone()];
    bench::run(&name, &args.args, &reexec)?;
    Ok(())
}

/// clap's help of `vcedit bench` (the flag is ours, so that `bench NAME --help` reaches the bench).
fn print_bench_help() -> Result<()> {
    use clap::CommandFactory;
    let mut cli = crate::Cli::command();
    let bench = cli
        .find_subcommand_mut("bench")
        .expect("the bench subcommand exists");
    bench.print_help()?;
    Ok(())
}
