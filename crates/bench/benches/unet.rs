//! `cargo bench -p vcedit-bench --bench unet -- ARGS` = `vcedit bench unet ARGS` (see `bench::unet`).

fn main() {
    bench::main_for_cargo_bench("unet");
}
