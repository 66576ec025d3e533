//! LPIPS-VGG timings with the full-width VGG16 (generated weights): target features (one forward pass),
//! loss + gradient against cached target features, and both together.
//!
//! `cargo bench -p vcedit-edit --bench lpips [-- SIZE ...]` (default sizes 256 and 512).

use std::time::Instant;

use edit::lpips::{Lpips, VGG16_WIDTHS};

fn image(h: usize, w: usize, phase: f32) -> Vec<f32> {
    (0..h * w * 3)
        .map(|i| 0.5 + 0.4 * ((i as f32) * 0.0137 + phase).sin())
        .collect()
}

/// Best of `runs` wall-clock seconds.
fn best_of(runs: usize, mut f: impl FnMut()) -> f64 {
    (0..runs)
        .map(|_| {
            let t = Instant::now();
            f();
            t.elapsed().as_secs_f64()
        })
        .fold(f64::INFINITY, f64::min)
}

fn main() {
    let sizes: Vec<usize> = std::env::args()
        .skip(1)
        .filter_map(|a| a.parse().ok())
        .collect();
    let sizes = if sizes.is_empty() {
        vec![256, 512]
    } else {
        sizes
    };
    let net = Lpips::synthetic(VGG16_WIDTHS, 0);
    println!(
        "LPIPS-VGG16 (full width), {} rayon threads",
        rayon::current_num_threads()
    );
    for s in sizes {
        let (render, target_image) = (image(s, s, 0.0), image(s, s, 1.0));
        let target = net.target(&target_image, s, s).unwrap();
        let runs = if s <= 256 { 5 } else { 3 };
        let forward = best_of(runs, || {
            net.target(&render, s, s).unwrap();
        });
        let value = best_of(runs, || {
            net.value(&render, s, s, &target).unwrap();
        });
        let with_grad = best_of(runs, || {
            net.loss_and_grad(&render, s, s, &target).unwrap();
        });
        let uncached = best_of(runs, || {
            let t = net.target(&target_image, s, s).unwrap();
            net.loss_and_grad(&render, s, s, &t).unwrap();
        });
        println!(
            "{s}x{s}: forward (target features) {forward:.3} s | value vs cached target {value:.3} s | \
             value + gradient vs cached target {with_grad:.3} s | target + value + gradient {uncached:.3} s | \
             target features {:.0} MB",
            net.target_bytes(s, s) as f64 / 1e6
        );
    }
}
