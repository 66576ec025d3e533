//! `vcedit metrics --source-scene A --edited-scene B`: compare two scenes rendered from the same cameras.
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
use serde::Serialize;
use splat::render::{ExtraChannels, Frame, RenderSettings};
use splat::{Camera, GaussianScene, Image, SplatDevice};
use std::path::PathBuf;
use std::time::Instant;

use crate::args::memory::MemoryCheckArg;
use crate::args::output::output_file;
use crate::args::parse::{finite, positive};
use crate::args::{
    BackgroundArg, CameraArgs, CameraSource, DeviceArg, SizeArg, DEFAULT_ORBIT_VIEWS,
};

/// `--json` without a file: JSON on stdout.
const JSON_TO_STDOUT: &str = "-";

#[derive(clap::Args, Debug)]
#[command(
    about = "Compare two scenes: cross-view consistency, preservation (PSNR/SSIM), CLIP directional similarity",
    mut_arg("max_views", |a| a.default_value("64")),
    after_help = "Cameras come from --cameras, else --orbit, else the source scene's folder (INRIA cameras.json), else an \
orbit of 32 views around the source scene (as `edit`); --max-views keeps an evenly spaced subset. Both scenes are rendered from \
the same cameras. --background affects PSNR/SSIM and CLIP, not the cross-view error.

Cross-view error: each view is warped into its nearest cameras with the scene's rendered depth; the mean absolute colour \
difference (0-1 scale) over pixels both cameras see. Lower is more consistent; a scene's own renders are the floor.

