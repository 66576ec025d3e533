#!/usr/bin/env python3
"""Reference InfEdit sampler on the tiny conformance model, for vcedit's conformance tests.

Written from the reference InfEdit implementation (sled-group/InfEdit: pipeline_ead.py's DDCM sampler,
app_infedit.py's AttentionRefine/LocalBlend controller, seq_aligner.get_mapper) on top of real diffusers
components (UNet2DConditionModel with a custom attention processor, AutoencoderKL, LCMScheduler) and
transformers (CLIPTextModel, CLIPTokenizer). Noise is drawn up front and saved, in the order the sampler
consumes it (VAE posterior sample, initial latents, one tensor per step), so the Rust side replays it.

One generalisation of the reference, needed because the tiny UNet is not SD 1.5: the local blend uses the
down/up cross-attention layers at the coarsest resolution that has them (for SD 1.5 at 512² these are exactly
the reference's `down_cross[2:4] + up_cross[:3]`, the 16x16 layers), averaged over layers and heads.

Records, per case: the settings, the noise, the input image, and after every step z_S, z_T, z_M, x̂0_T, x̂0_M
(after the local blend), plus the final decoded image, into fixtures/infedit/<case>.safetensors + cases.json.

Usage: python tools/make_infedit_fixtures.py   (needs torch, diffusers, transformers, safetensors)
"""
import json
import math
import os

import numpy as np
import torch
import torch.nn.functional as F
from diffusers import AutoencoderKL, LCMScheduler, UNet2DConditionModel
from safetensors.torch import save_file
from transformers import CLIPTextModel, CLIPTokenizer

HERE = os.path.dirname(os.path.abspath(__file__))
MODEL = os.path.join(HERE, "..", "fixtures", "models", "tiny-lcm")
OUT = os.path.join(HERE, "..", "fixtures", "infedit")
MAX_LEN = 77


# ---------------------------------------------------------------- token alignment (seq_aligner.get_mapper)
def nw_align(x, y):
    """Global alignment, gap 0, match 1, mismatch -1; tie order left, up, diagonal. Returns y->x mapper."""
    n, m = len(x), len(y)
    score = np.zeros((n + 1, m + 1), dtype=np.int64)
    trace = np.zeros((n + 1, m + 1), dtype=np.int64)
    trace[0, 1:] = 1
    trace[1:, 0] = 2
    trace[0, 0] = 4
    for i in range(1, n + 1):
        for j in range(1, m + 1):
            left = score[i, j - 1]
            up = score[i - 1, j]
            diag = score[i - 1, j - 1] + (1 if x[i - 1] == y[j - 1] else -1)
            best = max(left, up, diag)
            score[i, j] = best
            trace[i, j] = 1 if best == left else (2 if best == up else 3)
    out = []
    i, j = n, m
    while i > 0 or j > 0:
        code = trace[i, j]
        if code == 3:
            i, j = i - 1, j - 1
            out.append((j, i))
        elif code == 1:
            j -= 1
            out.append((j, -1))
        elif code == 2:
            i -= 1
        else:
            break
    out.reverse()
    return out


def get_mapper(tok, enc, src, tgt, local, mutual):
    x_seq, y_seq = tok.encode(src), tok.encode(tgt)
    e_seq, m_seq = tok.encode(local), tok.encode(mutual)
    base = nw_align(x_seq, y_seq)
    alphas = torch.ones(MAX_LEN)
    mapper = torch.zeros(MAX_LEN, dtype=torch.int64)
    for j, (_, s) in enumerate(base):
        alphas[j] = 0.0 if s == -1 else 1.0
        mapper[j] = s
    ly = len(y_seq)
    mapper[len(base):] = ly + torch.arange(MAX_LEN - ly)
    alpha_e = torch.zeros(MAX_LEN)
    alpha_m = torch.zeros(MAX_LEN)

    def hidden(text):
        ids = tok(text, padding="max_length", max_length=MAX_LEN, truncation=True, return_tensors="pt").input_ids
        return enc(ids)[0].squeeze(0)

    x_lat, y_lat = hidden(src), hidden(tgt)
    i = 0
    while i < ly:
        if alphas[i] == 0:
            start = i
            while alphas[i] == 0:
                i += 1
            best, best_s, best_t = -float("inf"), None, None
            for it in range(start, i):
                for is_ in range(int(mapper[start - 1]) + 1, int(mapper[i])):
                    # The reference compares the source hidden state at the target index with the target
                    # hidden state at the source index; kept as is.
                    sim = F.cosine_similarity(x_lat[it], y_lat[is_], dim=0)
                    if sim > best:
                        best, best_s, best_t = sim, is_, it
            if best_s is not None:
                mapper[best_t] = best_s
                alphas[best_t] = 1
                if x_seq[best_s] in e_seq:
                    alpha_e[best_t] = 1
        i += 1
    i, j = 1, 1
    while i < ly - 1 and j < len(e_seq) - 1:
        found = True
        while e_seq[j] != y_seq[i]:
            i += 1
            if i >= ly - 1:
                found = False
                break
        if found:
            alpha_e[i] = 1
        j += 1
    i, j = 1, 1
    while i < ly - 1 and j < len(m_seq) - 1:
        while m_seq[j] != y_seq[i]:
            i += 1
        if m_seq[j] == x_seq[mapper[i]]:
            alpha_m[i] = 1
            j += 1
        else:
            raise ValueError("mutual words not in source")
    return mapper, alphas, alpha_e, alpha_m, ly


