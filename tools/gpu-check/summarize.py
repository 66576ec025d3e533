#!/usr/bin/env python3
"""Collects tools/gpu-check/run.sh's step outputs into $OUT/gpu-check.json and $OUT/gpu-check.md.

Run after every step (so a call cut short still returns what it measured). Inputs, in the work folder:
steps.jsonl (one line per step: status, rc, seconds), STEP.out (each bench's `RESULT {json}` lines and other
stdout), build.json (the commit the binary was built from), edit-run.json (the editing slice's run.json).

The JSON: `machine`, `adapter`, `build`, `steps` (status and seconds of each), `results` (every RESULT line
by step), `table` (the headline rows: vcedit next to PyTorch, with their ratio), `edit_slice` (its stages
and the paper-scale estimate), `complete` (every step ran and passed).
"""
import argparse
import datetime
import json
import os
import re


def read_results(path):
    out = []
    if os.path.exists(path):
        for line in open(path, errors="replace"):
            if line.startswith("RESULT "):
                try:
                    out.append(json.loads(line[len("RESULT "):]))
                except json.JSONDecodeError:
                    pass
    return out


def find(results, **want):
    for r in results:
        if all(r.get(k) == v for k, v in want.items()):
            return r
    return None


def machine_info(work):
    text = open(os.path.join(work, "machine.out"), errors="replace").read() if os.path.exists(
        os.path.join(work, "machine.out")) else ""
    info = {}
    m = re.search(r"^name, memory.total.*\n(.+)$", text, re.M)
    if m:
        parts = [p.strip() for p in m.group(1).split(",")]
        keys = ["gpu", "memory_total", "driver", "sm_clock_max", "mem_clock_max", "power_limit"]
        info.update(dict(zip(keys, parts)))
    for key in ("deviceName", "driverName", "driverInfo", "apiVersion", "deviceType"):
        m = re.search(rf"^\s*{key}\s*=\s*(.+)$", text, re.M)
        if m:
            info[f"vulkan_{key}"] = m.group(1).strip()
    m = re.search(r"model name\s*:\s*(.+)", text)
    if m:
        info["cpu"] = m.group(1).strip()
    m = re.search(r"^-- cpu\n(\d+)", text, re.M)
    if m:
        info["cpu_threads"] = int(m.group(1))
    return info


def iteration_stages(times):
    """One run.json `iterations` entry as {stage name: seconds} (the names of run.json's `timings`)."""
    s = times.get("sampler", {})
    stages = {"render": times.get("render", 0), "encode": s.get("encode", 0), "CCM": s.get("ccm", 0),
              "UNet passes": s.get("unet", 0), "ECM": s.get("ecm", 0), "blend-map consistency": s.get("blend", 0),
              "decode": s.get("decode", 0), "fit": times.get("fit", 0)}
    # Parts of CCM and ECM (run.json has them since 2026-11-28): not stages of their own.
    if "ccm_lifting" in s:
        stages["of CCM: lifting"] = s["ccm_lifting"]
    if "ecm_fits" in s:
        stages["of ECM: fits"] = s["ecm_fits"]
    return stages


