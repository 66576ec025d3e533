#!/usr/bin/env python3
"""Reference renders and autograd gradients for vcedit's CPU Gaussian rasteriser.

The reference is gsplat 1.5.3's pure-torch code (gsplat/cuda/_torch_impl.py) for everything up to the
compositor: quaternion/scale -> covariance, EWA projection with the 0.3 low-pass (`_fully_fused_projection`),
and SH colours (`_spherical_harmonics`, then +0.5 and clamp at 0 as gsplat.rendering does). Compositing is a
brute-force torch implementation written here with the 3DGS rules:

- screen radius ceil(3*sqrt(largest eigenvalue)) with 3DGS's max(0.1, ...) under the root; a Gaussian is
  listed in every 16x16 tile its square [mean - r, mean + r] touches (floor/ceil, clamped to the grid);
- per pixel (centre at i+0.5, j+0.5) the Gaussians of its tile in increasing camera depth (ties by index);
  alpha = min(0.99, o*exp(-sigma)); skip if sigma < 0 or alpha < 1/255; the pixel stops (that Gaussian not
  counted) once T*(1-alpha) < 1e-4; weight alpha*T; background added with the final T.
  Vectorised per tile with a cumulative product: because T only decreases, "included" is exactly
  valid & (T after this Gaussian >= 1e-4).

Outputs (fixtures/render/):
- reference.json: the cameras, backgrounds and which tensors belong to which scene/view.
- playbot_3k.safetensors, playbot_31k.safetensors: rgb (H,W,3), alpha (H,W), depth (H,W) per view, float16.
  The scenes themselves are read from ../shared/assets/scenes (not committed).
- playbot_3k_grad.safetensors: gradients (float32) of a random linear loss of one 64x64 playbot-3k render.
- random_scene.safetensors: a self-contained random scene (SH degree 3, 4 extra channels, multiple tiles,
  saturated pixels, culled and off-screen Gaussians), its render and the autograd gradients of a random
  linear loss of rgb, alpha, depth and extras, all float64.

Usage: python tools/make_render_fixtures.py [--assets ../shared/assets] [--out fixtures/render]
Requires: torch, gsplat==1.5.3 (CPU is enough), numpy, safetensors.
"""
import argparse
import json
import math
import os

import numpy as np
import torch
from gsplat.cuda._torch_impl import (
    _fully_fused_projection,
    _quat_scale_to_covar_preci,
    _spherical_harmonics,
)
from safetensors.torch import save_file

TILE = 16


def read_ply(path):
    """3DGS PLY (binary little-endian or ASCII, float properties in any order) -> dict of float64 arrays."""
    with open(path, "rb") as f:
        header = []
        while True:
            line = f.readline().decode("ascii").strip()
            header.append(line)
            if line == "end_header":
                break
        body = f.read()
    fmt = next(l.split()[1] for l in header if l.startswith("format"))
    count = int(next(l.split()[2] for l in header if l.startswith("element vertex")))
    props = [l.split()[2] for l in header if l.startswith("property")]
    types = [l.split()[1] for l in header if l.startswith("property")]
    assert all(t in ("float", "float32") for t in types), "only float properties are supported"
    if fmt == "binary_little_endian":
        arr = np.frombuffer(body, dtype=np.dtype([(p, "<f4") for p in props]), count=count)
        cols = {p: arr[p].astype(np.float64) for p in props}
    else:
        rows = np.array([l.split() for l in body.decode("ascii").split("\n")[:count]], dtype=np.float64)
        cols = {p: rows[:, i] for i, p in enumerate(props)}
    rest = sorted((p for p in props if p.startswith("f_rest_")), key=lambda p: int(p[7:]))
    k = len(rest) // 3 + 1
    degree = int(round(math.sqrt(k))) - 1
    sh = np.zeros((count, k, 3))
    for c in range(3):
        sh[:, 0, c] = cols[f"f_dc_{c}"]
        for j in range(1, k):
            # INRIA layout: channel-major, f_rest_{c*(k-1) + (j-1)}.
            sh[:, j, c] = cols[rest[c * (k - 1) + (j - 1)]]
    return {
        "degree": degree,
        "means": np.stack([cols["x"], cols["y"], cols["z"]], 1),
        "log_scales": np.stack([cols[f"scale_{i}"] for i in range(3)], 1),
        "quats": np.stack([cols[f"rot_{i}"] for i in range(4)], 1),
        "opacity_logits": cols["opacity"],
        "sh": sh,
    }


