#!/usr/bin/env python3
"""nppp against Mitsuba 3 on translucent scenes (media inside dielectrics).

    check_media.py NPPP SCENE.json [SCENE.json ...] [--spp 1024] [--out DIR]
                   [--mesh-obj NAME=FILE ...] [--tol-mean 0.01] [--variant scalar_rgb]

For each scene: Mitsuba 3 (`volpathmis`, max_depth = M + 1, no roulette: render_mitsuba.py)
renders the reference, nppp renders
it twice with different seeds (plain path tracing), and the table shows the relative
difference of the image means and relMSE(nppp, Mitsuba) next to relMSE(nppp, nppp): two
renderers that agree differ by about their own noise, so the first relMSE is about the
second (their ratio near 1; both images have noise, so 1 is the expectation when Mitsuba's
noise equals nppp's). Exit status 1 when a mean differs by more than --tol-mean.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import compare_exr  # noqa: E402
import render_mitsuba  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("nppp", help="the nppp binary")
    ap.add_argument("scenes", nargs="+")
    ap.add_argument("--spp", type=int, default=1024)
    ap.add_argument("--out", default="out/media-check")
    ap.add_argument("--mesh-obj", action="append", default=[])
    ap.add_argument("--tol-mean", type=float, default=0.01)
    ap.add_argument("--variant", default="scalar_rgb")
    x = ap.parse_args(argv)
    os.makedirs(x.out, exist_ok=True)
    rows, failed = [], False
    for scene in x.scenes:
        name = os.path.splitext(os.path.basename(scene))[0]
        ref = os.path.join(x.out, f"{name}.mitsuba.exr")
        margs = [scene, "--out", ref, "--spp", str(x.spp), "--variant", x.variant]
        for m in x.mesh_obj:
            margs += ["--mesh-obj", m]
        if render_mitsuba.main(margs) not in (0, None):
            raise SystemExit(f"{scene}: Mitsuba failed")
        ours = []
        for seed in (101, 202):
            out = os.path.join(x.out, f"{name}.nppp-{seed}.exr")
            subprocess.run([x.nppp, "render", scene, "--estimators", "off", "--spp", str(x.spp),
                            "--seed", str(seed), "--out", out, "--quiet"], check=True)
            ours.append(compare_exr.read_rgb(out))
        b = compare_exr.read_rgb(ref)
        vs_ref = compare_exr.compare(ours[0], b)
        vs_ours = compare_exr.compare(ours[0], ours[1])
        rel = vs_ref["rel_diff_of_means"]
        worst = max(abs(v) for v in rel)
        ok = worst <= x.tol_mean
        failed |= not ok
        rows.append((name, vs_ref["mean_a"], vs_ref["mean_b"], rel, vs_ref["relmse"],
                     vs_ours["relmse"], ok))
    print(f"\n{x.spp} spp each; relMSE with eps 0.01\n")
    print("| scene | mean nppp | mean Mitsuba | (nppp - Mitsuba) / Mitsuba | relMSE nppp vs Mitsuba"
          " | relMSE nppp vs nppp | ratio | mean within tolerance |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    f3 = compare_exr.fmt3
    for name, ma, mb, rel, r_ref, r_own, ok in rows:
        pct = "[" + ", ".join(f"{v:+.2%}" for v in rel) + "]"
        print(f"| {name} | {f3(ma)} | {f3(mb)} | {pct} | {r_ref:.4g} | {r_own:.4g} | "
              f"{r_ref / r_own:.2f} | {'yes' if ok else 'NO'} |")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
