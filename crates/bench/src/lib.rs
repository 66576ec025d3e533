//! Measurements of vcedit's engines on this machine, one module per bench:
//!
//! | name | what |
//! | --- | --- |
//! | `device` | the adapter the GPU path opens: name, API, shader compiler, limits, free memory |
//! | `matmul` | GPU matrix products at SD 1.5's shapes (f32 and f16 weights), first call apart |
//! | `attention` | GPU attention at SD 1.5's shapes: the flash kernel against products around a softmax |
//! | `unet` | one UNet forward (SD 1.5 config with random weights, or a model folder), with or without an InfEdit-shaped attention hook |
//! | `codec` | the latent codec's encode and decode (AutoencoderKL and TAESD, or a model folder's) |
//! | `text` | tokenizer and CLIP text encoder |
//! | `render` | the splatting renderer: CPU stages, and with `gpu` forward/backward/fit step on the GPU beside the CPU |
//! | `lpips` | LPIPS-VGG16 (full width, generated weights): target features, value, value + gradient |
//! | `lift` | CCM's lifting round: many-channel maps on a coarse grid lifted onto a scene and rendered back |
//!
//! Each runs as `vcedit bench NAME ARGS` (one binary carries them all, which is what a borrowed GPU
//! machine without a Rust toolchain can run: tools/gpu-check) or `cargo bench -p vcedit-bench --bench NAME
//! -- ARGS`. Every measurement is one `RESULT {json}` line on stdout (progress goes to stderr), with the
//! first call (which compiles the GPU kernels it meets) reported apart from the warm ones.

use std::time::{Duration, Instant};

pub mod attention;
pub mod check;
pub mod codec;
pub mod device;
pub mod lift;
pub mod lpips;
pub mod matmul;
pub mod render;
pub mod scenes;
pub mod text;
pub mod unet;

/// The benches, in the order `vcedit bench --help` lists them.
pub const NAMES: [&str; 10] = [
    "device",
    "matmul",
    "attention",
    "unet",
    "codec",
    "text",
    "render",
    "lpips",
    "lift",
    "check",
];

/// The help of bench `name` (`vcedit bench NAME --help`): its module's documentation, which says what it
/// measures and lists its options, so the binary carries the text the source documents.
pub fn help(name: &str) -> Option<String> {
    let source = match name {
        "device" => include_str!("device.rs"),
        "matmul" => include_str!("matmul.rs"),
        "attention" => include_str!("attention.rs"),
        "unet" => include_str!("unet.rs"),
        "codec" => include_str!("codec.rs"),
        "text" => include_str!("text.rs"),
        "render" => include_str!("render.rs"),
        "lpips" => include_str!("lpips.rs"),
        "lift" => include_str!("lift.rs"),
        "check" => include_str!("check.rs"),
        _ => return None,
    };
    let lines: Vec<&str> = source
        .lines()
        .take_while(|l| l.starts_with("//!"))
        .map(|l| l.trim_start_matches("//!").strip_prefix(' ').unwrap_or(""))
        .collect();
    Some(format!("vcedit bench {name}: {}\n", lines.join("\n")))
}

/// A bench that could not run: a bad argument, a missing file, a GPU error. One line.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct BenchError(pub String);

impl BenchError {
    pub fn new(message: impl std::fmt::Display) -> Self {
        Self(message.to_string())
    }
}

macro_rules! from_error {
    ($($t:ty),*) => {$(
        impl From<$t> for BenchError {
            fn from(e: $t) -> Self {
                Self(e.to_string())
            }
        }
    )*};
}
from_error!(
    candle_core::Error,
    gpu::GpuError,
    diffusion::loader::LoadError,
    diffusion::unet::UNetError,
    diffusion::vae::VaeError,
    diffusion::clip::ClipError,
    diffusion::lpips::LpipsError,
    diffusion::tokenizer::TokenizerError,
    std::io::Error
);

pub type Result<T> = std::result::Result<T, BenchError>;

