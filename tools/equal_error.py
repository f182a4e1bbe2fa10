#!/usr/bin/env python3
"""Equal-error speed-ups of render configurations against plain path tracing,
measured in one run: every configuration renders the scene at the same spp,
in alternating rounds (seeds 1..rounds), against a high-spp PT reference.
Prints per configuration the median render time, the mean relMSE, the image
mean, the range of its per-round time ratios to PT's (the machine's timing
noise during the run), the time and relMSE multiples of PT's at equal spp (the thesis'
metric), and the equal-error speed-up (t_PT x relMSE_PT) / (t x relMSE).

A configuration is a label and the extra `nppp render` flags, e.g.
    --config "NPPP P=1" "--estimators neural --min-bounces 1"
PT (`--estimators off`) is always measured first. The scene's render block
gives M unless --max-bounces is set. `--scene-for LABEL SCENE` renders one
configuration from another scene file, e.g. a copy of the scene whose
instances name another estimator file, to compare two estimators in one
run (the copy must differ only in `estimator` keys: PT renders --scene).
`--nppp-for LABEL BINARY` renders one configuration with another build
(a change against the build before it, in one run; PT uses --nppp).
Standard library only; not part of the pipeline or of `make test`.

    python3 tools/equal_error.py --nppp ~/.cache/nppp-target/release/nppp \\
        --scene data/scenes/cornell-glass.json --spp 64 --rounds 3 \\
        --config "NPPP P=1" "--min-bounces 1" \\
        --config "floor P=1" "--estimators cost-floor --min-bounces 1"
"""

import argparse
import re
import shlex
import statistics
import sys
import tempfile
from pathlib import Path

from nppp_log import TIME, render_log

MEAN = re.compile(r"mean rgb \[([-0-9.e+ ]+)\]")
RELMSE = re.compile(r"relMSE ([0-9.e+-]+),")


def render(nppp, scene, spp, seed, flags, reference, out):
    cmd = [nppp, "render", scene, "--spp", str(spp), "--seed", str(seed),
           "--out", out, "--quiet"] + flags
    if reference:
        cmd += ["--reference", reference]
        _, (t, m, r) = render_log(cmd, TIME, MEAN, RELMSE)
    else:
        (_, (t, m)), r = render_log(cmd, TIME, MEAN), None
    mean = sum(float(x) for x in m.group(1).split()) / 3.0
    return float(t.group(1)), (float(r.group(1)) if r else None), mean


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--nppp", required=True, help="the nppp binary")
    ap.add_argument("--scene", required=True)
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--reference", help="reference EXR (rendered with PT if missing)")
    ap.add_argument("--reference-spp", type=int, default=2048)
    ap.add_argument("--max-bounces", type=int, help="M for every render (default: the scene's)")
    ap.add_argument("--common", default="",
                    help="flags for every render, the reference's included (e.g. \"--scale 0.5\")")
    ap.add_argument("--config", nargs=2, action="append", default=[],
                    metavar=("LABEL", "FLAGS"), help="a configuration to compare with PT")
    ap.add_argument("--scene-for", nargs=2, action="append", default=[],
                    metavar=("LABEL", "SCENE"),
                    help="render configuration LABEL from SCENE instead of --scene")
    ap.add_argument("--nppp-for", nargs=2, action="append", default=[],
                    metavar=("LABEL", "BINARY"),
                    help="render configuration LABEL with another nppp binary (a change "
                         "against the build before it, in one run)")
    a = ap.parse_args()
    labels = {l for l, _ in a.config}
    scene_for = dict(a.scene_for)
    nppp_for = dict(a.nppp_for)
    for flag, given in (("--scene-for", scene_for), ("--nppp-for", nppp_for)):
        for label in given:
            if label not in labels:
                ap.error(f"{flag} {label!r}: no --config has that label")
    common = ["--max-bounces", str(a.max_bounces)] if a.max_bounces is not None else []
    common += shlex.split(a.common)
    tmp = tempfile.mkdtemp(prefix="nppp-equal-error-")
    reference = a.reference or str(Path(tmp) / "reference.exr")
    configs = [("PT", ["--estimators", "off"])] + [(l, shlex.split(f)) for l, f in a.config]
    times = {l: [] for l, _ in configs}
    errs = {l: [] for l, _ in configs}
    means = {l: [] for l, _ in configs}
    out = str(Path(tmp) / "img.exr")
    try:
        if not Path(reference).exists():
            print(f"reference: PT at {a.reference_spp} spp -> {reference}", file=sys.stderr)
            render(a.nppp, a.scene, a.reference_spp, 1000, ["--estimators", "off"] + common,
                   None, reference)
        measure(a, configs, scene_for, nppp_for, common, reference, out, times, errs, means)
    finally:
        # The working image goes; a reference rendered here stays (the
        # table names it, for the next run's --reference).
        Path(out).unlink(missing_ok=True)
        if not any(Path(tmp).iterdir()):
            Path(tmp).rmdir()
    report(a, configs, reference, times, errs, means)


def measure(a, configs, scene_for, nppp_for, common, reference, out, times, errs, means):
    """Renders every configuration in alternating rounds into the lists."""
    for rnd in range(1, a.rounds + 1):
        for label, flags in configs:
            scene = scene_for.get(label, a.scene)
            nppp = nppp_for.get(label, a.nppp)
            t, r, m = render(nppp, scene, a.spp, rnd, flags + common, reference, out)
            times[label].append(t)
            errs[label].append(r)
            means[label].append(m)
            print(f"round {rnd} {label:>24}: {t:7.3f} s  relMSE {r:.5f}  mean {m:.5f}",
                  file=sys.stderr)


def report(a, configs, reference, times, errs, means):
    """The Markdown table of the measured rounds."""
    t_pt = statistics.median(times["PT"])
    e_pt = statistics.mean(errs["PT"])
    m_pt = statistics.mean(means["PT"])
    print(f"\n{a.scene}, {a.spp} spp, {a.rounds} alternating rounds, reference {reference}\n")
    print("| config | median time (s) | relMSE | mean / PT's | time x PT | relMSE x PT | equal-error speed-up "
          "| time x PT, per round |")
    print("|---|---:|---:|---:|---:|---:|---:|---|")
    for label, _ in configs:
        t = statistics.median(times[label])
        e = statistics.mean(errs[label])
        m = statistics.mean(means[label])
        # Each round's time over the same round's PT: how far the
        # machine's load moved the ratio while this run lasted.
        per_round = sorted(x / p for x, p in zip(times[label], times["PT"]))
        spread = f"{per_round[0]:.2f}-{per_round[-1]:.2f}" if label != "PT" else "-"
        print(f"| {label} | {t:.3f} | {e:.5f} | {m / m_pt:.4f} | {t / t_pt:.2f} | "
              f"{e / e_pt:.2f} | {t_pt * e_pt / (t * e):.2f}x | {spread} |")


if __name__ == "__main__":
    main()