def look_at(eye, target, up, width, height, fx, fy=None, cx=None, cy=None, name="view"):
    """OpenCV camera (x right, y down, z forward) at `eye` looking at `target`; world `up` maps to -y."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    rot = np.stack([x, y, z])
    return {
        "name": name,
        "width": width,
        "height": height,
        "fx": fx,
        "fy": fy if fy is not None else fx,
        "cx": cx if cx is not None else width / 2,
        "cy": cy if cy is not None else height / 2,
        "rotation": rot.tolist(),
        "translation": (-rot @ eye).tolist(),
    }


def render(scene, cam, background, extra=None):
    """Differentiable reference render. `scene` holds torch tensors (means, log_scales, quats,
    opacity_logits, sh [N,K,3], degree). Returns dict of images."""
    dtype = scene["means"].dtype
    W, H = cam["width"], cam["height"]
    rot = torch.tensor(cam["rotation"], dtype=dtype)
    trans = torch.tensor(cam["translation"], dtype=dtype)
    viewmat = torch.eye(4, dtype=dtype)
    viewmat[:3, :3] = rot
    viewmat[:3, 3] = trans
    K = torch.tensor([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1]], dtype=dtype)

    covars, _ = _quat_scale_to_covar_preci(scene["quats"], torch.exp(scene["log_scales"]), compute_preci=False)
    _, means2d, depths, conics, _ = _fully_fused_projection(
        scene["means"], covars, viewmat[None], K[None], W, H, eps2d=0.3, near_plane=0.01
    )
    means2d, depths, conics = means2d[0], depths[0], conics[0]
    opac = torch.sigmoid(scene["opacity_logits"])
    campos = -rot.T @ trans
    colors = _spherical_harmonics(scene["degree"], scene["means"] - campos, scene["sh"])
    colors = torch.clamp_min(colors + 0.5, 0.0)

    # 3DGS radius and tile rectangles (no gradient: they only select pairs).
    with torch.no_grad():
        a, b, c = conics[:, 0], conics[:, 1], conics[:, 2]
        det_conic = a * c - b * b
        cov_a, cov_b, cov_c = c / det_conic, -b / det_conic, a / det_conic
        det = cov_a * cov_c - cov_b * cov_b
        mid = 0.5 * (cov_a + cov_c)
        lam = mid + torch.sqrt(torch.clamp_min(mid * mid - det, 0.1))
        radius = torch.ceil(3.0 * torch.sqrt(lam))
        tiles_x, tiles_y = -(-W // TILE), -(-H // TILE)
        x0 = torch.clamp(torch.floor((means2d[:, 0] - radius) / TILE), 0, tiles_x)
        x1 = torch.clamp(torch.ceil((means2d[:, 0] + radius) / TILE), 0, tiles_x)
        y0 = torch.clamp(torch.floor((means2d[:, 1] - radius) / TILE), 0, tiles_y)
        y1 = torch.clamp(torch.ceil((means2d[:, 1] + radius) / TILE), 0, tiles_y)
        drawable = (depths > 0.01) & (det > 0) & torch.isfinite(radius) & (radius > 0) & (x1 > x0) & (y1 > y0)
        order = torch.argsort(torch.where(drawable, depths, torch.inf), stable=True)
        order = order[drawable[order]]

    feats = [colors, depths[:, None]]
    if extra is not None:
        feats.append(extra)
    feats = torch.cat(feats, 1)
    nf = feats.shape[1]
    out = torch.zeros(H, W, nf, dtype=dtype)
    t_final = torch.ones(H, W, dtype=dtype)
    out_rows = []
    t_rows = []
    for ty in range(tiles_y):
        row_out, row_t = [], []
        for tx in range(tiles_x):
            xs = torch.arange(tx * TILE, min(W, tx * TILE + TILE), dtype=dtype) + 0.5
            ys = torch.arange(ty * TILE, min(H, ty * TILE + TILE), dtype=dtype) + 0.5
            py, px = torch.meshgrid(ys, xs, indexing="ij")
            ids = order[(x0[order] <= tx) & (x1[order] > tx) & (y0[order] <= ty) & (y1[order] > ty)]
            h, w = py.shape
            if len(ids) == 0:
                row_out.append(torch.zeros(h, w, nf, dtype=dtype))
                row_t.append(torch.ones(h, w, dtype=dtype))
                continue
            dx = means2d[ids, 0][None, :] - px.reshape(-1, 1)
            dy = means2d[ids, 1][None, :] - py.reshape(-1, 1)
            cn = conics[ids]
            sigma = 0.5 * (cn[:, 0] * dx * dx + cn[:, 2] * dy * dy) + cn[:, 1] * dx * dy
            alpha = torch.clamp_max(opac[ids] * torch.exp(-sigma), 0.99)
            valid = (sigma >= 0) & (alpha >= 1.0 / 255.0)
            one_minus = torch.where(valid, 1.0 - alpha, torch.ones_like(alpha))
            t_after = torch.cumprod(one_minus, 1)
            t_before = torch.cat([torch.ones_like(t_after[:, :1]), t_after[:, :-1]], 1)
            included = valid & (t_after >= 1e-4)
            weights = torch.where(included, alpha * t_before, torch.zeros_like(alpha))
            t_fin = torch.prod(torch.where(included, one_minus, torch.ones_like(one_minus)), 1)
            row_out.append((weights @ feats[ids]).reshape(h, w, nf))
            row_t.append(t_fin.reshape(h, w))
        out_rows.append(torch.cat(row_out, 1))
        t_rows.append(torch.cat(row_t, 1))
    out = torch.cat(out_rows, 0)
    t_final = torch.cat(t_rows, 0)
    bg = torch.tensor(background, dtype=dtype)
    result = {
        "rgb": out[..., :3] + t_final[..., None] * bg,
        "alpha": 1.0 - t_final,
        "depth": out[..., 3],
    }
    if extra is not None:
        result["extra"] = out[..., 4:]
    return result


def to_torch(scene, dtype, requires_grad=False):
    out = {"degree": scene["degree"]}
    for k in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        out[k] = torch.tensor(scene[k], dtype=dtype, requires_grad=requires_grad)
    return out


def playbot_cameras():
    target = [0.0, -0.5, 0.0]
    up = [0.0, -1.0, 0.0]  # playbot stands on y = 0 and extends towards -y
    cams = [
        look_at([0.0, -1.2, -3.0], target, up, 128, 128, 140.0, name="front"),
        look_at([2.4, -0.2, 1.6], target, up, 128, 128, 150.0, 160.0, 60.0, 70.0, name="side"),
        look_at([-1.8, -2.2, 1.8], target, up, 160, 96, 120.0, 118.0, 83.0, 45.0, name="top"),
    ]
    backgrounds = [[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.2, 0.4, 0.6]]
    return cams, backgrounds


def random_scene(rng, n, degree, channels):
    """Gaussians in front of a camera at the origin looking down +z, with a mix of sizes and opacities."""
    k = (degree + 1) ** 2
    z = rng.uniform(1.5, 6.0, n)
    u = rng.uniform(-0.7, 0.7, n)
    v = rng.uniform(-0.6, 0.6, n)
    means = np.stack([u * z, v * z, z], 1)
    log_scales = rng.uniform(-3.5, -1.0, (n, 3))
    quats = rng.normal(size=(n, 4))
    logits = rng.uniform(-3.0, 4.0, n)
    sh = rng.normal(scale=0.25, size=(n, k, 3))
    sh[:, 0, :] = rng.normal(scale=0.8, size=(n, 3))
    # A few big, nearly opaque Gaussians saturate some pixels (T < 1e-4 stops).
    for i in range(4):
        means[i] = [0.3 * i - 0.5, 0.1, 2.0 + 0.05 * i]
        log_scales[i] = np.log([0.35, 0.3, 0.2])
        logits[i] = 6.0
    means[4] = [0.0, 0.0, -1.0]  # behind the camera: culled
    means[5] = [9.0, 0.5, 3.0]  # far outside the field of view: Jacobian clamp
    log_scales[5] = np.log([3.0, 2.0, 2.5])
    extra = rng.uniform(-1.0, 1.0, (n, channels))
    return {
        "degree": degree,
        "means": means,
        "log_scales": log_scales,
        "quats": quats,
        "opacity_logits": logits,
        "sh": sh,
    }, extra


def main():
    here = os.path.dirname(os.path.abspath(__file__))
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--assets", default=os.path.join(here, "..", "..", "shared", "assets"))
    ap.add_argument("--out", default=os.path.join(here, "..", "fixtures", "render"))
    args = ap.parse_args()
    os.makedirs(args.out, exist_ok=True)
    torch.set_grad_enabled(True)
    manifest = {"scenes": {}}

    # Real scenes: images only (float16).
    cams, backgrounds = playbot_cameras()
    for name in ("playbot-3k", "playbot-31k"):
        scene = read_ply(os.path.join(args.assets, "scenes", f"{name}.ply"))
        ts = to_torch(scene, torch.float64)
        tensors = {}
        views = []
        for cam, bg in zip(cams, backgrounds):
            with torch.no_grad():
                img = render(ts, cam, bg)
            for key in ("rgb", "alpha", "depth"):
                tensors[f"{cam['name']}.{key}"] = img[key].to(torch.float16).contiguous()
            views.append({"camera": cam, "background": bg})
            print(name, cam["name"], "mean rgb", float(img["rgb"].mean()), "mean alpha", float(img["alpha"].mean()))
        fname = name.replace("-", "_") + ".safetensors"
        save_file(tensors, os.path.join(args.out, fname))
        manifest["scenes"][name] = {"file": fname, "scene": f"scenes/{name}.ply", "views": views}

    # Gradients of a random linear loss on one playbot-3k view (float32 storage).
    rng = np.random.default_rng(7)
    scene = read_ply(os.path.join(args.assets, "scenes", "playbot-3k.ply"))
    ts = to_torch(scene, torch.float64, requires_grad=True)
    cam = look_at([1.5, -1.5, -2.2], [0.0, -0.5, 0.0], [0.0, -1.0, 0.0], 64, 64, 70.0, name="grad")
    bg = [0.3, 0.6, 0.1]
    img = render(ts, cam, bg)
    weights = {
        "rgb": torch.tensor(rng.uniform(-1, 1, (64, 64, 3))),
        "alpha": torch.tensor(rng.uniform(-1, 1, (64, 64))),
        "depth": torch.tensor(rng.uniform(-1, 1, (64, 64))),
    }
    loss = sum((img[k] * weights[k]).sum() for k in weights)
    loss.backward()
    tensors = {f"weight.{k}": v.to(torch.float32).contiguous() for k, v in weights.items()}
    for k in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        tensors[f"grad.{k}"] = ts[k].grad.to(torch.float32).contiguous()
    for k in ("rgb", "alpha", "depth"):
        tensors[f"out.{k}"] = img[k].detach().to(torch.float16).contiguous()
    save_file(tensors, os.path.join(args.out, "playbot_3k_grad.safetensors"))
    manifest["playbot_3k_grad"] = {
        "file": "playbot_3k_grad.safetensors",
        "scene": "scenes/playbot-3k.ply",
        "camera": cam,
        "background": bg,
        "loss": loss.item(),
    }
    print("playbot-3k grad loss", float(loss))

    # Self-contained random scene, float64 end to end.
    rng = np.random.default_rng(2024)
    channels = 4
    scene, extra = random_scene(rng, 60, 3, channels)
    ts = to_torch(scene, torch.float64, requires_grad=True)
    extra_t = torch.tensor(extra, dtype=torch.float64, requires_grad=True)
    cam = look_at([0.0, 0.0, 0.0], [0.05, -0.02, 1.0], [0.0, -1.0, 0.0], 40, 28, 30.0, 31.0, 19.7, 14.3, name="random")
    bg = [0.3, 0.1, 0.6]
    img = render(ts, cam, bg, extra_t)
    H, W = 28, 40
    weights = {
        "rgb": torch.tensor(rng.uniform(-1, 1, (H, W, 3))),
        "alpha": torch.tensor(rng.uniform(-1, 1, (H, W))),
        "depth": torch.tensor(rng.uniform(-1, 1, (H, W))),
        "extra": torch.tensor(rng.uniform(-1, 1, (H, W, channels))),
    }
    loss = sum((img[k] * weights[k]).sum() for k in weights)
    loss.backward()
    saturated = int((img["alpha"] > 1 - 1e-3).sum())
    print("random scene loss", float(loss), "saturated pixels", saturated)
    assert saturated > 0, "the random scene should saturate some pixels"
    tensors = {}
    for k in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        tensors[f"scene.{k}"] = ts[k].detach().contiguous()
        tensors[f"grad.{k}"] = ts[k].grad.contiguous()
    tensors["scene.extra"] = extra_t.detach().contiguous()
    tensors["grad.extra"] = extra_t.grad.contiguous()
    for k, v in weights.items():
        tensors[f"weight.{k}"] = v.contiguous()
    for k, v in img.items():
        tensors[f"out.{k}"] = v.detach().contiguous()
    save_file(tensors, os.path.join(args.out, "random_scene.safetensors"))
    manifest["random_scene"] = {
        "file": "random_scene.safetensors",
        "sh_degree": 3,
        "channels": channels,
        "camera": cam,
        "background": bg,
        "loss": loss.item(),
    }
    with open(os.path.join(args.out, "reference.json"), "w") as f:
        json.dump(manifest, f, indent=1)
        f.write("\n")
    total = sum(os.path.getsize(os.path.join(args.out, f)) for f in os.listdir(args.out))
    print(f"wrote {args.out} ({total / 1e6:.2f} MB)")


if __name__ == "__main__":
    main()
