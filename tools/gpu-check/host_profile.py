#!/usr/bin/env python3
"""Runs one command and says where its host time went, thread by thread, without a profiler.

    host_profile.py --label NAME [--every S] -- COMMAND...

Every S seconds (default 0.2) it reads /proc/PID/task/*/stat and status of the running command: the CPU
time each thread spent in user and kernel mode, and its voluntary and involuntary context switches. At the
end it prints the last reading of every thread (threads that ended keep their last one), summed by thread
name, and one `HOSTPROF {json}` line that summarize.py turns into a table row, on stdout. The command's
stdout and stderr go to stderr; its `vcedit fit` time line ("time: ... N device reads waited Xs") and
last held-out PSNR are also kept in the report.

What it answers: a process whose CPU time is close to its wall time is bound by the host (launching,
encoding, driver calls: the busiest thread says which); one far below it waits, for the device or for
itself. Linux only (/proc, wait4).
"""
import argparse
import json
import os
import re
import subprocess
import sys
import threading
import time

TICK = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def read_thread(task_dir):
    """(name, user s, system s, voluntary switches, involuntary switches) of one thread, or None."""
    try:
        stat = open(os.path.join(task_dir, "stat")).read()
        status = open(os.path.join(task_dir, "status")).read()
    except OSError:
        return None
    # The name is in parentheses and may hold spaces or parentheses itself: split at the last ')'.
    name = stat[stat.index("(") + 1:stat.rindex(")")]
    fields = stat[stat.rindex(")") + 2:].split()
    # fields[0] is the state (field 3 of proc(5)); utime and stime are fields 14 and 15.
    user, system = int(fields[11]) / TICK, int(fields[12]) / TICK
    vol = re.search(r"^voluntary_ctxt_switches:\s*(\d+)", status, re.M)
    invol = re.search(r"^nonvoluntary_ctxt_switches:\s*(\d+)", status, re.M)
    return name, user, system, int(vol.group(1)) if vol else 0, int(invol.group(1)) if invol else 0


def sample(pid, threads):
    task_root = f"/proc/{pid}/task"
    try:
        tids = os.listdir(task_root)
    except OSError:
        return
    for tid in tids:
        t = read_thread(os.path.join(task_root, tid))
        if t:
            # The main thread apart from the unnamed threads that share the process's name.
            threads[tid] = ("(main) " + t[0], *t[1:]) if tid == str(pid) else t


def group_name(name):
    """Threads of one pool share a name up to their number ("tokio-runtime-w", "rayon-3" -> "rayon-#")."""
    return re.sub(r"\d+", "#", name)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--label", required=True)
    ap.add_argument("--every", type=float, default=0.2)
    ap.add_argument("command", nargs=argparse.REMAINDER)
    a = ap.parse_args()
    cmd = a.command[1:] if a.command[:1] == ["--"] else a.command
    if not cmd:
        ap.error("no command given")

    t0 = time.time()
    # The command's own stdout and stderr go to stderr (stdout is this report's), read for the lines the
    # report keeps: a fit's time line and its last held-out PSNR.
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, errors="replace")
    time_line, psnr_line = [], []

    def pass_on(stream):
        for line in stream:
            sys.stderr.write(line)
            if "device reads waited" in line:
                time_line.append(line.strip())
            if "held-out PSNR" in line:
                psnr_line.append(line.strip())

    readers = [threading.Thread(target=pass_on, args=(s,), daemon=True) for s in (proc.stdout, proc.stderr)]
    for r in readers:
        r.start()
    threads = {}
    # wait4 rather than poll: the exit status comes with the whole process's resource use (every thread,
    # to the end), which the samples miss for the last interval of each thread.
    usage = None
    while usage is None:
        sample(proc.pid, threads)
        time.sleep(a.every)
        pid, status, ru = os.wait4(proc.pid, os.WNOHANG)
        if pid == proc.pid:
            usage = ru
            proc.returncode = os.waitstatus_to_exitcode(status)
    wall = time.time() - t0
    for r in readers:
        r.join(timeout=5)

    groups = {}
    for name, user, system, vol, invol in threads.values():
        g = groups.setdefault(group_name(name), {"threads": 0, "user": 0.0, "sys": 0.0, "vol": 0, "invol": 0})
        g["threads"] += 1
        g["user"] += user
        g["sys"] += system
        g["vol"] += vol
        g["invol"] += invol
    user, system = usage.ru_utime, usage.ru_stime
    top = sorted(groups.items(), key=lambda kv: -(kv[1]["user"] + kv[1]["sys"]))
    print(f"{a.label}: {wall:.1f} s wall, {user:.1f} s user + {system:.1f} s system CPU "
          f"({(user + system) / wall * 100:.0f} % of one core), {usage.ru_nvcsw} voluntary and "
          f"{usage.ru_nivcsw} involuntary switches, peak {usage.ru_maxrss / 1024:.0f} MiB, rc {proc.returncode}")
    print(f"  by thread (sampled every {a.every} s: a thread's last interval is missing)")
    print(f"  {'threads':<24} {'n':>3} {'user s':>8} {'sys s':>8} {'vol. sw':>9} {'invol. sw':>9}")
    for name, g in top[:8]:
        print(f"  {name:<24} {g['threads']:>3} {g['user']:>8.2f} {g['sys']:>8.2f} {g['vol']:>9} {g['invol']:>9}")
    waits = None
    if time_line:
        print("  " + time_line[-1])
        m = re.search(r"(\d+) device reads waited ([\d.]+)s", time_line[-1])
        if m:
            waits = {"reads": int(m.group(1)), "wait_s": float(m.group(2))}
    psnr = None
    if psnr_line:
        print("  " + psnr_line[-1])
        m = re.search(r"held-out PSNR ([\d.]+) dB", psnr_line[-1])
        psnr = float(m.group(1)) if m else None
    print("HOSTPROF " + json.dumps({
        "label": a.label, "rc": proc.returncode, "wall_s": round(wall, 2), "user_s": round(user, 2),
        "sys_s": round(system, 2), "peak_mib": round(usage.ru_maxrss / 1024), "device_reads": waits, "psnr_db": psnr,
        "threads": [{"name": n, **{k: (round(v, 2) if isinstance(v, float) else v) for k, v in g.items()}}
                    for n, g in top[:8]],
    }))
    sys.exit(proc.returncode)


if __name__ == "__main__":
    main()
