#!/usr/bin/env bash
# The hardware check: every measurement that decides vcedit's GPU direction, in one call on a borrowed GPU
# machine (no Rust, no network), from what tools/gpu-check/prepare.sh packed into .gpu-check/.
#
#   tools/gpu-check/run.sh                  on the GPU machine (see README.md for the exact call)
#   tools/gpu-check/run.sh --local          the same steps at small sizes here (Mesa lavapipe, CPU PyTorch
#                                           when installed); CI runs this
#   options: --budget SECONDS (default 480, 600 with --local: steps stop being started when it runs out)
#            --only STEP,STEP  (rerun some steps, e.g. after one failed)
#            --skip STEP,STEP
#            --runtimes cuda,wgpu  (the GPU runtimes compared side by side; default both there, wgpu here)
#            --full            (also the A/B steps of one runtime: routines, tilings, attention and
#                               convolution paths, kernel and host profiles, fit variants, the demo; they
#                               always run with --local)
#
# The core steps run once per runtime: `NAME-cuda` on CUDA (where it opened: `adapter-cuda`), `NAME` on
# wgpu (Vulkan); every other step on wgpu. `VCEDIT_GPU_RUNTIME` pins each process to its runtime.
#
# Every step runs under its own `timeout`, so a hang or crash costs that step alone. After each step the
# results so far are written to $OUT/gpu-check.json and $OUT/gpu-check.md (the table for
# docs/gpu-results.md), the full output to $OUT/gpu-check.log: a call cut short still returns what it
# measured. $OUT is the device tool's output folder; elsewhere it defaults to ./gpu-check-out.
set -uo pipefail
HERE=$(cd "$(dirname "$0")" && pwd)
ROOT=$(cd "$HERE/../.." && pwd)
cd "$ROOT"
PACK="$ROOT/.gpu-check"

MODE=device
BUDGET=""
ONLY=""
SKIP=""
RUNTIMES=""
FULL=0
while [ $# -gt 0 ]; do
  case "$1" in
    --local) MODE=local ;;
    --budget) BUDGET="$2"; shift ;;
    --only) ONLY="$2"; shift ;;
    --skip) SKIP="$2"; shift ;;
    --runtimes) RUNTIMES="${2//,/ }"; shift ;;
    --full) FULL=1 ;;
    *) echo "run.sh: unknown option $1 (--local, --budget S, --only A,B, --skip A,B, --runtimes cuda,wgpu, --full)" >&2; exit 2 ;;
  esac
  shift
done

# The budget: what one device call affords (see README.md). Locally every step must pass, so the budget
# only bounds a hang: the steps take ~6 min on 2 idle cores, and a 420-s budget failed CI's check on a
# loaded machine (2026-11-27: the last step, the demo, was left 64 s of its 120 and timed out).
[ -z "$BUDGET" ] && { [ "$MODE" = device ] && BUDGET=480 || BUDGET=600; }
# CUDA is compared on the card; here there is none (lavapipe is a Vulkan device).
[ -z "$RUNTIMES" ] && { [ "$MODE" = device ] && RUNTIMES="cuda wgpu" || RUNTIMES="wgpu"; }
# Every step not named for CUDA runs on wgpu, as before CUDA existed (`auto` would take CUDA first).
export VCEDIT_GPU_RUNTIME=wgpu
CUDA_OK=0
# full: whether the A/B steps run (always locally, so that CI keeps them working).
full() { [ "$MODE" = local ] || [ "$FULL" = 1 ]; }
OUT="${OUT:-$ROOT/gpu-check-out}"
mkdir -p "$OUT"
WORK=$(mktemp -d /tmp/gpu-check.XXXXXX)
# vcedit's caches (cubecl's compiled SPIR-V kernels and autotune results) start empty in every check: the
# first step to compile a kernel pays for it, later steps (the editing slice's first iteration) find it.
export XDG_CACHE_HOME="$WORK/cache"
LOG="$OUT/gpu-check.log"
: > "$LOG"
: > "$WORK/steps.jsonl"
START=$(date +%s)
NO_GPU=0
export PYTHONUNBUFFERED=1 RUST_BACKTRACE=0 XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-/tmp}"

say() { echo "$*" | tee -a "$LOG"; }
elapsed() { echo $(( $(date +%s) - START )); }
summarize() {
  python3 "$HERE/summarize.py" --work "$WORK" --out "$OUT" --mode "$MODE" --pack "$PACK" >>"$LOG" 2>&1 ||
    say "summarize.py failed (see the log)"
}

