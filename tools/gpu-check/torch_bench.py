#!/usr/bin/env python3
"""The PyTorch + diffusers side of tools/gpu-check: the same measurements as `vcedit bench`, on the same
weights (a diffusers model folder), so the ratio of the two is the figure.

  python torch_bench.py info
  python torch_bench.py matmul [--shapes 4096x320x1280] [--dtypes f32,tf32,f16]
  python torch_bench.py attention [--shapes 48x4096x4096x40] [--dtype f16]
  python torch_bench.py unet  --model DIR [--batches 1,6] [--size 64] [--dtype f16]
  python torch_bench.py codec --model DIR [--size 512] [--dtype f16]
  python torch_bench.py text  --model DIR [--batches 1,6] [--dtype f16]

CUDA when available (else the CPU, in f32: tools/gpu-check/run.sh --local). Attention is diffusers'
default processor (PyTorch SDPA). Every measurement is one `RESULT {json}` line, the first call apart
from the warm runs (each warm run ends with a device synchronisation).
"""
import argparse
import json
import sys
import time

import torch


def device():
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def sync():
    if torch.cuda.is_available():
        torch.cuda.synchronize()


def dtype_of(name):
    if device().type == "cpu":
        return torch.float32  # f16 convolutions on the CPU are slow or missing; the local mode is a smoke test
    return {"f16": torch.float16, "bf16": torch.bfloat16, "f32": torch.float32}[name]


def measure(fn, runs):
    """(first call, [warm runs]) in seconds; each ends with a device sync."""
    start = time.perf_counter()
    with torch.no_grad():
        fn()
    sync()
    first = time.perf_counter() - start
    warm = []
    for _ in range(runs):
        start = time.perf_counter()
        with torch.no_grad():
            fn()
        sync()
        warm.append(time.perf_counter() - start)
    return first, warm


