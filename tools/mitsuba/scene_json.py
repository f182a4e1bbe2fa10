"""Reader for nppp's scene JSON (see docs/scene-format.md), without Mitsuba.

Validates a scene file against the contract and turns every instance into a
plain triangle mesh in world space (numpy arrays), so that a reference
renderer can consume it. Every error names the offending key path or file and
raises SceneError; nothing is ever silently dropped or replaced.

Only the standard library and numpy are needed here; render_mitsuba.py does the
Mitsuba side.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field

import numpy as np

MAX_IMAGE_SIDE = 16384
MAX_ICOSPHERE_LEVELS = 8

DEFAULT_RENDER = {"spp": 64, "max_bounces": 5, "seed": 0, "estimator_min_bounces": 2}

MATERIAL_KEYS = {
    "diffuse": ({"type", "albedo"}, {"type", "albedo"}),
    "conductor": ({"type", "reflectance", "roughness"}, {"type", "reflectance", "roughness"}),
    "dielectric": ({"type", "ior"}, {"type", "ior"}),
    "translucent": ({"type", "ior", "sigma_s", "sigma_a", "g"}, {"type", "ior", "sigma_s", "sigma_a"}),
    "emitter": ({"type", "radiance"}, {"type", "radiance"}),
}
MESH_SOURCES = ("quad", "box", "icosphere", "obj")


class SceneError(Exception):
    """A scene that does not follow docs/scene-format.md. The message names the key path or file."""


# --------------------------------------------------------------------------
# small typed accessors


def _is_number(x):
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def _num(x, path):
    if not _is_number(x):
        raise SceneError(f"{path}: expected a number, got {json.dumps(x)}")
    x = float(x)
    if not math.isfinite(x):
        raise SceneError(f"{path}: non-finite number")
    return x


def _int(x, path, lo=None, hi=None):
    if isinstance(x, bool) or not (isinstance(x, int) or (isinstance(x, float) and x.is_integer())):
        raise SceneError(f"{path}: expected an integer, got {json.dumps(x)}")
    x = int(x)
    if lo is not None and x < lo:
        raise SceneError(f"{path}: must be >= {lo}, got {x}")
    if hi is not None and x > hi:
        raise SceneError(f"{path}: must be <= {hi}, got {x}")
    return x


def _vec3(x, path):
    if not isinstance(x, list) or len(x) != 3:
        raise SceneError(f"{path}: expected an array of 3 numbers, got {json.dumps(x)}")
    return np.array([_num(v, f"{path}[{i}]") for i, v in enumerate(x)], dtype=np.float64)


def _unit_range3(x, path):
    v = _vec3(x, path)
    for i in range(3):
        if not (0.0 <= v[i] <= 1.0):
            raise SceneError(f"{path}[{i}]: must be in [0, 1], got {v[i]}")
    return v


def _obj(x, path):
    if not isinstance(x, dict):
        raise SceneError(f"{path}: expected an object, got {json.dumps(x)[:60]}")
    return x


def _check_keys(d, path, allowed, required=()):
    for k in d:
        if k not in allowed:
            where = f"{path}.{k}" if path else k
            raise SceneError(
                f"{where}: unknown key (allowed here: {', '.join(sorted(allowed))}); "
                "this reference renderer refuses keys it does not understand"
            )
    for k in required:
        if k not in d:
            where = f"{path}.{k}" if path else k
            raise SceneError(f"{where}: missing required key")


# --------------------------------------------------------------------------
# data


@dataclass
class Camera:
    position: np.ndarray
    look_at: np.ndarray
    up: np.ndarray
    fov_y_deg: float
    width: int
    height: int
    # derived orthonormal frame (contract convention)
    forward: np.ndarray = field(default=None)
    right: np.ndarray = field(default=None)
    true_up: np.ndarray = field(default=None)


@dataclass
class Material:
    name: str
    type: str
    albedo: np.ndarray | None = None
    reflectance: np.ndarray | None = None
    roughness: float = 0.0
    ior: float = 1.0
    radiance: np.ndarray | None = None
    # translucent: per unit length in the mesh's own coordinates
    sigma_s: np.ndarray | None = None
    sigma_a: np.ndarray | None = None
    g: float = 0.0


@dataclass
class MeshData:
    """Object-space triangles. normals is per-vertex (smooth) or None (flat)."""

    positions: np.ndarray  # (N, 3) float64
    faces: np.ndarray  # (F, 3) int64
    normals: np.ndarray | None = None  # (N, 3) float64 or None


@dataclass
class Instance:
    index: int
    mesh_name: str
    material: Material
    positions: np.ndarray  # world space (N, 3)
    faces: np.ndarray
    normals: np.ndarray | None  # world space or None
    estimator: str | None = None
    scale: float = 1.0  # the transform's uniform scale (a medium's coefficients are divided by it)


@dataclass
class Scene:
    path: str
    camera: Camera
    materials: dict
    instances: list
    render: dict


# --------------------------------------------------------------------------
# camera


def parse_camera(c):
    c = _obj(c, "camera")
    _check_keys(c, "camera", {"position", "look_at", "up", "fov_y_deg", "width", "height"},
                ("position", "look_at", "fov_y_deg", "width", "height"))
    pos = _vec3(c["position"], "camera.position")
    tgt = _vec3(c["look_at"], "camera.look_at")
    up = _vec3(c.get("up", [0, 1, 0]), "camera.up")
    fov = _num(c["fov_y_deg"], "camera.fov_y_deg")
    if not (0.0 < fov < 180.0):
        raise SceneError(f"camera.fov_y_deg: must be in (0, 180), got {fov}")
    w = _int(c["width"], "camera.width", 1, MAX_IMAGE_SIDE)
    h = _int(c["height"], "camera.height", 1, MAX_IMAGE_SIDE)
    d = tgt - pos
    dn = np.linalg.norm(d)
    if not dn > 0:
        raise SceneError("camera.look_at: equals camera.position (degenerate camera)")
    fwd = d / dn
    r = np.cross(fwd, up)
    rn = np.linalg.norm(r)
    if not rn > 1e-12 * max(1.0, np.linalg.norm(up)):
        raise SceneError("camera.up: zero or parallel to the view direction (degenerate camera)")
    right = r / rn
    tup = np.cross(right, fwd)
    return Camera(pos, tgt, up, fov, w, h, fwd, right, tup)


# --------------------------------------------------------------------------
# materials


def parse_material(name, m):
    path = f"materials.{name}"
    m = _obj(m, path)
    if "type" not in m:
        raise SceneError(f"{path}.type: missing required key")
    t = m["type"]
    if t not in MATERIAL_KEYS:
        raise SceneError(f"{path}.type: unknown material type {json.dumps(t)} "
                         f"(known: {', '.join(MATERIAL_KEYS)})")
    allowed, required = MATERIAL_KEYS[t]
    _check_keys(m, path, allowed, required)
    mat = Material(name=name, type=t)
    if t == "diffuse":
        mat.albedo = _unit_range3(m["albedo"], f"{path}.albedo")
    elif t == "conductor":
        mat.reflectance = _unit_range3(m["reflectance"], f"{path}.reflectance")
        mat.roughness = _num(m["roughness"], f"{path}.roughness")
        if not (0.0 <= mat.roughness <= 1.0):
            raise SceneError(f"{path}.roughness: must be in [0, 1], got {mat.roughness}")
    elif t == "dielectric":
        mat.ior = _num(m["ior"], f"{path}.ior")
        if not mat.ior > 0:
            raise SceneError(f"{path}.ior: must be > 0, got {mat.ior}")
    elif t == "translucent":
        mat.ior = _num(m["ior"], f"{path}.ior")
        if not mat.ior > 0:
            raise SceneError(f"{path}.ior: must be > 0, got {mat.ior}")
        for key in ("sigma_s", "sigma_a"):
            v = _vec3(m[key], f"{path}.{key}")
            for i in range(3):
                if not (np.isfinite(v[i]) and v[i] >= 0):
                    raise SceneError(f"{path}.{key}[{i}]: must be finite and >= 0, got {v[i]}")
            setattr(mat, key, v)
        mat.g = _num(m.get("g", 0.0), f"{path}.g")
        if not abs(mat.g) < 1:
            raise SceneError(f"{path}.g: must be in (-1, 1), got {mat.g}")
    elif t == "emitter":
        mat.radiance = _vec3(m["radiance"], f"{path}.radiance")
        for i in range(3):
            if mat.radiance[i] < 0:
                raise SceneError(f"{path}.radiance[{i}]: must be >= 0, got {mat.radiance[i]}")
    return mat


# --------------------------------------------------------------------------
# meshes


def quad_mesh(q, path):
    if not isinstance(q, list) or len(q) != 4:
        raise SceneError(f"{path}: expected an array of 4 points")
    p = np.stack([_vec3(v, f"{path}[{i}]") for i, v in enumerate(q)])
    return MeshData(p, np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int64))


def box_mesh(b, path):
    b = _obj(b, path)
    _check_keys(b, path, {"min", "max"}, ("min", "max"))
    lo = _vec3(b["min"], f"{path}.min")
    hi = _vec3(b["max"], f"{path}.max")
    for i in range(3):
        if not lo[i] < hi[i]:
            raise SceneError(f"{path}.min: min[{i}] = {lo[i]} is not below max[{i}] = {hi[i]}")
    # 8 corners, index bit k selects max along axis k
    corners = np.array([[hi[0] if i & 1 else lo[0], hi[1] if i & 2 else lo[1], hi[2] if i & 4 else lo[2]]
                        for i in range(8)])
    faces = []
    for axis in range(3):
        a1, a2 = (axis + 1) % 3, (axis + 2) % 3
        for side in (0, 1):
            base = side << axis
            # corners of this face, going around in the (a1, a2) plane
            ring = [base, base | (1 << a1), base | (1 << a1) | (1 << a2), base | (1 << a2)]
            outward = np.zeros(3)
            outward[axis] = 1.0 if side else -1.0
            n = np.cross(corners[ring[1]] - corners[ring[0]], corners[ring[2]] - corners[ring[0]])
            if np.dot(n, outward) < 0:
                ring = ring[::-1]
            faces.append([ring[0], ring[1], ring[2]])
            faces.append([ring[0], ring[2], ring[3]])
    faces = np.array(faces, dtype=np.int64)
    _assert_outward(corners, faces, 0.5 * (lo + hi), path)
    return MeshData(corners, faces)


# the usual icosahedron (12 vertices in the contract's order, 20 faces CCW from outside)
_ICO_FACES = [
    [0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11],
    [1, 5, 9], [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8],
    [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9],
    [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1],
]


def icosphere_unit(levels):
    t = (1.0 + math.sqrt(5.0)) / 2.0
    verts = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0),
             (0, -1, t), (0, 1, t), (0, -1, -t), (0, 1, -t),
             (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]
    v = [np.array(p, dtype=np.float64) / np.linalg.norm(p) for p in verts]
    faces = [tuple(f) for f in _ICO_FACES]
    for _ in range(levels):
        cache = {}

        def mid(i, j):
            key = (min(i, j), max(i, j))
            if key not in cache:
                m = 0.5 * (v[i] + v[j])
                v.append(m / np.linalg.norm(m))  # projected onto the sphere at once
                cache[key] = len(v) - 1
            return cache[key]

        nf = []
        for a, b, c in faces:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            nf += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = nf
    return np.array(v), np.array(faces, dtype=np.int64)


def icosphere_mesh(s, path):
    s = _obj(s, path)
    _check_keys(s, path, {"center", "radius", "subdivisions"}, ("center", "radius", "subdivisions"))
    c = _vec3(s["center"], f"{path}.center")
    r = _num(s["radius"], f"{path}.radius")
    if not r > 0:
        raise SceneError(f"{path}.radius: must be > 0, got {r}")
    n = _int(s["subdivisions"], f"{path}.subdivisions", 0, MAX_ICOSPHERE_LEVELS)
    v, f = icosphere_unit(n)
    _assert_outward(v, f, np.zeros(3), path)
    return MeshData(c + r * v, f)


def _assert_outward(v, f, center, path):
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    cen = v[f].mean(axis=1) - center
    if not np.all(np.einsum("ij,ij->i", n, cen) > 0):
        raise SceneError(f"{path}: internal error, a face is not oriented outward")


_PLURAL = {"vertex": "vertices", "texture coordinate": "texture coordinates", "normal": "normals"}


def _obj_index(tok, defined, fname, lineno, what):
    """1-based or negative OBJ index -> 0-based. Negative indices count back from the
    elements defined so far; positive ones are range-checked once the file is read."""
    try:
        i = int(tok)
    except ValueError:
        raise SceneError(f"{fname}:{lineno}: {what} index {tok!r} is not an integer")
    if i > 0:
        return i - 1
    if i < 0:
        if defined + i < 0:
            raise SceneError(f"{fname}:{lineno}: relative {what} index {i} points before the first "
                             f"{what}: only {defined} defined so far")
        return defined + i
    raise SceneError(f"{fname}:{lineno}: {what} index 0 is invalid (OBJ indices start at 1)")


def load_obj(fname, smooth, path):
    """Parse a Wavefront OBJ. Returns MeshData (vertex normals only if smooth)."""
    try:
        with open(fname, "r", encoding="utf-8", errors="replace") as fh:
            lines = fh.readlines()
    except OSError as e:
        raise SceneError(f"{path}: cannot read OBJ file {fname}: {e.strerror}")
    vs, vns = [], []
    nvt = 0
    corners = []  # per triangle: 3 x (vi, ni or -1)
    checks = []  # (index, kind, lineno) to range-check after the whole file is read
    for lineno, raw in enumerate(lines, 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.split()
        tag = parts[0]
        try:
            if tag in ("v", "vn"):
                xyz = [float(x) for x in parts[1:4]]
                if len(xyz) != 3:
                    raise ValueError
                if not all(math.isfinite(x) for x in xyz):
                    raise SceneError(f"{fname}:{lineno}: non-finite {tag} coordinate")
                (vs if tag == "v" else vns).append(xyz)
            elif tag == "vt":
                nvt += 1
            elif tag == "f":
                poly = []
                for tok in parts[1:]:
                    sub = tok.split("/")
                    if (len(sub) > 3 or sub[0] == "" or (len(sub) == 2 and sub[1] == "")
                            or (len(sub) == 3 and sub[2] == "")):
                        raise SceneError(f"{fname}:{lineno}: face vertex {tok!r} is not one of "
                                         "v, v/vt, v//vn, v/vt/vn")
                    vi = _obj_index(sub[0], len(vs), fname, lineno, "vertex")
                    checks.append((vi, "vertex", lineno))
                    if len(sub) >= 2 and sub[1] != "":
                        ti = _obj_index(sub[1], nvt, fname, lineno, "texture coordinate")
                        checks.append((ti, "texture coordinate", lineno))
                    ni = -1
                    if len(sub) == 3:
                        ni = _obj_index(sub[2], len(vns), fname, lineno, "normal")
                        checks.append((ni, "normal", lineno))
                    poly.append((vi, ni))
                if len(poly) < 3:
                    raise SceneError(f"{fname}:{lineno}: a face needs at least 3 vertices")
                if smooth and any(ni < 0 for _, ni in poly):
                    raise SceneError(f"{path}: \"smooth\": true but {fname}:{lineno} has a face "
                                     "without vertex normals (use v//vn or v/vt/vn)")
                for i in range(1, len(poly) - 1):
                    corners.append((poly[0], poly[i], poly[i + 1]))
            # other statements (o, g, s, usemtl, mtllib, l, p, ...) carry no geometry we use
        except ValueError:
            raise SceneError(f"{fname}:{lineno}: cannot parse {line[:60]!r}")
    counts = {"vertex": len(vs), "texture coordinate": nvt, "normal": len(vns)}
    for idx, kind, lineno in checks:
        if idx >= counts[kind]:
            n = counts[kind]
            raise SceneError(f"{fname}:{lineno}: {kind} index {idx + 1} points past the file's "
                             f"{n} {kind if n == 1 else _PLURAL[kind]}")
    if not corners:
        raise SceneError(f"{path}: OBJ file {fname} has no faces")
    V = np.array(vs, dtype=np.float64)
    if not smooth:
        F = np.array([[c[0] for c in tri] for tri in corners], dtype=np.int64)
        return MeshData(V, F)
    # smooth: a vertex is a (position, normal) pair
    N = np.array(vns, dtype=np.float64)
    remap = {}
    pos, nrm, F = [], [], []
    for tri in corners:
        idx = []
        for key in tri:
            if key not in remap:
                remap[key] = len(pos)
                pos.append(V[key[0]])
                nrm.append(N[key[1]])
            idx.append(remap[key])
        F.append(idx)
    return MeshData(np.array(pos), np.array(F, dtype=np.int64), np.array(nrm))


def parse_mesh(name, m, scene_dir):
    path = f"meshes.{name}"
    m = _obj(m, path)
    sources = [k for k in m if k in MESH_SOURCES]
    unknown = [k for k in m if k not in MESH_SOURCES and k != "smooth"]
    if unknown:
        raise SceneError(f"{path}.{unknown[0]}: unknown mesh key or mesh source "
                         f"(this reference renderer knows {', '.join(MESH_SOURCES)} and 'smooth'); "
                         "export the mesh to OBJ and pass --mesh-obj NAME=FILE.obj (make: MESH_OBJ=NAME=FILE.obj), "
                         "or add the source to tools/mitsuba/scene_json.py")
    if len(sources) != 1:
        raise SceneError(f"{path}: needs exactly one mesh source out of {', '.join(MESH_SOURCES)}, "
                         f"got {sources or 'none'}")
    src = sources[0]
    smooth = m.get("smooth", False)
    if not isinstance(smooth, bool):
        raise SceneError(f"{path}.smooth: expected true or false")
    if smooth and src != "obj":
        raise SceneError(f"{path}.smooth: only obj meshes have vertex normals; {src} is flat shaded")
    if src == "quad":
        return quad_mesh(m["quad"], f"{path}.quad")
    if src == "box":
        return box_mesh(m["box"], f"{path}.box")
    if src == "icosphere":
        return icosphere_mesh(m["icosphere"], f"{path}.icosphere")
    f = m["obj"]
    if not isinstance(f, str) or not f:
        raise SceneError(f"{path}.obj: expected a file path")
    return load_obj(os.path.join(scene_dir, f), smooth, f"{path}.obj")


# --------------------------------------------------------------------------
# transforms


def rotation_matrix(axis, deg):
    """Right-hand rule rotation by deg degrees about the (normalized) axis (Rodrigues)."""
    a = axis / np.linalg.norm(axis)
    th = math.radians(deg)
    c, s = math.cos(th), math.sin(th)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) * c + s * K + (1 - c) * np.outer(a, a)


def parse_transform(t, path):
    """Returns (scale, R, translate): p' = R (scale p) + translate."""
    if t is None:
        return 1.0, np.eye(3), np.zeros(3)
    t = _obj(t, path)
    _check_keys(t, path, {"scale", "rotate", "translate"})
    s = _num(t.get("scale", 1.0), f"{path}.scale")
    if not s > 0:
        raise SceneError(f"{path}.scale: must be > 0, got {s}")
    R = np.eye(3)
    if "rotate" in t:
        r = _obj(t["rotate"], f"{path}.rotate")
        _check_keys(r, f"{path}.rotate", {"axis", "deg"}, ("axis", "deg"))
        axis = _vec3(r["axis"], f"{path}.rotate.axis")
        if not np.linalg.norm(axis) > 0:
            raise SceneError(f"{path}.rotate.axis: zero-length axis")
        R = rotation_matrix(axis, _num(r["deg"], f"{path}.rotate.deg"))
    tr = _vec3(t.get("translate", [0, 0, 0]), f"{path}.translate")
    return s, R, tr


