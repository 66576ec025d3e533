//! `vcedit inspect SCENE`: what is in a 3DGS scene.

use anyhow::{Context, Result};
use serde::Serialize;
use splat::cameras::robust_bounds;
use splat::GaussianScene;
use std::path::PathBuf;

use crate::args::output::require_extension;

#[derive(clap::Args)]
#[command(
    about = "Print statistics of a 3DGS scene (count, SH degree, bounds, opacities, scales, cameras)",
    after_help = "Examples:\n  vcedit inspect scene.ply\n  vcedit inspect output/garden   # an INRIA trainer output (adds the cameras)\n  vcedit inspect scene.ply --json > stats.json\n  vcedit inspect scene.ply --json stats.json   # text here, JSON in the file"
)]
pub struct Args {
    /// A scene file (PLY, compressed PLY, .splat, .spz, SOG), a SOG folder, or an INRIA trainer output
    /// folder (point_cloud/iteration_*/point_cloud.ply + cameras.json).
    #[arg(value_name = "SCENE")]
    pub scene: Option<PathBuf>,
    /// The statistics as JSON: `--json` prints them on stdout instead of the text, `--json=FILE` or
    /// `--json FILE` (a name ending in .json) writes them to FILE and prints the text, as in `metrics`.
    #[arg(long, value_name = "FILE", num_args = 0..=1, default_missing_value = "-")]
    pub json: Option<PathBuf>,
    #[command(flatten)]
    pub force: crate::args::output::ForceArg,
}

#[derive(Serialize)]
struct Summary {
    min: f32,
    median: f32,
    mean: f32,
    max: f32,
    /// Percentile -> value, for the percentiles listed in `PERCENTILES`.
    percentiles: Vec<(f32, f32)>,
}

#[derive(Serialize)]
struct Stats {
    path: PathBuf,
    count: usize,
    sh_degree: u32,
    bounds: Option<([f32; 3], [f32; 3])>,
    /// 1st-99th percentile box of the means: the scene without its outlying floaters.
    bounds_1_99: Option<([f32; 3], [f32; 3])>,
    /// sigmoid(opacity logit).
    opacity: Option<Summary>,
    /// exp(log-scale) of each Gaussian's largest axis.
    max_scale: Option<Summary>,
    cameras: Option<usize>,
}

const PERCENTILES: [f32; 5] = [1.0, 10.0, 50.0, 90.0, 99.0];

/// Summary statistics of `values` (sorted in place).
fn summarize(values: &mut [f32]) -> Option<Summary> {
    if values.is_empty() {
        return None;
    }
    values.sort_unstable_by(f32::total_cmp);
    let at = |p: f32| values[((values.len() - 1) as f32 * p / 100.0).round() as usize];
    Some(Summary {
        min: values[0],
        median: at(50.0),
        mean: (values.iter().map(|&v| v as f64).sum::<f64>() / values.len() as f64) as f32,
        max: values[values.len() - 1],
        percentiles: PERCENTILES.iter().map(|&p| (p, at(p))).collect(),
    })
}

fn stats(path: PathBuf, scene: &GaussianScene, cameras: Option<usize>) -> Stats {
    let mut opacity: Vec<f32> = (0..scene.len()).map(|i| scene.opacity(i)).collect();
    let mut max_scale: Vec<f32> = scene
        .log_scales
        .chunks_exact(3)
        .map(|s| s[0].max(s[1]).max(s[2]).exp())
        .collect();
    Stats {
        path,
        count: scene.len(),
        sh_degree: scene.sh_degree,
        bounds: scene.bounds(),
        bounds_1_99: robust_bounds(scene, 0.01),
        opacity: summarize(&mut opacity),
        max_scale: summarize(&mut max_scale),
        cameras,
    }
}

fn vec3(v: [f32; 3]) -> String {
    format!("({:.4}, {:.4}, {:.4})", v[0], v[1], v[2])
}

