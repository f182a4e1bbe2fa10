#!/usr/bin/env python3
"""Check the Mitsuba converter against shared/conformance/camera_pixel_grid.

    check_conformance.py [FIXTURE_DIR] [--variant scalar_rgb|llvm_ad_rgb] [--spp N]

Renders camera_pixel_grid.json at max_bounces 0 and checks that exactly the pixel
rectangles of camera_pixel_grid.expected.json ([c0, c1) x [r0, r1), row 0 at the top)
hold the emitter radiance and every other pixel is exactly 0. Exit status 0 on success.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
from render_mitsuba import VARIANTS, render  # noqa: E402
from scene_json import load_scene  # noqa: E402


def default_fixture_dir():
    repo = os.path.dirname(os.path.dirname(HERE))
    for cand in (os.path.join(repo, "shared", "conformance"),
                 os.path.join(os.path.dirname(repo), "shared", "conformance"),
                 "/work/shared/conformance"):
        if os.path.isfile(os.path.join(cand, "camera_pixel_grid.json")):
            return cand
    return None


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("fixture_dir", nargs="?", default=None)
    ap.add_argument("--variant", default="scalar_rgb", choices=VARIANTS)
    ap.add_argument("--spp", type=int, default=16)
    a = ap.parse_args(argv)
    fdir = a.fixture_dir or default_fixture_dir()
    if fdir is None:
        print("error: cannot find shared/conformance/camera_pixel_grid.json; pass its folder",
              file=sys.stderr)
        return 2
    with open(os.path.join(fdir, "camera_pixel_grid.expected.json")) as fh:
        expected = json.load(fh)
    scene = load_scene(os.path.join(fdir, "camera_pixel_grid.json"))
    img, info = render(scene, a.variant, spp=a.spp, max_bounces=expected["max_bounces"])
    h, w = img.shape[:2]
    want = np.zeros((h, w, 3), dtype=np.float32)
    for c0, r0, c1, r1, rad in expected["rects_c0_r0_c1_r1_radiance"]:
        want[r0:r1, c0:c1, :] = np.asarray(rad, dtype=np.float32)
    bad = np.any(img != want, axis=2)
    nbad = int(bad.sum())
    print(f"camera_pixel_grid: {w}x{h}, {a.spp} spp, M={expected['max_bounces']}, "
          f"variant {a.variant}: {nbad} pixels differ")
    if nbad:
        rows, cols = np.nonzero(bad)
        for r, c in list(zip(rows, cols))[:10]:
            print(f"  pixel (col {c}, row {r}): got {img[r, c].tolist()}, want {want[r, c].tolist()}")
        # where did each colour land?
        for ch, name in enumerate("RGB"):
            rr, cc = np.nonzero(img[:, :, ch] > 0)
            if len(rr):
                print(f"  {name} > 0 in cols [{cc.min()}, {cc.max() + 1}), rows [{rr.min()}, {rr.max() + 1})")
        print("FAIL")
        return 1
    print("PASS")
    return 0


if __name__ == "__main__":
    sys.exit(main())
