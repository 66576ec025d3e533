//! `vcedit metrics --source A --edited B`: compare two scenes rendered from the same cameras.
//!
//! - multi-view consistency of each scene's renders (each scene's own depth), the cross-view error;
//! - preservation of B against A: PSNR/SSIM over whole images, and outside a 3D box when `--mask-box`
//!   is given (pixels where the box's Gaussians of either scene cover less than half the pixel);
//! - with `--clip DIR`: the CLIP directional similarity of the renders for the prompt change.

use anyhow::{bail, Context, Result};
use edit::eval::clip_score::ClipModel;
use edit::eval::metrics::{
    preservation, render_consistency, ConsistencySummary, PreservationReport, WarpSettings,
};
use edit::present::report::MetricsSummary;
use edit::run::{mask_from_box, Box3};
use rayon::prelude::*;
use serde::Serialize;
use splat::cameras::{load_cameras, orbit_cameras, robust_bounds, to_working_resolution};
use splat::render::{render, ExtraChannels, RenderOutput, RenderSettings};
use splat::{Camera, GaussianScene, Image};
use std::path::PathBuf;
use std::time::Instant;

const DEFAULT_ORBIT_VIEWS: usize = 16;
const DEFAULT_ORBIT_SIZE: (u32, u32) = (512, 512);

#[derive(clap::Args, Debug)]
#[command(
    about = "Compare two scenes: cross-view consistency, preservation (PSNR/SSIM), CLIP directional similarity",
    after_help = "Cameras come from --cameras, else --orbit, else the source scene's folder (INRIA cameras.json), else an \
orbit of 16 views around the source scene. Both scenes are rendered from the same cameras.

Cross-view error: each view is warped into its nearest cameras with the scene's rendered depth; the mean absolute colour \
difference (0-1 scale) over pixels both cameras see. Lower is more consistent; a scene's own renders are the floor.

Examples:
  vcedit metrics --source scene.ply --edited out/edited.ply --orbit 24 --size 256
  vcedit metrics --source scene.ply --edited out/edited.ply --cameras data/ --mask-box -0.5,-0.5,0,0.5,0.5,1.2 --json m.json
  vcedit metrics --source scene.ply --edited out/edited.ply --clip models/clip-vit-large-patch14 \\
      --source-prompt \"a photo of a man\" --target-prompt \"a photo of a clown\""
)]
pub struct Args {
    /// The scene before editing (.ply or INRIA output folder).
    #[arg(long, value_name = "SCENE")]
    pub source: PathBuf,
    /// The scene after editing.
    #[arg(long, value_name = "SCENE")]
    pub edited: PathBuf,
    /// Cameras: a COLMAP model folder (or its sparse/0), a transforms*.json, or an INRIA cameras.json.
    #[arg(long, value_name = "FILE|DIR", conflicts_with = "orbit")]
    pub cameras: Option<PathBuf>,
    /// N views on an orbit around the source scene.
    #[arg(long, value_name = "N")]
    pub orbit: Option<usize>,
    /// Render size WxH (or N for NxN); cameras are centre-cropped to the aspect ratio, then scaled.
    /// Default: the cameras' own size; 512x512 for orbits.
    #[arg(long, value_name = "WxH")]
    pub size: Option<String>,
    /// Use at most this many cameras (evenly spaced); 0 = all.
    #[arg(long, default_value_t = 64)]
    pub max_views: usize,
    /// Editable region xmin,ymin,zmin,xmax,ymax,zmax: preservation is also measured outside it.
    #[arg(long, value_name = "BOX", allow_hyphen_values = true)]
    pub mask_box: Option<Box3>,
    /// Neighbouring cameras each view is compared with.
    #[arg(long, default_value_t = 3)]
    pub neighbours: usize,
    /// Occlusion test tolerance (fraction of the depth).
    #[arg(long, default_value_t = 0.03)]
    pub depth_tolerance: f32,
    /// Background colour R,G,B in [0, 1] of the renders (affects PSNR/SSIM and CLIP, not consistency).
    #[arg(long, value_name = "R,G,B", default_value = "0,0,0")]
    pub background: String,
    /// A transformers CLIPModel folder (e.g. openai/clip-vit-large-patch14) for the CLIP directional similarity.
    #[arg(long, value_name = "DIR", requires_all = ["source_prompt", "target_prompt"])]
    pub clip: Option<PathBuf>,
    /// What the source scene shows (CLIP).
    #[arg(long, value_name = "TEXT")]
    pub source_prompt: Option<String>,
    /// What the edited scene should show (CLIP).
    #[arg(long, value_name = "TEXT")]
    pub target_prompt: Option<String>,
    /// Also write the results as JSON to this file.
    #[arg(long, value_name = "FILE")]
    pub json: Option<PathBuf>,
}