def paper_estimate(run):
    """Seconds of a paper-scale edit (96 views, 15 steps, CCM at 2 and ECM at 3 of them, 2 iterations),
    scaled stage by stage from one iteration of the slice's run.json: the last one, which is warm (the
    first pays for compiling every GPU kernel it meets, ~30 s on an H200, whichever stage meets it
    first). Stages that grow with views and steps are scaled by both; the fit, whose step count is fixed,
    not at all."""
    iterations = run.get("iterations", [])
    if iterations:
        t = iteration_stages(iterations[-1])
    else:
        t = {s["stage"]: s["seconds"] for s in run.get("timings", [])}
    settings = run.get("settings", {})
    views = max(len(run.get("views", [])), 1)
    steps = max(settings.get("infedit", {}).get("steps") or 2, 1)
    consistency = settings.get("consistency", {})
    ccm_steps = max(len(consistency.get("ccm_steps") or [0]), 1)
    ecm_steps = max(len((consistency.get("ecm") or {}).get("steps") or [1]), 1)
    r = 96 / views

    def total(ecm_views_factor):
        # Where run.json splits ECM, its fits (a fixed number of steps) stay and the rest (decoding,
        # rendering and encoding every view) scales with the views: one estimate instead of a range.
        ecm, fits = t.get("ECM", 0), t.get("of ECM: fits")
        ecm_scaled = fits + (ecm - fits) * r if fits is not None else ecm * ecm_views_factor
        per_iteration = (
            t.get("render", 0) * r
            + t.get("encode", 0) * r
            + t.get("UNet passes", 0) * r * 15 / steps
            + t.get("blend-map consistency", 0) * r * 15 / steps
            + t.get("CCM", 0) * r * 2 / ccm_steps
            + ecm_scaled * 3 / ecm_steps
            + t.get("decode", 0) * r
            + t.get("fit", 0)
        )
        return round(2 * per_iteration, 1)

    # An ECM step fits a fixed number of Adam steps (576) but renders and encodes every view: without the
    # split, its time lies between "independent of the views" and "proportional to them".
    return {"views": views, "steps": steps, "iterations": len(iterations), "ccm_steps": ccm_steps,
            "estimated_from": "last iteration" if len(iterations) > 1 else "the only iteration (with kernel compilation)",
            "per_iteration_s": [{k: round(v, 2) for k, v in iteration_stages(it).items()} for it in iterations],
            "ecm_steps": ecm_steps, "estimate_96_views_15_steps_2_iterations_s": [total(1), total(r)]}


# The work ledger's units per stage (run.json's `work`, summed over iterations), the ones a stage's time
# is read against: UNet samples, lifting rounds, fit steps, codec passes, and on a GPU the kernel launches
# and device reads.
WORK_UNITS = ("unet_samples", "lifting_rounds", "render_backs", "fit_steps", "vae_encodes", "vae_decodes",
              "launches", "device_reads", "device_read_bytes")


def work_per_stage(run):
    work = run.get("work") or {}
    return {stage: {k: v for k, v in units.items() if k in WORK_UNITS and v}
            for stage, units in work.items() if isinstance(units, dict) and any(units.values())}


def describe_work(work):
    parts = []
    for stage, units in work.items():
        named = ", ".join(f"{v} {k.replace('_', ' ')}" for k, v in units.items() if k != "device_read_bytes")
        if "device_read_bytes" in units:
            named += f" ({units['device_read_bytes'] / 1e6:.1f} MB read)"
        parts.append(f"{stage}: {named}")
    return "; ".join(parts)


# The runtimes a core step runs on (run.sh's `on_runtimes`): wgpu under the step's own name, CUDA as
# NAME-cuda; the label goes into the row's name.
RUNTIME_STEPS = (("", ""), ("-cuda", ", CUDA"))


def on_runtimes(res, name):
    """(results, label) of step `name` on each runtime that ran it."""
    return [(res.get(name + suffix, []), label) for suffix, label in RUNTIME_STEPS if name + suffix in res]


def fmt_s(v):
    if v is None:
        return None
    return f"{v * 1e3:.2f} ms" if v < 1 else f"{v:.2f} s"


def ratio(a, b):
    return round(a / b, 2) if a and b else None