# --------------------------------------------------------------------------
# scene


def _check_closed(md, mname, matname):
    """The contract's "the mesh must be closed" for a translucent material, as nppp reads
    it: every edge shared by exactly two triangles that use it in opposite directions,
    vertices at bit-identical positions counting as one (OBJ files split them at normal
    seams). Mitsuba renders an open one without a word; nppp refuses it."""
    weld = {}
    ids = [weld.setdefault(tuple(p.tolist()), len(weld)) for p in md.positions]
    count = {}
    for f in md.faces:
        for k in range(3):
            a, b = ids[int(f[k])], ids[int(f[(k + 1) % 3])]
            if a != b:
                count[(a, b)] = count.get((a, b), 0) + 1
    for (a, b), n in count.items():
        if n != 1 or count.get((b, a), 0) != 1:
            raise SceneError(f"meshes.{mname}: the mesh is not closed (an edge is used {n} time(s) "
                             f"one way and {count.get((b, a), 0)} the other), which materials."
                             f"{matname} (translucent) requires")


def load_scene(path, mesh_obj=None):
    """mesh_obj: optional {mesh name: OBJ path (relative to the working directory)} that
    replaces those meshes' sources, e.g. a procedural mesh exported by the Rust side."""
    try:
        with open(path, "r", encoding="utf-8") as fh:
            text = fh.read()
    except OSError as e:
        raise SceneError(f"{path}: cannot read scene file: {e.strerror}")
    try:
        doc = json.loads(text, parse_constant=lambda c: (_ for _ in ()).throw(
            SceneError(f"{path}: non-finite number {c} in JSON")))
    except json.JSONDecodeError as e:
        raise SceneError(f"{path}: invalid JSON: {e}")
    if mesh_obj:
        meshes = doc.get("meshes") if isinstance(doc, dict) else None
        for name, objpath in mesh_obj.items():
            if not isinstance(meshes, dict) or name not in meshes:
                raise SceneError(f"--mesh-obj {name}={objpath}: the scene has no mesh {name!r}")
            m = meshes[name]
            smooth = m.get("smooth", False) if isinstance(m, dict) else False
            meshes[name] = {"obj": os.path.abspath(objpath)}
            if smooth is True and "obj" in m:
                meshes[name]["smooth"] = True
    return parse_scene(doc, os.path.dirname(os.path.abspath(path)), path)


