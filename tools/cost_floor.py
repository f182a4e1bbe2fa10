#!/usr/bin/env python3
"""How much could any estimator save on a scene? Times, side by side and in
alternating rounds, plain path tracing, PT + NPPP, free exits (`nppp render
--estimators free-exits`: the baked masks decide entries and every path
goes on from a free exit straight through the sphere) and the cost floor
(`--estimators cost-floor`: every entry ends its path for free) at each P,
and prints median render times and their ratios to PT.

The floor's time is a lower bound for any estimator that uses the same
masks: it pays only what every NPPP render pays before its decoder (the
sphere query and the mask lookup), and never continues a path. If the
floor's ratio at some P is above a target, no network, however fast or
accurate, reaches that target there. Free exits pay for the continued
paths too: NPPP's time over theirs is what its entries (latent lookup,
noise, decoder) cost.

Standard library only; not part of the pipeline or of `make test`.

    python3 tools/cost_floor.py --nppp ~/.cache/nppp-target/release/nppp \\
        --scene data/scenes/cornell-box.json --spp 32 --rounds 3
"""

import argparse
import re
import statistics
import sys
import tempfile
from pathlib import Path

from nppp_log import TIME, render_log

RATE = re.compile(r"([0-9.]+) M samples/s")


def render(nppp, scene, spp, mode, p, threads, out):
    cmd = [nppp, "render", scene, "--spp", str(spp), "--estimators", mode,
           "--out", out, "--quiet"]
    if p is not None:
        cmd += ["--min-bounces", str(p)]
    if threads:
        cmd += ["--threads", str(threads)]
    _, (t, r) = render_log(cmd, TIME, RATE)
    return float(t.group(1)), float(r.group(1))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--nppp", required=True, help="the nppp binary")
    ap.add_argument("--scene", required=True)
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--ps", default="0,1,2,3", help="the P values")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--threads", type=int, default=0, help="0: all cores")
    a = ap.parse_args()
    ps = [int(p) for p in a.ps.split(",")]
    configs = [("PT", "off", None)]
    for p in ps:
        configs += [(f"NPPP P={p}", "neural", p), (f"free exits P={p}", "free-exits", p),
                    (f"floor P={p}", "cost-floor", p)]
    times = {c[0]: [] for c in configs}
    rates = {c[0]: [] for c in configs}
    with tempfile.TemporaryDirectory() as tmp:
        out = str(Path(tmp) / "img.exr")
        # One untimed pass: page cache, estimator file, CPU frequency.
        render(a.nppp, a.scene, 1, "neural", 0, a.threads, out)
        for r in range(a.rounds):
            order = configs if r % 2 == 0 else list(reversed(configs))
            for label, mode, p in order:
                t, s = render(a.nppp, a.scene, a.spp, mode, p, a.threads, out)
                times[label].append(t)
                rates[label].append(s)
                print(f"round {r + 1} {label:<16} {t:7.2f} s {s:7.3f} M samples/s",
                      file=sys.stderr)
    pt = statistics.median(times["PT"])
    print(f"\n{a.scene}, {a.spp} spp, {a.rounds} alternating rounds, median render time\n")
    print("| configuration | seconds | M samples/s | time / PT |")
    print("|---|---|---|---|")
    for label, _, _ in configs:
        t = statistics.median(times[label])
        s = statistics.median(rates[label])
        print(f"| {label} | {t:.2f} | {s:.3f} | {t / pt:.2f}x |")


if __name__ == "__main__":
    main()
