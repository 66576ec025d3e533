//! The `vcedit` binary: a thin command-line layer over the `splat`, `diffusion` and `edit` crates.
//!
//! Each subcommand lives in its own module under `cmd/` with an `Args` struct and a `run` function; options
//! several commands share (size, background, cameras, editing knobs) and their value grammars are in `args/`,
//! progress bars and plain progress lines in `progress`.
//! Errors reach the user as one line (`error: ...` with its causes joined by ": ") and exit code 1;
//! usage errors exit with 2 (clap's convention).

use clap::{Parser, Subcommand};

mod args;
mod cmd;
mod embedded;
mod interrupt;
mod progress;
mod stdout;

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
    // One line per subcommand; keep them in the order a user meets them. The editing commands' options
    // are boxed: they are many times larger than the others'.
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
    EditImage(Box<cmd::edit_image::Args>),
    /// Edit a 3DGS scene from a source prompt to a target prompt, consistently across views (VcEdit).
    Edit(Box<cmd::edit::Args>),
    /// Convert a scene between formats (PLY, compressed PLY, .splat, .spz, SOG).
    Convert(cmd::convert::Args),
    /// Compare two scenes: cross-view consistency, preservation (PSNR/SSIM), CLIP directional similarity.
    Metrics(cmd::metrics::Args),
    /// Inspect a Stable Diffusion model folder (`vcedit model check DIR`).
    Model(cmd::model::Args),
    /// Train the self-made demo model (`train --out DIR`) or sample images from a model (`sample`).
    DemoModel(cmd::demo_model::Args),
    /// Measure this machine: GPU adapter, matrix products, UNet, codecs, text encoder, splatting.
    Bench(cmd::bench::Args),
}

