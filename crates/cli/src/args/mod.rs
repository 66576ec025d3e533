//! Options shared by several commands: clap groups that each command flattens into its `Args`
//! (`#[command(flatten)]`), so an option is spelt, parsed and documented once.
//!
//! | group             | options                                   | used by                              |
//! |-------------------|-------------------------------------------|--------------------------------------|
//! | [`SizeArg`]       | `--size` (default: the inputs' own size)  | render, metrics, fit                 |
//! | [`WorkingSize`]   | `--size` (default 512)                    | edit, edit-image (via `SamplerArgs`) |
//! | [`BackgroundArg`] | `--background`                            | render, metrics, fit, edit           |
//! | [`CameraArgs`]    | `--cameras`, `--orbit`, `--max-views`     | render, metrics, edit                |
//! | [`DeviceArg`]     | `--device`                                | render, fit, edit, edit-image, demo, metrics |
//! | [`PrecisionArg`]  | `--precision` (network weights on a GPU)  | edit, edit-image, demo               |
//! | [`ComputeArgs`]   | `--device` and `--precision` together      | edit, edit-image, demo               |
//! | [`editing`]       | model, prompts, InfEdit sampler knobs     | edit, edit-image                     |
//! | [`output::ForceArg`] | `--force`                              | render, edit, demo                   |
//! | [`memory::MemoryCheckArg`] | `--ignore-memory-check`          | edit, fit                            |
//!
//! Where commands write (never over an input, one run per output folder) is decided in [`output`]; the
//! memory estimate's refusal in [`memory`].
//!
//! The value grammars are the parsers of [`parse`]: sizes (`N` or `WxH`), colours (a name, `#rrggbb` or
//! `r,g,b` in 0..1), positive and non-negative whole numbers, fractions in [0, 1] and finite numbers.

pub mod editing;
pub mod memory;
pub mod output;
pub mod parse;

use std::fmt;
use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use diffusion::device::Precision;
use gpu::{DeviceChoice, GpuContext};
use splat::cameras::{
    load_cameras, orbit_cameras, robust_bounds, to_working_resolution, CameraSet,
};
use splat::{Camera, GaussianScene};

use parse::{parse_colour, parse_size, positive, whole};

/// A value the command refuses after parsing: a range one option's parser cannot check alone (it depends
/// on another option, or on the input). Reported like clap's usage errors, with exit code 2 (see
/// `main`); raised with [`usage!`](crate::usage).
#[derive(Debug)]
pub struct UsageError(pub String);

impl fmt::Display for UsageError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for UsageError {}

/// `bail!` with a [`UsageError`] (exit code 2).
#[macro_export]
macro_rules! usage {
    ($($arg:tt)*) => {
        return Err(anyhow::Error::new($crate::args::UsageError(format!($($arg)*))))
    };
}

/// `--device`: where rendering, fitting and the networks run.
#[derive(clap::Args, Debug, Clone)]
pub struct DeviceArg {
    /// Compute device: cpu, gpu (an error without one), auto (a hardware GPU when one is found, else the
    /// CPU), cuda (NVIDIA's runtime only) or wgpu (Vulkan/Metal/DX12 only; also `vulkan`). gpu and auto
    /// take CUDA where it runs, else Vulkan/Metal/DX12. Default: $VCEDIT_DEVICE, else auto.
    #[arg(long, value_name = "DEVICE")]
    pub device: Option<DeviceChoice>,
}

impl DeviceArg {
    /// Opens the chosen device for a command that runs `workload` (it picks the shader compiler) and
    /// says in the log which one runs: `None` means the CPU.
    pub fn open_for(&self, workload: gpu::Workload) -> Result<Option<GpuContext>> {
        let choice = match self.device {
            Some(c) => c,
            None => DeviceChoice::from_env_or(DeviceChoice::Auto)
                .context(format!("${}", gpu::DEVICE_ENV))?,
        };
        let ctx = gpu::open_for(choice, workload)?;
        match (&ctx, choice) {
            (Some(ctx), _) => {
                eprintln!("device: {}", ctx.describe());
                if let Some(why) = &ctx.passed_over {
                    eprintln!("        {why}");
                }
            }
            (None, DeviceChoice::Auto) => {
                let software = gpu::list_adapters().into_iter().find(|a| a.software);
                match software {
                    Some(a) => eprintln!(
                        "device: CPU (auto: no hardware GPU; {} is a software rasteriser, set {}=1 to use it)",
                        a.name,
                        gpu::ALLOW_SOFTWARE_ENV
                    ),
                    None => eprintln!("device: CPU (auto: no GPU found)"),
                }
                if let Some(why) = gpu::cuda_passed_over() {
                    eprintln!("        {why}");
                }
            }
            (None, _) => eprintln!("device: CPU"),
        }
        Ok(ctx)
    }
}