# step NAME TIMEOUT COMMAND...: runs COMMAND under `timeout`, records rc and seconds, keeps its output.
step() {
  local name=$1 limit=$2
  shift 2
  if [ -n "$ONLY" ] && [[ ",$ONLY," != *",$name,"* ]]; then return 0; fi
  if [[ ",$SKIP," == *",$name,"* ]]; then return 0; fi
  if [ "$NO_GPU" = 1 ] && { [ "$1" = "$V" ] || [ "$1" = env ]; } && [ "$name" != splat-cpu ] &&
     [[ "$name" != *-cuda ]]; then
    say "== $name: not run (vcedit opened no hardware GPU; see the adapter step)"
    echo "{\"step\":\"$name\",\"status\":\"no-gpu\",\"timeout\":$limit}" >> "$WORK/steps.jsonl"
    summarize
    return 0
  fi
  local left=$(( BUDGET - $(elapsed) ))
  if [ "$left" -lt 15 ]; then
    say "== $name: not started (budget of ${BUDGET}s used up)"
    echo "{\"step\":\"$name\",\"status\":\"budget\",\"timeout\":$limit}" >> "$WORK/steps.jsonl"
    summarize
    return 0
  fi
  [ "$limit" -gt "$left" ] && limit=$left
  say "== $name (timeout ${limit}s, at $(elapsed)s): $*"
  local t0 rc status
  t0=$(date +%s.%N)
  timeout -k 5 "$limit" "$@" >"$WORK/$name.out" 2>"$WORK/$name.err" </dev/null
  rc=$?
  local secs
  secs=$(python3 -c "import time,sys; print(round(time.time()-float(sys.argv[1]),2))" "$t0")
  case $rc in
    0) status=ok ;;
    124|137) status=timeout ;;
    *) status=failed ;;
  esac
  { echo "-- stdout"; cat "$WORK/$name.out"; echo "-- stderr"; tail -c 20000 "$WORK/$name.err"; } >> "$LOG"
  echo "{\"step\":\"$name\",\"status\":\"$status\",\"rc\":$rc,\"seconds\":$secs,\"timeout\":$limit}" >> "$WORK/steps.jsonl"
  if [ "$status" = ok ]; then
    say "   $name: ok in ${secs}s"
  else
    say "   $name: $status (rc $rc) after ${secs}s: $(grep -v '^\s*$' "$WORK/$name.err" | tail -n 2 | tr '\n' ' ' | cut -c1-300)"
  fi
  summarize
}

# on_runtimes NAME TIMEOUT COMMAND...: the step on each runtime of $RUNTIMES, CUDA first: NAME-cuda (where
# `adapter-cuda` opened CUDA), then NAME on wgpu.
on_runtimes() {
  local name=$1 limit=$2 rt
  shift 2
  for rt in $RUNTIMES; do
    case $rt in
      cuda) [ "$CUDA_OK" = 1 ] && step "$name-cuda" "$limit" env VCEDIT_GPU_RUNTIME=cuda "$@" ;;
      wgpu) step "$name" "$limit" "$@" ;;
    esac
  done
  return 0
}

# ---- unpacking: the binary, the inputs, and on the GPU machine the Vulkan loader and the wheels
[ -f "$PACK/bin/vcedit.xz" ] || { say "run.sh: $PACK/bin/vcedit.xz is missing: run tools/gpu-check/prepare.sh first"; exit 1; }
say "gpu-check ($MODE) in $WORK, budget ${BUDGET}s, output $OUT"
unxz() { xz -dc "$1" 2>/dev/null || python3 -c "import lzma,sys,shutil; shutil.copyfileobj(lzma.open(sys.argv[1]), sys.stdout.buffer)" "$1"; }
unxz "$PACK/bin/vcedit.xz" > "$WORK/vcedit" && chmod +x "$WORK/vcedit" || { say "cannot unpack vcedit"; exit 1; }
unxz "$PACK/inputs.tar.xz" | tar -C "$WORK" -xf - || { say "cannot unpack the inputs"; exit 1; }
V="$WORK/vcedit"
IN="$WORK/inputs"
SYSLIB="$WORK/sys/usr/lib/x86_64-linux-gnu"

