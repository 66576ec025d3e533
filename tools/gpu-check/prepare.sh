#!/usr/bin/env bash
# Packs everything tools/gpu-check/run.sh needs on a borrowed GPU machine (no Rust, no network) into the
# git-ignored folder .gpu-check/ of the repository root, and prints its size. Run it on the development
# machine; see tools/gpu-check/README.md for the call that carries the folder over.
#
#   tools/gpu-check/prepare.sh            build + download + pack
#   tools/gpu-check/prepare.sh --no-build pack the release binary already built
#
# What it packs:
#   bin/vcedit.xz      the stripped release `vcedit` (its `vcedit bench` subcommands are the benches)
#   debs/              the Vulkan loader and the GL dispatch libraries NVIDIA's Vulkan driver (libGLX_nvidia)
#                      loads (libvulkan1, libglvnd0, libglx0, libgl1, libegl1, libopengl0, libgles2: unpacked
#                      onto / there, as the device tool's notes say), and vulkaninfo (vulkan-tools and its
#                      X/Wayland client libraries, unpacked into a private folder there)
#   wheels/            diffusers and importlib_metadata (the device image has PyTorch, transformers,
#                      safetensors, huggingface_hub, numpy and pillow, but no diffusers)
#   cuda-headers.tar.xz  the CUDA 13.0 headers NVRTC compiles vcedit's CUDA kernels against (cuda/include,
#                      with CCCL under include/cccl: NVIDIA's nvidia-cuda-runtime and nvidia-cuda-cccl
#                      wheels), for a machine whose PyTorch brings NVRTC but no toolkit
#   inputs.tar.xz      playbot-31k.ply (a real scene), lego-200 (posed views), clip-bpe (the CLIP vocabulary
#                      for the SD 1.5-sized random weights, which are made there with PyTorch)
#   build.json         commit, date, toolchain: what the numbers belong to
set -euo pipefail
cd "$(dirname "$0")/../.."
ROOT=$(pwd)
PACK="$ROOT/.gpu-check"
SHARED="$ROOT/../shared/assets"
# The one limit that matters: the working tree plus carried folders must stay under 64 MiB.
LIMIT_MIB=64

build=1
for arg in "$@"; do
  case "$arg" in
    --no-build) build=0 ;;
    *) echo "prepare.sh: unknown option $arg" >&2; exit 2 ;;
  esac
done

for tool in xz strip tar python3; do
  command -v "$tool" >/dev/null || { echo "prepare.sh: $tool is needed" >&2; exit 1; }
done
for need in scenes/playbot-31k.ply lego-200/transforms_train.json clip-bpe/vocab.json clip-bpe/merges.txt; do
  [ -e "$SHARED/$need" ] || { echo "prepare.sh: $SHARED/$need is missing (the shared assets)" >&2; exit 1; }
done

if [ "$build" = 1 ]; then
  # Without the built-in demo model (16 MB that would not fit the carried files' limit); the device runs
  # in a copy of the checkout, whose models/demo the demo step reads.
  # With the CUDA runtime beside wgpu (`--features cuda`), so that one binary measures both.
  cargo build --release --bin vcedit --no-default-features --features cuda
fi
# Where cargo puts it (CARGO_TARGET_DIR or the workspace's target/).
BIN="$(cargo metadata --format-version 1 --no-deps | python3 -c 'import json,sys; print(json.load(sys.stdin)["target_directory"])')/release/vcedit"
[ -x "$BIN" ] || { echo "prepare.sh: $BIN is missing (run without --no-build)" >&2; exit 1; }

rm -rf "$PACK.tmp"
mkdir -p "$PACK.tmp"/{bin,debs,wheels}

echo "packing vcedit..."
strip -o "$PACK.tmp/bin/vcedit" "$BIN"
xz -T0 -6 "$PACK.tmp/bin/vcedit"

# Debian packages for amd64, fetched with a private package list so the machine's own apt state is untouched.
echo "downloading the Vulkan loader and vulkaninfo..."
lists=$(mktemp -d)
mkdir -p "$lists/partial"
apt_opts=(-oAPT::Sandbox::User=root -oAPT::Architecture=amd64 -oAPT::Architectures=amd64 "-oDir::State::Lists=$lists" -qq)
fetch_debs() {
  apt-get "${apt_opts[@]}" update >/dev/null &&
    (cd "$PACK.tmp/debs" && apt-get "${apt_opts[@]}" download \
      libvulkan1 libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2 \
      vulkan-tools libwayland-client0 libx11-6 libxcb1 libxau6 libxdmcp6 libbsd0 libmd0 >/dev/null)
}
fetch_debs || { sleep 5; fetch_debs; } || { echo "prepare.sh: apt-get download failed" >&2; exit 1; }
rm -rf "$lists"

