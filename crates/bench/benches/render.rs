//! `cargo bench -p vcedit-bench --bench render -- ARGS` = `vcedit bench render ARGS` (see `bench::render`).

fn main() {
    bench::main_for_cargo_bench("render");
}
