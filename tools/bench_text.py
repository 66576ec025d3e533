#!/usr/bin/env python3
"""Times transformers' CLIPTokenizer and an SD 1.5-config CLIPTextModel (random weights, CPU) on the shapes of
crates/bench/src/text.rs (vcedit bench text).

Usage: python tools/bench_text.py [THREADS] [--dtype f32|bf16] [--batches 1,2,6] [--runs 5]

`--dtype bf16` casts the model with `.to(torch.bfloat16)`. One `RESULT {json}` line per batch (best of the runs).
"""
import argparse
import json
import os
import time

import torch
from transformers import CLIPTextConfig, CLIPTextModel, CLIPTokenizer

ap = argparse.ArgumentParser()
ap.add_argument("threads", nargs="?", type=int, default=os.cpu_count())
ap.add_argument("--dtype", default="f32", choices=("f32", "bf16"))
ap.add_argument("--batches", default="1,2,6")
ap.add_argument("--runs", type=int, default=5)
args = ap.parse_args()
torch.set_num_threads(args.threads)
here = os.path.dirname(os.path.abspath(__file__))
real = os.path.join(here, "..", "..", "shared", "assets", "clip-bpe")
tok = CLIPTokenizer.from_pretrained(real if os.path.isdir(real) else os.path.join(here, "..", "fixtures", "models",
                                                                                   "tiny-lcm", "tokenizer"))
prompt = "a highly detailed photograph of a red fox sitting in a snowy forest at dawn, soft golden light"


def timed(label, runs, fn):
    fn()
    best = float("inf")
    for _ in range(runs):
        start = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - start)
    print(f"{label}: best {1e3 * best:.3f} ms")
    return best


timed("tokenizer encode (one prompt)", 1000,
      lambda: tok(prompt, padding="max_length", max_length=77, truncation=True))
cfg = CLIPTextConfig(vocab_size=49408, hidden_size=768, intermediate_size=3072, num_hidden_layers=12,
                     num_attention_heads=12, max_position_embeddings=77, hidden_act="quick_gelu")
model = CLIPTextModel(cfg).eval().to({"f32": torch.float32, "bf16": torch.bfloat16}[args.dtype])
print("threads", args.threads, args.dtype)
with torch.no_grad():
    for batch in (int(b) for b in args.batches.split(",")):
        ids = tok([prompt] * batch, padding="max_length", max_length=77, truncation=True, return_tensors="pt").input_ids
        best = timed(f"SD 1.5 text encoder, batch {batch} x 77", args.runs, lambda: model(ids))
        print("RESULT " + json.dumps(dict(bench="text", impl="torch", what="encode", dtype=args.dtype, batch=batch,
                                          threads=args.threads, seconds=round(best, 5))), flush=True)
