#!/usr/bin/env python3
"""Builds the LPIPS-VGG conformance fixtures in fixtures/lpips/ with the real `lpips` package.

The reference is `lpips.LPIPS(net='vgg', pretrained=True, pnet_rand=True)`: the package's own ScalingLayer,
VGG16 slicing, normalize_tensor, NetLinLayer and spatial average. `pnet_rand=True` builds the backbone with
`torchvision.models.vgg16(weights=None)`, so nothing is downloaded (downloads are also blocked below).

Full-width VGG16 weights are 58 MB, too big to commit, so the main fixture swaps in a *narrow* network with
the VGG16 topology (same 13 convs, pools and taps; widths 8/12/16/20/24), by replacing torchvision's `vgg16`
while LPIPS is constructed and then replacing the five `lin` layers by random ones of matching width. The
vcedit loader reads channel widths from the tensors, so it runs the same code path on these weights.

Outputs:
- fixtures/lpips/narrow/{vgg16,lpips_vgg}.safetensors: made from PyTorch checkpoints in the torchvision /
  lpips key layouts by tools/convert_lpips_weights.py, which is thereby tested too.
- fixtures/lpips/cases.safetensors: per case `<name>.render`, `<name>.target` (H x W x 3, interleaved) and
  `<name>.grad` (d LPIPS / d render from torch autograd, same layout).
- fixtures/lpips/cases.json: per case the size, input convention, network, LPIPS value and per-layer terms.

Cases: three with the narrow network (64x64 and 37x45 with `normalize=False`, i.e. images fed as they are;
48x80 with `normalize=True`, i.e. [0, 1] mapped to [-1, 1]); one (`real_lin`, 32x48) with the package's real
calibrated lin weights on a full-width VGG16 whose weights come from a deterministic generator that
`diffusion::lpips::synthetic_tensors` reproduces (splitmix64; see there), so a Rust test can rebuild the network
without committed backbone weights and read the lin weights from the installed package.

Usage: python tools/make_lpips_fixtures.py [--out fixtures/lpips]
Requires: torch, torchvision, lpips, safetensors, numpy.
"""
import argparse
import importlib.metadata
import importlib.util
import json
import os
import tempfile
import types
from unittest import mock

import numpy as np
import torch
import torch.hub
from safetensors.torch import load_file, save_file

HERE = os.path.dirname(os.path.abspath(__file__))
NARROW = [8, 12, 16, 20, 24]
VGG16 = [64, 128, 256, 512, 512]
CONVS_PER_STAGE = [2, 2, 3, 3, 3]
CONV_INDICES = [0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28]
SYNTHETIC_SEED = 11


def no_downloads(*args, **kwargs):
    raise RuntimeError("make_lpips_fixtures.py must not download anything")


def vgg_cfg(widths):
    cfg = []
    for width, n in zip(widths, CONVS_PER_STAGE):
        cfg += [width] * n + ["M"]
    return cfg


