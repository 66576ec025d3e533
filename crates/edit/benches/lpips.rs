//! LPIPS-VGG timings with the full-width VGG16 (generated weights): target features (one forward pass),
//! loss + gradient against cached target features, and both together.
//!
//! `cargo bench -p vcedit-edit --bench lpips [-- SIZE ...]` (default sizes 256 and 512).

use std::time::Instant;

use edit::eval::lpips::{Lpips, VGG16_WIDTHS};

fn image(h: usize, w: usize, phase: f32) -> Vec<f32> {
    (0..h * w * 3)
        .map(|i| 0.5 + 0.4 * ((i as f32) * 0.0137 + phase).sin())
        .collect()
}

/// CPU seconds (user + system) this process has used, from /proc/self/stat (Linux; 0 elsewhere).
fn cpu_seconds() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    // Fields after the parenthesised command name; utime and stime are the 12th and 13th of those.
    let rest = stat.rsplit(')').next().unwrap_or("");
    let fields: Vec<f64> = rest
        .split_whitespace()
        .skip(11)
        .take(2)
        .filter_map(|v| v.parse().ok())
        .collect();
    fields.iter().sum::<f64>() / 100.0
}

/// Best of `runs` (wall-clock seconds, CPU seconds). On a shared machine the CPU time shows what the work
/// costs when other processes inflate the wall time.
fn best_of(runs: usize, mut f: impl FnMut()) -> (f64, f64) {
    (0..runs)
        .map(|_| {
            let (t, c) = (Instant::now(), cpu_seconds());
            f();
            (t.elapsed().as_secs_f64(), cpu_seconds() - c)
        })
        .fold((f64::INFINITY, f64::INFINITY), |(w, c), (w2, c2)| {
            (w.min(w2), c.min(c2))
        })
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
        let show = |(wall, cpu): (f64, f64)| format!("{wall:.3} s (cpu {cpu:.2} s)");
        println!(
            "{s}x{s}: forward (target features) {} | value vs cached target {} | \
             value + gradient vs cached target {} | target + value + gradient {} | target features {:.0} MB",
            show(forward),
            show(value),
            show(with_grad),
            show(uncached),
            net.target_bytes(s, s) as f64 / 1e6
        );
    }
}
