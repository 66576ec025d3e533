#!/usr/bin/env python3
"""Times diffusers' AutoencoderKL (SD 1.x config) and AutoencoderTiny (SD TAESD config) with random weights on the
same shapes as `vcedit bench codec SIZE`, for a side-by-side comparison.

Usage: python tools/bench_vae.py [SIZE=256] [THREADS=2]
"""
import sys
import time

import torch
from diffusers import AutoencoderKL, AutoencoderTiny


def timed(label, runs, fn):
    with torch.no_grad():
        fn()  # warm-up
        start = time.perf_counter()
        for _ in range(runs):
            fn()
    print(f"torch {label}: {(time.perf_counter() - start) / runs:.3f} s")


def main():
    size = int(sys.argv[1]) if len(sys.argv) > 1 else 256
    torch.set_num_threads(int(sys.argv[2]) if len(sys.argv) > 2 else 2)
    image = torch.rand(1, 3, size, size) * 2 - 1
    latents = torch.randn(1, 4, size // 8, size // 8)
    print(f"image {size}x{size}, latents {size // 8}x{size // 8}, threads {torch.get_num_threads()}")
    kl = AutoencoderKL(down_block_types=("DownEncoderBlock2D",) * 4, up_block_types=("UpDecoderBlock2D",) * 4,
                       block_out_channels=(128, 256, 512, 512), layers_per_block=2).eval()
    timed("AutoencoderKL encode (mean)", 2, lambda: kl.encode(image).latent_dist.mean)
    timed("AutoencoderKL decode", 2, lambda: kl.decode(latents).sample)
    tiny = AutoencoderTiny().eval()
    timed("TAESD encode", 3, lambda: tiny.encode(image).latents)
    timed("TAESD decode", 3, lambda: tiny.decode(latents).sample)


if __name__ == "__main__":
    main()