if [ "$MODE" = device ]; then
  # The loader goes onto / (the device tool's instructions); vulkaninfo and its X/Wayland libraries into a
  # private folder, so the image's own libraries are never replaced.
  ON_ROOT="libvulkan1_ libegl1_ libglvnd0_ libopengl0_ libgl1_ libglx0_ libgles2_"
  mkdir -p "$WORK/sys"
  for f in "$PACK"/debs/*.deb; do
    base=$(basename "$f"); dest="$WORK/sys"
    for p in $ON_ROOT; do [[ "$base" == "$p"* ]] && dest=/; done
    dpkg -x "$f" "$dest" 2>>"$LOG"
  done
  ldconfig 2>>"$LOG"
  # NVIDIA's GLX/Vulkan library links the X client libraries; where the image lacks them, the private copies.
  ldconfig -p | grep -q 'libX11.so.6 ' || export LD_LIBRARY_PATH="$SYSLIB${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
  # The NVIDIA ICD and EGL vendor files live under /usr/local/nvidia there; name them when the loader's
  # default search does not find them.
  if [ -z "${VK_DRIVER_FILES:-}" ] && [ -f /usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json ] &&
     ! ls /usr/share/vulkan/icd.d/nvidia_icd*.json /etc/vulkan/icd.d/nvidia_icd*.json >/dev/null 2>&1; then
    export VK_DRIVER_FILES=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
    export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
  fi
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$WORK/site" \
    "$PACK"/wheels/*.whl >>"$LOG" 2>&1 || say "pip install of the wheels failed (the PyTorch steps will fail)"
  export PYTHONPATH="$WORK/site${PYTHONPATH:+:$PYTHONPATH}"
  MODEL="$WORK/sd15"; LAT=64; IMG=512; RUNS=3
  REQUIRE=--require-hardware
  # CUDA's run-time compiler, NVRTC, from the machine: a CUDA toolkit's, else PyTorch's CUDA wheels'
  # (libnvrtc.so.13 in site-packages/nvidia/cu13/lib with PyTorch's cu130 builds). vcedit loads it by name,
  # so its folder goes onto LD_LIBRARY_PATH.
  if [[ " $RUNTIMES " == *" cuda "* ]]; then
    NVRTC=$(python3 - <<'PY' 2>/dev/null
import glob, os, site, sys
roots = ["/usr/local/cuda/lib64", "/usr/local/cuda/lib"] + [p for p in sys.path if p.endswith("-packages")]
try:
    roots += site.getsitepackages()
except AttributeError:
    pass
for name in ("libnvrtc.so.13", "libnvrtc.so.12"):
    for root in roots:
        hits = sorted(glob.glob(os.path.join(root, "**", name + "*"), recursive=True))
        hits = [h for h in hits if "builtins" not in h and ".alt." not in h]
        if hits:
            print(hits[0])
            sys.exit()
PY
)
    if [ -n "$NVRTC" ]; then
      nvrtc_dir="$WORK/nvrtc"
      mkdir -p "$nvrtc_dir"
      # The soname's link (a wheel may carry only libnvrtc.so.13.0.88), beside the folder's own builtins.
      major=$(basename "$NVRTC" | sed -E 's/^libnvrtc\.so\.([0-9]+).*/\1/')
      ln -sf "$NVRTC" "$nvrtc_dir/libnvrtc.so.$major"
      export LD_LIBRARY_PATH="$nvrtc_dir:$(dirname "$NVRTC")${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
      say "NVRTC: $NVRTC"
    else
      say "NVRTC: not found on this machine (the CUDA steps will say so)"
    fi
    # The headers NVRTC compiles vcedit's kernels against: the machine's toolkit where it has one, else the
    # CUDA 13 headers prepare.sh packed (NVIDIA's nvidia-cuda-runtime and nvidia-cuda-cccl wheels).
    if [ -z "${CUDA_PATH:-}" ] && [ ! -f /usr/local/cuda/include/cuda_fp16.h ] && [ -f "$PACK/cuda-headers.tar.xz" ]; then
      unxz "$PACK/cuda-headers.tar.xz" | tar -C "$WORK" -xf - && export CUDA_PATH="$WORK/cuda"
    fi
    say "CUDA headers: ${CUDA_PATH:-/usr/local/cuda, the machine toolkit}"
  fi
else
  # lavapipe is a software adapter: allowed here, and only here.
  export VCEDIT_ALLOW_SOFTWARE_GPU=1
  # The tiny diffusers pipeline of the conformance fixtures: every step runs, in a couple of minutes.
  MODEL="$ROOT/fixtures/models/tiny-lcm"; LAT=8; IMG=64; RUNS=1
  REQUIRE=""
fi
cp "$PACK/build.json" "$WORK/build.json" 2>/dev/null
# Asked once: importing torch and diffusers takes seconds.
if python3 -c "import torch, diffusers" >/dev/null 2>&1; then TORCH=1; else TORCH=0; fi
have_torch() { [ "$TORCH" = 1 ]; }
TB="$HERE/torch_bench.py"

