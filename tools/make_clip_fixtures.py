#!/usr/bin/env python3
"""Builds the CLIP conformance fixture for `edit::clip_score` with the real transformers package.

Writes fixtures/clip/:
- tiny-clip/: a randomly initialised `transformers.CLIPModel` with small dimensions, saved with
  `save_pretrained` (config.json with text_config/vision_config, model.safetensors), the tiny CLIP-format
  BPE tokenizer of fixtures/models/tiny-lcm (vocab.json + merges.txt + tokenizer_config.json; the real 49k
  vocabulary would make the fixture too big) and a preprocessor_config.json (CLIPImageProcessor).
- cases.safetensors: input images (float RGB in [0, 1], HWC, of sizes that exercise the shortest-side
  resize, the centre crop and the no-resize case), their preprocessed `pixel_values`, projected image
  embeddings (`get_image_features`), projected text embeddings of the prompts (`get_text_features`), and
  the per-view CLIP directional similarity.
- cases.json: the prompts, tensor names, and the mean directional similarity.

Preprocessing reference: `CLIPImageProcessor` (torchvision backend) applied to float tensors with
`do_rescale=False`, i.e. resize of the shortest side with antialiased bicubic, centre crop, normalisation
with the OpenAI mean/std. The script checks that a direct torch implementation gives the same values.

Directional similarity as in InstructPix2Pix / Instruct-NeRF2NeRF (`ClipSimilarity`): image and text
features are L2-normalised first, then cos(f_img(edited) - f_img(source), f_txt(target) - f_txt(source)).

Usage: python tools/make_clip_fixtures.py [--out fixtures/clip]
Requires: torch, transformers, safetensors.
"""
import argparse
import json
import os
import shutil

import torch
import torch.nn.functional as F
from safetensors.torch import save_file
from transformers import CLIPConfig, CLIPImageProcessor, CLIPModel, CLIPTokenizer

HERE = os.path.dirname(os.path.abspath(__file__))
TOKENIZER_SRC = os.path.join(HERE, "..", "fixtures", "models", "tiny-lcm", "tokenizer")

MEAN = [0.48145466, 0.4578275, 0.40821073]
STD = [0.26862954, 0.26130258, 0.27577711]


def smooth_image(gen, height, width):
    """A random image with structure at several scales (so resizing and cropping matter), values in [0, 1]."""
    coarse = torch.rand(1, 3, 4, 5, generator=gen)
    img = F.interpolate(coarse, size=(height, width), mode="bilinear", align_corners=False)
    img = img + 0.25 * (torch.rand(1, 3, height, width, generator=gen) - 0.5)
    return img.clamp(0, 1)[0]  # [3, H, W]