/// `--precision`: how the networks compute: their weights on a GPU, their matrix products on the CPU.
#[derive(clap::Args, Debug, Clone)]
pub struct PrecisionArg {
    /// On a GPU: f16 weights (the default; half the memory, f32 arithmetic, relative error ~1e-3) or f32
    /// (the CPU's numbers up to summation order). On the CPU: bf16 products with f32 sums, weights held
    /// once in bf16 (the default where the CPU has AVX512-BF16; a UNet took 0.65-0.8x the f32 CPU time on
    /// a Zen 4, 0.3 % relative L2 on its output), else f32 (the default elsewhere, and on request). f16 on
    /// the CPU means f32 there; bf16 on a GPU is refused.
    #[arg(long, value_name = "f16|bf16|f32", value_parser = parse_precision)]
    pub precision: Option<String>,
}

/// `f16`, `bf16` or `f32` (also `fp16`, `fp32`), in lower case.
fn parse_precision(s: &str) -> std::result::Result<String, String> {
    let s = s.trim().to_ascii_lowercase();
    match s.as_str() {
        "f16" | "fp16" | "bf16" | "f32" | "fp32" => Ok(s),
        _ => Err(format!("'{s}' is not f16, bf16 or f32")),
    }
}

impl PrecisionArg {
    /// Where the networks and the splatting engine run: the GPU `gpu` opened (its weights' precision from
    /// `--precision`) or, for `None`, the CPU, whose products' precision this sets for the process and
    /// logs.
    pub fn compute(&self, gpu: Option<GpuContext>) -> Result<edit::compute::Compute> {
        let requested = self.precision.as_deref();
        match gpu {
            Some(ctx) => {
                let precision = match requested {
                    None => Precision::default(),
                    Some("bf16") => usage!(
                        "--precision bf16 is a CPU precision; on a GPU use f16 (default) or f32"
                    ),
                    Some(p) => p.parse()?,
                };
                Ok(edit::compute::Compute::on(Some(ctx), precision))
            }
            None => {
                let precision = diffusion::device::CpuPrecision::from_request(requested)?;
                diffusion::device::set_cpu_precision(precision)?;
                let why = match (precision, requested) {
                    (diffusion::device::CpuPrecision::Bf16, _) => "",
                    (_, Some(_)) => " (--precision)",
                    (_, None) => " (this CPU has no AVX512-BF16)",
                };
                eprintln!("CPU products: {}{why}", precision.describe());
                Ok(edit::compute::Compute::cpu())
            }
        }
    }
}

/// `--device` and `--precision`, for the commands that run the networks: where they and the splatting
/// engine run, and in what precision.
#[derive(clap::Args, Debug, Clone)]
pub struct ComputeArgs {
    #[command(flatten)]
    pub device: DeviceArg,
    #[command(flatten)]
    pub precision: PrecisionArg,
}

impl ComputeArgs {
    /// Opens the chosen device for the networks, with the chosen precision ([`PrecisionArg::compute`]).
    pub fn open(&self) -> Result<edit::compute::Compute> {
        self.open_for(gpu::Workload::Networks)
    }

    /// [`ComputeArgs::open`] for a command that runs `workload` (it picks the shader compiler).
    pub fn open_for(&self, workload: gpu::Workload) -> Result<edit::compute::Compute> {
        self.precision.compute(self.device.open_for(workload)?)
    }
}

/// The most views `--orbit` makes without `--allow-many-views`: a typo (100000 for 100) must not start
/// writing or rendering for hours.
pub const MAX_ORBIT_VIEWS: usize = 1000;

