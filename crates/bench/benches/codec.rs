//! `cargo bench -p vcedit-bench --bench codec -- ARGS` = `vcedit bench codec ARGS` (see `bench::codec`).

fn main() {
    bench::main_for_cargo_bench("codec");
}
