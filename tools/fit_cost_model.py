#!/usr/bin/env python3
"""Fits the `auto` pilot's cost model (crates/nppp-render/src/auto/mod.rs) to
timed renders: render time = a x the later rays' inner BVH node visits + b x
later closest-hit rays + c x shadow rays + d x estimator entry units + e x
mask skips + f x the later rays' leaf visits, by least squares on relative
error (every render counts the same, whatever its length). An entry's units
are the model's split of an entry into its fixed part, its decoder rows,
their multiply-adds and their noise normals (COST_PER_ENTRY ...
COST_PER_DECODER_NORMAL); the fit scales that split as a whole. The model
prices neither later rays nor leaf visits: they are fitted here to show
whether they should be (room-glass is in the set because its paths are
mostly refractions without shadow rays, which separates a ray's own cost
from its shadow ray's).

Renders the benchmark scenes and room-glass as plain PT and with their
estimators at P = 0, 1, 2, each with the next-event estimation `auto` would
try, in alternating rounds; reads the work each render counted from its
`work:` and `traced:` log lines; prints the weights in later inner
node-visit units (what the COST_PER_* constants hold), each render's
predicted over measured time, and the time ratios to PT (what the pilot
compares), measured and predicted. Standard library only; not part of the
pipeline or of `make test`.

    python3 tools/fit_cost_model.py --nppp ~/.cache/nppp-target/release/nppp

`--validate W...` predicts with the given weights instead of fitting (with
`--scene`, on scenes the fit never saw).
"""

import argparse
import json
import re
import statistics
import sys
import tempfile
from pathlib import Path

from nppp_log import TIME, render_log

WORK = re.compile(r"work: [0-9.]+ M units of auto's cost model: (\d+) later inner node visits, "
                  r"(\d+) later rays, (\d+) shadow rays, (\d+) estimator entries, (\d+) decoder rows "
                  r"of (\d+) multiply-adds and (\d+) noise normals in all, (\d+) mask skips")
TRACED = re.compile(r"([0-9.]+) M leaves by later rays")
TERMS = ["later inner node visit", "later ray", "shadow ray", "estimator entry unit", "mask skip",
         "later leaf visit"]
# The entry's split in crates/nppp-render/src/auto/mod.rs (COST_PER_ENTRY,
# COST_PER_DECODER_ROW, COST_PER_DECODER_MULTIPLY_ADD, COST_PER_DECODER_NORMAL).
ENTRY_SPLIT = (9.1, 0.22, 7.15 / 11_072.0, 0.146)

# scene file, common flags, the next-event estimation auto tries for its estimator
SCENES = [
    ("data/scenes/cornell-box.json", [], "picked"),
    ("data/scenes/cornell-gold.json", [], "picked"),
    ("data/scenes/cornell-glass.json", [], "off"),
    ("data/scenes/cornell-jade.json", ["--scale", "0.5"], "off"),
    ("data/scenes/tube.json", [], "first"),
    ("data/scenes/room.json", ["--scale", "0.5"], "picked"),
    ("data/scenes/room-skylight.json", ["--scale", "0.5"], "picked"),
    ("data/scenes/variants/room-glass.json", ["--scale", "0.5"], "off"),
]


def configs(nee):
    out = [("PT", ["--estimators", "off"])]
    for p in (0, 1, 2):
        out.append((f"P={p}" + ("" if nee == "off" else f"+{nee}"),
                    ["--estimators", "neural", "--min-bounces", str(p), "--entry-nee", nee]))
    return out


def render(nppp, scene, spp, seed, flags, out):
    cmd = [nppp, "render", scene, "--spp", str(spp), "--seed", str(seed),
           "--out", out, "--quiet"] + flags
    _, (t, w, leaves) = render_log(cmd, TIME, WORK, TRACED)
    inner, rays, shadow, entries, rows, macs, normals, skips = (float(x) for x in w.groups())
    e, r, m, n = ENTRY_SPLIT
    return float(t.group(1)), [inner, rays, shadow, e * entries + r * rows + m * macs + n * normals, skips,
                               float(leaves.group(1)) * 1e6]


