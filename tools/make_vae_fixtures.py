#!/usr/bin/env python3
"""Reference outputs for the AutoencoderKL and TAESD (AutoencoderTiny) conformance tests, made with diffusers.

Writes under fixtures/vae/:

- kl-tiny-lcm.safetensors, kl-tiny-ip2p.safetensors: for the tiny VAEs in fixtures/models/<name>/vae (built by
  tools/make_tiny_models.py; tiny-ip2p's weights are f16, upcast to f32 as both sides compute in f32):
  `image` [2,3,24,32] in [-1,1] -> `mean`, `logvar` (clamped, as DiagonalGaussianDistribution does), `noise`,
  `sample` = mean + exp(logvar/2)*noise (diffusers' own `sample(generator)` output, whose noise is `noise`);
  `latents` [2,4,h,w] -> `decoded` (vae.decode(latents).sample, unscaled latents).
- tiny-taesd/: a random AutoencoderTiny in diffusers layout (config.json + diffusion_pytorch_model.safetensors,
  f32, non-default config: SiLU, unequal encoder/decoder widths, uneven block counts).
  taesd-tiny-original-weights.safetensors: another random AutoencoderTiny (ReLU, as taesd.py hard-codes) in the original
  taesd.py index layout (taesd_encoder.safetensors / taesd_decoder.safetensors, decoder indices shifted by the
  clamp at index 0), weights in bf16; its references are computed from the bf16-rounded weights.
  taesd-tiny.safetensors / taesd-tiny-original.safetensors: `image` [2,3,24,32] in [-1,1] -> `latents`
  (AutoencoderTiny.encode); `decode_in` (std-2 latents, so the tanh clamp saturates) -> `decoded` in [-1,1].
- taesd-lego.safetensors: the real TAESD weights (../shared/assets/taesd, original layout, bf16), remapped to
  diffusers names and loaded into diffusers' AutoencoderTiny: `image` = two lego-200 views composited on white and
  resized to 128x128 (Lanczos), in [-1,1] -> `latents` -> `decoded` (decode of those latents). Skipped with a
  message when ../shared/assets is absent (the committed file then stays as it is).

Usage: python tools/make_vae_fixtures.py
Requires: torch, diffusers, safetensors, numpy, pillow.
"""
import json
import os
import sys

import numpy as np
import torch
from diffusers import AutoencoderKL, AutoencoderTiny
from PIL import Image
from safetensors.torch import load_file, save_file

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.join(HERE, "..")
OUT = os.path.join(ROOT, "fixtures", "vae")
ASSETS = os.path.join(ROOT, "..", "shared", "assets")
IMAGE_SHAPE = (2, 3, 24, 32)  # non-square so height/width mix-ups show


def gen(seed):
    return torch.Generator().manual_seed(seed)


def test_image(seed):
    """Smooth-ish image in [-1, 1]: a low-resolution random pattern upsampled bilinearly, plus fine noise."""
    coarse = torch.rand((IMAGE_SHAPE[0], 3, 6, 8), generator=gen(seed)) * 2 - 1
    smooth = torch.nn.functional.interpolate(coarse, size=IMAGE_SHAPE[2:], mode="bilinear", align_corners=False)
    fine = torch.rand(IMAGE_SHAPE, generator=gen(seed + 1)) * 0.4 - 0.2
    return (smooth + fine).clamp(-1, 1).contiguous()


def save(tensors, name):
    path = os.path.join(OUT, name)
    save_file({k: v.detach().float().contiguous() for k, v in tensors.items()}, path)
    print(f"wrote {os.path.relpath(path, ROOT)}: " + ", ".join(f"{k}{list(v.shape)}" for k, v in tensors.items()))


@torch.no_grad()
def kl_fixture(model_name, seed):
    vae = AutoencoderKL.from_pretrained(os.path.join(ROOT, "fixtures", "models", model_name, "vae"),
                                        torch_dtype=torch.float32).eval()
    image = test_image(seed)
    dist = vae.encode(image).latent_dist
    noise = torch.randn(dist.mean.shape, generator=gen(seed + 2))
    sample = dist.sample(generator=gen(seed + 2))
    assert torch.equal(sample, dist.mean + dist.std * noise), "diffusers' sample noise is not torch.randn"
    latents = torch.randn(dist.mean.shape, generator=gen(seed + 3))
    decoded = vae.decode(latents).sample
    save({"image": image, "mean": dist.mean, "logvar": dist.logvar, "noise": noise, "sample": sample,
          "latents": latents, "decoded": decoded}, f"kl-{model_name}.safetensors")


def randomise(model, seed, gain):
    """Replaces every parameter with N(0, gain²/fan_in) (biases N(0, 0.05²)) so all paths carry signal."""
    g = gen(seed)
    with torch.no_grad():
        for _, p in model.named_parameters():
            if p.dim() > 1:
                p.copy_(torch.randn(p.shape, generator=g) * gain / p[0].numel() ** 0.5)
            else:
                p.copy_(torch.randn(p.shape, generator=g) * 0.05)
    return model.eval()


