#!/usr/bin/env python3
"""Records UNet conformance fixtures from the real diffusers UNet2DConditionModel on the tiny models.

For each of fixtures/models/tiny-lcm and tiny-ip2p (the latter loaded from its f16 weights, run in f32) it
writes fixtures/unet/<model>.safetensors with:

- inputs: `sample` [B, C, H, W], `timesteps` [B] (different per sample), `encoder_hidden_states` [B, 77, D],
  `timestep_cond` [B, time_cond_proj_dim] (LCM model only);
- `noise_pred`: the UNet output with diffusers' default attention processors;
- `probs.<layer>`: softmax probabilities [B, heads, q_len, k_len] of named self- and cross-attention layers,
  captured by a custom attention processor;
- `hook.maps.<layer>` + `hook.noise_pred`: a processor that replaces the cross-attention probabilities of
  those layers for batch items 1.. with the given maps (item 0 untouched), and the resulting output;
- `nocond.noise_pred` (LCM model only): the output without `timestep_cond`;
- `swap.noise_pred`: a processor that, in every self-attention layer, replaces K and V of the last batch
  item with those of item 0 (InfEdit-style mutual self-attention), and the resulting output.

Metadata (safetensors header): the layer lists, the diffusers version and the latent size.

Usage: python tools/make_unet_fixtures.py [--models fixtures/models] [--out fixtures/unet]
"""
import argparse
import json
import os

import diffusers
import torch
from diffusers import UNet2DConditionModel
from safetensors.torch import save_file

CASES = {
    # model: (latent h, w, batch, timesteps, self layers, cross layers)
    "tiny-lcm": (
        8,
        12,
        [999, 500, 37],
        ["down_blocks.1.attentions.0.transformer_blocks.0.attn1", "mid_block.attentions.0.transformer_blocks.0.attn1"],
        [
            "down_blocks.0.attentions.0.transformer_blocks.0.attn2",
            "mid_block.attentions.0.transformer_blocks.0.attn2",
            "up_blocks.1.attentions.1.transformer_blocks.0.attn2",
        ],
    ),
    "tiny-ip2p": (
        9,
        7,
        [981, 261, 1],
        ["down_blocks.0.attentions.1.transformer_blocks.0.attn1", "up_blocks.1.attentions.2.transformer_blocks.0.attn1"],
        [
            "down_blocks.0.attentions.0.transformer_blocks.0.attn2",
            "mid_block.attentions.0.transformer_blocks.0.attn2",
            "up_blocks.1.attentions.0.transformer_blocks.0.attn2",
        ],
    ),
}


class Processor:
    """Plain attention written out (scores → softmax → weighted sum) with capture/replace/swap options."""

    def __init__(self, name, captured, maps=None, swap_last=False):
        self.name = name
        self.captured = captured
        self.maps = maps
        self.swap_last = swap_last

    def __call__(self, attn, hidden_states, encoder_hidden_states=None, attention_mask=None, temb=None, **kwargs):
        batch, tokens, _ = hidden_states.shape
        is_cross = encoder_hidden_states is not None
        context = encoder_hidden_states if is_cross else hidden_states
        heads = attn.heads

        def split(t):
            return t.view(batch, -1, heads, t.shape[-1] // heads).transpose(1, 2)

        q, k, v = split(attn.to_q(hidden_states)), split(attn.to_k(context)), split(attn.to_v(context))
        if self.swap_last and not is_cross:
            k, v = k.clone(), v.clone()
            k[-1], v[-1] = k[0], v[0]
        probs = (q @ k.transpose(-1, -2) * attn.scale).softmax(dim=-1)
        if self.name in self.captured:
            self.captured[self.name] = probs.detach().clone()
        if self.maps is not None and self.name in self.maps:
            probs = torch.cat([probs[:1], self.maps[self.name][1:]], dim=0)
        out = (probs @ v).transpose(1, 2).reshape(batch, tokens, -1)
        return attn.to_out[1](attn.to_out[0](out))


def set_processors(unet, make):
    unet.set_attn_processor({name: make(name[: -len(".processor")]) for name in unet.attn_processors})


def record(models_dir, out_dir, model_name):
    height, width, timesteps, self_layers, cross_layers = CASES[model_name]
    unet = UNet2DConditionModel.from_pretrained(os.path.join(models_dir, model_name, "unet"), torch_dtype=torch.float32)
    unet.eval()
    cfg = unet.config
    g = torch.Generator().manual_seed(1234)
    batch = len(timesteps)
    inputs = {
        "sample": torch.randn(batch, cfg.in_channels, height, width, generator=g),
        "timesteps": torch.tensor(timesteps, dtype=torch.float32),
        "encoder_hidden_states": torch.randn(batch, 77, cfg.cross_attention_dim, generator=g),
    }
    if cfg.time_cond_proj_dim is not None:
        inputs["timestep_cond"] = torch.randn(batch, cfg.time_cond_proj_dim, generator=g)

    def run(with_cond=True):
        with torch.no_grad():
            return unet(
                inputs["sample"],
                inputs["timesteps"].long(),
                encoder_hidden_states=inputs["encoder_hidden_states"],
                timestep_cond=inputs.get("timestep_cond") if with_cond else None,
            ).sample

    tensors = dict(inputs)
    tensors["noise_pred"] = run()
    if "timestep_cond" in inputs:
        # diffusers skips cond_proj when no condition is given (InfEdit calls the LCM UNet that way).
        tensors["nocond.noise_pred"] = run(with_cond=False)

    captured = {name: None for name in self_layers + cross_layers}
    set_processors(unet, lambda name: Processor(name, captured))
    written_out = run()
    gap = (written_out - tensors["noise_pred"]).abs().max().item()
    assert gap < 1e-5, f"explicit processor differs from diffusers' default by {gap}"
    for name, probs in captured.items():
        assert probs is not None, f"layer {name} was not called"
        tensors[f"probs.{name}"] = probs

    maps = {}
    for name in cross_layers:
        shape = captured[name].shape
        maps[name] = (3.0 * torch.randn(shape, generator=g)).softmax(dim=-1)
        tensors[f"hook.maps.{name}"] = maps[name]
    set_processors(unet, lambda name: Processor(name, {}, maps=maps))
    tensors["hook.noise_pred"] = run()

    set_processors(unet, lambda name: Processor(name, {}, swap_last=True))
    tensors["swap.noise_pred"] = run()

    meta = {
        "diffusers_version": diffusers.__version__,
        "self_layers": json.dumps(self_layers),
        "cross_layers": json.dumps(cross_layers),
    }
    path = os.path.join(out_dir, f"{model_name}.safetensors")
    save_file({k: v.contiguous().float() for k, v in tensors.items()}, path, metadata=meta)
    print(f"{path}: {os.path.getsize(path) / 1e6:.2f} MB, |noise_pred| max {tensors['noise_pred'].abs().max():.3f}")


def main():
    here = os.path.dirname(os.path.abspath(__file__))
    ap = argparse.ArgumentParser()
    ap.add_argument("--models", default=os.path.join(here, "..", "fixtures", "models"))
    ap.add_argument("--out", default=os.path.join(here, "..", "fixtures", "unet"))
    args = ap.parse_args()
    os.makedirs(args.out, exist_ok=True)
    torch.set_num_threads(2)
    for name in CASES:
        record(args.models, args.out, name)


if __name__ == "__main__":
    main()