def report(fields, first, warm):
    warm_sorted = sorted(warm)
    fields = dict(fields, impl="torch", device=device_name(), first_s=round(first, 6),
                  best_s=round(warm_sorted[0], 6), median_s=round(warm_sorted[len(warm) // 2], 6),
                  runs=len(warm))
    print("RESULT " + json.dumps(fields), flush=True)
    print(f"  {fields['bench']} {fields.get('what', '')} {fields.get('batch', '')}: best {fields['best_s']*1e3:.2f} ms "
          f"(first {first*1e3:.1f} ms)", file=sys.stderr)


def device_name():
    return torch.cuda.get_device_name(0) if torch.cuda.is_available() else "cpu"


def cmd_info(a):
    info = dict(bench="torch-info", torch=torch.__version__, cuda=torch.version.cuda, device=device_name())
    try:
        import diffusers
        info["diffusers"] = diffusers.__version__
    except ImportError as e:
        info["diffusers"] = f"missing: {e}"
    if torch.cuda.is_available():
        p = torch.cuda.get_device_properties(0)
        info.update(multiprocessors=p.multi_processor_count, memory_gib=round(p.total_memory / 2**30, 1),
                    capability=f"{p.major}.{p.minor}")
    print("RESULT " + json.dumps(info), flush=True)


def cmd_matmul(a):
    for shape in a.shapes.split(","):
        m, k, n = map(int, shape.split("x"))
        for name in a.dtypes.split(","):
            dt = torch.float32 if name in ("f32", "tf32") else dtype_of(name)
            torch.backends.cuda.matmul.allow_tf32 = name == "tf32"
            x = torch.randn(m, k, device=device(), dtype=dt)
            w = torch.randn(n, k, device=device(), dtype=dt)

            def run():
                for _ in range(a.repeat):
                    torch.nn.functional.linear(x, w)

            first, warm = measure(run, a.runs)
            warm = [t / a.repeat for t in warm]
            best = min(warm)
            fields = dict(bench="matmul", what="linear", precision=name, m=m, k=k, n=n, repeat=a.repeat,
                          ms=round(best * 1e3, 4), tflops=round(2 * m * k * n / best / 1e12, 3))
            report(fields, first, warm)
    torch.backends.cuda.matmul.allow_tf32 = False


def cmd_attention(a):
    """SDPA at `vcedit bench attention`'s shapes (ENTRIESxQUERIESxKEYSxHEAD_DIM, entries = batch × heads)."""
    dt = dtype_of(a.dtype)
    for shape in a.shapes.split(","):
        b, q_len, k_len, d = map(int, shape.split("x"))
        q = torch.randn(1, b, q_len, d, device=device(), dtype=dt)
        k = torch.randn(1, b, k_len, d, device=device(), dtype=dt)
        v = torch.randn(1, b, k_len, d, device=device(), dtype=dt)

        def run():
            for _ in range(a.repeat):
                torch.nn.functional.scaled_dot_product_attention(q, k, v)

        first, warm = measure(run, a.runs)
        warm = [t / a.repeat for t in warm]
        best = min(warm)
        fields = dict(bench="attention", dtype=a.dtype, entries=b, queries=q_len, keys=k_len, dim=d,
                      repeat=a.repeat, ms=round(best * 1e3, 4),
                      tflops=round(4 * b * q_len * k_len * d / best / 1e12, 3))
        report(fields, first, warm)


def cmd_unet(a):
    from diffusers import UNet2DConditionModel
    dt = dtype_of(a.dtype)
    unet = UNet2DConditionModel.from_pretrained(a.model, subfolder="unet", torch_dtype=dt).to(device()).eval()
    cfg = unet.config
    for batch in map(int, a.batches.split(",")):
        sample = torch.randn(batch, cfg.in_channels, a.size, a.size, device=device(), dtype=dt)
        context = torch.randn(batch, 77, cfg.cross_attention_dim, device=device(), dtype=dt)
        t = torch.full((batch,), 500, device=device())
        first, warm = measure(lambda: unet(sample, t, encoder_hidden_states=context).sample, a.runs)
        report(dict(bench="unet", what="forward", hook="none", batch=batch, size=a.size, dtype=str(dt)),
               first, warm)


def cmd_codec(a):
    from diffusers import AutoencoderKL
    dt = dtype_of(a.dtype)
    vae = AutoencoderKL.from_pretrained(a.model, subfolder="vae", torch_dtype=dt).to(device()).eval()
    f = 2 ** (len(vae.config.block_out_channels) - 1)
    image = torch.rand(a.batch, 3, a.size, a.size, device=device(), dtype=dt) * 2 - 1
    latents = torch.randn(a.batch, vae.config.latent_channels, a.size // f, a.size // f, device=device(), dtype=dt)
    first, warm = measure(lambda: vae.encode(image).latent_dist.mean, a.runs)
    report(dict(bench="codec", kind="kl", what="encode", size=a.size, batch=a.batch, dtype=str(dt)), first, warm)
    first, warm = measure(lambda: vae.decode(latents).sample, a.runs)
    report(dict(bench="codec", kind="kl", what="decode", size=a.size, batch=a.batch, dtype=str(dt)), first, warm)


def cmd_text(a):
    from transformers import CLIPTextModel, CLIPTokenizer
    dt = dtype_of(a.dtype)
    tok = CLIPTokenizer.from_pretrained(a.model, subfolder="tokenizer")
    enc = CLIPTextModel.from_pretrained(a.model, subfolder="text_encoder", torch_dtype=dt).to(device()).eval()
    prompt = "a highly detailed photograph of a red fox sitting in a snowy forest at dawn, soft golden light"
    for batch in map(int, a.batches.split(",")):
        ids = tok([prompt] * batch, padding="max_length", max_length=77, truncation=True,
                  return_tensors="pt").input_ids.to(device())
        first, warm = measure(lambda: enc(ids).last_hidden_state, a.runs)
        report(dict(bench="text", what="encode", batch=batch, dtype=str(dt)), first, warm)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    sub.add_parser("info")
    p = sub.add_parser("matmul")
    p.add_argument("--shapes", default="4096x320x320,4096x320x1280")
    p.add_argument("--dtypes", default="f32,tf32,f16")
    p.add_argument("--repeat", type=int, default=20)
    p.add_argument("--runs", type=int, default=3)
    p = sub.add_parser("attention")
    p.add_argument("--shapes", default="48x4096x4096x40,48x1024x1024x80,48x4096x77x40")
    p.add_argument("--dtype", default="f16")
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--runs", type=int, default=3)
    for name, batches in (("unet", "1,6"), ("text", "1,6")):
        p = sub.add_parser(name)
        p.add_argument("--model", required=True)
        p.add_argument("--batches", default=batches)
        p.add_argument("--size", type=int, default=64)
        p.add_argument("--dtype", default="f16")
        p.add_argument("--runs", type=int, default=3)
    p = sub.add_parser("codec")
    p.add_argument("--model", required=True)
    p.add_argument("--size", type=int, default=512)
    p.add_argument("--batch", type=int, default=1)
    p.add_argument("--dtype", default="f16")
    p.add_argument("--runs", type=int, default=3)
    a = ap.parse_args()
    torch.manual_seed(0)
    {"info": cmd_info, "matmul": cmd_matmul, "attention": cmd_attention, "unet": cmd_unet, "codec": cmd_codec, "text": cmd_text}[a.cmd](a)


if __name__ == "__main__":
    main()
