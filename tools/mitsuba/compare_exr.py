#!/usr/bin/env python3
"""Compare two OpenEXR images (A against the reference B).

    compare_exr.py A.exr B.exr [--eps 0.01] [--tol-mean X] [--json]

Prints, for linear RGB:
  mean RGB of A and of B (per channel, and the average of the three channels),
  relative difference of means  (mean(A) - mean(B)) / mean(B),
  ratio of means                mean(A) / mean(B) per channel,
  relMSE                        mean over pixels and channels of (A - B)^2 / (B^2 + eps),
  and the non-finite value count of each image.
With --tol-mean X the exit status is 1 when any |relative difference of means| exceeds X.
EXRs are read with Mitsuba's Bitmap (no OpenEXR Python package needed).
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np


def read_rgb(path):
    import mitsuba as mi

    if not mi.variant():
        mi.set_variant("scalar_rgb")
    try:
        bmp = mi.Bitmap(path)
    except Exception as e:  # noqa: BLE001
        raise SystemExit(f"error: cannot read {path}: {e}")
    try:
        bmp = bmp.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.Float32, False)
    except Exception as e:  # noqa: BLE001
        raise SystemExit(f"error: {path}: cannot convert to linear RGB float32 "
                         f"(pixel format {bmp.pixel_format()}): {e}")
    arr = np.array(bmp, dtype=np.float64)
    if arr.ndim == 2:
        arr = arr[:, :, None]
    return arr[:, :, :3]


def safe_div(a, b):
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(b != 0, a / np.where(b != 0, b, 1), np.nan)


def compare(a, b, eps=1e-2):
    if a.shape != b.shape:
        raise SystemExit(f"error: image sizes differ: A is {a.shape[1]}x{a.shape[0]}, "
                         f"B is {b.shape[1]}x{b.shape[0]}")
    fa, fb = np.isfinite(a), np.isfinite(b)
    ok = fa & fb
    a0, b0 = np.where(ok, a, 0.0), np.where(ok, b, 0.0)
    ma, mb = a0.reshape(-1, 3).mean(axis=0), b0.reshape(-1, 3).mean(axis=0)
    ma_all, mb_all = float(ma.mean()), float(mb.mean())
    rel = safe_div(ma - mb, mb)
    rel_all = (ma_all - mb_all) / mb_all if mb_all != 0 else float("nan")
    ratio = safe_div(ma, mb)
    relmse = float(np.mean((a0 - b0) ** 2 / (b0 ** 2 + eps)))
    mse = float(np.mean((a0 - b0) ** 2))
    return {
        "width": a.shape[1], "height": a.shape[0],
        "mean_a": ma.tolist(), "mean_b": mb.tolist(), "mean_a_all": ma_all, "mean_b_all": mb_all,
        "rel_diff_of_means": np.asarray(rel).tolist(), "rel_diff_of_means_all": rel_all,
        "ratio_of_means": np.asarray(ratio).tolist(),
        "relmse": relmse, "relmse_eps": eps, "mse": mse,
        "nonfinite_a": int((~fa).sum()), "nonfinite_b": int((~fb).sum()),
    }


def fmt3(v):
    return "[" + ", ".join(f"{x:.6g}" for x in v) + "]"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("a", help="image to test (A)")
    ap.add_argument("b", help="reference image (B)")
    ap.add_argument("--eps", type=float, default=1e-2, help="relMSE denominator offset (default 0.01)")
    ap.add_argument("--tol-mean", type=float, default=None,
                    help="fail (exit 1) when any |relative difference of means| exceeds this")
    ap.add_argument("--json", action="store_true", help="print the metrics as JSON")
    x = ap.parse_args(argv)
    r = compare(read_rgb(x.a), read_rgb(x.b), x.eps)
    if x.json:
        print(json.dumps({"a": x.a, "b": x.b, **r}, indent=1))
    else:
        print(f"A: {x.a} ({r['width']}x{r['height']})")
        print(f"B: {x.b} (reference)")
        print(f"mean RGB A:                  {fmt3(r['mean_a'])}  (all {r['mean_a_all']:.6g})")
        print(f"mean RGB B:                  {fmt3(r['mean_b'])}  (all {r['mean_b_all']:.6g})")
        print(f"rel. diff of means (A-B)/B:  {fmt3(r['rel_diff_of_means'])}  "
              f"(all {r['rel_diff_of_means_all']:+.4%})")
        print(f"ratio of means A/B per ch.:  {fmt3(r['ratio_of_means'])}")
        print(f"relMSE (eps {r['relmse_eps']:g}):          {r['relmse']:.6g}")
        print(f"MSE:                         {r['mse']:.6g}")
        if r["nonfinite_a"] or r["nonfinite_b"]:
            print(f"non-finite values: A {r['nonfinite_a']}, B {r['nonfinite_b']} "
                  "(excluded from the metrics)")
    if x.tol_mean is not None:
        worst = max(abs(v) for v in r["rel_diff_of_means"] if v == v) if r["rel_diff_of_means"] else 0
        if not worst <= x.tol_mean:
            print(f"FAIL: |relative difference of means| {worst:.4g} > {x.tol_mean:g}")
            return 1
        print(f"OK: |relative difference of means| {worst:.4g} <= {x.tol_mean:g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