Examples:
  vcedit metrics --source-scene scene.ply --edited-scene out/edited.ply \\
      --orbit 24 --json
  vcedit metrics --source-scene scene.ply --edited-scene out/edited.ply \\
      --cameras data/ --mask-box -0.5,-0.5,0,0.5,0.5,1.2 --json=m.json
  vcedit metrics --source-scene scene.ply --edited-scene out/edited.ply \\
      --clip models/clip-vit-large-patch14 \\
      --source-prompt \"a photo of a man\" --target-prompt \"a photo of a clown\""
)]
pub struct Args {
    /// The scene before editing (a scene file of any supported format, or an INRIA output folder).
    // `--source` alone is a prompt in `edit`; the old names stay as hidden aliases.
    #[arg(long = "source-scene", alias = "source", value_name = "SCENE")]
    pub source: PathBuf,
    /// The scene after editing.
    #[arg(long = "edited-scene", alias = "edited", value_name = "SCENE")]
    pub edited: PathBuf,
    #[command(flatten)]
    pub views: CameraArgs,
    #[command(flatten)]
    pub size: SizeArg,
    /// Editable region xmin,ymin,zmin,xmax,ymax,zmax: preservation is also measured outside it.
    #[arg(long, value_name = "BOX", allow_hyphen_values = true)]
    pub mask_box: Option<Box3>,
    /// Neighbouring cameras each view is compared with.
    #[arg(long, default_value_t = 3, value_parser = positive::<usize>, allow_negative_numbers = true)]
    pub neighbours: usize,
    /// Occlusion test tolerance (fraction of the depth).
    #[arg(long, default_value_t = 0.03, value_parser = finite::<f32>, allow_negative_numbers = true)]
    pub depth_tolerance: f32,
    #[command(flatten)]
    pub background: BackgroundArg,
    #[command(flatten)]
    pub device: DeviceArg,
    #[command(flatten)]
    pub memory: MemoryCheckArg,
    /// A transformers CLIPModel folder (e.g. openai/clip-vit-large-patch14) for the CLIP directional similarity.
    #[arg(long, value_name = "DIR", requires_all = ["source_prompt", "target_prompt"])]
    pub clip: Option<PathBuf>,
    /// What the source scene shows (CLIP).
    #[arg(long, value_name = "TEXT")]
    pub source_prompt: Option<String>,
    /// What the edited scene should show (CLIP).
    #[arg(long, value_name = "TEXT")]
    pub target_prompt: Option<String>,
    /// The results as JSON: `--json` prints them on stdout (the text goes to stderr), `--json=FILE` or
    /// `--json FILE` writes them to FILE as well as printing the text.
    #[arg(long, value_name = "FILE", num_args = 0..=1, default_missing_value = JSON_TO_STDOUT)]
    pub json: Option<PathBuf>,
    #[command(flatten)]
    pub force: crate::args::output::ForceArg,
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

/// The views to compare, and where they came from (for the output and its JSON).
fn choose_cameras(
    args: &Args,
    source: &GaussianScene,
    own: Option<splat::cameras::CameraSet>,
) -> Result<(Vec<Camera>, String)> {
    if args.views.orbit.is_some_and(|n| n < 2) {
        bail!("--orbit needs at least two views to compare views with each other");
    }
    let (cameras, from) = args
        .views
        .choose(source, own, args.size.size, DEFAULT_ORBIT_VIEWS)?;
    let from = match from {
        CameraSource::Scene => "the source scene's cameras.json".to_string(),
        other => other.to_string(),
    };
    Ok((args.views.evenly_spaced(cameras), from))
}

/// Renders of `scene` from every camera, with the box mask (1 inside, 0 outside) as an extra channel.
fn render_all(
    device: &SplatDevice,
    scene: &GaussianScene,
    cameras: &[Camera],
    settings: &RenderSettings,
    mask_box: Option<&Box3>,
) -> Result<Vec<Frame>> {
    let inside: Option<Vec<f32>> = mask_box.map(|b| {
        mask_from_box(scene, b)
            .into_iter()
            .map(|m| if m { 1.0 } else { 0.0 })
            .collect()
    });
    let extra = inside.as_ref().map(|v| ExtraChannels {
        values: v,
        channels: 1,
    });
    Ok(device.render_views(scene, cameras, settings, extra)?)
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
    let background = args.background.background;
    if args.depth_tolerance <= 0.0 {
        bail!(
            "--depth-tolerance {} must be positive",
            args.depth_tolerance
        );
    }
    args.views.validate()?;
    let json_file = args
        .json
        .as_ref()
        .filter(|p| p.as_os_str() != JSON_TO_STDOUT);
    if let Some(path) = json_file {
        let mut sources = splat::formats::scene_sources(&args.source);
        sources.extend(splat::formats::scene_sources(&args.edited));
        sources.extend(
            args.views
                .cameras
                .iter()
                .flat_map(|c| splat::cameras::camera_sources(c)),
        );
        sources.extend(args.clip.iter().cloned());
        let inputs: Vec<&std::path::Path> = sources.iter().map(PathBuf::as_path).collect();
        output_file(path, &inputs, args.force.force)?;
    }
    // Load CLIP first: a wrong folder should fail before minutes of rendering.
    let clip = match &args.clip {
        Some(dir) => Some(
            ClipModel::load(dir).with_context(|| format!("loading CLIP from {}", dir.display()))?,
        ),
        None => None,
    };
    let (source, own) = splat::open_scene(&args.source).context("the source scene")?;
    let (edited, _) = splat::open_scene(&args.edited).context("the edited scene")?;
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
    // Both scenes' frames and colour images are held together, while each worker thread renders a view.
    let pixels = w as u64 * h as u64;
    let (views, extra) = (cameras.len() as u64, u64::from(args.mask_box.is_some()));
    let gaussians = source.len().max(edited.len()) as u64;
    let held = 2 * views * (Frame::memory_bytes(pixels, gaussians, extra) + pixels * 12);
    let rendering = rayon::current_num_threads() as u64
        * splat::render::render_memory_bytes(pixels, gaussians, extra);
    args.memory.check(held + rendering, "--size or --orbit")?;
    let settings = RenderSettings { background };
    let device = SplatDevice::from(args.device.open_for(gpu::Workload::Splatting)?);
    let renders_a = render_all(
        &device,
        &source,
        &cameras,
        &settings,
        args.mask_box.as_ref(),
    )?;
    let renders_b = render_all(
        &device,
        &edited,
        &cameras,
        &settings,
        args.mask_box.as_ref(),
    )?;

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

    // The text goes to stdout, or to stderr when stdout carries the JSON.
    let json_on_stdout = args.json.is_some() && json_file.is_none();
    macro_rules! say {
        ($($t:tt)*) => {
            if json_on_stdout { eprintln!($($t)*) } else { crate::out!($($t)*) }
        };
    }
    say!("source   {}", args.source.display());
    say!("edited   {}", args.edited.display());
    say!("views    {} ({w}x{h}), {from}", cameras.len());
    say!(
        "cross-view error, source renders   {}",
        fmt_consistency(&cons_a.summary)
    );
    say!(
        "cross-view error, edited renders   {}",
        fmt_consistency(&cons_b.summary)
    );
    say!(
        "preservation, whole images         {}",
        fmt_preservation(&whole)
    );
    if let Some(o) = &outside {
        say!("preservation, outside the mask     {}", fmt_preservation(o));
    }
    if let Some(c) = &clip_report {
        say!(
            "CLIP directional similarity        {:.4}  (image similarity {:.4}, edited vs target text {:.4})",
            c.directional, c.image_similarity, c.target_text_similarity
        );
    }

    if args.json.is_some() {
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
        match json_file {
            Some(path) => {
                files::atomic_write(path, text.as_bytes())
                    .with_context(|| format!("writing {}", path.display()))?;
                eprintln!("wrote {}", path.display());
            }
            None => crate::out!("{text}"),
        }
    }
    Ok(())
}
