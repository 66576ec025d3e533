//! `vcedit convert IN OUT`: a scene from any supported format to any other.

use anyhow::{bail, Context, Result};
use std::path::PathBuf;

#[derive(clap::Args)]
#[command(
    about = "Convert a scene between formats (PLY, compressed PLY, .splat, .spz, SOG)",
    after_help = "The input format is recognised by content; the output format by name:\n  *.ply              INRIA PLY (exact)\n  *.compressed.ply   PlayCanvas/SuperSplat compressed PLY\n  *.splat            antimatter15 .splat (no SH beyond DC)\n  *.spz              Niantic .spz, version 4\n  *.sog              PlayCanvas SOG, zipped\n  DIR/meta.json      PlayCanvas SOG as a folder\nLossy outputs print their largest error per quantity.\n\nExamples:\n  vcedit convert scene.ply scene.spz\n  vcedit convert scene.compressed.ply scene.ply\n  vcedit convert output/garden garden.sog"
)]
pub struct Args {
    /// The scene to read: a file of any supported format, a SOG folder, or an INRIA output folder.
    pub input: PathBuf,
    /// The file to write; its name chooses the format.
    pub output: PathBuf,
}

pub fn run(args: Args) -> Result<()> {
    if splat::OutputFormat::for_path(&args.output).is_none() {
        bail!(
            "{}: unknown output format: name it *.ply, *.compressed.ply, *.splat, *.spz, *.sog or meta.json (a SOG folder)",
            args.output.display()
        );
    }
    let same = match (args.input.canonicalize(), args.output.canonicalize()) {
        (Ok(a), Ok(b)) => a == b,
        _ => args.input == args.output,
    };
    if same {
        bail!(
            "{}: the output is the input; write to another file",
            args.output.display()
        );
    }
    let scene = splat::read_scene(&args.input)
        .with_context(|| format!("cannot convert {}", args.input.display()))?;
    let report = splat::write_scene(&args.output, &scene)
        .with_context(|| format!("cannot convert {}", args.input.display()))?;
    println!(
        "{} -> {}: {report}",
        args.input.display(),
        args.output.display()
    );
    Ok(())
}
