//! `cargo bench -p vcedit-bench --bench text -- ARGS` = `vcedit bench text ARGS` (see `bench::text`).

fn main() {
    bench::main_for_cargo_bench("text");
}
