#!/usr/bin/env python3
"""Render an nppp scene JSON (docs/scene-format.md) with Mitsuba 3 as an independent reference.

    render_mitsuba.py SCENE.json --out FILE.exr [--spp N] [--variant scalar_rgb|llvm_ad_rgb]
                      [--max-bounces M] [--seed S] [--threads T] [--time]

Python and Mitsuba are an optional reference only; nothing in the Rust pipeline needs them.
See tools/mitsuba/README.md for the mapping from the contract onto Mitsuba 3.
"""

from __future__ import annotations

import argparse
import glob
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from scene_json import SceneError, load_scene  # noqa: E402

VARIANTS = ("scalar_rgb", "llvm_ad_rgb")


def find_libllvm():
    """Path of a libLLVM >= 16 for Dr.Jit's LLVM backend, or None."""
    env = os.environ.get("DRJIT_LIBLLVM_PATH")
    if env:
        return env
    for ver in range(25, 15, -1):
        for pat in (f"/usr/lib/*/libLLVM-{ver}.so", f"/usr/lib/*/libLLVM.so.{ver}*",
                    f"/usr/lib/llvm-{ver}/lib/libLLVM*.so*"):
            hits = sorted(glob.glob(pat))
            if hits:
                return hits[0]
    return None


def setup_mitsuba(variant, threads=None):
    """Import mitsuba with the given variant; returns (mi, dr)."""
    if variant.startswith("llvm"):
        lib = find_libllvm()
        if lib is None:
            raise SystemExit(
                "error: variant llvm_ad_rgb needs libLLVM >= 16 (Debian: apt-get install libllvm19); "
                "set DRJIT_LIBLLVM_PATH to the library")
        os.environ["DRJIT_LIBLLVM_PATH"] = lib
    import drjit as dr
    import mitsuba as mi

    if variant not in mi.variants():
        raise SystemExit(f"error: this Mitsuba build has no variant {variant}")
    try:
        mi.set_variant(variant)
    except Exception as e:  # noqa: BLE001
        raise SystemExit(f"error: cannot set Mitsuba variant {variant}: {e}")
    if threads is not None:
        # Mitsuba 3 renders on Dr.Jit's nanothread pool (scalar and LLVM variants alike);
        # N counts the calling thread, as in dr.set_thread_count's documentation.
        dr.set_thread_count(threads)
    return mi, dr


def rgb(v):
    return {"type": "rgb", "value": [float(x) for x in v]}


