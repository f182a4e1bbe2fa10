#!/usr/bin/env python3
"""Side-by-side render speed: nppp against Mitsuba 3 on the same scene.

Runs the renderers alternately ROUNDS times (so a noisy machine slows them
alike) at the same resolution, spp, M and thread count, and reports render
time alone (nppp's "in X s", Mitsuba's time after scene load and JIT
warm-up), medians and per-round ratios. Mitsuba runs with its default
Russian roulette (rr_depth 5) and with rr_depth 3, which matches nppp's
(roulette from the third bounce on, so the same work per sample).

usage: speed_compare.py NPPP_BINARY SCENE.json [--spp 64] [--threads 2] [--rounds 6]
                        [--variant llvm_ad_rgb] [--mesh-obj NAME=FILE.obj ...]
"""
import argparse
import os
import re
import statistics
import subprocess
import sys

HERE = os.path.dirname(os.path.abspath(__file__))


def run(cmd, pattern, env=None):
    out = subprocess.run(cmd, capture_output=True, text=True, env=env)
    text = out.stdout + out.stderr
    m = re.search(pattern, text)
    if out.returncode != 0 or not m:
        sys.exit(f"error: {' '.join(cmd)} failed (exit {out.returncode}):\n{text[-2000:]}")
    return float(m.group(1))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("nppp")
    ap.add_argument("scene")
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--rounds", type=int, default=6)
    ap.add_argument("--variant", default="llvm_ad_rgb")
    ap.add_argument("--mesh-obj", action="append", default=[])
    a = ap.parse_args()
    out_dir = os.environ.get("TMPDIR", "/tmp")
    runners = {
        "nppp": lambda: run(
            [a.nppp, "render", a.scene, "--spp", str(a.spp), "--threads", str(a.threads),
             "--estimators", "off", "--quiet", "--out", os.path.join(out_dir, "speed-nppp.exr")],
            r" in ([0-9.]+)s"),
    }
    for rr in (5, 3):
        cmd = [sys.executable, os.path.join(HERE, "render_mitsuba.py"), a.scene,
               "--out", os.path.join(out_dir, f"speed-mitsuba-rr{rr}.exr"), "--variant", a.variant,
               "--spp", str(a.spp), "--threads", str(a.threads), "--time", "--rr-depth", str(rr)]
        for m in a.mesh_obj:
            cmd += ["--mesh-obj", m]
        runners[f"mitsuba {a.variant} rr_depth {rr}"] = (lambda c: lambda: run(c, r"render ([0-9.]+) s"))(cmd)
    times = {k: [] for k in runners}
    for r in range(a.rounds):
        for k, f in runners.items():
            times[k].append(f())
        print(f"round {r + 1}: " + ", ".join(f"{k} {v[-1]:.2f} s" for k, v in times.items()), flush=True)
    base = statistics.median(times["nppp"])
    print(f"\nmedian render time over {a.rounds} rounds ({a.spp} spp, {a.threads} threads):")
    for k, v in times.items():
        med = statistics.median(v)
        per_round = [round(o / n, 2) for n, o in zip(times["nppp"], v)]
        ratio = "" if k == "nppp" else f"  nppp speed-up {med / base:.2f}x (per round {per_round})"
        print(f"  {k:32s} {med:6.2f} s{ratio}")


if __name__ == "__main__":
    main()