/// Runs bench `name` with `args` (the words after the name). `reexec` is the command line prefix that
/// runs the same bench in a fresh process (the UNet's load-memory measurement needs one).
pub fn run(name: &str, args: &[String], reexec: &[String]) -> Result<()> {
    // As the `vcedit` binary does for every command, so that benches measure what the commands run.
    diffusion::runtime::tune_allocator();
    match name {
        "device" => device::main(args),
        "matmul" => matmul::main(args),
        "attention" => attention::main(args),
        "unet" => unet::main(args, reexec),
        "codec" => codec::main(args),
        "text" => text::main(args),
        "render" => render::main(args),
        "lpips" => lpips::main(args),
        "lift" => lift::main(args),
        "check" => check::main(args),
        other => Err(BenchError(format!(
            "unknown bench '{other}' (expected one of {})",
            NAMES.join(", ")
        ))),
    }
}

/// The `main` of `cargo bench -p vcedit-bench --bench NAME`: cargo passes `--bench`, which is dropped.
pub fn main_for_cargo_bench(name: &str) {
    let args: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| a != "--bench")
        .collect();
    if let Err(e) = run(name, &args, &[]) {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
}

/// The value after `--name` in `args`.
pub fn arg_value(args: &[String], name: &str) -> Option<String> {
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1).cloned())
}

/// The value after `--name` parsed, or `default` when absent; a value that does not parse is an error
/// naming the option.
pub fn arg_parsed<T: std::str::FromStr>(args: &[String], name: &str, default: T) -> Result<T> {
    match arg_value(args, name) {
        None => Ok(default),
        Some(v) => v
            .parse()
            .map_err(|_| BenchError(format!("{name}: cannot read '{v}'"))),
    }
}

/// A comma-separated list after `--name`, each item parsed.
pub fn arg_list<T: std::str::FromStr>(
    args: &[String],
    name: &str,
    default: &str,
) -> Result<Vec<T>> {
    let text = arg_value(args, name).unwrap_or_else(|| default.to_string());
    text.split(',')
        .filter(|v| !v.is_empty())
        .map(|v| {
            v.trim()
                .parse()
                .map_err(|_| BenchError(format!("{name}: cannot read '{v}' in '{text}'")))
        })
        .collect()
}

/// Whether the bare word or flag `name` is among `args`.
pub fn has_flag(args: &[String], name: &str) -> bool {
    args.iter().any(|a| a == name)
}

/// Prints one measurement as `RESULT {json}` (the line tools parse).
pub fn report(value: serde_json::Value) {
    println!("RESULT {value}");
}

/// Timings of one measured operation: the first call (kernel compilation, uploads of cached weights)
/// and the warm calls after it.
#[derive(Clone, Debug)]
pub struct Timed {
    pub first: Duration,
    pub warm: Vec<Duration>,
}

impl Timed {
    /// Calls `f` once, then `runs` more times, timing each; `f` must wait for its own results.
    pub fn measure<T>(runs: usize, mut f: impl FnMut() -> Result<T>) -> Result<Timed> {
        let start = Instant::now();
        std::hint::black_box(f()?);
        let first = start.elapsed();
        let mut warm = Vec::with_capacity(runs);
        for _ in 0..runs {
            let start = Instant::now();
            std::hint::black_box(f()?);
            warm.push(start.elapsed());
        }
        Ok(Timed { first, warm })
    }

    pub fn best(&self) -> Duration {
        self.warm.iter().min().copied().unwrap_or(self.first)
    }

    pub fn median(&self) -> Duration {
        if self.warm.is_empty() {
            return self.first;
        }
        let mut v = self.warm.clone();
        v.sort();
        v[v.len() / 2]
    }

    /// `first_s`, `best_s`, `median_s`, `runs` as JSON fields, merged into `fields`.
    pub fn json(&self, mut fields: serde_json::Value) -> serde_json::Value {
        let map = fields.as_object_mut().expect("report fields are an object");
        map.insert("first_s".into(), secs(self.first).into());
        map.insert("best_s".into(), secs(self.best()).into());
        map.insert("median_s".into(), secs(self.median()).into());
        map.insert("runs".into(), self.warm.len().into());
        fields
    }
}

