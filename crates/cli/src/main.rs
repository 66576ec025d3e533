//! The `vcedit` binary: a thin command-line layer over the `splat`, `diffusion` and `edit` crates.
//!
//! Each subcommand lives in its own module under `cmd/` with an `Args` struct and a `run` function.
//! Errors reach the user as one line (`error: ...` with its causes joined by ": ") and exit code 1;
//! usage errors exit with 2 (clap's convention).

use clap::{Parser, Subcommand};

mod cmd;

#[derive(Parser)]
#[command(
    name = "vcedit",
    version,
    about = "Text-driven, view-consistent editing of 3D Gaussian Splatting scenes",
    long_about = None,
    propagate_version = true
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    // One line per subcommand; keep them in the order a user meets them.
    /// Print statistics of a 3DGS scene (count, SH degree, bounds, opacities, scales, cameras).
    Inspect(cmd::inspect::Args),
    /// Run the whole editing pipeline on a built-in procedural scene with the bundled demo model.
    Demo(cmd::demo::Args),
    /// Render a scene to one PNG per view (optionally depth and alpha).
    Render(cmd::render::Args),
    /// Write a self-contained HTML page to turn a scene around in 3D, or to compare two.
    View(cmd::view::Args),
    /// Train a 3DGS scene from posed images (COLMAP or transforms.json).
    Fit(cmd::fit::Args),
    /// Edit one image from a source prompt to a target prompt (InfEdit).
    EditImage(cmd::edit_image::Args),
    /// Edit a 3DGS scene from a source prompt to a target prompt, consistently across views (VcEdit).
    Edit(cmd::edit::Args),
    /// Compare two scenes: cross-view consistency, preservation (PSNR/SSIM), CLIP directional similarity.
    Metrics(cmd::metrics::Args),
    /// Inspect a Stable Diffusion model folder (`vcedit model check DIR`).
    Model(cmd::model::Args),
    /// Train the self-made demo model (`train --out DIR`) or sample images from a model (`sample`).
    DemoModel(cmd::demo_model::Args),
}

fn main() {
    let cli = Cli::parse();
    let result: anyhow::Result<()> = match cli.command {
        Command::Inspect(a) => cmd::inspect::run(a),
        Command::Demo(a) => cmd::demo::run(a),
        Command::Render(a) => cmd::render::run(a),
        Command::View(a) => cmd::view::run(a),
        Command::Fit(a) => cmd::fit::run(a),
        Command::EditImage(a) => cmd::edit_image::run(a),
        Command::Edit(a) => cmd::edit::run(a),
        Command::Metrics(a) => cmd::metrics::run(a),
        Command::Model(a) => cmd::model::run(a),
        Command::DemoModel(a) => cmd::demo_model::run(a),
    };
    if let Err(err) = result {
        // One clear line, never a backtrace: the chain of contexts says which file and what is wrong.
        let msg = err
            .chain()
            .map(|c| c.to_string())
            .collect::<Vec<_>>()
            .join(": ");
        eprintln!("error: {msg}");
        std::process::exit(1);
    }
}
