#!/usr/bin/env python3
"""Times diffusers' AutoencoderKL (SD 1.x config) and AutoencoderTiny (SD TAESD config) with random weights on the
same shapes as `vcedit bench codec SIZE`, for a side-by-side comparison.

Usage: python tools/bench_vae.py [SIZE=256] [THREADS=2] [--dtype f32|bf16] [--runs N] [--kl-only]

`--dtype bf16` casts the models and inputs with `.to(torch.bfloat16)`, as a PyTorch user runs bf16 on the CPU.
Each timing is the best of N calls after one warm-up; one `RESULT {json}` line per network and direction.
"""
import argparse
import json
import time

import torch
from diffusers import AutoencoderKL, AutoencoderTiny


def timed(label, runs, fn, fields):
    best, best_cpu = float("inf"), float("inf")
    with torch.no_grad():
        fn()  # warm-up
        for _ in range(runs):
            start, cpu_start = time.perf_counter(), time.process_time()
            fn()
            best = min(best, time.perf_counter() - start)
            best_cpu = min(best_cpu, time.process_time() - cpu_start)
    print(f"torch {label}: best {best:.3f} s")
    print("RESULT " + json.dumps(dict(fields, impl="torch", seconds=round(best, 4), cpu_seconds=round(best_cpu, 3))),
          flush=True)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("size", nargs="?", type=int, default=256)
    ap.add_argument("threads", nargs="?", type=int, default=2)
    ap.add_argument("--dtype", default="f32", choices=("f32", "bf16"))
    ap.add_argument("--runs", type=int, default=2)
    ap.add_argument("--kl-only", action="store_true")
    args = ap.parse_args()
    size = args.size
    torch.set_num_threads(args.threads)
    cast = {"f32": torch.float32, "bf16": torch.bfloat16}[args.dtype]
    image = (torch.rand(1, 3, size, size) * 2 - 1).to(cast)
    latents = torch.randn(1, 4, size // 8, size // 8).to(cast)
    print(f"image {size}x{size}, latents {size // 8}x{size // 8}, threads {torch.get_num_threads()}, {args.dtype}")
    base = dict(bench="codec", size=size, threads=args.threads, dtype=args.dtype)
    kl = AutoencoderKL(down_block_types=("DownEncoderBlock2D",) * 4, up_block_types=("UpDecoderBlock2D",) * 4,
                       block_out_channels=(128, 256, 512, 512), layers_per_block=2).eval().to(cast)
    timed("AutoencoderKL encode (mean)", args.runs, lambda: kl.encode(image).latent_dist.mean,
          dict(base, kind="kl", what="encode"))
    timed("AutoencoderKL decode", args.runs, lambda: kl.decode(latents).sample, dict(base, kind="kl", what="decode"))
    if args.kl_only:
        return
    tiny = AutoencoderTiny().eval().to(cast)
    timed("TAESD encode", args.runs, lambda: tiny.encode(image).latents, dict(base, kind="tiny", what="encode"))
    timed("TAESD decode", args.runs, lambda: tiny.decode(latents).sample, dict(base, kind="tiny", what="decode"))


if __name__ == "__main__":
    main()
