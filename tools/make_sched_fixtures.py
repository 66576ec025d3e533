#!/usr/bin/env python3
"""Records reference LCM and DDIM scheduler behaviour from the real diffusers code for vcedit's tests.

Two LCM implementations are recorded:
- "current": the installed diffusers (LCMScheduler);
- "diffusers022": the LCMScheduler of diffusers 0.22.0, the release VcEdit pins. That release does not import
  with current torch/huggingface_hub, so only its scheduling_lcm.py is executed, with its package-relative
  imports pointed at the installed diffusers' (unchanged) ConfigMixin/SchedulerMixin helpers. The source is
  fetched with `pip install --no-deps --target <dir> diffusers==0.22.0` into DIFFUSERS022 (default
  /tmp/diffusers022) when missing.

Random noise is injected by replacing the module's randn_tensor with a function returning a recorded tensor,
so the Rust side can pass the same noise explicitly.

Writes fixtures/sched/reference.json (configs, alphas_cumprod checksums, timesteps for many step counts,
boundary scalings) and fixtures/sched/steps.safetensors (alphas_cumprod per config; per scenario the
sample, model outputs, noises and the step outputs).

Usage: python tools/make_sched_fixtures.py
"""
import json
import os
import subprocess
import sys
import types

import numpy as np
import torch
from safetensors.torch import save_file

import diffusers.schedulers.scheduling_ddim as ddim_mod
import diffusers.schedulers.scheduling_lcm as lcm_mod
from diffusers import DDIMScheduler, LCMScheduler

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.join(HERE, "..")
OUT = os.path.join(ROOT, "fixtures", "sched")
D022 = os.environ.get("DIFFUSERS022", "/tmp/diffusers022")


def load_lcm_022():
    src_path = os.path.join(D022, "diffusers", "schedulers", "scheduling_lcm.py")
    if not os.path.exists(src_path):
        subprocess.check_call([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--target", D022,
                               "diffusers==0.22.0"])
    with open(src_path, encoding="utf-8") as f:
        src = f.read()
    src = (src.replace("from ..configuration_utils import", "from diffusers.configuration_utils import")
              .replace("from ..utils.torch_utils import", "from diffusers.utils.torch_utils import")
              .replace("from ..utils import", "from diffusers.utils import")
              .replace("from .scheduling_utils import", "from diffusers.schedulers.scheduling_utils import"))
    module = types.ModuleType("scheduling_lcm_022")
    module.__file__ = src_path
    sys.modules[module.__name__] = module
    exec(compile(src, src_path, "exec"), module.__dict__)
    return module


LCM022 = load_lcm_022()

LCM_CONFIGS = {
    # The tiny-lcm / LCM_Dreamshaper_v7 configuration.
    "lcm_sd": dict(beta_start=0.00085, beta_end=0.012, beta_schedule="scaled_linear", num_train_timesteps=1000,
                   original_inference_steps=50, clip_sample=False, set_alpha_to_one=True, steps_offset=1,
                   prediction_type="epsilon", timestep_spacing="leading"),
    # Other parameterisations: v-prediction with clipping and a cosine schedule.
    "lcm_v_clip": dict(beta_schedule="squaredcos_cap_v2", num_train_timesteps=1000, original_inference_steps=25,
                       clip_sample=True, clip_sample_range=1.5, set_alpha_to_one=False,
                       prediction_type="v_prediction"),
    "lcm_sample_linear": dict(beta_start=0.0001, beta_end=0.02, beta_schedule="linear", num_train_timesteps=800,
                              original_inference_steps=40, prediction_type="sample"),
}

DDIM_CONFIGS = {
    # The tiny-ip2p / SD 1.5 configuration.
    "ddim_sd": dict(beta_start=0.00085, beta_end=0.012, beta_schedule="scaled_linear", num_train_timesteps=1000,
                    clip_sample=False, set_alpha_to_one=False, steps_offset=1, prediction_type="epsilon",
                    timestep_spacing="leading"),
    "ddim_trailing_zero_snr_v": dict(beta_start=0.00085, beta_end=0.012, beta_schedule="scaled_linear",
                                     timestep_spacing="trailing", rescale_betas_zero_snr=True,
                                     prediction_type="v_prediction", clip_sample=False),
    "ddim_linspace_clip_sample": dict(beta_schedule="linear", timestep_spacing="linspace", clip_sample=True,
                                      prediction_type="sample", set_alpha_to_one=True),
    "ddim_cosine_threshold": dict(beta_schedule="squaredcos_cap_v2", thresholding=True,
                                  dynamic_thresholding_ratio=0.9, sample_max_value=2.0, clip_sample=False),
}

STEP_COUNTS = [1, 2, 3, 4, 5, 7, 8, 10, 15, 16, 25, 49, 50]
STRENGTHS = [1.0, 0.75, 0.5]
SHAPE = (2, 4, 4, 4)


def lcm_cls(version):
    return LCM022.LCMScheduler if version == "diffusers022" else LCMScheduler


def lcm_module(version):
    return LCM022 if version == "diffusers022" else lcm_mod


def make_lcm(version, config):
    cfg = dict(config)
    if version == "diffusers022":
        cfg.pop("timestep_scaling", None)
    return lcm_cls(version)(**cfg)


def lcm_timesteps(version, config, original):
    out = []
    for steps in STEP_COUNTS:
        for strength in STRENGTHS:
            s = make_lcm(version, config)
            try:
                s.set_timesteps(steps, original_inference_steps=original, strength=strength)
                ts = [int(t) for t in s.timesteps]
            except (ValueError, IndexError, ZeroDivisionError):
                ts = None
            out.append({"steps": steps, "strength": strength, "original_inference_steps": original,
                        "timesteps": ts})
    return out