# ---- the machine
step machine 30 bash -c '
  nvidia-smi || echo "nvidia-smi: not available"
  nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.max.sm,clocks.max.mem,power.limit --format=csv || true
  echo "-- vulkaninfo --summary"
  vi=$(command -v vulkaninfo || echo "'"$WORK"'/sys/usr/bin/vulkaninfo")
  LD_LIBRARY_PATH="'"$SYSLIB"'${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}" "$vi" --summary 2>&1 || echo "vulkaninfo: not available"
  echo "-- cpu"; nproc; grep -m1 "model name" /proc/cpuinfo; free -g | head -2'
NO_GPU=0
step adapter 60 "$V" bench device --device gpu $REQUIRE
# A measurement of anything but the card is worse than none: without a hardware adapter the vcedit GPU
# steps are not run, and the log says why.
# Where the default (SPIR-V) path cannot open the card, the WGSL path may: the rest of the check then runs on it.
if [ "$MODE" = device ] && grep -q '"step":"adapter","status":"failed\|"step":"adapter","status":"timeout' "$WORK/steps.jsonl"; then
  step adapter-wgsl 60 env VCEDIT_GPU_COMPILER=wgsl "$V" bench device --device gpu $REQUIRE
  if grep -q '"step":"adapter-wgsl","status":"ok' "$WORK/steps.jsonl"; then
    say "!! the default compiler path failed to open the card; the check goes on with VCEDIT_GPU_COMPILER=wgsl"
    export VCEDIT_GPU_COMPILER=wgsl
  fi
fi
if [ "$MODE" = device ] && grep -q '"step":"adapter","status":"failed\|"step":"adapter","status":"timeout' "$WORK/steps.jsonl" &&
   ! grep -q '"step":"adapter-wgsl","status":"ok' "$WORK/steps.jsonl"; then
  NO_GPU=1
  say "!! vcedit opened no hardware GPU: the vcedit GPU steps are skipped. Adapter step output:"
  tail -n 5 "$WORK/adapter.err" | tee -a "$LOG"
fi
# The CUDA runtime: the same kernels through NVRTC. `adapter-cuda` opens it (its failure is one line saying
# what is missing).
if [[ " $RUNTIMES " == *" cuda "* ]]; then
  step adapter-cuda 60 env VCEDIT_GPU_RUNTIME=cuda "$V" bench device --device gpu $REQUIRE
  grep -q '"step":"adapter-cuda","status":"ok' "$WORK/steps.jsonl" && CUDA_OK=1
fi
# The kernels against the CPU on each runtime (renderer forward and backward, lifting, LPIPS, and the tiny
# pipeline's text encoder, codec and UNet with f32 weights): the first numbers of a runtime come with proof
# that it computes what the CPU does.
on_runtimes check 150 "$V" bench check --device gpu --fixtures "$ROOT/fixtures"
# What the host costs around the kernels: launches, waited-for reads, fresh buffers, the fits' radix sort.
on_runtimes overhead 60 "$V" bench device --device gpu --overhead $REQUIRE
if have_torch; then
  step torch-info 60 python3 "$TB" info
fi

# ---- weights: SD 1.5's configs with random weights, written once as a diffusers folder, so that vcedit
# and PyTorch read the same weights (made here with PyTorch: shipping them would not fit the carry limit)
if [ "$MODE" = device ]; then
  step weights 150 python3 "$HERE/../make_random_sd15.py" --out "$MODEL" --vocab "$IN/clip-bpe" --fp16 --device cuda
fi

# ---- matrix products: SD 1.5's 4096x320x1280 (the first level's feed-forward at 512²)
if [ "$MODE" = device ]; then SHAPES=4096x320x320,4096x320x1280; REPEAT=20; else SHAPES=512x64x128; REPEAT=3; fi
on_runtimes matmul 60 "$V" bench matmul --precisions f32,f16 --shapes "$SHAPES" --repeat "$REPEAT" --runs 3
# The same products on the WGSL compiler (no cooperative matrices): the A/B for the SPIR-V path.
full && step matmul-wgsl 60 env VCEDIT_GPU_COMPILER=wgsl "$V" bench matmul --precisions f16 --shapes "$SHAPES" --repeat "$REPEAT" --runs 3
if have_torch; then step matmul-torch 60 python3 "$TB" matmul --shapes "$SHAPES" --repeat "$REPEAT"; fi
# The f16 weight product on each of the library's tensor-core routines: which one a card should use.
if [ "$MODE" = device ]; then ROUTINES=all; else ROUTINES=simple_cyclic_cmma,double_cyclic_cmma; fi
# On CUDA always (its routines are the ones Vulkan lacks: manual mma, double buffering, TMA).
[ "$CUDA_OK" = 1 ] && step matmul-routines-cuda 150 env VCEDIT_GPU_RUNTIME=cuda "$V" bench matmul --precisions f16 --shapes "$SHAPES" --routines "$ROUTINES" --repeat "$REPEAT" --runs 3
full && step matmul-routines 150 "$V" bench matmul --precisions f16 --shapes "$SHAPES" --routines "$ROUTINES" --repeat "$REPEAT" --runs 3
# The default routine on a grid of tilings (planes per cube, stage depth, rows per plane, buffering):
# every routine ran at 5-15 TFLOP/s on an H200 where cuBLAS reaches 155, so the tiling is the suspect.
# Shapes: the feed-forward product of one image and of one InfEdit step's batch of six (the UNet folds
# the batch into the rows).
if [ "$MODE" = device ]; then TILINGS=grid; TSHAPES=4096x320x1280,24576x320x1280; else TILINGS="default;planes=4,k=2"; TSHAPES=512x64x128; fi
full && step matmul-tilings 200 "$V" bench matmul --precisions f16 --shapes "$TSHAPES" --tilings "$TILINGS" --repeat "$REPEAT" --runs 2