def build_table(res, steps, mode, torch_present, work):
    rows = []
    torch_missing = "n/a (no PyTorch here)" if not torch_present else None

    def row(what, ours, theirs=None, first=None, note="", torch_expected=True):
        rows.append({
            "what": what,
            "vcedit": ours,
            "vcedit_first_call": first,
            "pytorch": theirs if theirs is not None else (torch_missing if torch_expected else None),
            "ratio_vcedit_over_pytorch": None,
            "note": note,
        })
        return rows[-1]

    mt = res.get("matmul-torch", [])
    # vcedit's default path (SPIR-V, tensor cores where the card has them), then the WGSL path (A/B).
    for step_name in ("matmul-cuda", "matmul", "matmul-wgsl"):
        for r in [x for x in res.get(step_name, []) if x.get("what") == "linear"]:
            shape = f"{r['m']}x{r['k']}x{r['n']}"
            t = find(mt, precision=r["precision"], m=r["m"], k=r["k"], n=r["n"])
            path = r.get("path", "unit")
            arithmetic = "f16 operands, f32 sums" if path in ("tensor-cores", "unit-f16") else "f32 arithmetic"
            err = f"; rel. error vs CPU f32 {r['rel_err']:.1e}" if r.get("rel_err") is not None else ""
            line = row(f"matmul {shape}, {r['precision']} weights, {path}, {r.get('compiler', '?')} (TFLOP/s)",
                       r.get("tflops"), t.get("tflops") if t else None, fmt_s(r.get("first_s")),
                       f"{arithmetic}{err}")
            if t:
                line["ratio_vcedit_over_pytorch"] = ratio(r["ms"], t["ms"])
                line["pytorch_tf32"] = (find(mt, precision="tf32", m=r["m"], k=r["k"], n=r["n"]) or {}).get("tflops")
    at = res.get("attention-torch", [])
    for r in [x for x in res.get("attention-cuda", []) + res.get("attention", []) if x.get("bench") == "attention"]:
        shape = f"{r['entries']}x{r['queries']}x{r['keys']}x{r['dim']}"
        t = find(at, entries=r["entries"], queries=r["queries"], keys=r["keys"], dim=r["dim"])
        err = f"; rel. error vs CPU f32 {r['rel_err']:.1e}" if r.get("rel_err") is not None else ""
        line = row(f"attention {shape}, {r['path']} ({r.get('matmul_path', '?')} products), "
                   f"{r.get('compiler', '?')} (ms)", r.get("ms"), t.get("ms") if t else None,
                   fmt_s(r.get("first_s")), f"PyTorch: fp16 SDPA{err}")
        line["ratio_vcedit_over_pytorch"] = ratio(r.get("ms"), t.get("ms") if t else None)
    for r in [x for x in res.get("matmul-routines-cuda", []) + res.get("matmul-routines", [])
              if x.get("bench") == "matmul"]:
        shape = f"{r['m']}x{r['k']}x{r['n']}"
        t = find(mt, precision="f16", m=r["m"], k=r["k"], n=r["n"])
        what = "" if r.get("what") == "linear" else ", activations × activations"
        line = row(f"matmul {shape}{what}, f16 weights, routine {r.get('routine')} (ran as {r.get('route')}), "
                   f"{r.get('compiler', '?')} (TFLOP/s)",
                   r.get("tflops"), t.get("tflops") if t else None, fmt_s(r.get("first_s")),
                   f"rel. error vs CPU f32 {r['rel_err']:.1e}" if r.get("rel_err") is not None else "")
        if t:
            line["ratio_vcedit_over_pytorch"] = ratio(r["ms"], t["ms"])
    for r in [x for x in res.get("matmul-tilings", []) if x.get("bench") == "matmul" and x.get("tiling")]:
        shape = f"{r['m']}x{r['k']}x{r['n']}"
        t = find(mt, precision="f16", m=r["m"], k=r["k"], n=r["n"])
        taken = "" if r.get("tiled") or r.get("tiling") == "default" else ", not taken"
        line = row(f"matmul {shape}, f16 weights, {r.get('route')}, tiling {r.get('tiling')}{taken} (TFLOP/s)",
                   r.get("tflops"), t.get("tflops") if t else None, fmt_s(r.get("first_s")),
                   f"rel. error vs CPU f32 {r['rel_err']:.1e}" if r.get("rel_err") is not None else "")
        if t:
            line["ratio_vcedit_over_pytorch"] = ratio(r["ms"], t["ms"])
    ut, ut32 = res.get("unet-torch", []), res.get("unet-torch-f32", [])
    # The routine and tiling run.sh chose for `unet-routine` / `unet-tiling` (the fastest of
    # `matmul-routines` / `matmul-tilings`).
    def chosen(name):
        path = os.path.join(work, name)
        return open(path).read().strip() if os.path.exists(path) else "?"
    for step_name, label in (("unet-cuda", ", CUDA"), ("unet", ""),
                             ("unet-tasks", ", 256 tasks per submission, 2nd process"),
                             ("unet-flash", ", flash attention for every head"), ("unet-wgsl", ", WGSL"),
                             ("unet-routine", f", routine {chosen('unet-routine.name')}"),
                             ("unet-tiling", f", tiling {chosen('unet-tiling.name')}")):
        for r in res.get(step_name, []):
            t = find(ut, batch=r["batch"])
            err = f"; rel. error vs CPU {r['rel_err']:.1e}" if r.get("rel_err") is not None else ""
            line = row(f"UNet forward, batch {r['batch']}, hook {r['hook']}{label} (s)", r.get("best_s"),
                       t.get("best_s") if t else None, fmt_s(r.get("first_s")),
                       "PyTorch: fp16 + SDPA, no hook" + (", same weights" if mode == "device" else "") + err)
            line["ratio_vcedit_over_pytorch"] = ratio(r.get("best_s"), t.get("best_s") if t else None)
            t32 = find(ut32, batch=r["batch"])
            if t32:
                line["pytorch_f32"] = t32.get("best_s")
    ct = res.get("codec-torch", [])
    for cd, rt in on_runtimes(res, "codec"):
        for r in cd:
            t = find(ct, what=r["what"])
            line = row(f"AutoencoderKL {r['what']}, {r['size']}²{rt} (s)", r.get("best_s"),
                       t.get("best_s") if t else None, fmt_s(r.get("first_s")))
            line["ratio_vcedit_over_pytorch"] = ratio(r.get("best_s"), t.get("best_s") if t else None)
    tt = res.get("text-torch", [])
    for tx, rt in on_runtimes(res, "text"):
        for r in [x for x in tx if x.get("what") == "encode"]:
            t = find(tt, batch=r["batch"])
            line = row(f"CLIP text encoder, batch {r['batch']}{rt} (s)", r.get("best_s"),
                       t.get("best_s") if t else None, fmt_s(r.get("first_s")))
            line["ratio_vcedit_over_pytorch"] = ratio(r.get("best_s"), t.get("best_s") if t else None)
    for name, where in (("lpips-cuda", "gpu, CUDA"), ("lpips", "gpu"), ("lpips-cpu", "cpu")):
        for r in res.get(name, []):
            if r.get("bench") != "lpips":
                continue
            row(f"LPIPS-VGG16 {r['what']}, {r['size']}², {where} (s)", r.get("best_s"), None,
                fmt_s(r.get("first_s")), "full width, generated weights; f32", torch_expected=False)
    for r in [x for x in res.get("overhead-cuda", []) + res.get("overhead", []) if x.get("bench") == "overhead"]:
        for key, what in (("launch_us", "launch of a one-element kernel (µs)"),
                          ("round_trip_us", "launch + 4-byte read, waited for (µs)"),
                          ("read_mib_ms", "1 MiB read back (ms)"),
                          ("fill_reused_us", "16 MiB fill, same buffer (µs)"),
                          ("fill_fresh_us", "16 MiB fill, fresh buffer of a new size (µs)"),
                          ("sort_60k_ms", "radix sort of 60k pairs by 32-bit keys + read (ms)")):
            row(f"host overhead: {what}, {r.get('compiler', '?')}", r.get(key), None, None,
                "what the host costs around kernels", torch_expected=False)
    wheres = {"lift-cuda": "gpu, CUDA", "lift": "gpu",
              "lift-pixels": "gpu, per pixel and rendered back densely (as before 2026-11-28)", "lift-cpu": "cpu"}
    for name, where in wheres.items():
        for r in res.get(name, []):
            if r.get("bench") != "lift":
                continue
            row(f"CCM lifting round, {r['what']}, {r['views']} views at {r['size']}², {r['channels']} channels, "
                f"{where} (s)", r.get("best_s"), None, fmt_s(r.get("first_s")),
                f"{r['gaussians'] // 1000}k Gaussians, {r['grid']}² maps", torch_expected=False)
    for name, rt in (("splat-cuda", ", CUDA"), ("splat", ""), ("splat-cpu", "")):
        for r in res.get(name, []):
            if r.get("bench") != "render":
                continue
            first = r.get("first_ms")
            n = r["gaussians"]
            count = f"{n // 1_000_000}M" if n >= 1_000_000 and n % 1_000_000 == 0 else f"{n // 1000}k"
            row(f"splat {r['stage']}, {count}, {r['width']}x{r['height']}, {r['device']}{rt} (ms)",
                r.get("median_ms"), None, f"{first:.1f} ms" if first is not None else None,
                torch_expected=False)
    for name, rt in (("fit-cuda", ", CUDA"), ("fit", "")):
        fit = steps.get(name, {})
        if fit.get("psnr") is not None:
            row(f"vcedit fit lego-200{rt} (s; held-out PSNR dB)", fit.get("seconds"), None, None,
                f"{fit['psnr']:.2f} dB, {fit.get('gaussians')} Gaussians"
                + (f"; {fit['reads']} device reads waited {fit['wait']:.1f} s" if "wait" in fit else ""),
                torch_expected=False)
    for name, rt in (("check-cuda", "CUDA"), ("check", "wgpu")):
        checked = [r for r in res.get(name, []) if r.get("bench") == "check" and r.get("what") != "summary"]
        if name not in steps:
            continue
        failed = [r["what"] for r in checked if not r.get("pass")]
        worst = max((r.get("rel_err") or 0 for r in checked), default=None)
        row(f"kernels against the CPU, {rt} (checks passed / run)", f"{len(checked) - len(failed)} / {len(checked)}",
            None, None, (f"failed: {', '.join(failed)}" if failed else "all within tolerance")
            + (f"; largest relative error {worst:.1e}" if worst is not None else ""), torch_expected=False)
    if "demo" in steps and steps["demo"].get("status") == "ok":
        row("vcedit demo (s)", steps["demo"].get("seconds"), None, None, "16 views at 128², 2 iterations"
            if mode == "device" else "2 views, 2 steps", torch_expected=False)
    return rows


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--work", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--mode", default="device")
    ap.add_argument("--pack", default="")
    a = ap.parse_args()
    steps = {}
    path = os.path.join(a.work, "steps.jsonl")
    if os.path.exists(path):
        for line in open(path):
            line = line.strip()
            if line:
                s = json.loads(line)
                steps[s["step"]] = s
    res = {name: read_results(os.path.join(a.work, f"{name}.out")) for name in steps}
    for fit_name in ("fit", "fit-cuda"):
        fit_out = os.path.join(a.work, f"{fit_name}.out")
        if fit_name not in steps or not os.path.exists(fit_out):
            continue
        m = re.search(r"held-out PSNR ([\d.]+) dB .*?(\d+) Gaussians", open(fit_out).read())
        if m:
            steps[fit_name]["psnr"] = float(m.group(1))
            steps[fit_name]["gaussians"] = int(m.group(2))
        # How long the host waited in device reads: near the total, the device is the bound; far below
        # it, the host's launching is.
        # (the time line is on stderr)
        fit_err = os.path.join(a.work, f"{fit_name}.err")
        m = re.search(r"(\d+) device reads waited ([\d.]+)s",
                      open(fit_err).read() if os.path.exists(fit_err) else "")
        if m:
            steps[fit_name]["reads"] = int(m.group(1))
            steps[fit_name]["wait"] = float(m.group(2))
    build = {}
    if os.path.exists(os.path.join(a.work, "build.json")):
        build = json.load(open(os.path.join(a.work, "build.json")))
    adapter = (res.get("adapter") or [{}])[0]
    adapter_cuda = (res.get("adapter-cuda") or [{}])[0]
    torch_info = (res.get("torch-info") or [{}])[0]

    def edit_slice(name):
        run_path = os.path.join(a.work, f"{name}-run.json")
        if not os.path.exists(run_path):
            return None
        run = json.load(open(run_path))
        edit = {"stages_s": {s["stage"]: round(s["seconds"], 2) for s in run.get("timings", [])},
                "total_s": steps.get(name, {}).get("seconds"),
                "gaussians": run.get("gaussians_before")}
        edit.update(paper_estimate(run))
        edit["work"] = work_per_stage(run)
        return edit
    edit, edit_cuda = edit_slice("edit"), edit_slice("edit-cuda")
    torch_present = "torch-info" in steps
    table = build_table(res, steps, a.mode, torch_present, a.work)
    complete = bool(steps) and all(s.get("status") == "ok" for s in steps.values())
    doc = {
        "version": 1,
        "mode": a.mode,
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "build": build,
        "machine": machine_info(a.work),
        "adapter": adapter.get("opened"),
        "adapter_cuda": adapter_cuda.get("opened"),
        "adapters_seen": adapter.get("adapters"),
        "pytorch": torch_info or "not installed",
        "steps": steps,
        "table": table,
        "edit_slice": edit,
        "edit_slice_cuda": edit_cuda,
        "results": res,
        "complete": complete,
    }
    tmp = os.path.join(a.out, ".gpu-check.json.tmp")
    json.dump(doc, open(tmp, "w"), indent=1)
    os.replace(tmp, os.path.join(a.out, "gpu-check.json"))

    # The markdown table for docs/gpu-results.md.
    card = doc["machine"].get("gpu") or (doc["adapter"] or {}).get("adapter") or "unknown card"
    lines = [f"### {doc['date'][:10]} · {card} · commit {build.get('commit', 'unknown')[:10]}"
             f"{' (+ uncommitted changes)' if build.get('uncommitted_changes') else ''} · {a.mode} mode", ""]
    ad = doc["adapter"] or {}
    if ad:
        cmma = ad.get("cmma") or []
        cores = (f"tensor cores for f16 products ({len(cmma)} cooperative-matrix shapes)" if ad.get("tensor_cores")
                 else f"no tensor cores ({len(cmma)} cooperative-matrix shapes)")
        lines.append(f"Adapter: {ad.get('adapter')} via {ad.get('api')}, compiler {ad.get('compiler')}, {cores}"
                     f"{' (software)' if ad.get('software') else ''}; driver {doc['machine'].get('driver', '?')}; "
                     f"PyTorch {torch_info.get('torch', 'n/a') if isinstance(torch_info, dict) else 'n/a'}.")
        lines.append("")
    cu = doc["adapter_cuda"] or {}
    if cu:
        lines.append(f"CUDA: {cu.get('adapter')}, {'tensor cores' if cu.get('tensor_cores') else 'no tensor cores'} "
                     f"({len(cu.get('cmma') or [])} WMMA shapes); rows marked CUDA ran there, the others on wgpu.")
        lines.append("")
    elif "adapter-cuda" in steps:
        err = open(os.path.join(a.work, "adapter-cuda.err"), errors="replace").read().strip().splitlines()
        lines.append(f"CUDA: not opened ({steps['adapter-cuda'].get('status')}: {err[-1] if err else 'no message'}).")
        lines.append("")
    lines += ["| what | vcedit (warm) | vcedit first call | PyTorch | vcedit / PyTorch | note |",
              "| --- | --- | --- | --- | --- | --- |"]
    for r in table:
        cell = lambda v: "–" if v is None else str(v)
        lines.append(f"| {r['what']} | {cell(r['vcedit'])} | {cell(r['vcedit_first_call'])} | {cell(r['pytorch'])} | "
                     f"{cell(r['ratio_vcedit_over_pytorch'])} | {r['note']} |")
    for slice_, rt in ((edit_cuda, " on CUDA"), (edit, "")):
        if not slice_:
            continue
        lo, hi = slice_["estimate_96_views_15_steps_2_iterations_s"]
        stages = ", ".join(f"{k} {v:.1f}" for k, v in slice_["stages_s"].items())
        per_it = "; ".join(f"iteration {i + 1}: " + ", ".join(f"{k} {v:.1f}" for k, v in it.items())
                           for i, it in enumerate(slice_["per_iteration_s"]))
        lines += ["", f"Editing slice{rt} ({slice_['views']} views × {slice_['steps']} steps × "
                      f"{slice_['iterations']} iterations, CCM/ECM/blend on): {slice_['total_s']} s in all; stages (s): "
                      f"{stages} ({per_it}). Estimate for 96 views × 15 steps × 2 iterations from the "
                      f"{slice_['estimated_from']}: **{lo:.0f}{'' if round(lo) == round(hi) else f'–{hi:.0f}'} s** "
                      f"(scaled from the slice, not a measurement)."]
        if slice_.get("work"):
            lines += ["", f"Work of the slice{rt} (its ledger, all iterations): {describe_work(slice_['work'])}."]
    # Kernel profiles (kernel_profile.py's tables, as the steps printed them).
    for name in ("unet-profile", "fit-profile"):
        path = os.path.join(a.work, f"{name}.out")
        if steps.get(name, {}).get("status") == "ok" and os.path.exists(path):
            text = [l.rstrip() for l in open(path, errors="replace") if not l.startswith("PROFILE ")]
            lines += ["", f"Kernel profile (`{name}`): " + (text[0] if text else "")] + [""] + text[1:]
    # The fit's host profile and A/Bs (host_profile.py's HOSTPROF lines).
    ab_path = os.path.join(a.work, "fit-ab.out")
    ab = [json.loads(l[len("HOSTPROF "):]) for l in (open(ab_path, errors="replace") if os.path.exists(ab_path) else [])
          if l.startswith("HOSTPROF ")]
    if ab:
        lines += ["", "Fit A/B (`fit-ab`: the same fit of lego-200 per variant; CPU time of the whole process; "
                      "the waits are the fit's own count of device reads):", "",
                  "| variant | wall s | held-out dB | CPU user + sys s | peak MiB | device reads, waited s | busiest threads (CPU s) |",
                  "| --- | --- | --- | --- | --- | --- | --- |"]
        for r in ab:
            reads = r.get("device_reads") or {}
            busy = ", ".join(f"{t['name']}×{t['threads']} {t['user'] + t['sys']:.1f}" for t in r["threads"][:3])
            lines.append(f"| {r['label']}{'' if r['rc'] == 0 else ' (rc ' + str(r['rc']) + ')'} | {r['wall_s']} | "
                         f"{r.get('psnr_db') or '–'} | "
                         f"{r['user_s']} + {r['sys_s']} | {r.get('peak_mib', '–')} | "
                         f"{reads.get('reads', '–')}, {reads.get('wait_s', '–')} | {busy} |")
    lines += ["", "Steps: " + ", ".join(f"{k} {v.get('status')}" + (f" {v.get('seconds')}s" if v.get('seconds') else "")
                                      for k, v in steps.items())]
    open(os.path.join(a.out, "gpu-check.md"), "w").write("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