def converter():
    spec = importlib.util.spec_from_file_location("convert_lpips_weights", os.path.join(HERE, "convert_lpips_weights.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def backbone_convs(model):
    """(torchvision index, Conv2d) of the LPIPS backbone; the slices keep torchvision's module names."""
    convs = []
    for k in range(1, 6):
        for name, layer in getattr(model.net, f"slice{k}").named_children():
            if isinstance(layer, torch.nn.Conv2d):
                convs.append((int(name), layer))
    assert [i for i, _ in convs] == CONV_INDICES
    return convs


def narrow_lpips():
    """LPIPS with the VGG16 code path but narrow random layers."""
    import lpips
    import lpips.pretrained_networks as pn
    from torchvision.models.vgg import make_layers

    def narrow_vgg16(pretrained=False, **kwargs):
        assert not pretrained
        return types.SimpleNamespace(features=make_layers(vgg_cfg(NARROW)))

    with mock.patch.object(pn.tv, "vgg16", narrow_vgg16):
        model = lpips.LPIPS(net="vgg", pretrained=True, pnet_rand=True, verbose=False)
    with torch.no_grad():
        # Kaiming init keeps activations alive through 13 layers (torch's default Conv2d init shrinks them
        # by ~3x per layer, leaving deep features dominated by the biases).
        for _, conv in backbone_convs(model):
            torch.nn.init.kaiming_normal_(conv.weight, nonlinearity="relu")
            conv.bias.uniform_(-0.05, 0.05)
        lins = []
        for k, width in enumerate(NARROW):
            lin = lpips.NetLinLayer(width, use_dropout=True)
            lin.model[1].weight.uniform_(0.0, 1.0)  # the calibrated weights are non-negative too
            setattr(model, f"lin{k}", lin)
            lins.append(lin)
        model.lins = torch.nn.ModuleList(lins)
    return model.eval()


def splitmix64(x):
    x = (x + np.uint64(0x9E3779B97F4A7C15)).astype(np.uint64)
    x = ((x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)).astype(np.uint64)
    x = ((x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)).astype(np.uint64)
    return x ^ (x >> np.uint64(31))


def synthetic_uniform(seed, stream, n):
    """Mirror of diffusion::lpips::synthetic_uniform: 24-bit uniforms in [0, 1) as float64."""
    i = np.arange(n, dtype=np.uint64)
    x = (np.uint64(seed) << np.uint64(40)) | (np.uint64(stream) << np.uint64(32)) | i
    return (splitmix64(x) >> np.uint64(40)).astype(np.float64) / float(1 << 24)


def set_synthetic_backbone(model, widths, seed):
    """Overwrites the backbone with diffusion::lpips::synthetic_tensors(widths, seed) (VGG keys only)."""
    with torch.no_grad():
        c_in = 3
        for j, (_, conv) in enumerate(backbone_convs(model)):
            c_out = conv.weight.shape[0]
            bound = np.sqrt(6.0 / (9 * c_in))
            w = (2.0 * synthetic_uniform(seed, 2 * j, c_out * c_in * 9) - 1.0) * bound
            b = (2.0 * synthetic_uniform(seed, 2 * j + 1, c_out) - 1.0) / 20.0
            conv.weight.copy_(torch.from_numpy(w.astype(np.float32)).reshape(c_out, c_in, 3, 3))
            conv.bias.copy_(torch.from_numpy(b.astype(np.float32)))
            c_in = c_out
    expected = [w for w, n in zip(widths, CONVS_PER_STAGE) for _ in range(n)]
    assert [conv.weight.shape[0] for _, conv in backbone_convs(model)] == expected


def image_pair(h, w, generator, low, high):
    """A smooth random target and a render that differs by a smooth colour shift plus noise, in [low, high]."""
    def smooth(channels, cells):
        coarse = torch.rand(1, channels, cells, cells, generator=generator)
        return torch.nn.functional.interpolate(coarse, size=(h, w), mode="bilinear", align_corners=False)

    target = 0.7 * smooth(3, 6) + 0.3 * torch.rand(1, 3, h, w, generator=generator)
    render = (target + 0.25 * (smooth(3, 4) - 0.5) + 0.1 * (torch.rand(1, 3, h, w, generator=generator) - 0.5)).clamp(0, 1)
    scale = high - low
    return render * scale + low, target * scale + low


def run_case(model, name, h, w, normalize, low, high, generator, network, tensors, cases):
    render, target = image_pair(h, w, generator, low, high)
    render = render.clone().requires_grad_(True)
    value, per_layer = model(render, target, retPerLayer=True, normalize=normalize)
    value.sum().backward()
    grad = render.grad
    assert torch.isfinite(grad).all(), f"{name}: torch gradient has NaN (a zero feature vector?)"
    hwc = lambda t: t.detach()[0].permute(1, 2, 0).contiguous().float()
    tensors[f"{name}.render"] = hwc(render)
    tensors[f"{name}.target"] = hwc(target)
    tensors[f"{name}.grad"] = hwc(grad)
    cases.append({
        "name": name,
        "height": h,
        "width": w,
        "input_range": "unit_to_signed" if normalize else "as_is",
        "network": network,
        "value": float(value.item()),
        "per_layer": [float(r.item()) for r in per_layer],
        "grad_max_abs": float(grad.abs().max().item()),
    })
    print(f"{name}: {h}x{w} normalize={normalize} LPIPS {value.item():.6f}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=os.path.join(HERE, "..", "fixtures", "lpips"))
    args = parser.parse_args()
    out = os.path.abspath(args.out)
    os.makedirs(out, exist_ok=True)

    os.environ["TORCH_HOME"] = tempfile.mkdtemp(prefix="lpips-fixtures-torch-home-")
    torch.hub.load_state_dict_from_url = no_downloads
    torch.hub.download_url_to_file = no_downloads
    torch.manual_seed(0)
    generator = torch.Generator().manual_seed(1234)
    tensors, cases = {}, []

    model = narrow_lpips()
    # Write the narrow weights as PyTorch checkpoints in the torchvision / lpips layouts and convert them with
    # the user-facing tool; the cases below run on the re-loaded converted weights.
    with tempfile.TemporaryDirectory() as tmp:
        vgg_pth, lin_pth = os.path.join(tmp, "vgg16.pth"), os.path.join(tmp, "vgg.pth")
        torch.save({f"features.{i}.{p}": getattr(conv, p).detach().clone()
                    for i, conv in backbone_convs(model) for p in ("weight", "bias")}, vgg_pth)
        torch.save({k: v for k, v in model.state_dict().items() if k.startswith("lin")}, lin_pth)
        narrow_dir = os.path.join(out, "narrow")
        converter().convert(vgg_pth, lin_pth, narrow_dir)
    vgg = load_file(os.path.join(narrow_dir, "vgg16.safetensors"))
    lin = load_file(os.path.join(narrow_dir, "lpips_vgg.safetensors"))
    for i, conv in backbone_convs(model):
        assert torch.equal(vgg[f"features.{i}.weight"], conv.weight) and torch.equal(vgg[f"features.{i}.bias"], conv.bias)
    for k in range(5):
        assert torch.equal(lin[f"lin{k}.model.1.weight"], getattr(model, f"lin{k}").model[1].weight)

    run_case(model, "narrow_64x64_as_is", 64, 64, False, 0.0, 1.0, generator, "narrow", tensors, cases)
    run_case(model, "narrow_48x80_unit_to_signed", 48, 80, True, 0.0, 1.0, generator, "narrow", tensors, cases)
    run_case(model, "narrow_37x45_as_is_signed_images", 37, 45, False, -1.0, 1.0, generator, "narrow", tensors, cases)

    import lpips
    full = lpips.LPIPS(net="vgg", pretrained=True, pnet_rand=True, verbose=False).eval()
    set_synthetic_backbone(full, VGG16, SYNTHETIC_SEED)
    network = {"synthetic_vgg16_seed": SYNTHETIC_SEED, "widths": VGG16, "lin": "lpips/weights/v0.1/vgg.pth"}
    run_case(full, "real_lin_32x48_as_is", 32, 48, False, 0.0, 1.0, generator, network, tensors, cases)

    save_file(tensors, os.path.join(out, "cases.safetensors"))
    meta = {
        "generator": "tools/make_lpips_fixtures.py",
        "lpips_version": importlib.metadata.version("lpips"),
        "torch_version": torch.__version__,
        "narrow_widths": NARROW,
        "cases": cases,
    }
    with open(os.path.join(out, "cases.json"), "w") as f:
        json.dump(meta, f, indent=1)
        f.write("\n")
    size = sum(os.path.getsize(os.path.join(d, n)) for d, _, names in os.walk(out) for n in names)
    print(f"wrote {out} ({size / 1024:.0f} KiB)")


if __name__ == "__main__":
    main()
