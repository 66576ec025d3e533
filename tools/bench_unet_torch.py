#!/usr/bin/env python3
"""PyTorch/diffusers side of the UNet benchmark, and the runner that compares it with ours.

Runs diffusers' UNet2DConditionModel with the SD 1.5 config and random weights at 64x64 latents (batch 1 and
6 by default), `torch.no_grad()`, default attention processor (SDPA), on the given thread count, in f32 and/or
bf16 (`--dtypes f32,bf16`: the same weights cast with `.to(torch.bfloat16)`, inputs in bf16, as a PyTorch user
runs bf16 on the CPU; oneDNN picks AMX or AVX512-BF16 kernels where the CPU has them). With both dtypes the
bf16 output's relative L2 against the f32 output on the first batch is printed too.

  python tools/bench_unet_torch.py                 # PyTorch only
  python tools/bench_unet_torch.py --compare       # also `cargo bench -p vcedit-bench --bench unet` (same threads), ratio table

Timings are the best of --runs runs after one warm-up. Both sides print `RESULT {json}` lines.
"""
import argparse
import json
import os
import resource
import subprocess
import sys
import time

SD15_UNET = dict(
    sample_size=64,
    in_channels=4,
    out_channels=4,
    down_block_types=("CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "DownBlock2D"),
    up_block_types=("UpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D"),
    block_out_channels=(320, 640, 1280, 1280),
    layers_per_block=2,
    cross_attention_dim=768,
    attention_head_dim=8,
    norm_num_groups=32,
    norm_eps=1e-5,
    downsample_padding=1,
    flip_sin_to_cos=True,
    freq_shift=0,
)


def torch_results(batches, runs, size, threads, dtypes=("f32",)):
    import torch
    from diffusers import UNet2DConditionModel

    torch.set_num_threads(threads)
    torch.manual_seed(0)
    unet = UNet2DConditionModel(**SD15_UNET).eval()
    models = {"f32": unet}
    if "bf16" in dtypes:
        models["bf16"] = UNet2DConditionModel(**SD15_UNET).eval()
        models["bf16"].load_state_dict(unet.state_dict())
        models["bf16"].to(torch.bfloat16)
    torch_dtype = {"f32": torch.float32, "bf16": torch.bfloat16}
    results, first_out = [], {}
    for batch in batches:
        sample = torch.randn(batch, 4, size, size)
        context = torch.randn(batch, 77, 768)
        t = torch.tensor([500] * batch)
        for dtype in dtypes:
            model, cast = models[dtype], torch_dtype[dtype]
            times, cpu_times = [], []
            for run in range(runs + 1):
                start, cpu_start = time.perf_counter(), time.process_time()
                with torch.no_grad():
                    out = model(sample.to(cast), t, encoder_hidden_states=context.to(cast)).sample
                secs, cpu = time.perf_counter() - start, time.process_time() - cpu_start
                assert out.shape == (batch, 4, size, size)
                note = " (warm-up)" if run == 0 else ""
                print(f"  torch {dtype} batch {batch} run {run}: {secs:.3f} s wall, {cpu:.2f} s cpu{note}", file=sys.stderr)
                if run > 0:
                    times.append(secs)
                    cpu_times.append(cpu)
            if batch == batches[0]:
                first_out[dtype] = out.float()
            peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
            results.append(dict(impl="torch", what="forward", dtype=dtype, batch=batch, size=size, threads=threads,
                                seconds=round(min(times), 3), cpu_seconds=round(min(cpu_times), 2), peak_rss_mb=round(peak)))
            print("RESULT " + json.dumps(results[-1]), flush=True)
    if "f32" in first_out and "bf16" in first_out:
        ref, low = first_out["f32"], first_out["bf16"]
        rel = float((low - ref).norm() / ref.norm())
        worst = float((low - ref).abs().max() / ref.std())
        results.append(dict(impl="torch", what="bf16_vs_f32", batch=batches[0], rel_l2=round(rel, 5),
                            max_diff_over_std=round(worst, 4)))
        print("RESULT " + json.dumps(results[-1]), flush=True)
    return results


def candle_results(batches, runs, size, threads):
    repo = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
    env = dict(os.environ, RAYON_NUM_THREADS=str(threads))
    cmd = ["cargo", "bench", "-p", "vcedit-bench", "--bench", "unet", "--",
           "--batches", ",".join(map(str, batches)), "--runs", str(runs), "--size", str(size)]
    proc = subprocess.run(cmd, cwd=repo, env=env, stdout=subprocess.PIPE, text=True, check=True)
    results = [json.loads(line[len("RESULT "):]) for line in proc.stdout.splitlines() if line.startswith("RESULT ")]
    for r in results:
        print("RESULT " + json.dumps(r), flush=True)
    return results


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--batches", default="1,6")
    ap.add_argument("--runs", type=int, default=2)
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--dtypes", default="f32", help="f32, bf16 or f32,bf16 (PyTorch side)")
    ap.add_argument("--compare", action="store_true", help="also run the candle benchmark and print ratios")
    args = ap.parse_args()
    batches = [int(b) for b in args.batches.split(",")]
    dtypes = tuple(args.dtypes.split(","))
    if any(d not in ("f32", "bf16") for d in dtypes):
        sys.exit(f"--dtypes: f32 and/or bf16, not {args.dtypes}")
    ours = candle_results(batches, args.runs, args.size, args.threads) if args.compare else []
    theirs = [r for r in torch_results(batches, args.runs, args.size, args.threads, dtypes)
              if r["what"] == "forward" and r["dtype"] == "f32"]
    if not ours:
        return
    print(f"\nUNet forward, SD 1.5 config, {args.size}x{args.size} latents, {args.threads} threads (best of {args.runs})")
    print("(wall = elapsed seconds; cpu = process CPU seconds, less sensitive to other load on the machine)")
    print(f"{'batch':>5} {'candle wall':>12} {'torch wall':>11} {'ratio':>6} {'candle cpu':>11} {'torch cpu':>10} {'ratio':>6}")
    for t in theirs:
        c = next(r for r in ours if r["what"] == "forward" and r["batch"] == t["batch"])
        print(f"{t['batch']:>5} {c['seconds']:>12.2f} {t['seconds']:>11.2f} {c['seconds'] / t['seconds']:>6.2f}"
              f" {c['cpu_seconds']:>11.2f} {t['cpu_seconds']:>10.2f} {c['cpu_seconds'] / t['cpu_seconds']:>6.2f}")
    print(f"load average at the end: {os.getloadavg()[0]:.1f} (on {os.cpu_count()} CPUs)")
    for r in ours:
        if r["what"] == "load_f16":
            print(f"loading SD 1.5 UNet from f16 safetensors: {r['seconds']:.1f} s, peak RSS {r['peak_rss_mb']} MB"
                  f" (after load: {r.get('anon_mb', '?')} MB f32 weights/heap + {r.get('file_mb', '?')} MB mapped file pages)")


if __name__ == "__main__":
    main()