def parse_scene(doc, scene_dir, path="<scene>"):
    doc = _obj(doc, "<root>")
    _check_keys(doc, "", {"camera", "materials", "meshes", "instances", "render"},
                ("camera", "materials", "meshes", "instances"))
    camera = parse_camera(doc["camera"])

    mats = _obj(doc["materials"], "materials")
    materials = {n: parse_material(n, m) for n, m in mats.items()}

    meshes_doc = _obj(doc["meshes"], "meshes")
    meshes = {}

    render = dict(DEFAULT_RENDER)
    if "render" in doc:
        r = _obj(doc["render"], "render")
        _check_keys(r, "render", set(DEFAULT_RENDER))
        for k in r:
            render[k] = _int(r[k], f"render.{k}", 0)
        if render["spp"] < 1:
            raise SceneError("render.spp: must be >= 1")

    insts = doc["instances"]
    if not isinstance(insts, list):
        raise SceneError("instances: expected an array")
    instances = []
    for i, inst in enumerate(insts):
        ip = f"instances[{i}]"
        inst = _obj(inst, ip)
        _check_keys(inst, ip, {"mesh", "material", "transform", "estimator"}, ("mesh", "material"))
        mname, matname = inst["mesh"], inst["material"]
        if not isinstance(mname, str) or mname not in meshes_doc:
            raise SceneError(f"{ip}.mesh: unknown mesh {json.dumps(mname)}")
        if not isinstance(matname, str) or matname not in materials:
            raise SceneError(f"{ip}.material: unknown material {json.dumps(matname)}")
        est = inst.get("estimator")
        if est is not None and not isinstance(est, str):
            raise SceneError(f"{ip}.estimator: expected a path")
        if mname not in meshes:
            meshes[mname] = parse_mesh(mname, meshes_doc[mname], scene_dir)
        md = meshes[mname]
        if materials[matname].type == "translucent":
            _check_closed(md, mname, matname)
        s, R, t = parse_transform(inst.get("transform"), f"{ip}.transform")
        pos = (s * md.positions) @ R.T + t
        nrm = None
        if md.normals is not None:
            nrm = md.normals @ R.T
            ln = np.linalg.norm(nrm, axis=1, keepdims=True)
            if np.any(ln == 0):
                raise SceneError(f"meshes.{mname}: zero-length vertex normal in the OBJ file")
            nrm = nrm / ln
        instances.append(Instance(i, mname, materials[matname], pos, md.faces, nrm, est, float(s)))
    # meshes that no instance uses still have to be valid
    for mname in meshes_doc:
        if mname not in meshes:
            meshes[mname] = parse_mesh(mname, meshes_doc[mname], scene_dir)
    return Scene(path, camera, materials, instances, render)
