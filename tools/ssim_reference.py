"""Reference SSIM value for crates/splat/src/loss.rs (`ssim_matches_torch_reference`).

Rebuilds the INRIA 3DGS trainer's SSIM (utils/loss_utils.py: an 11x11 Gaussian window with sigma 1.5 built
as the outer product of a normalised 1D window, conv2d per channel with padding 5 (zero padding, 'same'
output), C1 = 0.01^2, C2 = 0.03^2, mean over the map) in float64 torch, and evaluates it on the two integer
patterns the Rust test uses. Prints the value with full precision.

Run: /work/pyenv/bin/python tools/ssim_reference.py
"""
import math

import torch
import torch.nn.functional as F

H, W, C = 9, 13, 3


def pattern(a, b, m):
    vals = [((i * a + b) % m) / (m - 1) for i in range(H * W * C)]
    # Interleaved HWC -> NCHW.
    return torch.tensor(vals, dtype=torch.float64).reshape(H, W, C).permute(2, 0, 1).unsqueeze(0)


def window(size=11, sigma=1.5):
    g = torch.tensor([math.exp(-((i - size // 2) ** 2) / (2 * sigma**2)) for i in range(size)], dtype=torch.float64)
    g = g / g.sum()
    w2 = torch.outer(g, g)
    return w2.expand(C, 1, size, size).contiguous()


def ssim(x, y, size=11):
    w = window(size)
    pad = size // 2
    mu_x = F.conv2d(x, w, padding=pad, groups=C)
    mu_y = F.conv2d(y, w, padding=pad, groups=C)
    sxx = F.conv2d(x * x, w, padding=pad, groups=C) - mu_x**2
    syy = F.conv2d(y * y, w, padding=pad, groups=C) - mu_y**2
    sxy = F.conv2d(x * y, w, padding=pad, groups=C) - mu_x * mu_y
    c1, c2 = 0.01**2, 0.03**2
    m = ((2 * mu_x * mu_y + c1) * (2 * sxy + c2)) / ((mu_x**2 + mu_y**2 + c1) * (sxx + syy + c2))
    return m.mean()


if __name__ == "__main__":
    x = pattern(37, 11, 101)
    y = pattern(53, 7, 97)
    print(repr(ssim(x, y).item()))