def run_lcm_loop(version, config, steps, gen, tensors, key):
    s = make_lcm(version, config)
    s.set_timesteps(steps)
    sample = torch.randn(SHAPE, generator=gen)
    tensors[f"{key}/sample"] = sample.clone()
    module = lcm_module(version)
    original_randn = module.randn_tensor
    try:
        for i, t in enumerate(s.timesteps):
            model_output = torch.randn(SHAPE, generator=gen)
            noise = torch.randn(SHAPE, generator=gen)
            module.randn_tensor = lambda *a, _n=noise, **k: _n.clone()
            prev, denoised = s.step(model_output, t, sample, return_dict=False)
            tensors[f"{key}/{i}/model_output"] = model_output
            tensors[f"{key}/{i}/noise"] = noise
            tensors[f"{key}/{i}/prev_sample"] = prev.contiguous()
            tensors[f"{key}/{i}/denoised"] = denoised.contiguous()
            sample = prev
    finally:
        module.randn_tensor = original_randn
    return [int(t) for t in s.timesteps]


def run_ddim_loop(config, steps, eta, use_clipped, gen, tensors, key):
    s = DDIMScheduler(**config)
    s.set_timesteps(steps)
    sample = torch.randn(SHAPE, generator=gen) * 1.5
    tensors[f"{key}/sample"] = sample.clone()
    for i, t in enumerate(s.timesteps):
        model_output = torch.randn(SHAPE, generator=gen)
        noise = torch.randn(SHAPE, generator=gen)
        out = s.step(model_output, t, sample, eta=eta, use_clipped_model_output=use_clipped,
                     variance_noise=noise if eta > 0 else None)
        tensors[f"{key}/{i}/model_output"] = model_output
        tensors[f"{key}/{i}/noise"] = noise
        tensors[f"{key}/{i}/prev_sample"] = out.prev_sample.contiguous()
        tensors[f"{key}/{i}/pred_original_sample"] = out.pred_original_sample.contiguous()
        sample = out.prev_sample
    return [int(t) for t in s.timesteps]


def main():
    os.makedirs(OUT, exist_ok=True)
    gen = torch.Generator().manual_seed(1234)
    tensors = {}
    ref = {"shape": list(SHAPE), "lcm": {}, "ddim": {}}

    for name, config in LCM_CONFIGS.items():
        entry = {"config": config, "variants": {}}
        tensors[f"alphas/{name}"] = make_lcm("current", config).alphas_cumprod.contiguous()
        for version in ("diffusers022", "current"):
            s = make_lcm(version, config)
            scalings = []
            for t in [0, 1, 19, 159, 500, 999]:
                c_skip, c_out = s.get_scalings_for_boundary_condition_discrete(torch.tensor(t))
                scalings.append({"t": t, "c_skip": float(c_skip), "c_out": float(c_out)})
            loops = {}
            for steps in (1, 4, 15) if name == "lcm_sd" else (3,):
                if steps > config.get("original_inference_steps", 50):
                    continue
                key = f"lcm/{name}/{version}/{steps}"
                loops[str(steps)] = {"key": key, "timesteps": run_lcm_loop(version, config, steps, gen, tensors, key)}
            entry["variants"][version] = {
                "final_alpha_cumprod": float(s.final_alpha_cumprod),
                "timesteps": lcm_timesteps(version, config, None)
                + (lcm_timesteps(version, config, 100) if name == "lcm_sd" else []),
                "scalings": scalings,
                "loops": loops,
            }
        ref["lcm"][name] = entry

    for name, config in DDIM_CONFIGS.items():
        s = DDIMScheduler(**config)
        tensors[f"alphas/{name}"] = s.alphas_cumprod.contiguous()
        timesteps = []
        for steps in STEP_COUNTS + [999, 1000]:
            s.set_timesteps(steps)
            timesteps.append({"steps": steps, "timesteps": [int(t) for t in s.timesteps]})
        loops = {}
        for eta, use_clipped in ((0.0, False), (1.0, False), (0.5, True)):
            key = f"ddim/{name}/eta{eta}/clipped{int(use_clipped)}"
            loops[key] = {"eta": eta, "use_clipped_model_output": use_clipped, "steps": 4,
                          "timesteps": run_ddim_loop(config, 4, eta, use_clipped, gen, tensors, key)}
        ref["ddim"][name] = {"config": config, "final_alpha_cumprod": float(s.final_alpha_cumprod),
                             "timesteps": timesteps, "loops": loops}

    # add_noise at a few timesteps (same for both schedulers; recorded once with the SD LCM config).
    s = LCMScheduler(**LCM_CONFIGS["lcm_sd"])
    x0 = torch.randn(SHAPE, generator=gen)
    noise = torch.randn(SHAPE, generator=gen)
    tensors["add_noise/x0"] = x0
    tensors["add_noise/noise"] = noise
    ref["add_noise_timesteps"] = [0, 159, 500, 999]
    for t in ref["add_noise_timesteps"]:
        tensors[f"add_noise/{t}"] = s.add_noise(x0, noise, torch.tensor([t])).contiguous()

    save_file({k: v.to(torch.float32).clone().contiguous() for k, v in tensors.items()},
              os.path.join(OUT, "steps.safetensors"))
    with open(os.path.join(OUT, "reference.json"), "w") as f:
        json.dump(ref, f, indent=1)
    print("wrote", os.path.abspath(OUT), len(tensors), "tensors")


if __name__ == "__main__":
    main()