/// A GPU launch timed as the device sees it: the first call (kernel compilation), and the best of the
/// warm runs, each `repeat` launches with one wait for the device, in seconds per launch.
#[derive(Clone, Debug)]
pub struct Launches {
    pub first: Duration,
    pub best: f64,
    pub repeat: usize,
}

impl Launches {
    /// Times `runs` warm runs of `launch` (`first`: the caller's timed first call).
    pub fn measure<T>(
        context: &gpu::GpuContext,
        first: Duration,
        runs: usize,
        repeat: usize,
        launch: impl Fn() -> candle_core::Result<T>,
    ) -> Result<Launches> {
        let mut best = f64::INFINITY;
        for _ in 0..runs.max(1) {
            let start = Instant::now();
            for _ in 0..repeat {
                std::hint::black_box(launch()?);
            }
            sync(context)?;
            best = best.min(start.elapsed().as_secs_f64() / repeat as f64);
        }
        Ok(Launches {
            first,
            best,
            repeat,
        })
    }

    /// TFLOP/s at `flops` floating-point operations per launch.
    pub fn tflops(&self, flops: f64) -> f64 {
        flops / self.best / 1e12
    }

    /// "1.234 ms, 5.67 TFLOP/s (first call 89.0 ms)" at `flops` per launch, for the bench's log.
    pub fn summary(&self, flops: f64) -> String {
        format!(
            "{:.3} ms, {:.2} TFLOP/s (first call {:.1} ms)",
            self.best * 1e3,
            self.tflops(flops),
            self.first.as_secs_f64() * 1e3
        )
    }

    /// `best_s`, `ms`, `tflops` (at `flops` per launch), `first_s` and `repeat` as JSON fields, merged
    /// into `fields`.
    pub fn json(&self, flops: f64, mut fields: serde_json::Value) -> serde_json::Value {
        let map = fields.as_object_mut().expect("report fields are an object");
        map.insert("best_s".into(), ((self.best * 1e9).round() / 1e9).into());
        map.insert("ms".into(), ((self.best * 1e6).round() / 1e3).into());
        let tflops = (self.tflops(flops) * 1e3).round() / 1e3;
        map.insert("tflops".into(), tflops.into());
        map.insert("first_s".into(), secs(self.first).into());
        map.insert("repeat".into(), self.repeat.into());
        fields
    }
}

/// Sizes written `AxBx..`: `N` positive whole numbers; `form` says which for the error (e.g.
/// `MxKxN (e.g. 4096x320x1280)`).
pub fn parse_sizes<const N: usize>(s: &str, form: &str) -> Result<[usize; N]> {
    let dims: Vec<usize> = s.split('x').filter_map(|v| v.parse().ok()).collect();
    match <[usize; N]>::try_from(dims) {
        Ok(dims) if dims.iter().all(|&d| d > 0) => Ok(dims),
        _ => Err(BenchError::new(format!("--shapes: '{s}' is not {form}"))),
    }
}

/// Seconds rounded to microseconds (JSON stays readable).
pub fn secs(d: Duration) -> f64 {
    (d.as_secs_f64() * 1e6).round() / 1e6
}

/// A `/proc/self/status` memory field in MB (`VmHWM` = peak RSS, `RssAnon` = heap, `RssFile` = mapped
/// files); NaN where the file is missing (not Linux).
pub fn status_mb(field: &str) -> f64 {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    status
        .lines()
        .find_map(|l| l.strip_prefix(field).and_then(|v| v.strip_prefix(':')))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<f64>().ok())
        .map(|kb| kb / 1024.0)
        .unwrap_or(f64::NAN)
}

/// The process's peak resident memory in MB.
pub fn peak_rss_mb() -> f64 {
    status_mb("VmHWM")
}