def original_to_diffusers(encoder_sd, decoder_sd):
    """taesd.py keys -> diffusers keys: encoder indices are equal, the decoder's are shifted by its clamp (index 0)."""
    out = {f"encoder.layers.{k}": v for k, v in encoder_sd.items()}
    for k, v in decoder_sd.items():
        index, rest = k.split(".", 1)
        out[f"decoder.layers.{int(index) - 1}.{rest}"] = v
    return out


def diffusers_to_original(state_dict):
    enc, dec = {}, {}
    for k, v in state_dict.items():
        if k.startswith("encoder.layers."):
            enc[k[len("encoder.layers."):]] = v
        elif k.startswith("decoder.layers."):
            index, rest = k[len("decoder.layers."):].split(".", 1)
            dec[f"{int(index) + 1}.{rest}"] = v
        else:
            raise KeyError(k)
    return enc, dec


@torch.no_grad()
def taesd_references(model, seed, name):
    image = test_image(seed)
    latents = model.encode(image).latents
    decode_in = torch.randn(latents.shape, generator=gen(seed + 5)) * 2
    decoded = model.decode(decode_in).sample
    save({"image": image, "latents": latents, "decode_in": decode_in, "decoded": decoded}, name)


def tiny_taesd():
    torch.manual_seed(0)
    model = AutoencoderTiny(
        encoder_block_out_channels=(8, 8, 8),
        decoder_block_out_channels=(12, 12, 12),
        num_encoder_blocks=(1, 2, 1),
        num_decoder_blocks=(2, 1, 1),
        act_fn="silu",
        latent_channels=4,
    )
    randomise(model, 31, 1.0)
    folder = os.path.join(OUT, "tiny-taesd")
    model.save_pretrained(folder, safe_serialization=True)
    taesd_references(model, 40, "taesd-tiny.safetensors")

    torch.manual_seed(1)
    model = AutoencoderTiny(
        encoder_block_out_channels=(8, 8, 8),
        decoder_block_out_channels=(8, 8, 8),
        num_encoder_blocks=(1, 1, 2),
        num_decoder_blocks=(1, 2, 1),
        act_fn="relu",
        latent_channels=4,
    )
    randomise(model, 32, 1.0)
    bf16 = {k: v.to(torch.bfloat16) for k, v in model.state_dict().items()}
    model.load_state_dict({k: v.float() for k, v in bf16.items()})
    enc, dec = diffusers_to_original(bf16)
    # One file with encoder./decoder. prefixes: files named taesd_{encoder,decoder}.safetensors are the real
    # TAESD's (../shared/assets) and are never committed; the tests write the original layout to a temp dir.
    both = {**{"encoder." + k: v for k, v in enc.items()}, **{"decoder." + k: v for k, v in dec.items()}}
    save_file(both, os.path.join(OUT, "taesd-tiny-original-weights.safetensors"))
    taesd_references(model, 50, "taesd-tiny-original.safetensors")


def lego_image(name, size):
    rgba = np.asarray(Image.open(os.path.join(ASSETS, "lego-200", "train", name)).convert("RGBA"), dtype=np.float32)
    rgba /= 255.0
    rgb = rgba[..., :3] * rgba[..., 3:] + (1.0 - rgba[..., 3:])  # over white
    pil = Image.fromarray((rgb * 255.0 + 0.5).astype(np.uint8)).resize((size, size), Image.LANCZOS)
    return torch.from_numpy(np.asarray(pil, dtype=np.float32) / 127.5 - 1.0).permute(2, 0, 1)


@torch.no_grad()
def real_taesd():
    folder = os.path.join(ASSETS, "taesd")
    if not os.path.isdir(folder):
        print(f"skipping taesd-lego: {os.path.abspath(folder)} is absent")
        return
    enc = load_file(os.path.join(folder, "taesd_encoder.safetensors"))
    dec = load_file(os.path.join(folder, "taesd_decoder.safetensors"))
    model = AutoencoderTiny().eval()  # SD 1.x TAESD defaults
    model.load_state_dict({k: v.float() for k, v in original_to_diffusers(enc, dec).items()}, strict=True)
    image = torch.stack([lego_image("r_0.png", 128), lego_image("r_24.png", 128)])
    latents = model.encode(image).latents
    decoded = model.decode(latents).sample
    err = (decoded.clamp(-1, 1) - image).abs().mean().item()
    print(f"taesd-lego: latents std {latents.std():.3f}, mean |reconstruction error| {err:.4f} (in [-1,1] units)")
    save({"image": image, "latents": latents, "decoded": decoded}, "taesd-lego.safetensors")


def main():
    os.makedirs(OUT, exist_ok=True)
    torch.set_num_threads(max(1, os.cpu_count() or 1))
    kl_fixture("tiny-lcm", 100)
    kl_fixture("tiny-ip2p", 200)
    tiny_taesd()
    real_taesd()
    total = sum(os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(OUT) for f in fs)
    print(f"fixtures/vae: {total / 1e6:.2f} MB")
    if total > 3e6:
        sys.exit("fixtures/vae exceeds its 3 MB budget")


if __name__ == "__main__":
    main()
