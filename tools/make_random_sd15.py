#!/usr/bin/env python3
"""Writes an SD 1.5-architecture pipeline folder with RANDOM weights (diffusers layout), for benchmarks.

No real weights exist on the development machines; this folder has SD 1.5's exact configs (UNet, VAE,
CLIP ViT-L/14 text encoder, LCM scheduler as in LCM_Dreamshaper_v7) so timings and memory match a real
checkpoint. The tokenizer is the real CLIP vocabulary given with --vocab (vocab.json + merges.txt).

Usage: python tools/make_random_sd15.py --out /tmp/sd15-random --vocab ../shared/assets/clip-bpe [--fp16]
       [--device cuda]   (initialise the weights on that device: seconds on a GPU instead of a minute)
"""
import argparse
import json
import os
import shutil

import torch
from diffusers import AutoencoderKL, LCMScheduler, UNet2DConditionModel
from transformers import CLIPTextConfig, CLIPTextModel


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", required=True)
    ap.add_argument("--vocab", required=True)
    ap.add_argument("--fp16", action="store_true")
    ap.add_argument("--device", default="cpu")
    a = ap.parse_args()
    with torch.device(a.device):
        write(a)


def write(a):
    dtype = torch.float16 if a.fp16 else torch.float32
    os.makedirs(a.out, exist_ok=True)
    torch.manual_seed(0)
    unet = UNet2DConditionModel(
        sample_size=64, cross_attention_dim=768, attention_head_dim=8, time_cond_proj_dim=256,
        block_out_channels=(320, 640, 1280, 1280), layers_per_block=2,
    )
    unet.to(dtype).save_pretrained(os.path.join(a.out, "unet"))
    del unet
    vae = AutoencoderKL(
        down_block_types=("DownEncoderBlock2D",) * 4, up_block_types=("UpDecoderBlock2D",) * 4,
        block_out_channels=(128, 256, 512, 512), layers_per_block=2, latent_channels=4, sample_size=512,
    )
    vae.to(dtype).save_pretrained(os.path.join(a.out, "vae"))
    te = CLIPTextModel(CLIPTextConfig(
        vocab_size=49408, hidden_size=768, intermediate_size=3072, num_hidden_layers=12, num_attention_heads=12,
        max_position_embeddings=77, hidden_act="quick_gelu", bos_token_id=49406, eos_token_id=49407, pad_token_id=1,
    ))
    te.to(dtype).save_pretrained(os.path.join(a.out, "text_encoder"))
    tok = os.path.join(a.out, "tokenizer")
    os.makedirs(tok, exist_ok=True)
    for f in ("vocab.json", "merges.txt"):
        shutil.copy(os.path.join(a.vocab, f), tok)
    with open(os.path.join(tok, "tokenizer_config.json"), "w") as f:
        json.dump({"model_max_length": 77, "pad_token": "<|endoftext|>"}, f)
    LCMScheduler(beta_start=0.00085, beta_end=0.012, beta_schedule="scaled_linear", original_inference_steps=50,
                 set_alpha_to_one=True, steps_offset=1, clip_sample=False).save_pretrained(os.path.join(a.out, "scheduler"))
    with open(os.path.join(a.out, "model_index.json"), "w") as f:
        json.dump({"_class_name": "LatentConsistencyModelPipeline", "unet": ["diffusers", "UNet2DConditionModel"],
                   "vae": ["diffusers", "AutoencoderKL"], "text_encoder": ["transformers", "CLIPTextModel"],
                   "tokenizer": ["transformers", "CLIPTokenizer"], "scheduler": ["diffusers", "LCMScheduler"]}, f)
    print("wrote", a.out)


if __name__ == "__main__":
    main()
