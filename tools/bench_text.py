#!/usr/bin/env python3
"""Times transformers' CLIPTokenizer and an SD 1.5-config CLIPTextModel (random weights, f32, CPU) on the shapes of
crates/bench/src/text.rs (vcedit bench text). Usage: python tools/bench_text.py [THREADS]"""
import os
import sys
import time

import torch
from transformers import CLIPTextConfig, CLIPTextModel, CLIPTokenizer

threads = int(sys.argv[1]) if len(sys.argv) > 1 else os.cpu_count()
torch.set_num_threads(threads)
here = os.path.dirname(os.path.abspath(__file__))
real = os.path.join(here, "..", "..", "shared", "assets", "clip-bpe")
tok = CLIPTokenizer.from_pretrained(real if os.path.isdir(real) else os.path.join(here, "..", "fixtures", "models",
                                                                                   "tiny-lcm", "tokenizer"))
prompt = "a highly detailed photograph of a red fox sitting in a snowy forest at dawn, soft golden light"


def timed(label, runs, fn):
    fn()
    start = time.perf_counter()
    for _ in range(runs):
        fn()
    print(f"{label}: {1e3 * (time.perf_counter() - start) / runs:.3f} ms")


timed("tokenizer encode (one prompt)", 1000,
      lambda: tok(prompt, padding="max_length", max_length=77, truncation=True))
cfg = CLIPTextConfig(vocab_size=49408, hidden_size=768, intermediate_size=3072, num_hidden_layers=12,
                     num_attention_heads=12, max_position_embeddings=77, hidden_act="quick_gelu")
model = CLIPTextModel(cfg).eval()
print("threads", threads)
with torch.no_grad():
    for batch in (1, 2, 6):
        ids = tok([prompt] * batch, padding="max_length", max_length=77, truncation=True, return_tensors="pt").input_ids
        timed(f"SD 1.5 text encoder, batch {batch} x 77", 5, lambda: model(ids))
