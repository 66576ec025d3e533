//! `vcedit convert IN OUT`: a scene from any supported format to any other.

use anyhow::{bail, Result};
use std::path::{Path, PathBuf};

use crate::args::output::scene_output;

#[derive(clap::Args)]
#[command(
    about = "Convert a scene between formats (PLY, compressed PLY, .splat, .spz, SOG)",
    after_help = "The input format is recognised by content (a .splat file, which has no signature, by its name); the output format by name:\n  *.ply              INRIA PLY (exact)\n  *.compressed.ply   PlayCanvas/SuperSplat compressed PLY\n  *.splat            antimatter15 .splat (no SH beyond DC)\n  *.spz              Niantic .spz, version 4\n  *.sog              PlayCanvas SOG, zipped\n  DIR/meta.json      PlayCanvas SOG as a folder\nLossy outputs print their largest error per quantity.\n\nExamples:\n  vcedit convert scene.ply scene.spz\n  vcedit convert scene.compressed.ply scene.ply\n  vcedit convert output/garden garden.sog"
)]
pub struct Args {
    /// The scene to read: a file of any supported format, a SOG folder, or an INRIA output folder.
    pub input: PathBuf,
    /// The file to write; its name chooses the format.
    pub output: PathBuf,
    #[command(flatten)]
    pub force: crate::args::output::ForceArg,
}

pub fn run(args: Args) -> Result<()> {
    if splat::OutputFormat::for_path(&args.output).is_none() {
        bail!(
            "{}: unknown output format: name it *.ply, *.compressed.ply, *.splat, *.spz, *.sog or meta.json (a SOG folder)",
            args.output.display()
        );
    }
    // The output policy: never the input or inside its folder, an existing output only with --force, a
    // SOG folder only over a SOG scene (by content), the folder writable; all before reading.
    let sources = splat::formats::scene_sources(&args.input);
    let inputs: Vec<&Path> = sources.iter().map(PathBuf::as_path).collect();
    scene_output(&args.output, &inputs, args.force.force)?;
    // Both errors name their file already.
    let scene = splat::read_scene(&args.input)?;
    let report = splat::write_scene(&args.output, &scene)?;
    crate::out!(
        "{} -> {}: {report}",
        args.input.display(),
        args.output.display()
    );
    Ok(())
}