# ---- attention at SD 1.5's shapes (one view's six branches × 8 heads): our flash kernel, products around a
# softmax (the default for heads wider than 8 on tensor cores) and the library's flash attention (cubek's
# cooperative-matrix tiles on tensor cores, else its unit routine); PyTorch SDPA. Locally 8-wide heads:
# lavapipe compiles the library's kernel for 40-wide heads for minutes.
if [ "$MODE" = device ]; then ASHAPES=48x4096x4096x40,48x1024x1024x80,48x4096x77x40; AREPEAT=5; else ASHAPES=8x256x256x8,8x256x77x8; AREPEAT=1; fi
on_runtimes attention 90 "$V" bench attention --shapes "$ASHAPES" --repeat "$AREPEAT" --runs 3
if have_torch; then step attention-torch 60 python3 "$TB" attention --shapes "$ASHAPES" --repeat "$AREPEAT"; fi

# ---- the UNet, batch 1 and 6 (one InfEdit step), plain and with the InfEdit-shaped hook; PyTorch fp16 SDPA
# `--check`: batch 1 once more on the CPU, so the table says what the GPU path's rounding costs end to end.
on_runtimes unet 180 "$V" bench unet --model "$MODEL" --device gpu --size "$LAT" --batches 1,6 --hooks none,device --runs "$RUNS" --check
# Where the UNet's GPU time goes: cubecl's per-kernel profile of batch 6 (it waits for every kernel, so
# its total is kernel time, and the gap to the `unet` row is what launching and waiting cost), summed by
# kernel over one warm forward (tools/gpu-check/kernel_profile.py).
[ "$MODE" = device ] && full && step unet-profile 90 env CUBECL_DEBUG_LOG="$WORK/unet.prof" CUBECL_DEBUG_OPTION=profile \
  bash -c '"$1" bench unet --model "$2" --device gpu --size "$3" --batches 6 --hooks none --runs 2 >/dev/null &&
    unset CUBECL_DEBUG_LOG && python3 "$4" "$5" --segments 3 --label "UNet forward, batch 6"' \
  _ "$V" "$MODEL" "$LAT" "$HERE/kernel_profile.py" "$WORK/unet.prof"
