//! `vcedit render SCENE`: render a scene to PNG files from given or generated cameras.

use anyhow::{bail, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use splat::cameras::{load_cameras, orbit_cameras, robust_bounds, to_working_resolution};
use splat::render::{render, RenderOutput, RenderSettings};
use splat::{Camera, Image};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Views rendered for a scene that brings no cameras when neither --cameras nor --orbit is given.
const DEFAULT_ORBIT_VIEWS: usize = 8;
/// Image size of generated orbit views unless --size says otherwise.
const DEFAULT_ORBIT_SIZE: (u32, u32) = (512, 512);

#[derive(clap::Args, Debug)]
#[command(
    about = "Render a scene to one PNG per view (optionally depth and alpha)",
    after_help = "Cameras come from --cameras, else from the scene folder (INRIA output with cameras.json), else an orbit \
of 8 views around the scene. Files are named NNNN_<camera name>.png (+ _depth.png, _alpha.png).

Examples:
  vcedit render scene.ply --orbit 24 --out renders/
  vcedit render output/garden --out renders/ --size 512x512 --depth --alpha
  vcedit render scene.ply --cameras data/transforms.json --out renders/ --background 1,1,1"
)]
pub struct Args {
    /// A .ply file, or an INRIA trainer output folder (point_cloud/iteration_*/point_cloud.ply + cameras.json).
    pub scene: PathBuf,
    /// Cameras: a COLMAP model folder (or its sparse/0), a transforms*.json, or an INRIA cameras.json.
    #[arg(long, value_name = "FILE|DIR", conflicts_with = "orbit")]
    pub cameras: Option<PathBuf>,
    /// Render N views on an orbit around the scene instead of its own cameras.
    #[arg(long, value_name = "N")]
    pub orbit: Option<usize>,
    /// Output folder (created if needed).
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    /// Image size WxH (or one number for a square). Cameras are centre-cropped to the aspect ratio, then
    /// scaled. Default: the cameras' own size; 512x512 for orbits.
    #[arg(long, value_name = "WxH", value_parser = parse_size)]
    pub size: Option<(u32, u32)>,
    /// Also write the depth of each view (grey PNG, near = bright; normalised per view between the 1st and
    /// 99th percentile of the visible depths; empty pixels black).
    #[arg(long)]
    pub depth: bool,
    /// Also write the accumulated opacity of each view (grey PNG).
    #[arg(long)]
    pub alpha: bool,
    /// Background colour R,G,B in [0, 1].
    #[arg(long, value_name = "R,G,B", default_value = "0,0,0", value_parser = parse_color)]
    pub background: [f32; 3],
}

fn parse_size(s: &str) -> Result<(u32, u32), String> {
    let parse = |v: &str| -> Result<u32, String> {
        let n: u32 = v
            .trim()
            .parse()
            .map_err(|_| format!("'{v}' is not a whole number"))?;
        if n == 0 || n > 16384 {
            return Err(format!("{n} is out of range (1..=16384)"));
        }
        Ok(n)
    };
    match s.split_once(['x', 'X']) {
        Some((w, h)) => Ok((parse(w)?, parse(h)?)),
        None => {
            let n = parse(s)?;
            Ok((n, n))
        }
    }
}

fn parse_color(s: &str) -> Result<[f32; 3], String> {
    let parts: Vec<&str> = s.split(',').collect();
    if parts.len() != 3 {
        return Err("expected three numbers R,G,B in [0, 1], e.g. 1,1,1".into());
    }
    let mut c = [0.0f32; 3];
    for (v, p) in c.iter_mut().zip(&parts) {
        *v = p
            .trim()
            .parse()
            .map_err(|_| format!("'{p}' is not a number"))?;
        if !(0.0..=1.0).contains(v) {
            return Err(format!("{v} is outside [0, 1]"));
        }
    }
    Ok(c)
}

/// The views to render, and a short description of where they came from.
fn choose_cameras(
    args: &Args,
    scene: &splat::GaussianScene,
    own: Option<splat::cameras::CameraSet>,
) -> Result<(Vec<Camera>, String)> {
    let orbit = |n: usize| -> Result<Vec<Camera>> {
        let (lo, hi) = robust_bounds(scene, 0.01)
            .context("the scene is empty, so there is nothing to orbit around; pass --cameras")?;
        let (w, h) = args.size.unwrap_or(DEFAULT_ORBIT_SIZE);
        Ok(orbit_cameras(lo, hi, n, w, h))
    };
    let (cams, source) = if let Some(path) = &args.cameras {
        let set = load_cameras(path)?;
        (set.cameras, format!("cameras from {}", path.display()))
    } else if let Some(n) = args.orbit {
        if n == 0 {
            bail!("--orbit needs at least one view");
        }
        return Ok((orbit(n)?, format!("an orbit of {n} views")));
    } else if let Some(set) = own {
        (set.cameras, "the scene's cameras.json".to_string())
    } else {
        return Ok((
            orbit(DEFAULT_ORBIT_VIEWS)?,
            format!("an orbit of {DEFAULT_ORBIT_VIEWS} views (the scene has no cameras; see --cameras, --orbit)"),
        ));
    };
    if cams.is_empty() {
        bail!("{source}: no cameras");
    }
    let cams = match args.size {
        Some((w, h)) => cams
            .iter()
            .map(|c| to_working_resolution(c, w, h))
            .collect(),
        None => cams,
    };
    Ok((cams, source))
}

