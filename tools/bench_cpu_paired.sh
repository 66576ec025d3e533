#!/usr/bin/env bash
# Paired CPU timings of vcedit and PyTorch, f32 and bf16, in interleaved rounds on one machine: the SD 1.5 UNet
# (random weights, 64² latents, batches 1 and 6), the SD VAE and TAESD at SIZE², the CLIP text encoder (batches 1
# and 6). Each round runs, per network: vcedit bf16, PyTorch bf16, vcedit f32, PyTorch f32 (one warm call, one
# timed call each); the summary takes the best of the rounds. Needs a release build (`cargo build --release`)
# and a Python with torch, diffusers and transformers.
#
#   tools/bench_cpu_paired.sh [--rounds 3] [--threads 2] [--size 512] [--python PY] [--out FILE] [--only unet,codec,text]
#                             [--precisions bf16,f32]
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
repo="$here/.."
rounds=3 threads=2 size=512 python=python3 out=bench-cpu-paired.log only=unet,codec,text precisions=bf16,f32
while [ $# -gt 0 ]; do
  case "$1" in
    --rounds) rounds=$2; shift 2 ;;
    --threads) threads=$2; shift 2 ;;
    --size) size=$2; shift 2 ;;
    --python) python=$2; shift 2 ;;
    --out) out=$2; shift 2 ;;
    --only) only=$2; shift 2 ;;
    --precisions) precisions=$2; shift 2 ;;
    *) echo "bench_cpu_paired: unknown argument $1" >&2; exit 2 ;;
  esac
done
vcedit="$repo/target/release/vcedit"
[ -x "$vcedit" ] || { echo "bench_cpu_paired: no $vcedit (run cargo build --release)" >&2; exit 2; }
export RAYON_NUM_THREADS=$threads
: > "$out"
# Runs one command and appends its RESULT lines, tagged with the round and the precision, to the log.
run() {
  local round=$1 precision=$2; shift 2
  "$@" 2>/dev/null | grep '^RESULT ' | sed "s/^RESULT {/RESULT {\"round\":$round,\"precision\":\"$precision\",/" >> "$out"
}
for round in $(seq 1 "$rounds"); do
  echo "round $round of $rounds (load $(cut -d' ' -f1 /proc/loadavg))" >&2
  for precision in ${precisions//,/ }; do
    case ",$only," in *,unet,*)
      run "$round" "$precision" "$vcedit" bench unet --device cpu --precision "$precision" --batches 1,6 --runs 1 --skip-load
      run "$round" "$precision" "$python" "$here/bench_unet_torch.py" --batches 1,6 --runs 1 --threads "$threads" --dtypes "$precision" ;;
    esac
    case ",$only," in *,codec,*)
      run "$round" "$precision" "$vcedit" bench codec --device cpu --precision "$precision" --size "$size" --runs 1
      run "$round" "$precision" "$python" "$here/bench_vae.py" "$size" "$threads" --dtype "$precision" --runs 1 ;;
    esac
    case ",$only," in *,text,*)
      run "$round" "$precision" "$vcedit" bench text --device cpu --precision "$precision" --batches 1,6 --runs 3
      run "$round" "$precision" "$python" "$here/bench_text.py" "$threads" --dtype "$precision" --batches 1,6 --runs 3 ;;
    esac
  done
done
echo "load at the end: $(cut -d' ' -f1 /proc/loadavg)" >&2
"$python" - "$out" <<'PY'
import json, sys
best = {}
for line in open(sys.argv[1]):
    r = json.loads(line[len("RESULT "):])
    if r.get("what") not in ("forward", "encode", "decode"):
        continue
    impl = "PyTorch" if r.get("impl") == "torch" else "vcedit"
    net = {"unet": "UNet", "codec": "VAE" if r.get("kind") == "kl" else "TAESD", "text": "CLIP text"}[r.get("bench", "unet")]
    secs = r.get("seconds", r.get("best_s"))
    key = (net, r["what"], r.get("batch", 1), impl, r["precision"])
    best[key] = min(best.get(key, secs), secs)
rows = sorted({k[:3] for k in best})
print(f"{'network':<10} {'what':<8} {'batch':>5} {'vcedit bf16':>12} {'PyTorch bf16':>13} {'vcedit f32':>11} {'PyTorch f32':>12} {'bf16 ratio':>10}")
for net, what, batch in rows:
    cell = lambda impl, p: best.get((net, what, batch, impl, p))
    vals = [cell("vcedit", "bf16"), cell("PyTorch", "bf16"), cell("vcedit", "f32"), cell("PyTorch", "f32")]
    ratio = f"{vals[0] / vals[1]:.2f}" if vals[0] and vals[1] else "-"
    fmt = lambda v: f"{v:.3f} s" if v is not None else "-"
    print(f"{net:<10} {what:<8} {batch:>5} {fmt(vals[0]):>12} {fmt(vals[1]):>13} {fmt(vals[2]):>11} {fmt(vals[3]):>12} {ratio:>10}")
PY