# The same UNet in a second process with 256 kernels per command submission instead of cubecl's 32 (is a
# forward bound by submissions? batch 1 costs a third of batch 6), and its first call says what the SPIR-V
# kernels the `unet` step persisted save in a new process.
[ "$MODE" = device ] && full && step unet-tasks 120 env CUBECL_WGPU_MAX_TASKS=256 "$V" bench unet --model "$MODEL" --device gpu --size "$LAT" --batches 1,6 --hooks none --runs "$RUNS"
# The whole forward with the flash kernel for every head (the default before products): the A/B for the
# attention path.
[ "$MODE" = device ] && full && step unet-flash 120 env VCEDIT_GPU_ATTENTION=flash "$V" bench unet --model "$MODEL" --device gpu --size "$LAT" --batches 6 --hooks none --runs "$RUNS"
# ... and with the library's flash attention for every head (the default on GPUs without tensor cores).
[ "$MODE" = device ] && full && step unet-library 120 env VCEDIT_GPU_ATTENTION=library "$V" bench unet --model "$MODEL" --device gpu --size "$LAT" --batches 6 --hooks none --runs "$RUNS"
# ... and with every convolution that is not pointwise on one path, against the default that times both per
# problem (the `unet` step's `conv_path` says how many took the direct kernel): im2col, whose product runs
# on tensor cores, and the convolution library's direct kernel (on lavapipe faster on some shapes and much
# slower on others).
[ "$MODE" = device ] && full && step unet-im2col 120 env VCEDIT_GPU_CONV=im2col "$V" bench unet --model "$MODEL" --device gpu --size "$LAT" --batches 6 --hooks none --runs "$RUNS"
[ "$MODE" = device ] && full && step unet-direct 120 env VCEDIT_GPU_CONV=direct "$V" bench unet --model "$MODEL" --device gpu --size "$LAT" --batches 6 --hooks none --runs "$RUNS"
# The whole forward on the tensor-core routine that was fastest at 4096x320x1280 in `matmul-routines`
# (the default included, as the A/B baseline of the same process kind): does the gain carry to the network?
BEST_ROUTINE=$(python3 - "$WORK/matmul-routines.out" <<'PY' 2>/dev/null
import json, sys
best = None
for line in open(sys.argv[1], errors="replace"):
    if line.startswith("RESULT "):
        r = json.loads(line[7:])
        if r.get("n") == 1280 and r.get("route") == r.get("routine") and r.get("tflops"):
            if best is None or r["tflops"] > best["tflops"]:
                best = r
print(best["routine"] if best else "")
PY
)
if [ "$MODE" = device ] && full && [ -n "$BEST_ROUTINE" ]; then
  say "   fastest tensor-core routine at 4096x320x1280: $BEST_ROUTINE"
  # summarize.py labels the step's rows with it.
  echo "$BEST_ROUTINE" > "$WORK/unet-routine.name"
  step unet-routine 120 env VCEDIT_GPU_MATMUL_ROUTINE="$BEST_ROUTINE" "$V" bench unet --model "$MODEL" --device gpu --size "$LAT" --batches 1,6 --hooks none --runs "$RUNS"
fi
# The whole forward on the tiling of `matmul-tilings` whose products took the least time in all (a tiling
# counts only where it ran on tensor cores for every shape; every product of the default routine takes it
# where the library's inference accepts it for the shape).
BEST_TILING=$(python3 - "$WORK/matmul-tilings.out" <<'PY' 2>/dev/null
import json, sys
runs = {}
for line in open(sys.argv[1], errors="replace"):
    if line.startswith("RESULT "):
        r = json.loads(line[7:])
        if r.get("what") != "linear" or not r.get("tiling"):
            continue
        ran = r.get("route") == r.get("routine") and (r.get("tiled") or r.get("tiling") == "default")
        runs.setdefault(r["tiling"], []).append(r["ms"] if ran and r.get("ms") else None)
shapes = max((len(v) for v in runs.values()), default=0)
total = {t: sum(v) for t, v in runs.items() if len(v) == shapes and None not in v}
best = min(total, key=total.get) if total else ""
print(best if best != "default" else "")
PY
)
if [ "$MODE" = device ] && full && [ -n "$BEST_TILING" ]; then
  say "   fastest tiling of matmul-tilings: $BEST_TILING"
  echo "$BEST_TILING" > "$WORK/unet-tiling.name"
  step unet-tiling 120 env VCEDIT_GPU_MATMUL_TILING="$BEST_TILING" "$V" bench unet --model "$MODEL" --device gpu --size "$LAT" --batches 1,6 --hooks none --runs "$RUNS" --check
fi
full && step unet-wgsl 120 env VCEDIT_GPU_COMPILER=wgsl "$V" bench unet --model "$MODEL" --device gpu --size "$LAT" --batches 6 --hooks none --runs "$RUNS"
if have_torch; then
  step unet-torch 90 python3 "$TB" unet --model "$MODEL" --size "$LAT" --batches 1,6 --dtype f16 --runs 5
  full && step unet-torch-f32 60 python3 "$TB" unet --model "$MODEL" --size "$LAT" --batches 6 --dtype f32 --runs 3
fi

# ---- splatting: forward, backward, one fit step; the GPU at 125k/512² and 1M/1080p, the CPU at 125k/512²
if [ "$MODE" = device ]; then
  on_runtimes splat 150 "$V" bench render gpu n=125k,1m size=512,1080p device=gpu runs=5
  full && step splat-cpu 60 "$V" bench render gpu n=125k size=512 device=cpu runs=3
else
  on_runtimes splat 120 "$V" bench render gpu n=10k size=128 device=gpu runs=1 sh=2
  step splat-cpu 60 "$V" bench render gpu n=10k size=128 device=cpu runs=1 sh=2
fi