/// A closed stdout (`vcedit inspect x.ply | head -1`) ends the program quietly with the conventional
/// SIGPIPE status, as other Unix tools do. Rust starts programs with SIGPIPE ignored, so a write to a
/// closed pipe fails instead and `println!` panics. Output files are written atomically (temporary file,
/// then rename), so an interrupted run leaves no partial output.
#[cfg(unix)]
fn quiet_on_closed_pipe() {
    // SAFETY: restores one signal's default disposition before any other thread exists.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}

/// Mesa's Vulkan drivers (Wayland window-system code, Mesa 22) print "error: XDG_RUNTIME_DIR is invalid or
/// not set in the environment." on every adapter probe when the variable is missing, as in containers and
/// CI, even on runs that end up on the CPU. vcedit never opens a window: pointing the variable at the
/// temporary folder keeps the probe quiet.
#[cfg(unix)]
fn quiet_window_system_probe() {
    const VAR: &str = "XDG_RUNTIME_DIR";
    let valid = std::env::var_os(VAR).is_some_and(|d| {
        std::path::Path::new(&d).is_absolute() && std::path::Path::new(&d).is_dir()
    });
    if !valid {
        // Before any other thread exists (edition 2021: set_var is not yet `unsafe`).
        std::env::set_var(VAR, std::env::temp_dir());
    }
}

fn main() {
    #[cfg(unix)]
    quiet_on_closed_pipe();
    #[cfg(unix)]
    quiet_window_system_probe();
    // Every command allocates large per-view buffers (renders, activations) over and over.
    diffusion::runtime::tune_allocator();
    let cli = Cli::parse();
    let result: anyhow::Result<()> = match cli.command {
        Command::Inspect(a) => cmd::inspect::run(a),
        Command::Demo(a) => cmd::demo::run(a),
        Command::Render(a) => cmd::render::run(a),
        Command::View(a) => cmd::view::run(a),
        Command::Fit(a) => cmd::fit::run(a),
        Command::EditImage(a) => cmd::edit_image::run(*a),
        Command::Edit(a) => cmd::edit::run(*a),
        Command::Metrics(a) => cmd::metrics::run(a),
        Command::Convert(a) => cmd::convert::run(a),
        Command::Model(a) => cmd::model::run(a),
        Command::DemoModel(a) => cmd::demo_model::run(a),
        Command::Bench(a) => cmd::bench::run(a),
    };
    if let Err(err) = result {
        let mut line = one_line(&err);
        if line.contains("GPU out of memory") {
            // wgpu cannot tell how much GPU memory is free (gfx-rs/wgpu#2447), so the check before a run
            // is an estimate; when the device still runs out, say which knobs shrink the work.
            line.push_str(
                "; lower --view-batch, --max-views or --size (edit), --size (fit, render), or run with --device cpu",
            );
        }
        eprintln!("error: {line}");
        // A refused value is a usage error, as clap's own (exit code 2); anything else exits with 1.
        let usage = err.chain().any(|e| e.is::<args::UsageError>());
        std::process::exit(if usage { 2 } else { 1 });
    }
}

/// The error as one line: its contexts and causes joined by ": ", each said once, without backtraces.
/// Many error types already put their source in their own message (`"{path}: {source}"`, `"{0}"` over a
/// wrapped error); a cause whose text the line already holds is not repeated.
fn one_line(err: &anyhow::Error) -> String {
    let mut line = String::new();
    for cause in err.chain() {
        let text = without_backtrace(&cause.to_string());
        let text = text.trim();
        if text.is_empty() || line.contains(text) {
            continue;
        }
        if !line.is_empty() {
            line.push_str(": ");
        }
        line.push_str(text);
    }
    line
}

/// `text` without a captured backtrace (some libraries' errors print one in their message when
/// `RUST_BACKTRACE` is set): everything from the first line that looks like a backtrace frame (`  12: ...`)
/// or a "stack backtrace:" header. Remaining lines are joined with spaces.
fn without_backtrace(text: &str) -> String {
    let is_frame = |l: &str| {
        let t = l.trim_start();
        let digits = t.chars().take_while(char::is_ascii_digit).count();
        (digits > 0 && t[digits..].starts_with(": ")) || t.starts_with("stack backtrace:")
    };
    text.lines()
        .take_while(|l| !is_frame(l))
        .map(str::trim)
        .filter(|l| !l.is_empty())
        .collect::<Vec<_>>()
        .join(" ")
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::CommandFactory;

    /// Every subcommand (nested ones too) with its path, e.g. "model check".
    fn all_commands() -> Vec<(String, clap::Command)> {
        fn walk(prefix: &str, cmd: &clap::Command, out: &mut Vec<(String, clap::Command)>) {
            for sub in cmd.get_subcommands() {
                let name = format!("{prefix}{}", sub.get_name()).trim().to_string();
                out.push((name.clone(), sub.clone()));
                walk(&format!("{name} "), sub, out);
            }
        }
        let mut out = Vec::new();
        walk("", &Cli::command(), &mut out);
        out
    }

    /// What an option is, as a user sees it: its help line, its value names and its possible values.
    fn meaning(arg: &clap::Arg) -> String {
        let values: Vec<String> = arg
            .get_possible_values()
            .iter()
            .map(|v| v.get_name().to_string())
            .collect();
        format!(
            "{:?} {:?} {values:?} {}",
            arg.get_help().map(|h| h.to_string()),
            arg.get_value_names(),
            arg.get_action().takes_values()
        )
    }

    /// Every command that generates an orbit for a scene without cameras makes the same one, and says so.
    #[test]
    fn the_default_orbit_is_one_and_every_command_says_it() {
        let said = format!("orbit of {} views", args::DEFAULT_ORBIT_VIEWS);
        let with_orbit: Vec<(String, clap::Command)> = all_commands()
            .into_iter()
            .filter(|(_, c)| c.get_arguments().any(|a| a.get_long() == Some("orbit")))
            .collect();
        assert!(
            with_orbit.len() >= 3,
            "render, metrics and edit have --orbit"
        );
        for (name, cmd) in with_orbit {
            let notes = cmd
                .get_after_help()
                .map(|h| h.to_string())
                .unwrap_or_default();
            assert!(notes.contains(&said), "{name}: {notes}");
        }
    }

    /// The README says which options the commands share and that they mean the same everywhere: each
    /// has one help text, value grammar and choice list in every command that has it.
    #[test]
    fn the_options_the_readme_calls_shared_mean_the_same_in_every_command() {
        let readme = std::fs::read_to_string(
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../README.md"),
        )
        .unwrap();
        let claim = "Options shared by the commands mean the same everywhere:";
        let paragraph = readme
            .split("\n\n")
            .find(|p| p.contains(claim))
            .expect("the README's shared-options paragraph");
        let mut options: Vec<String> = paragraph
            .split('`')
            .skip(1)
            .step_by(2)
            .filter(|code| code.starts_with("--"))
            .map(|code| code.split([' ', '=']).next().unwrap().to_string())
            .collect();
        options.dedup();
        for must in [
            "--size",
            "--background",
            "--orbit",
            "--max-views",
            "--device",
        ] {
            assert!(
                options.iter().any(|o| o == must),
                "{must} not in {options:?}"
            );
        }
        // `--iterations` is one more: render → edit → fit rounds wherever a user sees it.
        options.push("--iterations".into());
        let commands = all_commands();
        for option in &options {
            let long = option.trim_start_matches("--");
            let users: Vec<(&str, String)> = commands
                .iter()
                .flat_map(|(name, cmd)| {
                    cmd.get_arguments()
                        .filter(|a| a.get_long() == Some(long) && !a.is_hide_set())
                        .map(|a| (name.as_str(), meaning(a)))
                        .collect::<Vec<_>>()
                })
                .collect();
            assert!(!users.is_empty(), "{option}: no command has it");
            for (name, m) in &users {
                assert_eq!(m, &users[0].1, "{option} in {name} against {}", users[0].0);
            }
        }
    }

    /// The message clap gives for `vcedit ARGS...`, which must fail to parse.
    fn parse_error(args: &[&str]) -> String {
        let argv = std::iter::once("vcedit").chain(args.iter().copied());
        match Cli::try_parse_from(argv) {
            Ok(_) => panic!("{args:?} parsed"),
            Err(e) => e.to_string(),
        }
    }

    #[test]
    fn errors_print_each_cause_once_without_backtraces() {
        #[derive(Debug)]
        struct Wraps(std::io::Error);
        impl std::fmt::Display for Wraps {
            // Says its source itself, as `#[error("{0}")]` over a `#[from]` does.
            fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                write!(f, "model.safetensors: {}", self.0)
            }
        }
        impl std::error::Error for Wraps {
            fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
                Some(&self.0)
            }
        }
        let err = anyhow::Error::new(Wraps(std::io::Error::other("disk on fire")))
            .context("loading model m");
        assert_eq!(
            one_line(&err),
            "loading model m: model.safetensors: disk on fire"
        );
        let with_trace = anyhow::anyhow!(
            "shape mismatch in conv_in\n   0: candle_core::error::Error::bt\n             at src/error.rs:1\n   1: main"
        )
        .context("loading model m");
        assert_eq!(
            one_line(&with_trace),
            "loading model m: shape mismatch in conv_in"
        );
    }

    #[test]
    fn the_command_line_is_well_formed() {
        // Conflicts, defaults set with mut_arg and flattened groups all name real arguments.
        Cli::command().debug_assert();
    }

    #[test]
    fn negative_numbers_reach_the_value_parsers() {
        let edit_image = |option: &'static str, value: &'static str| {
            let mut args = vec![
                "edit-image",
                "--model",
                "m",
                "--image",
                "i",
                "--source",
                "a",
            ];
            args.extend(["--target", "b", "--out", "o.png", option, value]);
            args
        };
        let cases: [(Vec<&str>, &str, &str); 9] = [
            (
                vec!["render", "s.ply", "--out", "o", "--size", "-64"],
                "--size",
                "must be positive",
            ),
            (
                vec!["render", "s.ply", "--out", "o", "--orbit", "-3"],
                "--orbit",
                "must be positive",
            ),
            (
                vec!["fit", "--data", "d", "--out", "o.ply", "--steps", "-1"],
                "--steps",
                "must be positive",
            ),
            (
                vec![
                    "metrics",
                    "--source",
                    "a",
                    "--edited",
                    "b",
                    "--max-views",
                    "-2",
                ],
                "--max-views",
                "must not be negative",
            ),
            (edit_image("--steps", "-1"), "--steps", "must be positive"),
            (edit_image("--cross", "-0.5"), "--cross", "between 0 and 1"),
            (vec!["demo", "--views", "-4"], "--views", "must be positive"),
            (
                vec![
                    "edit",
                    "--scene",
                    "s.ply",
                    "--model",
                    "m",
                    "--source",
                    "a",
                    "--target",
                    "b",
                    "--out",
                    "o",
                    "--ccm-steps",
                    "3,-1",
                ],
                "--ccm-steps",
                "must not be negative",
            ),
            (
                vec!["render", "s.ply", "--out", "o", "--background", "-1,0,0"],
                "--background",
                "#rrggbb",
            ),
        ];
        for (args, option, says) in cases {
            let err = parse_error(&args);
            assert!(
                err.contains(option) && err.contains(says),
                "{args:?}: {err}"
            );
            assert!(!err.contains("unexpected argument"), "{args:?}: {err}");
        }
    }

    #[test]
    fn shared_options_parse_the_same_everywhere() {
        for args in [
            &["render", "s.ply", "--out", "o", "--background", "grey"][..],
            &[
                "fit",
                "--data",
                "d",
                "--out",
                "o.ply",
                "--background",
                "grey",
            ][..],
            &[
                "metrics",
                "--source",
                "a",
                "--edited",
                "b",
                "--background",
                "grey",
            ][..],
        ] {
            let argv = std::iter::once("vcedit").chain(args.iter().copied());
            let background = match Cli::try_parse_from(argv).unwrap().command {
                Command::Render(a) => a.background.background,
                Command::Fit(a) => a.background.background,
                Command::Metrics(a) => a.background.background,
                _ => unreachable!(),
            };
            assert_eq!(background, [0.5; 3], "{args:?}");
        }
        // --cameras and --orbit exclude each other in every command that has them.
        let err = parse_error(&[
            "render",
            "s.ply",
            "--out",
            "o",
            "--cameras",
            "c",
            "--orbit",
            "3",
        ]);
        assert!(err.contains("cannot be used with"), "{err}");
    }

    /// Words of a shell command line: spaces split, double quotes group.
    fn shell_words(line: &str) -> Vec<String> {
        let mut words = Vec::new();
        let (mut word, mut quoted, mut any) = (String::new(), false, false);
        for c in line.chars() {
            match c {
                '"' => (quoted, any) = (!quoted, true),
                ' ' if !quoted => {
                    if any {
                        words.push(std::mem::take(&mut word));
                    }
                    any = false;
                }
                _ => (word, any) = (word + &c.to_string(), true),
            }
        }
        if any {
            words.push(word);
        }
        words
    }

    #[test]
    fn help_examples_parse() {
        let mut cli = Cli::command();
        cli.build();
        let mut checked = 0;
        let mut commands: Vec<&clap::Command> = cli.get_subcommands().collect();
        while let Some(cmd) = commands.pop() {
            commands.extend(cmd.get_subcommands());
            let Some(help) = cmd.get_after_help() else {
                continue;
            };
            // Example lines start with "  vcedit"; a trailing backslash continues them.
            let mut lines = help
                .to_string()
                .lines()
                .map(str::to_string)
                .collect::<Vec<_>>();
            lines.reverse();
            while let Some(line) = lines.pop() {
                let Some(mut example) = line.trim().strip_prefix("vcedit ").map(str::to_string)
                else {
                    continue;
                };
                while example.ends_with('\\') {
                    example.pop();
                    example += &lines.pop().unwrap_or_default();
                }
                // Without a trailing comment or output redirection.
                let example = example.split(" #").next().unwrap_or_default();
                let example = example.split(" >").next().unwrap_or_default();
                if example.contains("...") {
                    continue; // an abbreviation of an earlier example
                }
                let argv = std::iter::once("vcedit".to_string()).chain(shell_words(example));
                if let Err(e) = Cli::try_parse_from(argv) {
                    panic!("`vcedit {example}` does not parse:\n{e}");
                }
                checked += 1;
            }
        }
        println!("{checked} examples parse");
        assert!(checked >= 15, "only {checked} examples found");
    }
}
