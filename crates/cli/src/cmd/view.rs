//! `vcedit view SCENE [SCENE2]`: a self-contained HTML page to turn one scene around, or to compare two.

use anyhow::{bail, Result};
use edit::present::viewer::{
    write_viewer_page, InitialView, ViewerOptions, ViewerScene, DEFAULT_CAP,
};
use std::path::{Path, PathBuf};

use crate::args::output::{output_file, ForceArg};

#[derive(clap::Args, Debug)]
#[command(
    about = "Write a self-contained HTML page with an interactive 3D view of a scene, or of two side by side",
    after_help = "The page opens from disk in any browser with WebGL2 (no server, no network): drag to turn, wheel to \
zoom, W A S D Q E and the arrow keys to fly (SuperSplat's keys), a full-screen button; with two scenes a divider, buttons and a slider compare them (the first left, the second right). The scenes \
are embedded (32 bytes per Gaussian, plus 9, 24 or 45 with SH of degree 1, 2 or 3; 4/3 of that as base64) with \
view-dependent SH colours; the top SH bands are dropped where the page's scene data would pass 28 MB. Larger scenes \
keep their --cap most visible Gaussians. The view starts at the first scene's first camera (INRIA output folder), else on an \
orbit around it.

Examples:
  vcedit view scene.ply
  vcedit view output/garden edited.ply --out compare.html
  vcedit view big.ply --cap 100000"
)]
pub struct Args {
    /// A scene file (PLY, compressed PLY, .splat, .spz, SOG), a SOG folder, or an INRIA trainer output
    /// folder (point_cloud/iteration_*/point_cloud.ply + cameras.json).
    pub scene: PathBuf,
    /// A second scene to compare with the first (shown right of the divider).
    pub scene2: Option<PathBuf>,
    /// The page to write. Default: <name of SCENE>-view.html in the current folder.
    #[arg(long, value_name = "FILE.html")]
    pub out: Option<PathBuf>,
    #[command(flatten)]
    pub force: ForceArg,
    /// Most Gaussians embedded per scene (the most visible are kept).
    #[arg(long, value_name = "N", default_value_t = DEFAULT_CAP, value_parser = parse_cap)]
    pub cap: usize,
}

fn parse_cap(s: &str) -> Result<usize, String> {
    match s.trim().parse::<usize>() {
        Ok(n) if n > 0 => Ok(n),
        _ => Err(format!("'{s}' is not a positive whole number")),
    }
}

/// The name a scene goes by: its file or folder name.
fn scene_name(path: &Path) -> String {
    let trimmed: PathBuf = path.components().collect();
    trimmed
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| path.display().to_string())
}

pub fn run(args: Args) -> Result<()> {
    let mut paths = vec![args.scene.clone()];
    paths.extend(args.scene2.clone());
    let out = args.out.clone().unwrap_or_else(|| {
        let name = scene_name(&args.scene);
        let stem = Path::new(&name)
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or(name);
        PathBuf::from(format!("{stem}-view.html"))
    });
    if paths.iter().any(|p| files::same_file(p, &out)) {
        bail!("--out {} is one of the scenes", out.display());
    }
    let inputs: Vec<PathBuf> = paths
        .iter()
        .flat_map(|p| splat::formats::scene_sources(p))
        .collect();
    let input_refs: Vec<&Path> = inputs.iter().map(PathBuf::as_path).collect();
    output_file(&out, &input_refs, args.force.force)?;

    let mut scenes = Vec::new();
    let mut cameras = None;
    for p in &paths {
        // The reader's errors name the file.
        let (scene, cams) = splat::open_scene(p)?;
        if scene.is_empty() {
            bail!("{}: the scene has no Gaussians", p.display());
        }
        if cameras.is_none() {
            cameras = cams;
        }
        scenes.push(scene);
    }
    let names: Vec<String> = paths.iter().map(|p| scene_name(p)).collect();
    let view = match &cameras {
        Some(set) => InitialView::from_cameras(&set.cameras, &scenes[0], None),
        None => InitialView::around(&scenes[0]),
    };
    let shown: Vec<ViewerScene<'_>> = names
        .iter()
        .zip(&scenes)
        .map(|(label, scene)| ViewerScene { label, scene })
        .collect();
    let title = match names.as_slice() {
        [a, b] => format!("{a} | {b}"),
        _ => names[0].clone(),
    };
    let options = ViewerOptions {
        cap: args.cap,
        ..Default::default()
    };
    let embedded = write_viewer_page(&out, &title, &shown, &view, &options)?;
    for ((name, scene), e) in names.iter().zip(&scenes).zip(embedded) {
        let shading = match e.sh_degree {
            0 => String::new(),
            d => format!(" with SH degree {d}"),
        };
        crate::out!(
            "{name}: {} Gaussians, {} embedded{shading} (~{:.1} MB)",
            scene.len(),
            e.count,
            e.page_bytes() as f64 / 1e6
        );
    }
    crate::out!("{}", out.display());
    Ok(())
}