/// User + system CPU seconds of this process (from /proc/self/stat, 100 Hz ticks), to judge runs on a
/// machine shared with other work: wall time inflates under contention, CPU time much less.
pub fn cpu_seconds() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    // Fields after the parenthesised command name; utime and stime are fields 14 and 15 overall.
    let rest = stat.rsplit_once(')').map(|(_, r)| r).unwrap_or("");
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let ticks = |i: usize| {
        fields
            .get(i)
            .and_then(|v| v.parse::<f64>().ok())
            .unwrap_or(f64::NAN)
    };
    (ticks(11) + ticks(12)) / 100.0
}

/// The 1-minute load average (Linux), printed with CPU measurements: the machine may be shared.
pub fn load_average() -> Option<f64> {
    std::fs::read_to_string("/proc/loadavg")
        .ok()?
        .split_whitespace()
        .next()?
        .parse()
        .ok()
}

/// Random plain tensors for every parameter `build` asks for (no `Var`s, so the fused inference kernels
/// run as with loaded weights), as a `VarBuilder` to build the network from.
pub fn random_weights<T, E: std::fmt::Display>(
    build: impl Fn(candle_nn::VarBuilder) -> std::result::Result<T, E>,
) -> Result<candle_nn::VarBuilder<'static>> {
    use candle_core::{DType, Device, Tensor};
    let varmap = candle_nn::VarMap::new();
    let vb = candle_nn::VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
    build(vb).map_err(BenchError::new)?;
    let tensors = varmap
        .data()
        .lock()
        .expect("varmap lock")
        .iter()
        .map(|(k, v)| Ok((k.clone(), (v.as_tensor().detach() * 0.05)?)))
        .collect::<candle_core::Result<std::collections::HashMap<String, Tensor>>>()?;
    Ok(candle_nn::VarBuilder::from_tensors(
        tensors,
        DType::F32,
        &Device::Cpu,
    ))
}

/// Opens the GPU for the networks from `--device` (default `default`) and `--precision` (default f16):
/// `None` for `cpu`, or for `auto` without a usable GPU. On the CPU, `--precision` sets how its products
/// run (`bf16`, the default where the CPU has AVX512-BF16, or `f32`; see
/// [`diffusion::device::CpuPrecision::from_request`]).
pub fn network_device(
    args: &[String],
    default: &str,
) -> Result<Option<diffusion::device::GpuDevice>> {
    let choice: gpu::DeviceChoice = arg_value(args, "--device")
        .unwrap_or_else(|| default.into())
        .parse()?;
    let requested = arg_value(args, "--precision");
    let cpu_precision = diffusion::device::CpuPrecision::from_request(requested.as_deref());
    // bf16 names the CPU's precision; on a GPU only f16 and f32 parse.
    let gpu_precision =
        match requested.as_deref() {
            Some(p) if p.trim().eq_ignore_ascii_case("bf16") => None,
            Some(p) => Some(p.parse::<diffusion::device::Precision>().map_err(|_| {
                BenchError::new(format!("--precision: '{p}' is not f16, bf16 or f32"))
            })?),
            None => Some(diffusion::device::Precision::default()),
        };
    match gpu::open(choice)? {
        Some(ctx) => {
            let precision = gpu_precision.ok_or_else(|| {
                BenchError::new("--precision bf16 is a CPU precision; a GPU takes f16 or f32")
            })?;
            Ok(Some(diffusion::device::GpuDevice::with_precision(
                ctx, precision,
            )))
        }
        None => {
            let precision = cpu_precision.map_err(BenchError::new)?;
            diffusion::device::set_cpu_precision(precision).map_err(BenchError::new)?;
            Ok(None)
        }
    }
}

/// Where the networks run, for a bench's first line: the GPU and its weights' precision, or the CPU's
/// thread count and how its products run (bf16 or f32).
pub fn networks_on(gpu: Option<&diffusion::device::GpuDevice>) -> String {
    match gpu {
        Some(g) => format!("{} ({} weights)", g.name(), g.precision()),
        None => format!(
            "CPU, {} threads, {}",
            rayon::current_num_threads(),
            diffusion::device::cpu_precision().describe()
        ),
    }
}

