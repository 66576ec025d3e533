#!/usr/bin/env python3
"""Builds the tiny, randomly initialised conformance models with the real diffusers/transformers packages.

Two complete pipelines in diffusers layout (model_index.json + unet/ vae/ text_encoder/ tokenizer/ scheduler/):

- fixtures/models/tiny-lcm : LCM-style UNet (time_cond_proj_dim), 4 input channels, conv proj_in/out,
  quick_gelu text encoder, tokenizer as vocab.json + merges.txt (the older hub layout), LCMScheduler config,
  weights in f32.
- fixtures/models/tiny-ip2p: InstructPix2Pix-style UNet (8 input channels), per-block head counts, linear
  proj_in/out, gelu text encoder, tokenizer as tokenizer.json only (what current transformers saves) with
  "!" as pad token and an absurd model_max_length, DDIMScheduler config, weights stored in f16.

The tokenizer vocabulary is a small CLIP-format BPE learnt here from a word list (the real 49k vocabulary would
make the fixtures too big); the real vocabulary is tested separately against ../shared/assets/clip-bpe.

Usage: python tools/make_tiny_models.py [--out fixtures/models]
Requires: torch, diffusers, transformers, safetensors (pip install torch diffusers transformers safetensors).
"""
import argparse
import collections
import json
import os
import shutil

import torch
from diffusers import AutoencoderKL, DDIMScheduler, LCMScheduler, UNet2DConditionModel
from transformers import CLIPTextConfig, CLIPTextModel, CLIPTokenizer

WORDS = """a an the of on in with and photo picture man woman clown grandma cat dog lion bear brown
red green blue yellow white black orange purple pink gray striped checkered dotted gradient solid sphere
box cube cylinder torus cone vase table floor hat wearing elf face doll robot toy painting style statue
marble wooden golden metal glass stone snow fire water sky grass tree house car bird horse fish flower""".split()


def bytes_to_unicode():
    """CLIP's reversible byte -> printable unicode map (same construction as the GPT-2/CLIP tokenizers)."""
    bs = list(range(ord("!"), ord("~") + 1)) + list(range(ord("¡"), ord("¬") + 1)) + list(range(ord("®"), ord("ÿ") + 1))
    cs = bs[:]
    n = 0
    for b in range(256):
        if b not in bs:
            bs.append(b)
            cs.append(256 + n)
            n += 1
    return dict(zip(bs, [chr(c) for c in cs]))


def learn_bpe(words, num_merges):
    """Greedy BPE on a word list: words end with </w>, the most frequent adjacent pair is merged each round."""
    corpus = collections.Counter(words)
    seqs = {w: list(w[:-1]) + [w[-1] + "</w>"] for w in corpus}
    merges = []
    for _ in range(num_merges):
        pairs = collections.Counter()
        for w, s in seqs.items():
            for a, b in zip(s, s[1:]):
                pairs[(a, b)] += corpus[w]
        if not pairs:
            break
        best = max(pairs.items(), key=lambda kv: (kv[1], kv[0]))[0]
        merges.append(best)
        for w, s in seqs.items():
            out, i = [], 0
            while i < len(s):
                if i + 1 < len(s) and (s[i], s[i + 1]) == best:
                    out.append(s[i] + s[i + 1])
                    i += 2
                else:
                    out.append(s[i])
                    i += 1
            seqs[w] = out
    return merges


def write_clip_bpe(folder, merges):
    """Writes vocab.json + merges.txt in the CLIP layout: bytes, bytes+</w>, merges, then the two specials."""
    os.makedirs(folder, exist_ok=True)
    byte_chars = list(bytes_to_unicode().values())
    vocab = byte_chars + [c + "</w>" for c in byte_chars] + ["".join(m) for m in merges]
    vocab += ["<|startoftext|>", "<|endoftext|>"]
    ids = {}
    for tok in vocab:
        ids.setdefault(tok, len(ids))
    with open(os.path.join(folder, "vocab.json"), "w", encoding="utf-8") as f:
        json.dump(ids, f, ensure_ascii=False)
    with open(os.path.join(folder, "merges.txt"), "w", encoding="utf-8") as f:
        f.write("#version: 0.2\n")
        for a, b in merges:
            f.write(f"{a} {b}\n")
    return len(ids)


