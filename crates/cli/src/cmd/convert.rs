//! `vcedit convert IN OUT`: a scene from any supported format to any other.

use anyhow::{bail, Context, Result};
use std::path::{Path, PathBuf};

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
}

pub fn run(args: Args) -> Result<()> {
    if splat::OutputFormat::for_path(&args.output).is_none() {
        bail!(
            "{}: unknown output format: name it *.ply, *.compressed.ply, *.splat, *.spz, *.sog or meta.json (a SOG folder)",
            args.output.display()
        );
    }
    check_output(&args.input, &args.output)?;
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

/// Refuses an output that would replace or mix with the input: the same file by any name (a symbolic or
/// hard link included); a SOG folder written into the input's own folder (or the input folder itself);
/// a SOG folder written into a folder that holds other files but no SOG scene (someone else's folder:
/// its `means_l.webp` would be replaced silently).
fn check_output(input: &Path, output: &Path) -> Result<()> {
    if input == output || files::same_file(input, output) {
        bail!(
            "{}: the output is the input; write to another file",
            output.display()
        );
    }
    if splat::OutputFormat::for_path(output) != Some(splat::OutputFormat::SogFolder) {
        return Ok(());
    }
    let folder = match output.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    let Ok(folder_real) = folder.canonicalize() else {
        return Ok(()); // a new folder
    };
    if input
        .canonicalize()
        .is_ok_and(|input_real| input_real.starts_with(&folder_real))
    {
        bail!(
            "{}: the SOG folder would be written where the input {} lives; write it to a new folder",
            folder.display(),
            input.display()
        );
    }
    let holds_files = std::fs::read_dir(folder)
        .with_context(|| format!("{}: cannot list the folder", folder.display()))?
        .next()
        .is_some();
    if holds_files && !output.exists() {
        bail!(
            "{}: the folder holds other files and no SOG scene (meta.json); write the SOG folder to a new or empty folder",
            folder.display()
        );
    }
    Ok(())
}