def bsdf_dict(mat):
    """Mitsuba BSDF for a contract material (emitters get a black diffuse)."""
    if mat.type == "diffuse":
        return {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": rgb(mat.albedo)}}
    if mat.type == "conductor":
        if mat.roughness == 0.0:
            inner = {"type": "conductor", "material": "none",
                     "specular_reflectance": rgb(mat.reflectance)}
        else:
            inner = {"type": "roughconductor", "distribution": "ggx", "alpha": float(mat.roughness),
                     "sample_visible": True, "material": "none",
                     "specular_reflectance": rgb(mat.reflectance)}
        return {"type": "twosided", "bsdf": inner}
    if mat.type in ("dielectric", "translucent"):
        return {"type": "dielectric", "int_ior": float(mat.ior), "ext_ior": 1.0}
    if mat.type == "emitter":
        return {"type": "diffuse", "reflectance": rgb([0.0, 0.0, 0.0])}
    raise SceneError(f"materials.{mat.name}.type: no Mitsuba mapping for {mat.type}")


def medium_dict(mat, scale):
    """The homogeneous medium inside a translucent instance, in world units: the
    contract's coefficients are per unit length of the mesh's own coordinates."""
    sigma_t = (mat.sigma_s + mat.sigma_a) / scale
    albedo = np.divide(mat.sigma_s, mat.sigma_s + mat.sigma_a,
                       out=np.zeros(3), where=(mat.sigma_s + mat.sigma_a) > 0)
    # A channel with no extinction at all beside channels with some made
    # volpathmis drop every path that scatters in the medium (its spectral MIS
    # divides by that channel's zero transmittance pdf: the image no longer
    # depended on g and came out 4.5% dark). A clear channel gets an extinction of
    # 1e-6 of the densest one, which changes no image measurably.
    if sigma_t.max() > 0:
        sigma_t = np.maximum(sigma_t, 1e-6 * sigma_t.max())
    # scalar_rgb reads an "rgb" sigma_t as a reflectance in [0, 1] (and stops with a
    # traceback above 1): larger coefficients go through the medium's "scale".
    k = float(max(1.0, sigma_t.max()))
    return {"type": "homogeneous", "sigma_t": rgb(sigma_t / k), "scale": k, "albedo": rgb(albedo),
            "phase": {"type": "hg", "g": float(mat.g)}}


def make_mesh(mi, inst):
    """A mi.Mesh with world-space vertices; emitters never get vertex normals."""
    mat = inst.material
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(bsdf_dict(mat))
    if mat.type == "emitter":
        props["emitter"] = mi.load_dict({"type": "area", "radiance": rgb(mat.radiance)})
    if mat.type == "translucent":
        props["interior"] = mi.load_dict(medium_dict(mat, inst.scale))
    normals = inst.normals if mat.type != "emitter" else None
    nv, nf = len(inst.positions), len(inst.faces)
    mesh = mi.Mesh(f"instance{inst.index}_{inst.mesh_name}", nv, nf, props=props,
                   has_vertex_normals=normals is not None)
    params = mi.traverse(mesh)

    def put(key, arr):
        params[key] = type(params[key])(np.ascontiguousarray(arr).ravel())

    put("vertex_positions", inst.positions.astype(np.float32))
    put("faces", inst.faces.astype(np.uint32))
    if normals is not None:
        put("vertex_normals", normals.astype(np.float32))
    params.update()
    return mesh


def default_rr_depth(scene, max_bounces):
    """Mitsuba's rr_depth when none is asked for: its default (5) on surfaces, none
    within max_depth where a medium is (see scene_dict)."""
    has_media = any(i.material.type == "translucent" for i in scene.instances)
    return int(max_bounces) + 2 if has_media else 5


def scene_dict(mi, scene, spp, max_bounces, seed, rr_depth=None):
    cam = scene.camera
    has_media = any(i.material.type == "translucent" for i in scene.instances)
    if rr_depth is None:
        rr_depth = default_rr_depth(scene, max_bounces)
    # Mitsuba clips camera rays to [near_clip, far_clip] (defaults 1e-2 and 1e4, absolute units);
    # the contract has no clipping, so size both from the scene.
    dist = float(np.linalg.norm(cam.look_at - cam.position))
    reach = max([float(np.linalg.norm(i.positions - cam.position, axis=1).max())
                 for i in scene.instances] + [dist])
    d = {
        "type": "scene",
        # A volumetric integrator only where a medium needs it: on surfaces `path` is the
        # same estimator. volpathmis weights the colour channels of a medium walk by
        # spectral MIS, as nppp does; volpath follows one channel's extinction, which
        # in strongly chromatic media gives the others rare huge samples (an image 1%
        # dark at 2048 spp). Media also get no Russian roulette unless asked: Mitsuba's
        # ends a walk at least 5% per event from rr_depth on, which in high-albedo media
        # made its green vary by +-2.7% between seeds at 4096 spp.
        "integrator": {"type": "volpathmis" if has_media else "path",
                       "max_depth": int(max_bounces) + 1, "hide_emitters": False,
                       **({} if rr_depth is None else {"rr_depth": int(rr_depth)})},
        "sensor": {
            "type": "perspective",
            "fov_axis": "y",
            "fov": float(cam.fov_y_deg),
            "near_clip": 1e-4 * dist,
            "far_clip": 4.0 * reach,
            "to_world": mi.ScalarTransform4f().look_at(
                origin=[float(x) for x in cam.position],
                target=[float(x) for x in cam.look_at],
                up=[float(x) for x in cam.up]),
            "film": {"type": "hdrfilm", "width": cam.width, "height": cam.height,
                     "rfilter": {"type": "box"}, "pixel_format": "rgb",
                     "component_format": "float32"},
            "sampler": {"type": "independent", "sample_count": int(spp), "seed": int(seed)},
        },
    }
    for inst in scene.instances:
        d[f"instance{inst.index}"] = make_mesh(mi, inst)
    return d


def render(scene, variant="scalar_rgb", spp=None, max_bounces=None, seed=None, threads=None,
           timing=False, log=print, rr_depth=None):
    """Render a parsed scene; returns (image HxWx3 float32 numpy, info dict)."""
    spp = scene.render["spp"] if spp is None else spp
    max_bounces = scene.render["max_bounces"] if max_bounces is None else max_bounces
    seed = scene.render["seed"] if seed is None else seed
    mi, dr = setup_mitsuba(variant, threads)
    t0 = time.perf_counter()
    mscene = mi.load_dict(scene_dict(mi, scene, spp, max_bounces, seed, rr_depth))
    t_load = time.perf_counter() - t0
    t_warm = 0.0
    if timing and variant.startswith("llvm"):
        t0 = time.perf_counter()
        warm = mi.render(mscene, spp=1, seed=seed + 1)
        dr.eval(warm)
        dr.sync_thread()
        t_warm = time.perf_counter() - t0
    t0, c0 = time.perf_counter(), time.process_time()
    img = mi.render(mscene, spp=spp, seed=seed)
    dr.eval(img)
    dr.sync_thread()
    t_render = time.perf_counter() - t0
    c_render = time.process_time() - c0
    arr = np.array(img, dtype=np.float32)
    info = {
        "variant": variant, "spp": spp, "max_bounces": max_bounces, "max_depth": max_bounces + 1,
        "seed": seed, "rr_depth": default_rr_depth(scene, max_bounces) if rr_depth is None else rr_depth,
        "threads": dr.thread_count(), "load_s": t_load, "warmup_s": t_warm,
        "render_s": t_render, "render_cpu_s": c_render,
        "samples_per_s": scene.camera.width * scene.camera.height * spp / t_render,
        "mi": mi,
    }
    return arr, info


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", help="scene JSON (docs/scene-format.md)")
    ap.add_argument("--out", required=True,
                    help="output OpenEXR (linear RGB float32); a path not ending in .exr is a "
                         "folder and gets FOLDER/<scene name>.mitsuba.exr")
    ap.add_argument("--spp", type=int, help="samples per pixel (default: scene render.spp, else 64)")
    ap.add_argument("--variant", default="scalar_rgb", choices=VARIANTS)
    ap.add_argument("--max-bounces", type=int,
                    help="M scattering events (default: scene render.max_bounces, else 5); "
                         "Mitsuba max_depth = M + 1")
    ap.add_argument("--seed", type=int, help="sampler seed (default: scene render.seed, else 0)")
    ap.add_argument("--threads", type=int, help="CPU threads (default: all cores)")
    ap.add_argument("--rr-depth", type=int,
                    help="Russian roulette from this many scattering events on (Mitsuba's "
                         "rr_depth; default 5, and none within max_depth in scenes with a "
                         "translucent object, where Mitsuba's roulette is heavy-tailed); nppp "
                         "starts at 3, so 3 matches its work per sample")
    ap.add_argument("--time", action="store_true",
                    help="print samples/s of the render alone (scene load and JIT warm-up excluded)")
    ap.add_argument("--mesh-obj", action="append", default=[], metavar="NAME=FILE.obj",
                    help="render meshes.NAME from this OBJ instead of its own source (for mesh "
                         "sources this tool does not know, e.g. a procedural mesh the Rust side "
                         "exported); repeatable")
    a = ap.parse_args(argv)
    mesh_obj = {}
    for item in a.mesh_obj:
        name, sep, path = item.partition("=")
        if not sep or not name or not path:
            ap.error(f"--mesh-obj expects NAME=FILE.obj, got {item!r}")
        mesh_obj[name] = path
    if os.path.isdir(a.out) or not a.out.lower().endswith(".exr"):
        stem = os.path.splitext(os.path.basename(a.scene))[0]
        a.out = os.path.join(a.out, f"{stem}.mitsuba.exr")
    for name in ("spp", "threads"):
        v = getattr(a, name)
        if v is not None and v < 1:
            ap.error(f"--{name} must be >= 1")
    if a.max_bounces is not None and a.max_bounces < 0:
        ap.error("--max-bounces must be >= 0")
    try:
        scene = load_scene(a.scene, mesh_obj)
        for name, path in mesh_obj.items():
            print(f"note: meshes.{name} rendered from {path} (--mesh-obj)")
        arr, info = render(scene, a.variant, a.spp, a.max_bounces, a.seed, a.threads, a.time,
                           rr_depth=a.rr_depth)
    except SceneError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    bad = int(np.count_nonzero(~np.isfinite(arr)))
    if bad:
        print(f"error: Mitsuba produced {bad} non-finite values; not writing {a.out}", file=sys.stderr)
        return 3
    mi = info["mi"]
    if a.threads is not None and a.threads < 2:
        # Mitsuba 3.9's EXR writer waits on the thread pool and hangs with no worker thread.
        import drjit as dr
        dr.set_thread_count(os.cpu_count() or 2)
    out_dir = os.path.dirname(os.path.abspath(a.out))
    os.makedirs(out_dir, exist_ok=True)
    bmp = mi.Bitmap(arr, mi.Bitmap.PixelFormat.RGB)
    bmp.write(a.out)
    h, w = arr.shape[:2]
    print(f"wrote {a.out}: {w}x{h}, {info['spp']} spp, M={info['max_bounces']} "
          f"(max_depth {info['max_depth']}), variant {info['variant']}, seed {info['seed']}, "
          f"mean RGB {arr.reshape(-1, 3).mean(axis=0).round(6).tolist()}")
    if a.time:
        print(f"time: load {info['load_s']:.3f} s, warm-up {info['warmup_s']:.3f} s, "
              f"render {info['render_s']:.3f} s (process CPU {info['render_cpu_s']:.3f} s; "
              f"{w * h * info['spp'] / info['render_cpu_s']:.4g} samples per CPU-second)")
        print(f"samples/s: {info['samples_per_s']:.4g} ({w}x{h}x{info['spp']} samples, "
              f"threads {info['threads']}, variant {info['variant']})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
