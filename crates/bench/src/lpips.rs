//! LPIPS-VGG16 with the full-width network (generated weights, `Lpips::synthetic`): the target features
//! (one forward pass), the value against cached target features, and value + gradient (what a fitting
//! step with LPIPS costs), on the CPU or a GPU.
//!
//! `vcedit bench lpips [--sizes 256,512] [--runs 3] [--device cpu|gpu|auto]`.

use diffusion::lpips::{Lpips, VGG16_WIDTHS};

use crate::{arg_list, arg_parsed, network_device, networks_on, report, Result, Timed};

/// A smooth test image, different per `phase`.
fn image(h: usize, w: usize, phase: f32) -> Vec<f32> {
    (0..h * w * 3)
        .map(|i| 0.5 + 0.4 * ((i as f32) * 0.0137 + phase).sin())
        .collect()
}

pub fn main(args: &[String]) -> Result<()> {
    let sizes: Vec<usize> = arg_list(args, "--sizes", "256,512")?;
    let runs: usize = arg_parsed(args, "--runs", 3)?;
    let gpu = network_device(args, "cpu")?;
    // The network keeps f32 weights on a GPU whatever `--precision` says (`Lpips::on`).
    let net = Lpips::synthetic(VGG16_WIDTHS, 0).on(diffusion::device::Device::from(gpu));
    let on = networks_on(net.device().gpu());
    eprintln!("lpips bench: VGG16 full width, generated weights, {on}");
    for s in sizes {
        let (render, target_image) = (image(s, s, 0.0), image(s, s, 1.0));
        let target = net.target(&target_image, s, s)?;
        let measured = [
            (
                "target features",
                Timed::measure(runs, || Ok(net.target(&render, s, s)?))?,
            ),
            (
                "value",
                Timed::measure(runs, || Ok(net.value(&render, s, s, &target)?))?,
            ),
            (
                "value + gradient",
                Timed::measure(runs, || Ok(net.loss_and_grad(&render, s, s, &target)?))?,
            ),
        ];
        for (what, timed) in measured {
            eprintln!(
                "  {s}x{s} {what}: best {:.3} s (first call {:.3} s)",
                timed.best().as_secs_f64(),
                timed.first.as_secs_f64()
            );
            report(timed.json(serde_json::json!({
                "bench": "lpips", "what": what, "size": s, "device": on,
                "target_mb": net.target_bytes(s, s) as f64 / 1e6,
            })));
        }
    }
    Ok(())
}