# ---------------------------------------------------------------- controller (AttentionRefine + LocalBlend)
class Controller:
    def __init__(self, mapper, alphas, alpha_e, alpha_m, t_len, num_steps, start_steps, cross, self_, blend_hw,
                 thresh_e, thresh_m):
        self.mapper, self.alphas = mapper, alphas
        self.alpha_e, self.alpha_m = alpha_e, alpha_m
        self.alpha_me = (alpha_e.bool() & alpha_m.bool()).float()
        self.t_len = t_len
        self.num_steps, self.start_steps = num_steps, start_steps
        self.cross, self.self_ = cross, self_
        self.blend_hw = blend_hw
        self.thresh_e, self.thresh_m = thresh_e, thresh_m
        self.cur_step = 0
        self.store = {}  # layer name -> summed [2*heads, N, 77]

    def progress(self):
        return (self.cur_step + self.start_steps + 1) / self.num_steps

    def self_qkv(self, q, k, v, heads):
        # q/k/v: [6*heads, N, d] in [S_u, T_u, M_u, S_c, T_c, M_c] order.
        def pick(x, idx):
            return torch.cat([x[b * heads:(b + 1) * heads] for b in idx])
        if self.self_ <= self.progress():
            qi, ki, vi = [0, 1, 1, 3, 4, 4], [0, 1, 0, 3, 4, 3], [0, 1, 0, 3, 4, 3]
        else:
            qi, ki, vi = [0, 0, 0, 3, 3, 3], [0, 0, 0, 3, 3, 3], [0, 1, 0, 3, 4, 3]
        return pick(q, qi), pick(k, ki), pick(v, vi)

    def refine(self, base, target):
        return base[:, :, self.mapper] * self.alphas + target * (1 - self.alphas)

    def cross_probs(self, name, probs, heads, hw):
        b = probs.shape[0] // heads
        cond = probs[(b // 2) * heads:].reshape(3, heads, *probs.shape[1:])
        a_s, a_t, a_m = cond[0], cond[1], cond[2]
        ref_s = self.refine(a_s, a_t)
        ref_m = self.refine(a_m, a_t)
        new_t = ref_s if self.cross >= self.progress() else a_t
        if hw == self.blend_hw and not name.startswith("mid"):
            st = torch.cat([ref_s, ref_m])
            self.store[name] = self.store[name] + st if name in self.store else st
        new_cond = torch.stack([a_s, new_t, a_m]).reshape(3 * heads, *probs.shape[1:])
        return torch.cat([probs[:(b // 2) * heads], new_cond])

    def blend(self, i, x_s, x_t, x_m, alpha_prod):
        tau_e = max(0.15 / alpha_prod ** 0.5, self.thresh_e)
        maps = []
        for name in sorted(self.store, key=lambda n: self.order.index(n)):
            s = self.store[name]
            h2 = s.shape[0] // 2
            maps.append(s.reshape(2, h2, 1, self.blend_hw[0], self.blend_hw[1], MAX_LEN))
        maps = torch.cat(maps, dim=1)
        maps_s, maps_m = maps[0], maps[1]

        def mask(m, ind, th):
            m = m * ind.reshape(1, 1, 1, 1, -1)
            m = m[:, :, :, :, 1:self.t_len - 1].mean(0, keepdim=True).max(-1)[0]
            m = F.interpolate(m, size=x_t.shape[2:])
            m = m / m.max(2, keepdim=True)[0].max(3, keepdim=True)[0]
            return m > th
        mask_e = mask(maps_m, self.alpha_e, tau_e)
        mask_m = mask(maps_s, self.alpha_m - self.alpha_me, self.thresh_m)
        mask_me = mask(maps_m, self.alpha_me, self.thresh_e)
        out = x_t if self.alpha_e.sum() == 0 else torch.where(mask_e, x_t, x_m)
        out = torch.where(mask_m, x_s, out)
        if self.cur_step + self.start_steps + 1 == self.num_steps:
            out = torch.where(mask_me, x_m, out)
        return out


class Processor:
    def __init__(self, ctrl, name):
        self.ctrl, self.name = ctrl, name

    def __call__(self, attn, hidden_states, encoder_hidden_states=None, attention_mask=None, temb=None, **kw):
        is_cross = encoder_hidden_states is not None
        ctx = encoder_hidden_states if is_cross else hidden_states
        b, n, _ = hidden_states.shape
        hw = self.ctrl.sizes[self.name]
        q = attn.head_to_batch_dim(attn.to_q(hidden_states))
        k = attn.head_to_batch_dim(attn.to_k(ctx))
        v = attn.head_to_batch_dim(attn.to_v(ctx))
        if not is_cross:
            q, k, v = self.ctrl.self_qkv(q, k, v, attn.heads)
        probs = attn.get_attention_scores(q, k, None)
        if is_cross:
            probs = self.ctrl.cross_probs(self.name, probs, attn.heads, hw)
        out = attn.batch_to_head_dim(torch.bmm(probs, v))
        out = attn.to_out[1](attn.to_out[0](out))
        return out


def attn_sizes(unet, latent_hw):
    """Spatial size of each attention module, from a probe pass with hooks."""
    sizes = {}
    handles = []
    for name, mod in unet.named_modules():
        if mod.__class__.__name__ == "Attention":
            def hook(m, args, kwargs, name=name):
                hs = args[0] if args else kwargs["hidden_states"]
                sizes[name] = hs.shape[1]
            handles.append(mod.register_forward_pre_hook(hook, with_kwargs=True))
    with torch.no_grad():
        unet(torch.zeros(1, 4, *latent_hw), 1, encoder_hidden_states=torch.zeros(1, MAX_LEN, unet.config.cross_attention_dim))
    for h in handles:
        h.remove()
    out = {}
    for name, n in sizes.items():
        # Reduce the latent grid until it has n cells.
        h, w = latent_hw
        while h * w > n:
            h, w = (h + 1) // 2, (w + 1) // 2
        out[name] = (h, w)
    return out


def blend_hw(unet, latent_hw):
    h, w = latent_hw
    size = latent_hw
    types = unet.config.down_block_types
    for i, t in enumerate(types):
        if "CrossAttn" in t:
            size = (h, w)
        if i + 1 < len(types):
            h, w = (h + 1) // 2, (w + 1) // 2
    return size


# ---------------------------------------------------------------- sampler (pipeline_ead + ddcm_sampler)
def run_case(case, parts):
    tok = CLIPTokenizer.from_pretrained(os.path.join(MODEL, "tokenizer"))
    enc = CLIPTextModel.from_pretrained(os.path.join(MODEL, "text_encoder")).eval()
    unet = UNet2DConditionModel.from_pretrained(os.path.join(MODEL, "unet")).eval()
    vae = AutoencoderKL.from_pretrained(os.path.join(MODEL, "vae")).eval()
    sched = LCMScheduler.from_pretrained(os.path.join(MODEL, "scheduler"))

    steps = case["steps"]
    size = case["size"]
    f = 2 ** (len(vae.config.block_out_channels) - 1)
    latent_hw = (size // f, size // f)
    g = torch.Generator().manual_seed(case["seed"])

    # Input image: a smooth deterministic pattern in [-1, 1].
    yy, xx = torch.meshgrid(torch.linspace(-1, 1, size), torch.linspace(-1, 1, size), indexing="ij")
    image = torch.stack([torch.sin(3 * xx + case["seed"]), torch.cos(2 * yy), xx * yy], 0)[None].clamp(-1, 1)

    # diffusers 0.22's LCM timestep selection (what VcEdit pins): every `skip`-th of the reversed origin steps.
    c = sched.config.num_train_timesteps // 50
    origin = np.asarray(list(range(1, 51))) * c - 1
    skip = len(origin) // steps
    full = origin[::-1][::skip][:steps].copy()
    strength = case.get("strength")
    start = 0 if strength is None else steps - min(int(steps * strength), steps)
    timesteps = full[start:]
    acp = sched.alphas_cumprod

    with torch.no_grad():
        def embed(text):
            ids = tok(text, padding="max_length", max_length=MAX_LEN, truncation=True, return_tensors="pt").input_ids
            return enc(ids)[0]
        src_c, tgt_c = embed(case["source"]), embed(case["target"])
        src_u, tgt_u = embed(case.get("positive", "")), embed(case.get("negative", ""))
        cfg = case["guidance_target"] > 1.0
        assert cfg, "the reference sampler needs CFG"
        ctx = torch.cat([src_u, tgt_u, src_u, src_c, tgt_c, src_c])

        mapper, alphas, alpha_e, alpha_m, t_len = get_mapper(
            tok, enc, case["source"], case["target"], case["target_blend"], case.get("source_blend", ""))
        ctrl = Controller(mapper, alphas, alpha_e, alpha_m, t_len, steps, start, case["cross"], case["self"],
                          blend_hw(unet, latent_hw), case["thresh_e"], case["thresh_m"])
        ctrl.sizes = attn_sizes(unet, latent_hw)
        ctrl.order = [n for n, _ in unet.named_modules() if n in ctrl.sizes]
        unet.set_attn_processor({n + ".processor": Processor(ctrl, n) for n in ctrl.sizes})

        noises = []

        def randn(shape):
            n = torch.randn(shape, generator=g)
            noises.append(n)
            return n

        post = vae.encode(image).latent_dist
        x0 = (post.mean + post.std * randn(post.mean.shape)) * vae.config.scaling_factor
        init = randn(x0.shape)
        if strength is None:
            z = init
        else:
            a = acp[int(timesteps[0])]
            z = a.sqrt() * x0 + (1 - a).sqrt() * init
        zs = zt = zm = z
        gs, gt, eta = case["guidance_source"], case["guidance_target"], case["eta"]
        rec = {}
        for i, t in enumerate(timesteps):
            t = int(t)
            inp = torch.cat([zs, zt, zm, zs, zt, zm])
            out = unet(inp, t, encoder_hidden_states=ctx).sample
            ctrl.cur_step += 1
            su, tu, mu, sc, tc, mc = out.chunk(6)
            es, et, em = su + gs * (sc - su), tu + gt * (tc - tu), mu + gs * (mc - mu)
            n = randn(zt.shape)
            a_t = acp[t]
            idx = list(full).index(t)
            a_prev = acp[int(full[idx + 1])] if idx + 1 < len(full) else a_t

            def ddcm(x_s, x_b, e_s, e_b):
                b_t, b_prev = 1 - a_t, 1 - a_prev
                var = eta * b_prev
                e_c = (x_s - a_t ** 0.5 * x0) / b_t ** 0.5
                pred = x0 + ((x_b - x_s) - b_t ** 0.5 * (e_b - e_s)) / a_t ** 0.5
                dirx = (b_prev - var) ** 0.5 * ((e_b - e_s) + e_c)
                noise = var ** 0.5 * n
                if len(full) > 1:
                    return a_prev ** 0.5 * x0 + dirx + noise, a_prev ** 0.5 * pred + dirx + noise, pred
                return x0, pred, pred
            _, zt_new, pred_t = ddcm(zs, zt, es, et)
            zs_new, zm_new, pred_m = ddcm(zs, zm, es, em)
            zs, zt, zm = zs_new, zt_new, zm_new
            if i > 0:
                zt = ctrl.blend(i, zs, zt, zm, a_t)
            for key, val in (("z_s", zs), ("z_t", zt), ("z_m", zm), ("pred_t", pred_t), ("pred_m", pred_m)):
                rec[f"step{i}_{key}"] = val.contiguous()
        decoded = (vae.decode(pred_t / vae.config.scaling_factor).sample / 2 + 0.5).clamp(0, 1)

    tensors = {f"noise{k}": v.contiguous() for k, v in enumerate(noises)}
    tensors.update(rec)
    tensors["image"] = image.contiguous()
    tensors["decoded"] = decoded.contiguous()
    tensors["alphas"] = alphas.contiguous()
    tensors["alpha_e"] = alpha_e.contiguous()
    tensors["mapper"] = mapper.to(torch.int64).contiguous()
    save_file(tensors, os.path.join(OUT, f"{case['name']}.safetensors"))
    parts.append(dict(case, timesteps=[int(t) for t in timesteps], blend_hw=list(ctrl.blend_hw)))


CASES = [
    dict(name="man_clown", source="a man", target="a clown", target_blend="clown"),
    dict(name="cat_dog_hat", source="a photo of a cat", target="a photo of a dog wearing a hat",
         target_blend="dog wearing a hat"),
    dict(name="reorder_whole_blend", source="a red striped vase on a table",
         target="a table with a green vase", target_blend="a table with a green vase"),
    dict(name="mutual_words", source="a red sphere on the floor", target="a blue sphere on the floor",
         target_blend="blue", source_blend="floor", cross=1.0, self=0.0),
    dict(name="denoise_eta", source="a dog", target="a lion", target_blend="lion", strength=0.6, eta=0.5,
         steps=6),
]


def main():
    os.makedirs(OUT, exist_ok=True)
    parts = []
    for c in CASES:
        case = dict(steps=8, size=64, seed=3, guidance_source=1.0, guidance_target=2.0, cross=0.7, self=0.3,
                    thresh_e=0.6, thresh_m=0.6, eta=1.0)
        case.update(c)
        run_case(case, parts)
    with open(os.path.join(OUT, "cases.json"), "w") as fh:
        json.dump(parts, fh, indent=1)
    print("wrote", len(parts), "cases to", os.path.abspath(OUT))


if __name__ == "__main__":
    main()
