//! `cargo bench -p vcedit-bench --bench lpips -- ARGS` = `vcedit bench lpips ARGS` (see `bench::lpips`).

fn main() {
    bench::main_for_cargo_bench("lpips");
}