/// The GPU `--device` names (default `gpu`) for a bench that runs only there; an error naming the bench
/// where there is none.
pub fn required_gpu(args: &[String], bench: &str) -> Result<gpu::GpuContext> {
    let choice: gpu::DeviceChoice = arg_value(args, "--device")
        .unwrap_or_else(|| "gpu".into())
        .parse()?;
    gpu::open(choice)?
        .ok_or_else(|| BenchError::new(format!("{bench} bench: no GPU (device {choice})")))
}

/// Waits for every GPU command submitted so far.
pub fn sync(ctx: &gpu::GpuContext) -> Result<()> {
    gpu::cubecl::future::block_on(ctx.client.sync())
        .map_err(gpu::server_error)
        .map_err(BenchError::from)
}

/// Largest absolute difference over the largest magnitude of `want` (the GPU path against the CPU).
/// ‖got − want‖₂ / ‖want‖₂ over all elements.
pub fn relative_l2(got: &candle_core::Tensor, want: &candle_core::Tensor) -> Result<f32> {
    let diff = (got - want)?.sqr()?.sum_all()?.to_scalar::<f32>()?;
    let norm = want.sqr()?.sum_all()?.to_scalar::<f32>()?;
    Ok((diff / norm.max(f32::MIN_POSITIVE)).sqrt())
}

pub fn relative_error(got: &candle_core::Tensor, want: &candle_core::Tensor) -> Result<f32> {
    let diff = (got - want)?
        .abs()?
        .flatten_all()?
        .max(0)?
        .to_scalar::<f32>()?;
    let scale = want.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?;
    Ok(diff / scale.max(f32::MIN_POSITIVE))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn words(s: &str) -> Vec<String> {
        s.split_whitespace().map(String::from).collect()
    }

    #[test]
    fn every_bench_has_a_help_with_its_options() {
        for name in NAMES {
            let help = help(name).unwrap();
            assert!(help.lines().count() > 1, "{name}: {help}");
        }
        assert!(help("unet").unwrap().contains("--batches"));
        assert!(help("nothing").is_none());
    }

    #[test]
    fn arguments_parse_or_name_the_option() {
        let args = words("--runs 3 --batches 1,6 gpu --size x");
        assert_eq!(arg_parsed(&args, "--runs", 1usize).unwrap(), 3);
        assert_eq!(arg_parsed(&args, "--missing", 7usize).unwrap(), 7);
        assert_eq!(arg_list::<usize>(&args, "--batches", "2").unwrap(), [1, 6]);
        assert_eq!(arg_list::<usize>(&args, "--other", "2,4").unwrap(), [2, 4]);
        assert!(has_flag(&args, "gpu"));
        let e = arg_parsed(&args, "--size", 1usize).unwrap_err();
        assert_eq!(e.to_string(), "--size: cannot read 'x'");
        assert!(run("nonesuch", &[], &[])
            .unwrap_err()
            .to_string()
            .contains("unknown bench 'nonesuch'"));
    }

    #[test]
    fn timings_keep_the_first_call_apart() {
        let mut calls = 0;
        let t = Timed::measure(3, || {
            calls += 1;
            std::thread::sleep(Duration::from_millis(if calls == 1 { 30 } else { 1 }));
            Ok(())
        })
        .unwrap();
        assert_eq!(calls, 4);
        assert_eq!(t.warm.len(), 3);
        assert!(t.first >= Duration::from_millis(30));
        assert!(t.best() < Duration::from_millis(30) && t.best() <= t.median());
        let j = t.json(serde_json::json!({"what": "x"}));
        assert_eq!(j["runs"], 3);
        assert_eq!(j["what"], "x");
        assert!(j["first_s"].as_f64().unwrap() >= 0.03);
    }
}