# ---- the codec (AutoencoderKL) at 512², the text encoder
on_runtimes codec 120 "$V" bench codec --model "$MODEL" --device gpu --size "$IMG" --runs 2
if have_torch; then step codec-torch 60 python3 "$TB" codec --model "$MODEL" --size "$IMG" --dtype f16; fi
on_runtimes text 60 "$V" bench text --model "$MODEL" --device gpu --batches 1,6
if have_torch; then step text-torch 60 python3 "$TB" text --model "$MODEL" --batches 1,6 --dtype f16; fi

# ---- LPIPS-VGG16 (the fits' perceptual loss; generated full-width weights): value + input gradient
if [ "$MODE" = device ]; then LPIPS_SIZE=512 LPIPS_RUNS=5; else LPIPS_SIZE=64 LPIPS_RUNS=1; fi
on_runtimes lpips 90 "$V" bench lpips --device gpu --sizes "$LPIPS_SIZE" --runs "$LPIPS_RUNS"
full && step lpips-cpu 90 "$V" bench lpips --device cpu --sizes "$LPIPS_SIZE" --runs 1

# ---- CCM's lifting round (one attention layer: 16² maps, 144 channels, 8 views at 512², 31k Gaussians),
# through the device seam and as it ran before (host resampling, full-resolution maps over the bus)
if [ "$MODE" = device ]; then LIFT=(--views 8 --size 512 --channels 144 --runs 3); else LIFT=(--views 2 --size 64 --channels 8 --gaussians 3000 --runs 1); fi
on_runtimes lift 90 "$V" bench lift --device gpu "${LIFT[@]}"
# the A/B of the grid lifting and sparse render-back: the maps upsampled on the device and lifted per pixel,
# every pixel rendered back, as before 2026-11-28
full && step lift-pixels 90 env VCEDIT_GPU_LIFT=pixels VCEDIT_GPU_SPARSE_BACK=off "$V" bench lift --device gpu "${LIFT[@]}"
full && step lift-cpu 60 "$V" bench lift --device cpu "${LIFT[@]}"

# ---- an editing slice at paper settings (SD 1.5 size, 512²): 8 views x 2 steps x 2 iterations, CCM, ECM
# and the blend on (CCM at step 0, ECM at step 1); the paper-scale estimate is computed from the second
# iteration's stages (the first pays for compiling the kernels)
# (locally ECM's fits take 8 Adam steps instead of the reference's 576)
# (one iteration locally: the script's path is the same, and two took 3 of CI's 7 minutes for the check)
if [ "$MODE" = device ]; then EDIT_SIZE=(--orbit 8 --fit-steps 400 --iterations 2); else EDIT_SIZE=(--orbit 2 --fit-steps 10 --ecm-min-steps 8 --iterations 1); fi
# Per runtime: `edit-cuda` writes edit-cuda/ and edit-cuda-run.json.
for rt in $RUNTIMES; do
  case $rt in cuda) [ "$CUDA_OK" = 1 ] || continue; name=edit-cuda ;; *) name=edit ;; esac
  step "$name" 240 env VCEDIT_GPU_RUNTIME="$rt" "$V" edit --scene "$IN/playbot-31k.ply" "${EDIT_SIZE[@]}" \
    --model "$MODEL" --source "a toy robot" --target "a golden toy robot" --steps 2 --ccm-steps 0 \
    --ecm-steps 1 --size "$IMG" --device gpu --out "$WORK/$name"
  [ -f "$WORK/$name/run.json" ] && cp "$WORK/$name/run.json" "$WORK/$name-run.json"
done

# ---- a whole fit from posed images (lego-200), and the demo end to end
if [ "$MODE" = device ]; then FIT_SIZE=(--steps 5000); else FIT_SIZE=(--steps 30 --init-points 2000); fi
for rt in $RUNTIMES; do
  case $rt in cuda) [ "$CUDA_OK" = 1 ] || continue; name=fit-cuda ;; *) name=fit ;; esac
  step "$name" 150 env VCEDIT_GPU_RUNTIME="$rt" "$V" fit --data "$IN/lego-200" --out "$WORK/lego-$rt.ply" \
    --background white --device gpu "${FIT_SIZE[@]}"
done
# Where a fit's time goes: 1500 steps of the same fit under the kernel profile, beside its wall time.
# FIT_PROFILE_STEPS=5000 profiles the whole fit (~1 min on an H200): the last quarter of its launches is
# then shown apart (late steps, at ~60k Gaussians, cost 3-4x the early ones; the backward dominates).
FIT_PROFILE_STEPS=${FIT_PROFILE_STEPS:-1500}
[ "$MODE" = device ] && full && step fit-profile $(( FIT_PROFILE_STEPS / 25 + 60 )) env CUBECL_DEBUG_LOG="$WORK/fit.prof" CUBECL_DEBUG_OPTION=profile \
  bash -c 't0=$(date +%s%N); "$1" fit --data "$2" --out "$3" --background white --device gpu --steps "$6" \
      >/dev/null 2>&1 || exit 1; wall=$(( ($(date +%s%N) - t0) / 1000000 )); unset CUBECL_DEBUG_LOG
    python3 "$4" "$5" --label "vcedit fit lego-200, $6 steps, ${wall} ms wall" || exit 1
    [ "$6" -gt 1500 ] && python3 "$4" "$5" --segments 4 --label "the last quarter of its launches"; exit 0' \
  _ "$V" "$IN/lego-200" "$WORK/lego-profile.ply" "$HERE/kernel_profile.py" "$WORK/fit.prof" "$FIT_PROFILE_STEPS"
