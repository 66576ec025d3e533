//! `cargo bench -p vcedit-bench --bench lift -- ARGS` = `vcedit bench lift ARGS` (see `bench::lift`).

fn main() {
    bench::main_for_cargo_bench("lift");
}
