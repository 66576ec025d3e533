#!/usr/bin/env python3
"""Records reference outputs of the real transformers CLIP tokenizer and text encoder for vcedit's tests.

Writes under fixtures/text/:
- tokens-<name>.json for the tokenizers of fixtures/models/tiny-lcm (vocab.json + merges.txt),
  fixtures/models/tiny-ip2p (tokenizer.json, pad "!") and, when ../shared/assets/clip-bpe exists, the real
  CLIP vocabulary (49408 tokens). Per prompt of a varied corpus: the padded/truncated ids the pipelines feed
  the text encoder (max_length 77), the untruncated ids, the number of real tokens, the per-token strings
  (tokenizer.decode([id])) and the decoded text.
- encoder-<model>.safetensors for both tiny text encoders (run in float32): input ids [B, 77], the token
  embeddings, last_hidden_state, the pooled output and the hidden state with clip_skip = 1.

Usage: python tools/make_text_fixtures.py
Requires: torch, transformers (5.x), safetensors.
"""
import json
import os

import torch
from safetensors.torch import save_file
from transformers import CLIPTextModel, CLIPTokenizer

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.join(HERE, "..")
OUT = os.path.join(ROOT, "fixtures", "text")
MODELS = os.path.join(ROOT, "fixtures", "models")
REAL_BPE = os.path.join(ROOT, "..", "shared", "assets", "clip-bpe")
MAX_LEN = 77

LONG = ("a highly detailed photograph of a red fox sitting in a snowy forest at dawn, soft golden light, "
        "volumetric fog, 85mm lens, shallow depth of field, award-winning wildlife photography, trending on "
        "artstation, ultra realistic, 8k, sharp focus, intricate fur texture, cinematic composition, "
        "muted color palette, bokeh background with pine trees and falling snowflakes")

CORPUS = [
    "a photo of a cat",
    "Turn him into a clown",
    "a man wearing a hat",
    "A MAN WEARING A Striped Hat!!!",
    "grandma's wooden table, isn't it? they're here; we'll see... you'd've",
    "rock'n'roll 'quoted' \"double\" `back`",
    "numbers 3.14159 and 1,000,000 in 2024 or 42nd",
    "punctuation -- ... !? ?! (brackets) [square] {curly} <angle> a/b a\\b #tag @user $5 %20 ^_^ ~ | &",
    "multiple   spaces\tand\ttabs\nnew\nlines\r\nwindows  ",
    "   leading and trailing   ",
    "",
    "   ",
    "naïve café résumé Ünïcödé Straße ΣΟΦΙΑ ΟΔΟΣ İstanbul",
    "e\u0301 decomposed accent and cafe\u0301",
    "ﬁ ligature ½ fraction Ⅻ roman ² superscript ٣ arabic digit",
    "中文 日本語のテキスト 한국어 텍스트",
    "emoji 😀👍🏽🇫🇷 🐱‍👤 ❤️",
    "हिन्दी पाठ and ภาษาไทย and العربية",
    "spaces:\u00a0nbsp\u3000ideographic\u2028line\u0085nel\u200bzwsp",
    "control\x00chars\x07bell",
    "a<|endoftext|>b<|startoftext|>c <|ENDOFTEXT|>",
    "exclaim! twice!! thrice!!!",
    "the the the the",
    "photograph clowns hats spheres",
    " ".join(["a"] * 75),
    " ".join(["a"] * 76),
    LONG,
    LONG + " " + LONG,
]


def tokenizer_record(tok, name):
    cases = []
    for prompt in CORPUS:
        padded = tok(prompt, padding="max_length", max_length=MAX_LEN, truncation=True)
        full = tok(prompt).input_ids
        cases.append({
            "prompt": prompt,
            "ids": padded.input_ids,
            "num_tokens": int(sum(padded.attention_mask)),
            "full_ids": full,
            "token_strings": [tok.decode([i]) for i in full],
            "decoded": tok.decode(full),
            "decoded_skip_special": tok.decode(full, skip_special_tokens=True),
        })
    out = {
        "tokenizer": name,
        "transformers_class": type(tok).__name__,
        "max_length": MAX_LEN,
        "vocab_size": len(tok),
        "pad_token_id": tok.pad_token_id,
        "cases": cases,
    }
    path = os.path.join(OUT, f"tokens-{name}.json")
    with open(path, "w", encoding="utf-8") as f:
        json.dump(out, f, ensure_ascii=False, indent=0)
    print("wrote", path)


ENCODER_PROMPTS = [
    "a photo of a cat",
    "a man wearing a striped hat, photograph",
    "grandma's golden robot toy on a marble table",
    LONG,
]


def encoder_record(model_name):
    folder = os.path.join(MODELS, model_name)
    tok = CLIPTokenizer.from_pretrained(os.path.join(folder, "tokenizer"))
    model = CLIPTextModel.from_pretrained(os.path.join(folder, "text_encoder"), dtype=torch.float32).eval()
    ids = tok(ENCODER_PROMPTS, padding="max_length", max_length=MAX_LEN, truncation=True,
              return_tensors="pt").input_ids
    with torch.no_grad():
        out = model(ids, output_hidden_states=True)
        # diffusers' clip_skip = 1: the hidden state before the last layer, through the final LayerNorm.
        skip1 = model.final_layer_norm(out.hidden_states[-2])
        token_embeddings = model.get_input_embeddings()(ids)
    tensors = {
        "input_ids": ids.to(torch.int64).contiguous(),
        "token_embeddings": token_embeddings.contiguous(),
        "last_hidden_state": out.last_hidden_state.contiguous(),
        "pooler_output": out.pooler_output.contiguous(),
        "clip_skip_1": skip1.contiguous(),
    }
    path = os.path.join(OUT, f"encoder-{model_name}.safetensors")
    save_file(tensors, path, metadata={"prompts": json.dumps(ENCODER_PROMPTS)})
    print("wrote", path)


def main():
    os.makedirs(OUT, exist_ok=True)
    for name in ("tiny-lcm", "tiny-ip2p"):
        tok = CLIPTokenizer.from_pretrained(os.path.join(MODELS, name, "tokenizer"))
        tokenizer_record(tok, name)
        encoder_record(name)
    if os.path.isdir(REAL_BPE):
        tokenizer_record(CLIPTokenizer.from_pretrained(REAL_BPE), "clip-bpe")
    else:
        print("skipping the real vocabulary:", REAL_BPE, "is absent")


if __name__ == "__main__":
    main()