/// Views of the orbit generated for a scene without cameras when neither --cameras nor --orbit is given:
/// the same in every command, so `render` and `metrics` see the views an `edit` edited.
pub const DEFAULT_ORBIT_VIEWS: usize = 32;

/// Size of generated orbit views when `--size` does not give one.
pub const DEFAULT_ORBIT_SIZE: (u32, u32) = (512, 512);

/// `--size` for commands whose default is the size of their input views.
#[derive(clap::Args, Debug, Clone)]
pub struct SizeArg {
    /// Image size WxH, or N for NxN (each side 1 to 16384); views are centre-cropped to its aspect ratio,
    /// then resampled.
    ///
    /// Default: the input views' own size; 512x512 for generated orbit views.
    #[arg(long, value_name = "WxH", value_parser = parse_size, allow_hyphen_values = true)]
    pub size: Option<(u32, u32)>,
}

/// `--size` for the diffusion commands, which work at one resolution.
#[derive(clap::Args, Debug, Clone)]
pub struct WorkingSize {
    /// Image size WxH, or N for NxN (each side 1 to 16384); views are centre-cropped to its aspect ratio,
    /// then resampled.
    ///
    /// The editing commands work at this one resolution, inputs and renders alike: a multiple of what
    /// the model needs (64 for SD 1.x, 32 for the demo model; `vcedit model check` prints it).
    #[arg(
        long,
        value_name = "WxH",
        default_value = "512",
        value_parser = parse_size,
        allow_hyphen_values = true
    )]
    pub size: (u32, u32),
}

/// `--background`, the colour behind every render (and behind transparent input images).
#[derive(clap::Args, Debug, Clone)]
pub struct BackgroundArg {
    /// Background colour: a name (black, white, grey, red, green, blue, ...), #rrggbb, or r,g,b with each
    /// component from 0 to 1.
    ///
    /// Names (any case): black, white, grey or gray, red, green, blue, yellow, cyan, magenta. Hex: #rrggbb,
    /// e.g. #336699. Components: r,g,b with each from 0 to 1, e.g. 1,1,1 or 0.2,0.4,0.6.
    #[arg(
        long,
        value_name = "COLOUR",
        default_value = "black",
        default_value_if("white_background", clap::builder::ArgPredicate::IsPresent, "white"),
        value_parser = parse_colour,
        allow_hyphen_values = true
    )]
    pub background: [f32; 3],
    /// The same as --background white (the INRIA trainer's -w / --white_background).
    #[arg(
        short = 'w',
        long,
        visible_alias = "white_background",
        conflicts_with = "background"
    )]
    pub white_background: bool,
}

/// Which views a command renders: cameras from a file, an orbit, or the scene's own cameras, and at most how
/// many of them. Commands give `--max-views` their default with
/// `#[command(mut_arg("max_views", |a| a.default_value("N")))]` and say in their notes how they pick views.
#[derive(clap::Args, Debug, Clone)]
pub struct CameraArgs {
    /// Cameras: a COLMAP model folder (or its sparse/0), a transforms*.json, or an INRIA cameras.json.
    /// Default: the scene folder's cameras.json (INRIA trainer output), else an orbit.
    #[arg(long, value_name = "FILE|DIR", conflicts_with = "orbit")]
    pub cameras: Option<PathBuf>,
    /// Use N views on an orbit around the scene instead of its own cameras.
    #[arg(long, value_name = "N", value_parser = positive::<usize>, allow_negative_numbers = true)]
    pub orbit: Option<usize>,
    /// Use at most this many of the views, evenly spaced over them (first and last included); 0 = all.
    #[arg(long, value_name = "N", value_parser = whole::<usize>, allow_negative_numbers = true)]
    pub max_views: Option<usize>,
    /// Allow --orbit above 1000 views.
    #[arg(long)]
    pub allow_many_views: bool,
}

/// Where the chosen views came from.
#[derive(Debug, Clone, PartialEq)]
pub enum CameraSource {
    /// `--cameras PATH`.
    File(PathBuf),
    /// An orbit: `--orbit N`, or the command's default orbit when the scene has no cameras (`by_default`).
    Orbit { views: usize, by_default: bool },
    /// The scene folder's cameras.json.
    Scene,
}