# Where a fit's host time goes, and A/Bs: 1500 steps under host_profile.py (CPU time per thread, context
# switches, the fit's own device-read waits, its held-out PSNR) as `auto` runs it (WGSL), WGSL with the
# raster backward's shared-memory staging (VCEDIT_GPU_STAGED_BACKWARD=on: swapped bits there), on SPIR-V
# (an edit's splatting path), SPIR-V with staging (shared float atomics), and SPIR-V with staging and
# plane sums (VCEDIT_GPU_PLANE_SUMS). Variants are comma-separated settings. (It found the 34 -> 83-90 s
# regression of 2026-11-27: a WGSL fit loaded the SPIR-V kernels an earlier step had persisted; and on
# 2026-11-28 that SPIR-V's raster backward is 5.5x WGSL's, plane sums alone not helping.)
if [ "$MODE" = device ]; then
  AB_SIZE="${FIT_AB_SIZE:---steps 1500}"
  AB_VARIANTS="${FIT_AB_VARIANTS:-auto VCEDIT_GPU_STAGED_BACKWARD=on VCEDIT_GPU_COMPILER=spirv VCEDIT_GPU_COMPILER=spirv,VCEDIT_GPU_STAGED_BACKWARD=on VCEDIT_GPU_COMPILER=spirv,VCEDIT_GPU_STAGED_BACKWARD=on,VCEDIT_GPU_PLANE_SUMS=on}"
else
  AB_SIZE="--steps 30 --init-points 2000"
  AB_VARIANTS="auto"
fi
# A variant that fails is a row with its exit code; the rest still run.
full && step fit-ab "${FIT_AB_TIMEOUT:-240}" bash -c 'failed=0; for v in $5; do
    if [ "$v" = auto ]; then set_env=(); else IFS=, read -r -a set_env <<< "$v"; fi
    env "${set_env[@]}" python3 "$4" --label "$v" -- "$1" fit --data "$2" --out "$3" --force --background white \
      --device gpu $6 || failed=1
  done; exit $failed' _ "$V" "$IN/lego-200" "$WORK/lego-ab.ply" "$HERE/host_profile.py" "$AB_VARIANTS" "$AB_SIZE"
# The packed vcedit has no built-in demo model (prepare.sh): the checkout's is named.
if [ "$MODE" = device ]; then
  full && step demo 150 "$V" demo --model "$ROOT/models/demo" --device gpu --out "$WORK/demo"
else
  # 180 s: the first run on empty caches also times both convolution paths per problem (~40 s on lavapipe;
  # 75 s in all in CI on 2026-11-29, 34 s with im2col forced). Since CCM and ECM run at every step of a
  # short schedule (2026-12-07), ECM's fits stretched to 576 steps over 2 views took 347 s here: the
  # smoke test keeps them short (both modules still run, on the device).
  step demo 180 "$V" demo --model "$ROOT/models/demo" --device gpu --out "$WORK/demo" --views 2 \
    --steps 2 --iterations 1 --fit-steps 5 --ecm-min-steps 16
fi

summarize
say "done in $(elapsed)s; results: $OUT/gpu-check.json, $OUT/gpu-check.md, log $LOG"
cat "$OUT/gpu-check.md" 2>/dev/null
# The work folder (unpacked inputs, weights, outputs) goes unless GPU_CHECK_KEEP=1.
[ "${GPU_CHECK_KEEP:-0}" = 1 ] || rm -rf "$WORK"
# Here (--local, CI) every step must pass: that keeps the check working for the next borrowed machine.
# There, a failed step is a finding, not a failure of the check: it fails only when vcedit found no GPU.
python3 - "$OUT/gpu-check.json" "$MODE" <<'EOF'
import json, sys
d = json.load(open(sys.argv[1]))
if sys.argv[2] == "local":
    sys.exit(0 if d.get("complete") else 1)
sys.exit(0 if d["steps"].get("adapter", {}).get("status") == "ok" else 1)
EOF
