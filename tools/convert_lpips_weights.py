#!/usr/bin/env python3
"""Makes the LPIPS-VGG weights folder that vcedit reads (`--lpips DIR`) from PyTorch checkpoints.

vcedit reads safetensors only, so run this once on a machine that has the two PyTorch files:

- the torchvision VGG16 ImageNet weights: a state dict with `features.N.weight` / `features.N.bias`, e.g. the
  torch hub cache file `<torch hub dir>/checkpoints/vgg16-397923af.pth` (the default, if present). A state
  dict of a whole `lpips.LPIPS` model (`net.sliceK.N.*` keys) is accepted too, and so is a .safetensors file
  with either key layout (e.g. timm's `vgg16.tv_in1k`, which holds the torchvision weights).
- the lpips package's calibrated linear layers `lpips/weights/v0.1/vgg.pth` (default: taken from the
  installed `lpips` package). Keys `lin0.model.1.weight` ... `lin4.model.1.weight`.

Output: DIR/vgg16.safetensors (keys `features.{0,2,5,7,10,12,14,17,19,21,24,26,28}.{weight,bias}`) and
DIR/lpips_vgg.safetensors (keys `lin{0..4}.model.1.weight`), all float32. Shapes are checked (3x3 kernels,
channel counts chained from RGB, lin widths equal to the tapped layers); the channel widths themselves may
differ from VGG16's 64/128/256/512/512 (the conformance fixtures use a narrow network).

PyTorch checkpoints are read with `torch.load(weights_only=True)`, so nothing in them is executed; nothing is downloaded.

Usage: python tools/convert_lpips_weights.py --out DIR [--vgg VGG16.pth] [--lin lpips/weights/v0.1/vgg.pth]
Requires: torch, safetensors.
"""
import argparse
import importlib.util
import os
import re
import sys

import torch
from safetensors.torch import load_file, save_file

# Conv layers of torchvision's vgg16().features and the stage each belongs to (taps after stages' last conv).
CONV_INDICES = [0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28]
CONVS_PER_STAGE = [2, 2, 3, 3, 3]
VGG_FILE = "vgg16.safetensors"
LIN_FILE = "lpips_vgg.safetensors"
HUB_VGG16 = "vgg16-397923af.pth"


def default_vgg_path():
    path = os.path.join(torch.hub.get_dir(), "checkpoints", HUB_VGG16)
    return path if os.path.isfile(path) else None


def default_lin_path():
    spec = importlib.util.find_spec("lpips")
    if spec is None or spec.origin is None:
        return None
    path = os.path.join(os.path.dirname(spec.origin), "weights", "v0.1", "vgg.pth")
    return path if os.path.isfile(path) else None


def load_state_dict(path):
    if path.endswith(".safetensors"):
        return load_file(path)
    obj = torch.load(path, map_location="cpu", weights_only=True)
    if isinstance(obj, dict) and "state_dict" in obj and isinstance(obj["state_dict"], dict):
        obj = obj["state_dict"]
    if not isinstance(obj, dict):
        raise SystemExit(f"{path}: expected a state dict, found {type(obj).__name__}")
    return obj


def vgg_tensors(state, path):
    """features.N.{weight,bias} from a torchvision or lpips state dict."""
    renamed = {}
    for key, value in state.items():
        if key.startswith("module."):
            key = key[len("module."):]
        m = re.fullmatch(r"(?:net\.slice\d+\.|features\.)(\d+)\.(weight|bias)", key)
        if m:
            renamed[f"features.{m.group(1)}.{m.group(2)}"] = value
    problems = []
    out = {}
    c_in = 3
    for index in CONV_INDICES:
        w, b = renamed.get(f"features.{index}.weight"), renamed.get(f"features.{index}.bias")
        if w is None or b is None:
            problems.append(f"missing features.{index}.weight/bias")
            c_in = None
            continue
        if w.ndim != 4 or tuple(w.shape[2:]) != (3, 3) or (c_in is not None and w.shape[1] != c_in):
            problems.append(f"features.{index}.weight has shape {tuple(w.shape)}, expected [C, {c_in}, 3, 3]")
        if tuple(b.shape) != (w.shape[0],):
            problems.append(f"features.{index}.bias has shape {tuple(b.shape)}, expected [{w.shape[0]}]")
        out[f"features.{index}.weight"] = w.detach().float().contiguous()
        out[f"features.{index}.bias"] = b.detach().float().contiguous()
        c_in = w.shape[0]
    if problems:
        raise SystemExit(f"{path}: not VGG16 weights: " + "; ".join(problems))
    return out


def tap_widths(vgg):
    widths, conv = [], 0
    for n in CONVS_PER_STAGE:
        conv += n
        widths.append(vgg[f"features.{CONV_INDICES[conv - 1]}.weight"].shape[0])
    return widths


def lin_tensors(state, path, widths):
    problems = []
    out = {}
    for k, width in enumerate(widths):
        key = f"lin{k}.model.1.weight"
        t = state.get(key)
        if t is None:
            problems.append(f"missing {key}")
            continue
        if t.numel() != width:
            problems.append(f"{key} has shape {tuple(t.shape)}, expected [1, {width}, 1, 1]")
            continue
        out[key] = t.detach().float().reshape(1, width, 1, 1).contiguous()
    if problems:
        raise SystemExit(f"{path}: not LPIPS-VGG linear layers: " + "; ".join(problems))
    return out


def convert(vgg_path, lin_path, out_dir):
    vgg = vgg_tensors(load_state_dict(vgg_path), vgg_path)
    widths = tap_widths(vgg)
    lin = lin_tensors(load_state_dict(lin_path), lin_path, widths)
    os.makedirs(out_dir, exist_ok=True)
    save_file(vgg, os.path.join(out_dir, VGG_FILE))
    save_file(lin, os.path.join(out_dir, LIN_FILE))
    return widths


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True, help="folder to write vgg16.safetensors and lpips_vgg.safetensors")
    parser.add_argument("--vgg", help=f"torchvision VGG16 state dict, .pth or .safetensors (default: torch hub cache {HUB_VGG16})")
    parser.add_argument("--lin", help="lpips weights/v0.1/vgg.pth (default: from the installed lpips package)")
    args = parser.parse_args(argv)
    vgg_path = args.vgg or default_vgg_path()
    lin_path = args.lin or default_lin_path()
    if vgg_path is None:
        sys.exit(f"no --vgg given and {HUB_VGG16} is not in {torch.hub.get_dir()}/checkpoints")
    if lin_path is None:
        sys.exit("no --lin given and the lpips package (with weights/v0.1/vgg.pth) is not installed")
    widths = convert(vgg_path, lin_path, args.out)
    print(f"wrote {os.path.join(args.out, VGG_FILE)} and {LIN_FILE} (stage widths {widths})")


if __name__ == "__main__":
    main()
