#!/usr/bin/env python3
"""Sums a CubeCL kernel profile by kernel: where a command's GPU time goes.

    CUBECL_DEBUG_LOG=run.prof CUBECL_DEBUG_OPTION=profile vcedit bench unet ...
    tools/gpu-check/kernel_profile.py run.prof [--segments 3] [--top 20]

cubecl's profile option waits for every kernel and logs one `| duration | kernel name ...` line per launch
(and, at exit, its own summary, which this ignores). `--segments N` cuts the launches into N equal parts
and reports the last one: a bench that ran a first call and N-1 timed runs of the same work thereby reports
one warm run, without the first call's pipeline creation. Prints a markdown table and a `PROFILE {json}`
line. (Not named profile.py: that would shadow Python's own `profile` module for every script in this
folder, torch_bench.py's imports included.)
"""
import argparse
import collections
import json
import re

LAUNCH = re.compile(r"^\|\s*([0-9.]+)(ns|µs|us|ms|s)\s*\|\s*([^|]+?)\s*(\||$)")
UNIT_MS = {"ns": 1e-6, "µs": 1e-3, "us": 1e-3, "ms": 1.0, "s": 1e3}


def kernel_name(raw):
    # Library products are named by their generic signature (MatmulEntry | TensorArgs | ...): one name.
    if raw.startswith("MatmulEntry"):
        return "matmul library (cubek)"
    # Our kernels end in a hash of their compile-time arguments: one name for all variants.
    return re.sub(r"_[0-9a-f]{8}$", "", raw)


def launches(path):
    out = []
    with open(path, errors="replace") as f:
        for line in f:
            m = LAUNCH.match(line)
            if m and m.group(3) not in ("Name", "Total"):
                out.append((float(m.group(1)) * UNIT_MS[m.group(2)], kernel_name(m.group(3))))
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("log")
    ap.add_argument("--segments", type=int, default=1)
    ap.add_argument("--top", type=int, default=20)
    ap.add_argument("--label", default="")
    args = ap.parse_args()
    rows = launches(args.log)
    if not rows:
        print(f"{args.log}: no kernel launches logged (was CUBECL_DEBUG_OPTION=profile set?)")
        return 1
    per = len(rows) // max(args.segments, 1)
    seg = rows[(args.segments - 1) * per:] if args.segments > 1 else rows
    total = sum(ms for ms, _ in seg)
    by = collections.defaultdict(lambda: [0.0, 0])
    for ms, name in seg:
        by[name][0] += ms
        by[name][1] += 1
    ranked = sorted(by.items(), key=lambda kv: -kv[1][0])
    print(f"{args.label or args.log}: {len(seg)} launches, {total:.2f} ms of kernel time"
          + (f" (last of {args.segments} equal parts of {len(rows)} launches)" if args.segments > 1 else ""))
    print("| kernel | launches | ms | share |")
    print("| --- | --- | --- | --- |")
    for name, (ms, n) in ranked[:args.top]:
        print(f"| {name} | {n} | {ms:.2f} | {100 * ms / total:.1f} % |")
    print("PROFILE " + json.dumps({
        "label": args.label, "launches": len(seg), "kernel_ms": round(total, 3),
        "kernels": [{"name": k, "launches": n, "ms": round(ms, 3)} for k, (ms, n) in ranked[:args.top]],
    }))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