impl fmt::Display for CameraSource {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            CameraSource::File(path) => write!(f, "cameras from {}", path.display()),
            CameraSource::Orbit { views, .. } => write!(f, "an orbit of {views} views"),
            CameraSource::Scene => write!(f, "the scene's cameras.json"),
        }
    }
}

impl CameraArgs {
    /// The checks of these options that need no file: run before any work.
    pub fn validate(&self) -> Result<()> {
        if let Some(n) = self.orbit {
            if n > MAX_ORBIT_VIEWS && !self.allow_many_views {
                crate::usage!(
                    "--orbit {n}: more than {MAX_ORBIT_VIEWS} views; pass --allow-many-views if you mean it"
                );
            }
        }
        if let Some(path) = &self.cameras {
            if !path.exists() {
                bail!("--cameras {}: no such file or folder", path.display());
            }
        }
        Ok(())
    }

    /// The views to render: `--cameras`, else `--orbit`, else the scene's own cameras (`own`), else an orbit
    /// of `default_orbit` views around `scene`. Loaded cameras are centre-cropped and scaled to `size` when
    /// it is given; orbits are made at `size`, else at [`DEFAULT_ORBIT_SIZE`]. `--max-views` is not applied
    /// here (see [`CameraArgs::evenly_spaced`], [`CameraArgs::view_limit`]).
    pub fn choose(
        &self,
        scene: &GaussianScene,
        own: Option<CameraSet>,
        size: Option<(u32, u32)>,
        default_orbit: usize,
    ) -> Result<(Vec<Camera>, CameraSource)> {
        let orbit = |views: usize, by_default: bool| -> Result<(Vec<Camera>, CameraSource)> {
            let (lo, hi) = robust_bounds(scene, 0.01).context(
                "the scene is empty, so there is nothing to orbit around; pass --cameras",
            )?;
            let (w, h) = size.unwrap_or(DEFAULT_ORBIT_SIZE);
            let cameras = orbit_cameras(lo, hi, views, w, h);
            Ok((cameras, CameraSource::Orbit { views, by_default }))
        };
        let (cameras, source) = if let Some(path) = &self.cameras {
            (
                load_cameras(path)?.cameras,
                CameraSource::File(path.clone()),
            )
        } else if let Some(n) = self.orbit {
            return orbit(n, false);
        } else if let Some(set) = own.filter(|set| !set.cameras.is_empty()) {
            (set.cameras, CameraSource::Scene)
        } else {
            return orbit(default_orbit, true);
        };
        if cameras.is_empty() {
            bail!("{source}: no cameras");
        }
        Ok(match size {
            Some((w, h)) => (
                cameras
                    .iter()
                    .map(|c| to_working_resolution(c, w, h))
                    .collect(),
                source,
            ),
            None => (cameras, source),
        })
    }

    /// At most `--max-views` of `cameras`, evenly spaced over the list (first and last included).
    pub fn evenly_spaced(&self, cameras: Vec<Camera>) -> Vec<Camera> {
        let max = self.max_views.unwrap_or(0);
        if max == 0 || cameras.len() <= max {
            return cameras;
        }
        edit::present::report::subset_indices(cameras.len(), max)
            .into_iter()
            .map(|i| cameras[i].clone())
            .collect()
    }

