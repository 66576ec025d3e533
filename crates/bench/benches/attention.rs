//! `cargo bench -p vcedit-bench --bench attention -- ARGS` = `vcedit bench attention ARGS` (see
//! `bench::attention`).

fn main() {
    bench::main_for_cargo_bench("attention");
}