def reference_preprocess(img_chw, shortest, crop):
    """Shortest side -> `shortest` (antialiased bicubic, as torchvision on float tensors), centre crop, normalise."""
    _, h, w = img_chw.shape
    if h <= w:
        new_h, new_w = shortest, int(shortest * w / h)
    else:
        new_h, new_w = int(shortest * h / w), shortest
    x = img_chw[None]
    if (new_h, new_w) != (h, w):
        x = F.interpolate(x, size=(new_h, new_w), mode="bicubic", align_corners=False, antialias=True)
    top = int((new_h - crop) / 2.0)
    left = int((new_w - crop) / 2.0)
    x = x[:, :, top : top + crop, left : left + crop]
    mean = torch.tensor(MEAN).view(1, 3, 1, 1)
    std = torch.tensor(STD).view(1, 3, 1, 1)
    return (x - mean) / std


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default=os.path.join(HERE, "..", "fixtures", "clip"))
    args = ap.parse_args()
    torch.manual_seed(0)

    tokenizer = CLIPTokenizer(
        os.path.join(TOKENIZER_SRC, "vocab.json"), os.path.join(TOKENIZER_SRC, "merges.txt")
    )
    vocab_size = len(tokenizer)
    config = CLIPConfig(
        text_config=dict(
            vocab_size=vocab_size,
            hidden_size=32,
            intermediate_size=48,
            num_hidden_layers=2,
            num_attention_heads=4,
            max_position_embeddings=77,
            hidden_act="quick_gelu",
            bos_token_id=tokenizer.bos_token_id,
            eos_token_id=tokenizer.eos_token_id,
            pad_token_id=tokenizer.pad_token_id,
        ),
        vision_config=dict(
            hidden_size=24,
            intermediate_size=40,
            num_hidden_layers=2,
            num_attention_heads=3,
            image_size=32,
            patch_size=8,
            hidden_act="quick_gelu",
        ),
        projection_dim=16,
    )
    model = CLIPModel(config).eval()
    # Random init leaves LayerNorms at identity and biases at zero; perturb them so the test sees them.
    with torch.no_grad():
        for name, p in model.named_parameters():
            if name.endswith("bias") or "layer_norm" in name or "layrnorm" in name or "layernorm" in name:
                p.add_(0.1 * torch.randn_like(p))

    model_dir = os.path.join(args.out, "tiny-clip")
    if os.path.isdir(model_dir):
        shutil.rmtree(model_dir)
    model.save_pretrained(model_dir)
    for name in ["vocab.json", "merges.txt", "tokenizer_config.json"]:
        shutil.copy(os.path.join(TOKENIZER_SRC, name), os.path.join(model_dir, name))
    size = config.vision_config.image_size
    processor = CLIPImageProcessor(size={"shortest_edge": size}, crop_size={"height": size, "width": size})
    processor.save_pretrained(model_dir)

    gen = torch.Generator().manual_seed(1)
    # (height, width): wide (crop left/right), tall (crop top/bottom, odd margin), exact size, upsampling.
    shapes = [(40, 48), (57, 40), (32, 32), (20, 26)]
    sources = [smooth_image(gen, h, w) for h, w in shapes]
    edited = [(s + 0.3 * (smooth_image(gen, *s.shape[1:]) - 0.5)).clamp(0, 1) for s in sources]
    prompts = ["a photo of a man", "a photo of a clown", "a red cat wearing a hat", "a blue dog"]
    # Pairs (source prompt index, target prompt index) per view.
    prompt_pairs = [(0, 1), (2, 3), (0, 1), (2, 3)]

    tensors = {}
    with torch.no_grad():
        ids = tokenizer(prompts, padding="max_length", max_length=77, return_tensors="pt").input_ids
        text = model.get_text_features(input_ids=ids).pooler_output
        tensors["text_ids"] = ids.to(torch.int64)
        tensors["text_embeds"] = text.contiguous()
        directional = []
        for k, (src, edt) in enumerate(zip(sources, edited)):
            feats = []
            for tag, img in (("source", src), ("edited", edt)):
                ref = reference_preprocess(img, size, size)
                via_processor = processor(
                    images=img, do_rescale=False, return_tensors="pt"
                ).pixel_values
                diff = (ref - via_processor).abs().max().item()
                assert diff < 1e-5, f"reference preprocessing differs from CLIPImageProcessor by {diff}"
                f = model.get_image_features(pixel_values=ref).pooler_output
                tensors[f"{tag}_{k}_image"] = img.permute(1, 2, 0).contiguous()
                tensors[f"{tag}_{k}_pixel_values"] = ref[0].contiguous()
                tensors[f"{tag}_{k}_embeds"] = f[0].contiguous()
                feats.append(f / f.norm(dim=1, keepdim=True))
            s, t = prompt_pairs[k]
            ts = text[s : s + 1] / text[s : s + 1].norm(dim=1, keepdim=True)
            tt = text[t : t + 1] / text[t : t + 1].norm(dim=1, keepdim=True)
            directional.append(F.cosine_similarity(feats[1] - feats[0], tt - ts).item())
        tensors["directional"] = torch.tensor(directional, dtype=torch.float64)

    os.makedirs(args.out, exist_ok=True)
    save_file(tensors, os.path.join(args.out, "cases.safetensors"))
    meta = {
        "generator": "tools/make_clip_fixtures.py",
        "transformers_model": "CLIPModel (random init, perturbed norms and biases)",
        "prompts": prompts,
        "views": [
            {"height": h, "width": w, "source_prompt": prompt_pairs[k][0], "target_prompt": prompt_pairs[k][1]}
            for k, (h, w) in enumerate(shapes)
        ],
        "directional_mean": sum(directional) / len(directional),
    }
    with open(os.path.join(args.out, "cases.json"), "w") as f:
        json.dump(meta, f, indent=2)
    print(json.dumps(meta, indent=2))


if __name__ == "__main__":
    main()