fn print_text(s: &Stats) -> Result<()> {
    crate::out!("scene        {}", s.path.display());
    crate::out!(
        "gaussians    {}  (SH degree {}, {} coefficients per colour channel)",
        s.count,
        s.sh_degree,
        splat::scene::sh_coeffs(s.sh_degree)
    );
    if let (Some((lo, hi)), Some((rlo, rhi))) = (s.bounds, s.bounds_1_99) {
        crate::out!("bounds       min {}  max {}", vec3(lo), vec3(hi));
        crate::out!("  1-99%      min {}  max {}", vec3(rlo), vec3(rhi));
    }
    let line = |label: &str, note: &str, m: &Summary| -> Result<()> {
        crate::out!(
            "{label:<12} min {:.4}  median {:.4}  mean {:.4}  max {:.4}   ({note})",
            m.min,
            m.median,
            m.mean,
            m.max
        );
        let pct: Vec<String> = m
            .percentiles
            .iter()
            .map(|(p, v)| format!("p{p}: {v:.4}"))
            .collect();
        crate::out!("             {}", pct.join("  "));
        Ok(())
    };
    if let Some(m) = &s.opacity {
        line("opacity", "sigmoid of the stored logit", m)?;
    }
    if let Some(m) = &s.max_scale {
        line("scale", "exp of the largest stored log-scale", m)?;
    }
    match s.cameras {
        Some(n) => crate::out!("cameras      {n} (cameras.json)"),
        None => crate::out!("cameras      none (a bare .ply; renders will use generated orbits)"),
    }
    Ok(())
}

/// The scene and where the JSON goes. `--json FILE` takes a value, so `inspect --json scene.ply` (the
/// flag before the scene, JSON meant for stdout) reads the scene as that value: it is taken back here.
/// A JSON file must be named *.json, so that `inspect --json a.ply b.ply` never writes over a scene.
fn scene_and_json(args: &Args) -> Result<(PathBuf, Option<PathBuf>)> {
    let (scene, json) = match (&args.scene, &args.json) {
        (Some(scene), json) => (scene.clone(), json.clone()),
        (None, Some(json)) if json.as_os_str() != "-" => (json.clone(), Some(PathBuf::from("-"))),
        (None, _) => {
            crate::usage!("the scene to inspect is missing: vcedit inspect SCENE [--json [FILE]]")
        }
    };
    if let Some(file) = json.as_ref().filter(|p| p.as_os_str() != "-") {
        if require_extension(file, "--json", &["json"], "the JSON file").is_err() {
            crate::usage!(
                "--json {}: the JSON file must end in .json (`--json` alone prints it)",
                file.display()
            );
        }
    }
    Ok((scene, json))
}

pub fn run(args: Args) -> Result<()> {
    let (scene_path, json) = scene_and_json(&args)?;
    let json_file = json.as_ref().filter(|p| p.as_os_str() != "-");
    if let Some(path) = json_file {
        let sources = splat::formats::scene_sources(&scene_path);
        let inputs: Vec<&std::path::Path> = sources.iter().map(PathBuf::as_path).collect();
        crate::args::output::output_file(path, &inputs, args.force.force)?;
    }
    let (scene, cameras) = splat::open_scene(&scene_path)?;
    let s = stats(scene_path.clone(), &scene, cameras.map(|c| c.cameras.len()));
    match (&json, json_file) {
        (Some(_), None) => crate::out!("{}", serde_json::to_string_pretty(&s)?),
        (_, Some(path)) => {
            print_text(&s)?;
            files::atomic_write(path, serde_json::to_string_pretty(&s)?.as_bytes())
                .with_context(|| format!("writing {}", path.display()))?;
            eprintln!("wrote {}", path.display());
        }
        (None, _) => print_text(&s)?,
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn summaries_use_sorted_order() {
        let mut v = vec![5.0, 1.0, 3.0, 2.0, 4.0];
        let s = summarize(&mut v).unwrap();
        assert_eq!((s.min, s.median, s.mean, s.max), (1.0, 3.0, 3.0, 5.0));
        assert_eq!(s.percentiles[0], (1.0, 1.0));
        assert!(summarize(&mut []).is_none());
    }
}