/// What `--json` writes.
#[derive(Serialize)]
struct Output {
    source: PathBuf,
    edited: PathBuf,
    cameras: String,
    views: usize,
    width: u32,
    height: u32,
    consistency_settings: WarpSettings,
    mask_box: Option<[[f32; 3]; 2]>,
    /// `source_consistency` / `final_consistency` are the source and edited scenes' renders.
    metrics: MetricsSummary,
    seconds: f64,
}

fn parse_background(s: &str) -> Result<[f32; 3]> {
    let v: Vec<f32> = s
        .split(',')
        .map(|x| x.trim().parse::<f32>())
        .collect::<Result<_, _>>()
        .with_context(|| format!("--background {s}: expected R,G,B"))?;
    if v.len() != 3 || v.iter().any(|c| !(0.0..=1.0).contains(c)) {
        bail!("--background {s}: expected three numbers in [0, 1]");
    }
    Ok([v[0], v[1], v[2]])
}

fn choose_cameras(
    args: &Args,
    source: &GaussianScene,
    own: Option<splat::cameras::CameraSet>,
) -> Result<(Vec<Camera>, String)> {
    let size = args
        .size
        .as_deref()
        .map(super::edit_opts::parse_size)
        .transpose()?;
    let orbit = |n: usize| -> Result<Vec<Camera>> {
        let (lo, hi) = robust_bounds(source, 0.01)
            .context("the source scene is empty: nothing to orbit around; pass --cameras")?;
        let (w, h) = size.unwrap_or(DEFAULT_ORBIT_SIZE);
        Ok(orbit_cameras(lo, hi, n, w, h))
    };
    // Generated orbits already have the requested size; loaded cameras are adapted to it.
    let (cams, from, loaded) = if let Some(path) = &args.cameras {
        let set = load_cameras(path)?;
        (
            set.cameras,
            format!("cameras from {}", path.display()),
            true,
        )
    } else if let Some(n) = args.orbit {
        if n < 2 {
            bail!("--orbit needs at least two views to compare views with each other");
        }
        (orbit(n)?, format!("an orbit of {n} views"), false)
    } else if let Some(set) = own.filter(|s| !s.cameras.is_empty()) {
        (
            set.cameras,
            "the source scene's cameras.json".to_string(),
            true,
        )
    } else {
        (
            orbit(DEFAULT_ORBIT_VIEWS)?,
            format!("an orbit of {DEFAULT_ORBIT_VIEWS} views"),
            false,
        )
    };
    if cams.is_empty() {
        bail!("{from}: no cameras");
    }
    let picked = edit::present::report::subset_indices(cams.len(), args.max_views);
    let cams: Vec<Camera> = picked
        .iter()
        .map(|&i| match size {
            Some((w, h)) if loaded => to_working_resolution(&cams[i], w, h),
            _ => cams[i].clone(),
        })
        .collect();
    Ok((cams, from))
}

/// Renders of `scene` from every camera, with the box mask (1 inside, 0 outside) as an extra channel.
fn render_all(
    scene: &GaussianScene,
    cameras: &[Camera],
    settings: &RenderSettings,
    mask_box: Option<&Box3>,
) -> Vec<RenderOutput> {
    let inside: Option<Vec<f32>> = mask_box.map(|b| {
        mask_from_box(scene, b)
            .into_iter()
            .map(|m| if m { 1.0 } else { 0.0 })
            .collect()
    });
    // Views in parallel; the renderer parallelises inside a view too, which rayon balances.
    cameras
        .par_iter()
        .map(|c| {
            let extra = inside.as_ref().map(|v| ExtraChannels {
                values: v,
                channels: 1,
            });
            render(scene, c, settings, extra)
        })
        .collect()
}

fn fmt_consistency(c: &ConsistencySummary) -> String {
    match (c.mean_abs_error, c.psnr) {
        (Some(e), Some(p)) => format!(
            "{e:.4}  ({p:.2} dB; {} pairs, {:.0}% co-visible)",
            c.pairs,
            100.0 * c.covisible_fraction
        ),
        _ => format!("n/a (no co-visible pixels over {} pairs)", c.pairs),
    }
}

fn fmt_preservation(p: &PreservationReport) -> String {
    match (p.psnr, p.ssim) {
        (Some(psnr), Some(ssim)) => format!(
            "PSNR {psnr:.2} dB, SSIM {ssim:.4}  ({:.0}% of pixels)",
            100.0 * p.fraction
        ),
        _ => "n/a (every pixel is inside the mask)".to_string(),
    }
}