/// A file-name-safe version of a camera name.
fn file_stem(index: usize, name: &str) -> String {
    let clean: String = name
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' {
                c
            } else {
                '_'
            }
        })
        .take(64)
        .collect();
    if clean.is_empty() {
        format!("{index:04}")
    } else {
        format!("{index:04}_{clean}")
    }
}

/// Depth as a grey image: per-pixel mean depth (depth / alpha) where alpha > 0.5, mapped so the 1st
/// percentile is white and the 99th is dark grey; other pixels black.
fn depth_image(out: &RenderOutput) -> Image {
    let mean_depth: Vec<Option<f32>> = out
        .depth
        .iter()
        .zip(&out.alpha)
        .map(|(&d, &a)| (a > 0.5 && d.is_finite()).then(|| d / a))
        .collect();
    let mut visible: Vec<f32> = mean_depth.iter().flatten().copied().collect();
    let mut img = Image::new(out.width, out.height, 1);
    if visible.is_empty() {
        return img;
    }
    visible.sort_unstable_by(f32::total_cmp);
    let at = |q: f32| visible[((visible.len() - 1) as f32 * q) as usize];
    let (near, far) = (at(0.01), at(0.99));
    let range = (far - near).max(1e-6);
    for (px, d) in img.data.iter_mut().zip(&mean_depth) {
        if let Some(d) = d {
            *px = 1.0 - 0.8 * ((d - near) / range).clamp(0.0, 1.0);
        }
    }
    img
}

fn save(img: &Image, path: &Path) -> Result<()> {
    img.save_png(path)
        .with_context(|| format!("writing {}", path.display()))
}

pub fn run(args: Args) -> Result<()> {
    let t0 = Instant::now();
    let (scene, own_cameras) = splat::open_scene(&args.scene)?;
    let (cameras, source) = choose_cameras(&args, &scene, own_cameras)?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("{}: cannot create the output folder", args.out.display()))?;
    eprintln!(
        "{}: {} Gaussians (SH degree {}), rendering {} views from {source}",
        args.scene.display(),
        scene.len(),
        scene.sh_degree,
        cameras.len()
    );
    let settings = RenderSettings {
        background: args.background,
    };
    let bar = ProgressBar::new(cameras.len() as u64);
    bar.set_style(
        ProgressStyle::with_template("[{bar:30}] {pos}/{len} views, {elapsed} elapsed, ETA {eta}")
            .expect("valid template")
            .progress_chars("=> "),
    );
    let t_render = Instant::now();
    for (i, cam) in cameras.iter().enumerate() {
        let out = render(&scene, cam, &settings, None);
        let stem = file_stem(i, &cam.name);
        save(&out.rgb_image(), &args.out.join(format!("{stem}.png")))?;
        if args.depth {
            save(
                &depth_image(&out),
                &args.out.join(format!("{stem}_depth.png")),
            )?;
        }
        if args.alpha {
            let alpha = Image::from_data(out.width, out.height, 1, out.alpha.clone());
            save(&alpha, &args.out.join(format!("{stem}_alpha.png")))?;
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    let per_view = t_render.elapsed().as_secs_f64() / cameras.len().max(1) as f64;
    eprintln!(
        "wrote {} views to {} ({:.0} ms per view, {:.1} s total)",
        cameras.len(),
        args.out.display(),
        per_view * 1e3,
        t0.elapsed().as_secs_f64()
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_and_colours_parse() {
        assert_eq!(parse_size("640x480"), Ok((640, 480)));
        assert_eq!(parse_size("256"), Ok((256, 256)));
        assert!(parse_size("0x10").is_err());
        assert!(parse_size("axb").is_err());
        assert_eq!(parse_color("1, 0.5,0"), Ok([1.0, 0.5, 0.0]));
        assert!(parse_color("1,2,0").is_err());
        assert!(parse_color("1,1").is_err());
    }

    #[test]
    fn file_stems_are_safe_and_ordered() {
        assert_eq!(file_stem(3, "r_12"), "0003_r_12");
        assert_eq!(file_stem(0, "a/b c.png"), "0000_a_b_c_png");
        assert_eq!(file_stem(7, ""), "0007");
    }
}