def text_encoder(vocab_size, act, seed):
    torch.manual_seed(seed)
    cfg = CLIPTextConfig(
        vocab_size=vocab_size,
        hidden_size=32,
        intermediate_size=64,
        num_hidden_layers=2,
        num_attention_heads=4,
        max_position_embeddings=77,
        hidden_act=act,
        layer_norm_eps=1e-5,
        bos_token_id=vocab_size - 2,
        eos_token_id=vocab_size - 1,
        pad_token_id=1,
        projection_dim=32,
    )
    return CLIPTextModel(cfg).eval()


def randomise(model, seed):
    """Random weights everywhere, including the zero-initialised output convs, so every path is exercised."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in model.named_parameters():
            if "norm" in name and name.endswith("weight"):
                p.copy_(1.0 + 0.1 * torch.randn(p.shape, generator=g))
            else:
                fan_in = p[0].numel() if p.dim() > 1 else 1
                p.copy_(torch.randn(p.shape, generator=g) / max(fan_in, 1) ** 0.5 * (0.5 if p.dim() > 1 else 0.1))
    return model.eval()


def build_lcm(out, merges):
    root = os.path.join(out, "tiny-lcm")
    shutil.rmtree(root, ignore_errors=True)
    vocab_size = write_clip_bpe(os.path.join(root, "tokenizer"), merges)
    tok = CLIPTokenizer.from_pretrained(os.path.join(root, "tokenizer"))
    # Keep the older layout only: rewrite the config, drop tokenizer.json if transformers added one.
    with open(os.path.join(root, "tokenizer", "tokenizer_config.json"), "w") as f:
        json.dump({"model_max_length": 77, "bos_token": "<|startoftext|>", "eos_token": "<|endoftext|>",
                   "unk_token": "<|endoftext|>", "pad_token": "<|endoftext|>", "do_lower_case": True,
                   "tokenizer_class": "CLIPTokenizer"}, f, indent=2)
    assert tok.convert_tokens_to_ids("<|endoftext|>") == vocab_size - 1

    te = randomise(text_encoder(vocab_size, "quick_gelu", 1), 11)
    te.save_pretrained(os.path.join(root, "text_encoder"), safe_serialization=True)

    torch.manual_seed(2)
    unet = UNet2DConditionModel(
        sample_size=16,
        in_channels=4,
        out_channels=4,
        down_block_types=("CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "DownBlock2D"),
        up_block_types=("UpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D"),
        block_out_channels=(16, 32, 32),
        layers_per_block=1,
        norm_num_groups=8,
        cross_attention_dim=32,
        attention_head_dim=4,
        time_cond_proj_dim=16,
    )
    randomise(unet, 12).save_pretrained(os.path.join(root, "unet"), safe_serialization=True)

    torch.manual_seed(3)
    vae = AutoencoderKL(
        in_channels=3,
        out_channels=3,
        down_block_types=("DownEncoderBlock2D",) * 3,
        up_block_types=("UpDecoderBlock2D",) * 3,
        block_out_channels=(16, 32, 32),
        layers_per_block=1,
        latent_channels=4,
        norm_num_groups=8,
        sample_size=64,
        scaling_factor=0.18215,
    )
    randomise(vae, 13).save_pretrained(os.path.join(root, "vae"), safe_serialization=True)

    LCMScheduler(
        beta_start=0.00085, beta_end=0.012, beta_schedule="scaled_linear", num_train_timesteps=1000,
        original_inference_steps=50, clip_sample=False, set_alpha_to_one=True, steps_offset=1,
        prediction_type="epsilon", timestep_spacing="leading", timestep_scaling=10.0,
    ).save_pretrained(os.path.join(root, "scheduler"))
    write_index(root, "LatentConsistencyModelPipeline", "LCMScheduler")


def build_ip2p(out, merges):
    root = os.path.join(out, "tiny-ip2p")
    shutil.rmtree(root, ignore_errors=True)
    tmp = os.path.join(out, "_bpe_tmp")
    vocab_size = write_clip_bpe(tmp, merges)
    tok = CLIPTokenizer.from_pretrained(tmp, pad_token="!", model_max_length=int(1e30))
    tok.save_pretrained(os.path.join(root, "tokenizer"))
    shutil.rmtree(tmp)
    for legacy in ("vocab.json", "merges.txt"):
        p = os.path.join(root, "tokenizer", legacy)
        if os.path.exists(p):
            os.remove(p)
    assert os.path.exists(os.path.join(root, "tokenizer", "tokenizer.json"))

    te = randomise(text_encoder(vocab_size, "gelu", 4), 21)
    te.half().save_pretrained(os.path.join(root, "text_encoder"), safe_serialization=True)

    torch.manual_seed(5)
    unet = UNet2DConditionModel(
        sample_size=8,
        in_channels=8,
        out_channels=4,
        down_block_types=("CrossAttnDownBlock2D", "DownBlock2D"),
        up_block_types=("UpBlock2D", "CrossAttnUpBlock2D"),
        block_out_channels=(16, 32),
        layers_per_block=2,
        norm_num_groups=4,
        cross_attention_dim=32,
        attention_head_dim=(2, 4),
        use_linear_projection=True,
        act_fn="silu",
    )
    randomise(unet, 22).half().save_pretrained(os.path.join(root, "unet"), safe_serialization=True)

    torch.manual_seed(6)
    vae = AutoencoderKL(
        in_channels=3,
        out_channels=3,
        down_block_types=("DownEncoderBlock2D",) * 2,
        up_block_types=("UpDecoderBlock2D",) * 2,
        block_out_channels=(16, 32),
        layers_per_block=2,
        latent_channels=4,
        norm_num_groups=4,
        sample_size=32,
        scaling_factor=0.5,
    )
    randomise(vae, 23).half().save_pretrained(os.path.join(root, "vae"), safe_serialization=True)

    DDIMScheduler(
        beta_start=0.00085, beta_end=0.012, beta_schedule="scaled_linear", num_train_timesteps=1000,
        clip_sample=False, set_alpha_to_one=False, steps_offset=1, prediction_type="epsilon",
    ).save_pretrained(os.path.join(root, "scheduler"))
    write_index(root, "StableDiffusionInstructPix2PixPipeline", "DDIMScheduler")


def write_index(root, pipeline, scheduler):
    index = {
        "_class_name": pipeline,
        "_diffusers_version": "0.22.0",
        "scheduler": ["diffusers", scheduler],
        "text_encoder": ["transformers", "CLIPTextModel"],
        "tokenizer": ["transformers", "CLIPTokenizer"],
        "unet": ["diffusers", "UNet2DConditionModel"],
        "vae": ["diffusers", "AutoencoderKL"],
        "safety_checker": [None, None],
        "feature_extractor": [None, None],
    }
    with open(os.path.join(root, "model_index.json"), "w") as f:
        json.dump(index, f, indent=2)


def main():
    ap = argparse.ArgumentParser()
    here = os.path.dirname(os.path.abspath(__file__))
    ap.add_argument("--out", default=os.path.join(here, "..", "fixtures", "models"))
    args = ap.parse_args()
    os.makedirs(args.out, exist_ok=True)
    merges = learn_bpe(WORDS * 3 + ["photograph", "clowns", "hats", "spheres"], 300)
    build_lcm(args.out, merges)
    build_ip2p(args.out, merges)
    print("wrote", os.path.abspath(args.out))


if __name__ == "__main__":
    main()
