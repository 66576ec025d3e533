//! `cargo bench -p vcedit-bench --bench matmul -- ARGS` = `vcedit bench matmul ARGS` (see `bench::matmul`).

fn main() {
    bench::main_for_cargo_bench("matmul");
}