pub fn run(args: Args) -> Result<()> {
    let t0 = Instant::now();
    let background = parse_background(&args.background)?;
    if args.depth_tolerance <= 0.0 || !args.depth_tolerance.is_finite() {
        bail!(
            "--depth-tolerance {} must be positive",
            args.depth_tolerance
        );
    }
    if args.neighbours == 0 {
        bail!("--neighbours must be at least 1");
    }
    // Load CLIP first: a wrong folder should fail before minutes of rendering.
    let clip = match &args.clip {
        Some(dir) => Some(
            ClipModel::load(dir).with_context(|| format!("loading CLIP from {}", dir.display()))?,
        ),
        None => None,
    };
    let (source, own) = splat::open_scene(&args.source)
        .with_context(|| format!("opening the source scene {}", args.source.display()))?;
    let (edited, _) = splat::open_scene(&args.edited)
        .with_context(|| format!("opening the edited scene {}", args.edited.display()))?;
    if source.is_empty() || edited.is_empty() {
        bail!(
            "{} has no Gaussians",
            if source.is_empty() {
                args.source.display()
            } else {
                args.edited.display()
            }
        );
    }
    let (cameras, from) = choose_cameras(&args, &source, own)?;
    if cameras.len() < 2 {
        bail!("{from}: need at least two views");
    }
    let (w, h) = (cameras[0].width, cameras[0].height);
    eprintln!(
        "rendering {} views ({}x{}) of both scenes from {from}",
        cameras.len(),
        w,
        h
    );
    let settings = RenderSettings { background };
    let renders_a = render_all(&source, &cameras, &settings, args.mask_box.as_ref());
    let renders_b = render_all(&edited, &cameras, &settings, args.mask_box.as_ref());

    let consistency_settings = WarpSettings {
        neighbours: args.neighbours,
        depth_tolerance: args.depth_tolerance,
        ..Default::default()
    };
    eprintln!("measuring cross-view consistency");
    let cons_a = render_consistency(&cameras, &renders_a, &consistency_settings)?;
    let cons_b = render_consistency(&cameras, &renders_b, &consistency_settings)?;

    let images_a: Vec<Image> = renders_a.iter().map(|r| r.rgb_image()).collect();
    let images_b: Vec<Image> = renders_b.iter().map(|r| r.rgb_image()).collect();
    let refs_a: Vec<&Image> = images_a.iter().collect();
    let refs_b: Vec<&Image> = images_b.iter().collect();
    let whole = preservation(&refs_a, &refs_b, None)?;
    let outside = match &args.mask_box {
        Some(_) => {
            // Editable where either scene's box Gaussians cover the pixel.
            let masks: Vec<Vec<f32>> = renders_a
                .iter()
                .zip(&renders_b)
                .map(|(a, b)| {
                    a.extra
                        .iter()
                        .zip(&b.extra)
                        .map(|(x, y)| x.max(*y))
                        .collect()
                })
                .collect();
            let refs: Vec<&[f32]> = masks.iter().map(Vec::as_slice).collect();
            Some(preservation(&refs_a, &refs_b, Some(&refs))?)
        }
        None => None,
    };
    let clip_report = match (&clip, &args.source_prompt, &args.target_prompt) {
        (Some(model), Some(sp), Some(tp)) => {
            eprintln!("CLIP directional similarity ({} views)", cameras.len());
            Some(
                model
                    .directional_similarity(&refs_a, &refs_b, sp, tp)
                    .context("CLIP directional similarity")?,
            )
        }
        _ => None,
    };

    let metrics = MetricsSummary {
        source_consistency: Some(cons_a.summary.clone()),
        final_consistency: Some(cons_b.summary.clone()),
        preservation_whole: Some(whole.clone()),
        preservation_outside_mask: outside.clone(),
        clip: clip_report.clone(),
        ..Default::default()
    };

    println!("source   {}", args.source.display());
    println!("edited   {}", args.edited.display());
    println!("views    {} ({w}x{h}), {from}", cameras.len());
    println!(
        "cross-view error, source renders   {}",
        fmt_consistency(&cons_a.summary)
    );
    println!(
        "cross-view error, edited renders   {}",
        fmt_consistency(&cons_b.summary)
    );
    println!(
        "preservation, whole images         {}",
        fmt_preservation(&whole)
    );
    if let Some(o) = &outside {
        println!("preservation, outside the mask     {}", fmt_preservation(o));
    }
    if let Some(c) = &clip_report {
        println!(
            "CLIP directional similarity        {:.4}  (image similarity {:.4}, edited vs target text {:.4})",
            c.directional, c.image_similarity, c.target_text_similarity
        );
    }

    if let Some(path) = &args.json {
        let out = Output {
            source: args.source.clone(),
            edited: args.edited.clone(),
            cameras: from,
            views: cameras.len(),
            width: w,
            height: h,
            consistency_settings,
            mask_box: args.mask_box.as_ref().map(|b| [b.min, b.max]),
            metrics,
            seconds: t0.elapsed().as_secs_f64(),
        };
        let text = serde_json::to_string_pretty(&out)?;
        splat::atomic_write(path, text.as_bytes())
            .with_context(|| format!("writing {}", path.display()))?;
        eprintln!("wrote {}", path.display());
    }
    Ok(())
}