echo "downloading the diffusers wheel..."
pip_download() {
  python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation py \
    --platform any -d "$PACK.tmp/wheels" diffusers==0.42.1 importlib_metadata==8.7.0
}
pip_download || { sleep 5; pip_download; } || { echo "prepare.sh: pip download failed" >&2; exit 1; }

echo "downloading the CUDA headers..."
headers_dl=$(mktemp -d)
pip_headers() {
  python3 -m pip download -q --no-deps --only-binary=:all: --platform manylinux2014_x86_64 --python-version 3.12 \
    -d "$headers_dl" "nvidia-cuda-runtime==13.0.*" "nvidia-cuda-cccl==13.0.*"
}
pip_headers || { sleep 5; pip_headers; } || { echo "prepare.sh: pip download of the CUDA headers failed" >&2; exit 1; }
python3 - "$headers_dl" "$PACK.tmp/cuda-headers.tar.xz" <<'PY'
import glob, io, lzma, sys, tarfile, zipfile
src, out = sys.argv[1:]
with lzma.open(out, "wb", preset=6) as xz, tarfile.open(fileobj=xz, mode="w") as tar:
    for wheel in sorted(glob.glob(f"{src}/*.whl")):
        with zipfile.ZipFile(wheel) as z:
            for name in z.namelist():
                # nvidia/cu13/include/... -> cuda/include/...; CCCL's Thrust and CUB are left out (the kernels
                # include libcu++'s cuda/ and nv/ only), which keeps the pack within the carried limit.
                if "/include/" not in name or name.endswith("/"):
                    continue
                rel = name.split("/include/", 1)[1]
                if rel.startswith(("cccl/thrust/", "cccl/cub/")):
                    continue
                info = tarfile.TarInfo("cuda/include/" + rel)
                data = z.read(name)
                info.size = len(data)
                tar.addfile(info, io.BytesIO(data))
PY
rm -rf "$headers_dl"

echo "packing the inputs..."
staging=$(mktemp -d)
mkdir -p "$staging/inputs/clip-bpe"
cp "$SHARED/scenes/playbot-31k.ply" "$staging/inputs/"
cp -r "$SHARED/lego-200" "$staging/inputs/lego-200"
cp "$SHARED/clip-bpe/vocab.json" "$SHARED/clip-bpe/merges.txt" "$staging/inputs/clip-bpe/"
tar -C "$staging" -cf - inputs | xz -T0 -6 > "$PACK.tmp/inputs.tar.xz"
chmod -R u+w "$staging" && rm -rf "$staging"

commit=$(git rev-parse HEAD 2>/dev/null || echo unknown)
dirty=$(git status --porcelain --untracked-files=no 2>/dev/null | wc -l)
python3 - "$PACK.tmp/build.json" "$commit" "$dirty" "$(rustc --version 2>/dev/null || echo unknown)" <<'EOF'
import json, sys, datetime
path, commit, dirty, rustc = sys.argv[1:]
json.dump({"commit": commit, "uncommitted_changes": dirty != "0", "rustc": rustc,
           "packed": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")},
          open(path, "w"), indent=1)
EOF

rm -rf "$PACK"
mv "$PACK.tmp" "$PACK"

# Size check: what travels is the tracked files, untracked files git does not ignore, and the carried folder.
pack_bytes=$(du -sb "$PACK" | cut -f1)
tree_bytes=$(git ls-files -z --cached --others --exclude-standard | xargs -0 -r stat -c %s -- 2>/dev/null | awk '{s+=$1} END {print s+0}')
total=$((pack_bytes + tree_bytes))
mib() { awk -v b="$1" 'BEGIN {printf "%.1f MiB", b / 1048576}'; }
echo "carried folder .gpu-check: $(mib "$pack_bytes") (vcedit $(mib "$(stat -c %s "$PACK/bin/vcedit.xz")"), inputs $(mib "$(stat -c %s "$PACK/inputs.tar.xz")"), wheels $(mib "$(du -sb "$PACK/wheels" | cut -f1)"), debs $(mib "$(du -sb "$PACK/debs" | cut -f1)"), CUDA headers $(mib "$(stat -c %s "$PACK/cuda-headers.tar.xz")"))"
echo "working tree: $(mib "$tree_bytes"); together $(mib "$total") of the ${LIMIT_MIB} MiB that may travel"
if [ "$total" -gt $((LIMIT_MIB * 1048576)) ]; then
  echo "prepare.sh: over the ${LIMIT_MIB} MiB limit" >&2
  exit 1
fi