    /// How many of `available` views to use: `--max-views`, or all of them when it is 0 or absent.
    pub fn view_limit(&self, available: usize) -> usize {
        match self.max_views {
            Some(n) if n > 0 => n,
            _ => available,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(clap::Parser, Debug)]
    struct WithBackground {
        #[command(flatten)]
        background: BackgroundArg,
    }

    #[test]
    fn white_background_is_the_inria_spelling_of_background_white() {
        let parse = |args: &[&str]| {
            WithBackground::try_parse_from(std::iter::once("vcedit").chain(args.iter().copied()))
                .map(|a| a.background.background)
        };
        assert_eq!(parse(&[]).unwrap(), [0.0; 3]);
        for flag in ["-w", "--white-background", "--white_background"] {
            assert_eq!(parse(&[flag]).unwrap(), [1.0; 3], "{flag}");
        }
        assert_eq!(parse(&["--background", "red"]).unwrap(), [1.0, 0.0, 0.0]);
        // Two colours at once is a usage error, not a silent pick.
        let err = parse(&["-w", "--background", "red"]).unwrap_err();
        assert_eq!(err.kind(), clap::error::ErrorKind::ArgumentConflict);
    }

    fn camera(name: &str, size: u32) -> Camera {
        let mut c = orbit_cameras([-1.0; 3], [1.0; 3], 1, size, size).remove(0);
        c.name = name.to_string();
        c
    }

    fn args(cameras: Option<&str>, orbit: Option<usize>, max_views: Option<usize>) -> CameraArgs {
        CameraArgs {
            cameras: cameras.map(PathBuf::from),
            orbit,
            max_views,
            allow_many_views: false,
        }
    }

    /// A few Gaussians around the origin: something to orbit around.
    fn ball() -> GaussianScene {
        let mut s = GaussianScene::new(0);
        for i in 0..8 {
            let t = i as f32;
            s.means
                .extend_from_slice(&[0.3 * t.sin(), 0.3 * t.cos(), 0.1 * t - 0.4]);
            s.log_scales.extend_from_slice(&[-2.0; 3]);
            s.quats.extend_from_slice(&[1.0, 0.0, 0.0, 0.0]);
            s.opacity_logits.push(3.0);
            s.sh.extend_from_slice(&[1.0, 0.0, 0.0]);
        }
        s
    }

    fn camera_set(cameras: Vec<Camera>) -> CameraSet {
        CameraSet {
            image_paths: vec![None; cameras.len()],
            cameras,
            points: None,
        }
    }

    #[test]
    fn orbit_beats_the_scene_cameras_and_the_default_orbit_fills_in() {
        let scene = ball();
        let own = camera_set(vec![camera("a", 40), camera("b", 40)]);
        let (cams, source) = args(None, Some(3), None)
            .choose(&scene, Some(own.clone()), Some((32, 24)), 8)
            .unwrap();
        assert_eq!(
            source,
            CameraSource::Orbit {
                views: 3,
                by_default: false
            }
        );
        assert_eq!(cams.len(), 3);
        assert_eq!((cams[0].width, cams[0].height), (32, 24));

        let (cams, source) = args(None, None, None)
            .choose(&scene, Some(own), Some((20, 20)), 8)
            .unwrap();
        assert_eq!(source, CameraSource::Scene);
        assert_eq!(
            cams.iter().map(|c| c.name.as_str()).collect::<Vec<_>>(),
            ["a", "b"]
        );
        assert_eq!((cams[0].width, cams[0].height), (20, 20));

        let (cams, source) = args(None, None, None)
            .choose(&scene, None, None, 8)
            .unwrap();
        assert!(matches!(
            source,
            CameraSource::Orbit {
                views: 8,
                by_default: true
            }
        ));
        assert_eq!((cams[0].width, cams[0].height), DEFAULT_ORBIT_SIZE);
    }

    #[test]
    fn huge_orbits_need_to_be_asked_for() {
        let err = args(None, Some(100_000), None)
            .validate()
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("--orbit 100000") && err.contains("--allow-many-views"),
            "{err}"
        );
        assert!(args(None, Some(MAX_ORBIT_VIEWS), None).validate().is_ok());
        let mut many = args(None, Some(100_000), None);
        many.allow_many_views = true;
        assert!(many.validate().is_ok());
    }

    #[test]
    fn an_empty_scene_has_no_orbit() {
        let err = args(None, Some(4), None)
            .choose(&GaussianScene::new(0), None, None, 8)
            .unwrap_err();
        assert!(err.to_string().contains("pass --cameras"), "{err}");
    }

    #[test]
    fn max_views_picks_evenly_or_limits() {
        let cams: Vec<Camera> = (0..10).map(|i| camera(&i.to_string(), 8)).collect();
        let picked = args(None, None, Some(4)).evenly_spaced(cams.clone());
        let names: Vec<&str> = picked.iter().map(|c| c.name.as_str()).collect();
        assert_eq!(names, ["0", "3", "6", "9"]);
        assert_eq!(
            args(None, None, Some(0)).evenly_spaced(cams.clone()).len(),
            10
        );
        assert_eq!(args(None, None, None).evenly_spaced(cams).len(), 10);
        assert_eq!(args(None, None, Some(0)).view_limit(7), 7);
        assert_eq!(args(None, None, Some(96)).view_limit(7), 96);
    }
}