def solve(a, b):
    """Gaussian elimination with partial pivoting for a small square system."""
    n = len(b)
    m = [row[:] + [b[i]] for i, row in enumerate(a)]
    for c in range(n):
        p = max(range(c, n), key=lambda r: abs(m[r][c]))
        m[c], m[p] = m[p], m[c]
        for r in range(n):
            if r != c and m[c][c] != 0.0:
                f = m[r][c] / m[c][c]
                m[r] = [x - f * y for x, y in zip(m[r], m[c])]
    return [m[i][n] / m[i][i] for i in range(n)]


def predict(w, x):
    return sum(a * b for a, b in zip(w, x))


def ratios(rows, w, scenes):
    """Measured and predicted time ratios to PT: what the pilot compares."""
    print("\n| scene | config | time x PT measured | predicted |")
    print("|---|---|---:|---:|")
    errs = []
    for scene in scenes:
        base = next((r for r in rows if r[0] == (scene, "PT")), None)
        if base is None:
            continue
        pb = predict(w, base[2])
        for (s, label), t, x in rows:
            if s == scene and label != "PT":
                meas, pred = t / base[1], predict(w, x) / pb
                errs.append(pred / meas - 1.0)
                print(f"| {Path(scene).stem} | {label} | {meas:.2f} | {pred:.2f} |")
    if errs:
        rms = (sum(e * e for e in errs) / len(errs)) ** 0.5
        print(f"\nratio error: RMS {rms * 100:.1f}%, largest {max(abs(e) for e in errs) * 100:.1f}%")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--nppp", required=True)
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--dump", help="also write every render's time and counts here (JSON)")
    ap.add_argument("--validate", nargs=len(TERMS), type=float, metavar="W",
                    help="no fit: predict with these weights (later-inner-node-visit units, in the order "
                         + ", ".join(TERMS) + ") the time ratios of --scene's renders")
    ap.add_argument("--scene", action="append", nargs=3, metavar=("FILE", "COMMON", "NEE"),
                    help="render this scene instead of the fit's set (COMMON: its flags as one "
                         "string, NEE: off, first or picked); repeatable")
    args = ap.parse_args()
    scenes = SCENES if not args.scene else [(f, c.split(), n) for f, c, n in args.scene]

    runs = {}
    with tempfile.TemporaryDirectory(prefix="nppp-fit-cost-") as tmp:
        out = str(Path(tmp) / "render.exr")
        for rnd in range(1, args.rounds + 1):
            for scene, common, nee in scenes:
                for label, flags in configs(nee):
                    t, x = render(args.nppp, scene, args.spp, rnd, common + flags, out)
                    runs.setdefault((scene, label), []).append((t, x))
                    print(f"round {rnd} {Path(scene).stem:>14} {label:>14}: {t:.3f} s", file=sys.stderr)

    rows = []
    for key, rs in runs.items():
        t = statistics.median(r[0] for r in rs)
        x = [statistics.mean(r[1][k] for r in rs) for k in range(len(TERMS))]
        rows.append((key, t, x))
    if args.dump:
        with open(args.dump, "w") as f:
            json.dump([{"scene": k[0], "config": k[1], "seconds": t, "counts": x} for k, t, x in rows], f)
    names = [s for s, _, _ in scenes]
    if args.validate:
        ratios(rows, args.validate, names)
        return
    # Weighted least squares: minimize sum ((x . w - t) / t)^2.
    n = len(TERMS)
    ata = [[sum(x[i] * x[j] / (t * t) for _, t, x in rows) for j in range(n)] for i in range(n)]
    atb = [sum(x[i] / t for _, t, x in rows) for i in range(n)]
    w = solve(ata, atb)
    unit = w[0]
    print("\n| term | seconds per item (2 threads) | in later inner node visits |")
    print("|---|---:|---:|")
    for name, v in zip(TERMS, w):
        print(f"| {name} | {v * 1e9:.1f} ns | {v / unit:.3f} |")
    print("\n| scene | config | measured s | predicted / measured |")
    print("|---|---|---:|---:|")
    for (scene, label), t, x in rows:
        print(f"| {Path(scene).stem} | {label} | {t:.3f} | {predict(w, x) / t:.2f} |")
    ratios(rows, w, names)


if __name__ == "__main__":
    main()
