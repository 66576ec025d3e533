//! `vcedit render SCENE`: render a scene to PNG files from given or generated cameras.

use anyhow::Result;
use splat::render::RenderSettings;
use splat::{Image, SplatDevice};
use std::path::{Path, PathBuf};
use std::time::Instant;

use crate::args::memory::MemoryCheckArg;
use crate::args::output::{fingerprint, ForceArg, OutputDir};
use crate::args::{
    BackgroundArg, CameraArgs, CameraSource, DeviceArg, SizeArg, DEFAULT_ORBIT_VIEWS,
};
use crate::progress::Reporter;

#[derive(clap::Args, Debug)]
#[command(
    about = "Render a scene to one PNG per view (optionally depth and alpha)",
    after_help = "Cameras come from --cameras, else --orbit, else the scene folder (INRIA output with cameras.json), \
else an orbit of 32 views around the scene; --max-views keeps an evenly spaced subset. Files are named \
NNNN_<camera name>.png (+ _depth.png, _alpha.png).

Examples:
  vcedit render scene.ply --orbit 24 --out renders/
  vcedit render output/garden --out renders/ --size 512x512 --depth --alpha
  vcedit render scene.ply --cameras data/transforms.json --out renders/ \\
      --background 1,1,1"
)]
pub struct Args {
    /// A scene file (PLY, compressed PLY, .splat, .spz, SOG), a SOG folder, or an INRIA trainer output
    /// folder (point_cloud/iteration_*/point_cloud.ply + cameras.json).
    pub scene: PathBuf,
    #[command(flatten)]
    pub views: CameraArgs,
    /// Output folder (created if needed). A folder holding another run's renders is refused (see --force).
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    #[command(flatten)]
    pub force: ForceArg,
    #[command(flatten)]
    pub size: SizeArg,
    /// Also write the depth of each view (grey PNG, near = bright; normalised per view between the 1st and
    /// 99th percentile of the visible depths; empty pixels black).
    #[arg(long)]
    pub depth: bool,
    /// Also write the accumulated opacity of each view (grey PNG).
    #[arg(long)]
    pub alpha: bool,
    #[command(flatten)]
    pub background: BackgroundArg,
    #[command(flatten)]
    pub device: DeviceArg,
    #[command(flatten)]
    pub memory: MemoryCheckArg,
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
fn depth_image(width: u32, height: u32, depth: &[f32], alpha: &[f32]) -> Image {
    let mean_depth: Vec<Option<f32>> = depth
        .iter()
        .zip(alpha)
        .map(|(&d, &a)| (a > 0.5 && d.is_finite()).then(|| d / a))
        .collect();
    let mut visible: Vec<f32> = mean_depth.iter().flatten().copied().collect();
    let mut img = Image::new(width, height, 1);
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
    // The error names the file ("PATH: cannot write: ...").
    Ok(img.save_png(path)?)
}

pub fn run(args: Args) -> Result<()> {
    let t0 = Instant::now();
    args.views.validate()?;
    let (scene, own_cameras) = splat::open_scene(&args.scene)?;
    let (cameras, source) =
        args.views
            .choose(&scene, own_cameras, args.size.size, DEFAULT_ORBIT_VIEWS)?;
    let cameras = args.views.evenly_spaced(cameras);
    let source = match source {
        CameraSource::Orbit {
            by_default: true, ..
        } => format!("{source} (the scene has no cameras; see --cameras, --orbit)"),
        _ => source.to_string(),
    };
    // One view at a time: its render, and the images written from it (f32 colour, 8-bit copies, depth).
    let pixels = cameras
        .iter()
        .map(|c| c.width as u64 * c.height as u64)
        .max()
        .unwrap_or(0);
    args.memory.check(
        splat::render::render_memory_bytes(pixels, scene.len() as u64, 0) + pixels * 16,
        "--size",
    )?;
    // Everything that decides the files written; a folder of another render is not mixed with this one.
    let settings_key = fingerprint(&(
        &args.scene,
        &args.views,
        &args.size,
        args.depth,
        args.alpha,
        &args.background,
    ));
    let mut sources = splat::formats::scene_sources(&args.scene);
    sources.extend(
        args.views
            .cameras
            .iter()
            .flat_map(|c| splat::cameras::camera_sources(c)),
    );
    let inputs: Vec<&Path> = sources.iter().map(PathBuf::as_path).collect();
    let out_dir = OutputDir::open(
        &args.out,
        "render",
        &settings_key,
        args.force.force,
        &inputs,
    )?;
    eprintln!(
        "{}: {} Gaussians (SH degree {}), rendering {} views from {source}",
        args.scene.display(),
        scene.len(),
        scene.sh_degree,
        cameras.len()
    );
    let settings = RenderSettings {
        background: args.background.background,
    };
    // The networks are not used here: their weight precision does not matter.
    let device = SplatDevice::from(args.device.open_for(gpu::Workload::Splatting)?);
    let mut progress = Reporter::new();
    progress.stage("rendering views", cameras.len() as u64);
    let t_render = Instant::now();
    device.for_each_render(&scene, &cameras, &settings, None, &mut |i, out| {
        let cam = &cameras[i];
        let rgb = out.rgb_image();
        let stem = file_stem(i, &cam.name);
        save(&rgb, &args.out.join(format!("{stem}.png")))?;
        if args.depth {
            save(
                &depth_image(rgb.width, rgb.height, &out.depth, &out.alpha),
                &args.out.join(format!("{stem}_depth.png")),
            )?;
        }
        if args.alpha {
            let alpha = Image::from_data(rgb.width, rgb.height, 1, out.alpha);
            save(&alpha, &args.out.join(format!("{stem}_alpha.png")))?;
        }
        progress.advance(1);
        anyhow::Ok(())
    })?;
    progress.finish();
    out_dir.finish();
    let per_view = t_render.elapsed().as_secs_f64() / cameras.len().max(1) as f64;
    eprintln!(
        "wrote {} to {} ({:.0} ms per view, {:.1} s total)",
        edit::present::count(cameras.len(), "view", "views"),
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
    fn file_stems_are_safe_and_ordered() {
        assert_eq!(file_stem(3, "r_12"), "0003_r_12");
        assert_eq!(file_stem(0, "a/b c.png"), "0000_a_b_c_png");
        assert_eq!(file_stem(7, ""), "0007");
    }
}
