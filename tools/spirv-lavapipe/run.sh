#!/usr/bin/env bash
# The workspace's GPU tests (or `vcedit bench …`) on the SPIR-V compiler path on Mesa 25's lavapipe, built
# against cubecl-spirv 0.11.3 with implicit-shared-memory.patch applied (see README.md).
#
#   tools/spirv-lavapipe/run.sh test [TEST ARGS…]    cargo test --workspace --release --lib [ARGS…]
#   tools/spirv-lavapipe/run.sh vcedit ARGS…         the patched vcedit binary, e.g. `bench unet --small …`
#
# Builds in a target folder of its own (CARGO_TARGET_DIR, else the cache folder below: the patched crate
# rebuilds everything above it) and leaves Cargo.lock as it was. Needs Mesa 25 lavapipe unpacked where
# .ci/run puts it (VCEDIT_MESA25_DIR).
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/../.." && pwd)
HERE="$ROOT/tools/spirv-lavapipe"
CACHE="${XDG_CACHE_HOME:-$HOME/.cache}/vcedit-ci"
WORK="$CACHE/spirv-lavapipe"
MESA25="${VCEDIT_MESA25_DIR:-$CACHE/mesa25}"
[ -f "$MESA25/lvp_icd.json" ] || { echo "no Mesa 25 lavapipe in $MESA25 (.ci/run unpacks it there)" >&2; exit 1; }
mode="${1:-test}"; shift || true

# The registry's copy of the crate the workspace locks, patched.
src=$(cargo metadata --format-version 1 --manifest-path "$ROOT/Cargo.toml" | python3 -c '
import json, os, sys
print(next(os.path.dirname(p["manifest_path"]) for p in json.load(sys.stdin)["packages"] if p["name"] == "cubecl-spirv"))')
rm -rf "$WORK/cubecl-spirv"
mkdir -p "$WORK"
cp -r "$src" "$WORK/cubecl-spirv"
patch -s -d "$WORK/cubecl-spirv" -p1 < "$HERE/implicit-shared-memory.patch"

# `--config patch…` rewrites Cargo.lock's entry for the crate: put it back afterwards.
cp "$ROOT/Cargo.lock" "$WORK/Cargo.lock.orig"
trap 'cp "$WORK/Cargo.lock.orig" "$ROOT/Cargo.lock"' EXIT
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$WORK/target}"
cargo_patched() { cargo --config "patch.crates-io.cubecl-spirv.path=\"$WORK/cubecl-spirv\"" "$@"; }

export VK_ICD_FILENAMES="$MESA25/lvp_icd.json"
export LD_LIBRARY_PATH="$MESA25/root/usr/lib/x86_64-linux-gnu${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
export VCEDIT_GPU_COMPILER="${VCEDIT_GPU_COMPILER:-spirv}"
cd "$ROOT"
case "$mode" in
  test) cargo_patched test --workspace --release --lib "$@" ;;
  vcedit)
    cargo_patched build --release -p vcedit --quiet
    "$CARGO_TARGET_DIR/release/vcedit" "$@" ;;
  *) echo "usage: $0 test [ARGS…] | vcedit ARGS…" >&2; exit 2 ;;
esac
