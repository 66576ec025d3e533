//! LPIPS-VGG against the `lpips` package (fixtures from tools/make_lpips_fixtures.py): value, per-layer terms
//! and the gradient w.r.t. the render from torch autograd.

use std::path::{Path, PathBuf};

use candle_core::Device;
use diffusion::lpips::{synthetic_tensors, InputRange, Lpips, VGG16_WIDTHS};
use serde_json::Value;

fn fixtures() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../fixtures/lpips")
}

struct Case {
    name: String,
    height: usize,
    width: usize,
    range: InputRange,
    value: f64,
    per_layer: Vec<f64>,
    render: Vec<f32>,
    target: Vec<f32>,
    grad: Vec<f32>,
    meta: Value,
}

fn cases() -> Vec<Case> {
    let meta: Value =
        serde_json::from_str(&std::fs::read_to_string(fixtures().join("cases.json")).unwrap())
            .unwrap();
    let tensors =
        candle_core::safetensors::load(fixtures().join("cases.safetensors"), &Device::Cpu).unwrap();
    let values = |key: String| -> Vec<f32> {
        tensors[&key]
            .flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap()
    };
    meta["cases"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| {
            let name = c["name"].as_str().unwrap().to_string();
            Case {
                height: c["height"].as_u64().unwrap() as usize,
                width: c["width"].as_u64().unwrap() as usize,
                range: match c["input_range"].as_str().unwrap() {
                    "as_is" => InputRange::AsIs,
                    "unit_to_signed" => InputRange::UnitToSigned,
                    other => panic!("unknown input range {other}"),
                },
                value: c["value"].as_f64().unwrap(),
                per_layer: c["per_layer"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .map(|v| v.as_f64().unwrap())
                    .collect(),
                render: values(format!("{name}.render")),
                target: values(format!("{name}.target")),
                grad: values(format!("{name}.grad")),
                meta: c.clone(),
                name,
            }
        })
        .collect()
}

/// Runs one case and returns (value relative error, worst per-layer relative error, gradient error relative
/// to the largest gradient component).
fn compare(net: &Lpips, case: &Case) -> (f64, f64, f64) {
    let (h, w) = (case.height, case.width);
    let target = net.target(&case.target, h, w).unwrap();
    let loss = net.loss_and_grad(&case.render, h, w, &target).unwrap();
    let value_err = (f64::from(loss.value) - case.value).abs() / case.value.abs();
    let layer_err = loss
        .per_layer
        .iter()
        .zip(&case.per_layer)
        .map(|(a, b)| (f64::from(*a) - b).abs() / b.abs())
        .fold(0.0, f64::max);
    let grad_scale = case.grad.iter().fold(0.0f32, |m, g| m.max(g.abs()));
    let grad_err = loss
        .grad
        .iter()
        .zip(&case.grad)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max)
        / grad_scale;
    println!(
        "{}: value {} (torch {}), rel err {value_err:.2e}; per-layer rel err {layer_err:.2e}; \
         grad max err / max|grad| {grad_err:.2e}",
        case.name, loss.value, case.value
    );
    (value_err, layer_err, f64::from(grad_err))
}

fn assert_close(case: &Case, (value_err, layer_err, grad_err): (f64, f64, f64)) {
    assert!(
        value_err <= 1e-4,
        "{}: value rel err {value_err}",
        case.name
    );
    assert!(
        layer_err <= 1e-4,
        "{}: per-layer rel err {layer_err}",
        case.name
    );
    assert!(grad_err <= 1e-4, "{}: grad err {grad_err}", case.name);
}

#[test]
fn narrow_network_matches_the_lpips_package() {
    let loaded = Lpips::load(&fixtures().join("narrow")).unwrap();
    assert_eq!(loaded.widths(), [8, 12, 16, 20, 24]);
    assert_eq!(loaded.input_range(), InputRange::AsIs);
    let mut ran = 0;
    let mut net = Some(loaded);
    for case in cases().iter().filter(|c| c.meta["network"] == "narrow") {
        let current = net.take().unwrap().with_input_range(case.range);
        assert_close(case, compare(&current, case));
        net = Some(current);
        ran += 1;
    }
    assert_eq!(ran, 3);
}

#[test]
fn narrow_network_value_without_gradient_matches() {
    let net = Lpips::load(&fixtures().join("narrow")).unwrap();
    let all = cases();
    let case = all
        .iter()
        .find(|c| c.name == "narrow_37x45_as_is_signed_images")
        .unwrap();
    let (h, w) = (case.height, case.width);
    let distance = net.distance(&case.render, &case.target, h, w).unwrap();
    assert!((f64::from(distance) - case.value).abs() <= 1e-4 * case.value);
}

/// The same cases with the network on the GPU (lavapipe in CI), to the CPU's tolerance: the network keeps
/// f32 weights on a device whose products default to f16 ([`Lpips::on`]).
#[test]
fn narrow_network_on_the_gpu_matches_the_lpips_package() {
    use diffusion::device::{Device, GpuDevice};
    let Some(ctx) = gpu::testing::context_or_skip() else {
        return;
    };
    let device = Device::Gpu(GpuDevice::new(ctx));
    let mut ran = 0;
    for case in cases().iter().filter(|c| c.meta["network"] == "narrow") {
        let net = Lpips::load(&fixtures().join("narrow"))
            .unwrap()
            .with_input_range(case.range)
            .on(device.clone());
        assert!(matches!(net.device(), Device::Gpu(_)));
        assert_close(case, compare(&net, case));
        ran += 1;
    }
    assert_eq!(ran, 3);
}

/// The package's calibrated lin weights on a full-width VGG16 with generated weights, through the user's path:
/// tools/convert_lpips_weights.py turns the generated backbone and the lpips package's own `vgg.pth` into a
/// weights folder, which [`Lpips::load`] reads. Needs the Python environment next to the repository
/// (`../pyenv` with torch, safetensors and lpips); skips without it. Nothing is copied into the repository.
#[test]
fn real_lin_weights_through_the_converter_match_the_lpips_package() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let python = root.join("../pyenv/bin/python");
    let lin_pth = root.join("../pyenv/lib/python3.11/site-packages/lpips/weights/v0.1/vgg.pth");
    for needed in [&python, &lin_pth] {
        if !needed.is_file() {
            println!("SKIP: {} not found", needed.display());
            return;
        }
    }
    let all = cases();
    let case = all.iter().find(|c| c.name.starts_with("real_lin")).unwrap();
    let network = &case.meta["network"];
    let seed = network["synthetic_vgg16_seed"].as_u64().unwrap();
    let widths: Vec<usize> = network["widths"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_u64().unwrap() as usize)
        .collect();
    assert_eq!(widths, VGG16_WIDTHS);

    let tmp = tempfile::tempdir().unwrap();
    let backbone = tmp.path().join("vgg16-generated.safetensors");
    let (vgg, _) = synthetic_tensors(VGG16_WIDTHS, seed);
    candle_core::safetensors::save(&vgg, &backbone).unwrap();
    let out = tmp.path().join("lpips");
    let status = std::process::Command::new(&python)
        .arg(root.join("tools/convert_lpips_weights.py"))
        .arg("--vgg")
        .arg(&backbone)
        .arg("--lin")
        .arg(&lin_pth)
        .arg("--out")
        .arg(&out)
        .status()
        .unwrap();
    assert!(status.success(), "convert_lpips_weights.py failed");

    let net = Lpips::load(&out).unwrap().with_input_range(case.range);
    assert_eq!(net.widths(), VGG16_WIDTHS);
    assert_close(case, compare(&net, case));
}
