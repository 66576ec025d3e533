//! Writes a grid of random world samples (128x128 renders) and their captions.
//!
//! `cargo run --release -p vcedit-demo --example world_grid -- OUT.png [SEED] [COLS] [ROWS] [SIZE]`

use demo::world::dataset::{write_sample_grid, DatasetConfig};
use std::time::Instant;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let out = args.get(1).map_or("world_grid.png", |s| s.as_str());
    let num = |i: usize, d: u64| args.get(i).and_then(|s| s.parse().ok()).unwrap_or(d);
    let (seed, cols, rows, size) = (
        num(2, 0),
        num(3, 8) as usize,
        num(4, 4) as usize,
        num(5, 128) as u32,
    );
    let config = DatasetConfig {
        width: size,
        height: size,
        ..Default::default()
    };
    let start = Instant::now();
    match write_sample_grid(std::path::Path::new(out), &config, seed, cols, rows) {
        Ok(captions) => {
            let secs = start.elapsed().as_secs_f64();
            for (k, c) in captions.iter().enumerate() {
                println!("{k:3} {c}");
            }
            println!(
                "{} samples in {secs:.2} s ({:.1} ms each) -> {out}",
                captions.len(),
                1e3 * secs / captions.len() as f64
            );
        }
        Err(e) => {
            eprintln!("error: {e}");
            std::process::exit(1);
        }
    }
}
