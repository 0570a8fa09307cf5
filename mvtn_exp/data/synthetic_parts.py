"""Embedded synthetic part-segmentation dataset: 5 categories assembled from labelled primitives.

Every face of a shape belongs to one part, and every sampled point takes the part of the face it
was sampled on. Categories and their parts (Y-up, front +Z, floor at y=0 where there is one):

- ``airplane``: fuselage (revolved, nose +Z), swept wings, tail (fin and stabiliser), engines
  (0, 2 or 4 pods under the wings: absent from about 3 in 10 planes; seen from below).
- ``chair``: seat, 4 legs, back, arms (on about half of the chairs).
- ``lamp``: base, stem, open shade, bulb: a sphere held wholly inside the shade's height, so a
  camera level with it sees only the shade wall; it shows through the shade's openings, from
  above or below.
- ``mug``: open body, handle on +X, contents (a thin liquid disc inside the body, in about 4 of 5
  mugs): seen only from above the rim.
- ``table``: top, 4 legs, shelf (a low shelf between the legs on about 3 in 5 tables).

Global part ids number ``PART_NAMES`` (``"category/part"``, sorted: a category's parts are
consecutive). Every instance draws its proportions from a numpy Generator seeded by (seed, split,
category, index), in a fixed order whatever the face budget; the shape is centred (bounding box at
the origin) and scaled into the unit sphere, then optionally rotated about the origin. Each split
is generated once and cached as an ``.npz`` whose name hashes every setting that determines it.
"""
from __future__ import annotations

import copy
import zlib

import numpy as np
import torch
import trimesh

from .mesh_io import normalize_unit_sphere
from .packed import PACKED_ARRAYS, PackedShapes, cached_arrays, triangle_areas, validate
from .synthetic import Part, _areas, _box, _check, _cyl, _legs, _outward, _revolve, _arc_tube, _tm, random_rotation
from .synthetic_cache import SPLITS, cache_file, split_count

GEOMETRY_VERSION = "2"  # bump whenever a builder or the cached arrays change: old caches then miss
PARTS = {
    "airplane": ("engines", "fuselage", "tail", "wings"),
    "chair": ("arms", "back", "legs", "seat"),
    "lamp": ("base", "bulb", "shade", "stem"),
    "mug": ("body", "contents", "handle"),
    "table": ("legs", "shelf", "top"),
}
CLASSES: list[str] = sorted(PARTS)
PART_NAMES: list[str] = [f"{c}/{p}" for c in CLASSES for p in sorted(PARTS[c])]
PARTS_OF: dict[int, list[int]] = {i: [PART_NAMES.index(f"{c}/{p}") for p in sorted(PARTS[c])]
                                  for i, c in enumerate(CLASSES)}
EXTRA = ("rotations", "part_labels", "face_parts", "point_faces")
Labelled = list[tuple[str, Part]]  # (part name within the category, closed mesh)


# ----------------------------------------------------------------------------- primitives
def _zcyl(radius, length, centre, res) -> Part:
    """Closed cylinder with its axis along Z."""
    return _tm(trimesh.creation.cylinder(radius=radius, height=length, sections=res), centre, False)


def _ellipsoid(radii, centre, res) -> Part:
    m = trimesh.creation.uv_sphere(radius=1.0, count=[max(res // 4, 4), max(res // 2, 6)])
    return _outward(np.asarray(m.vertices, np.float64) * radii + centre, np.asarray(m.faces, np.int64))


def _sheared(part: Part, k: float) -> Part:
    """Move each vertex back (-Z) by ``k |x|``: a box from x=0 outwards becomes a swept wing."""
    v = part[0].copy()
    v[:, 2] -= k * np.abs(v[:, 0])
    return v, part[1]


# ----------------------------------------------------------------------------- category builders
# Each builder draws its proportions from ``r`` (always in the same order, whatever ``res``) and
# returns labelled closed parts in the canonical pose.
def _airplane(r, res) -> Labelled:
    L, R = r.uniform(1.6, 2.2), r.uniform(0.09, 0.15)
    span, chord, sweep = r.uniform(1.3, 2.0), r.uniform(0.22, 0.38), r.uniform(0.0, 0.5)
    wy, zw = r.uniform(-0.6, 0.6), r.uniform(0.45, 0.6)  # wing height (in R), place along the body (in L)
    fin_h, fin_c, stab = r.uniform(0.25, 0.45), r.uniform(0.2, 0.3), r.uniform(0.4, 0.7)
    n_eng = int(r.choice([0, 2, 4], p=[0.3, 0.45, 0.25]))
    re, le, xe = r.uniform(0.35, 0.55) * R, r.uniform(0.25, 0.4), r.uniform(0.25, 0.4) * span / 2
    profile = [[0, 0], [0.45 * R, 0], [R, 0.25 * L], [R, 0.85 * L], [0.5 * R, 0.97 * L], [0, L], [0, 0]]
    fuselage = _tm(trimesh.creation.revolve(np.asarray(profile, np.float64), sections=res), (0, 0, -L / 2), False)
    y, z = wy * R, (zw - 0.5) * L
    parts = [("fuselage", fuselage)]
    parts += [("wings", _sheared(_box((span / 2, 0.03, chord), (s * span / 4, y, z)), sweep)) for s in (-1, 1)]
    tail_z = -L / 2 + fin_c / 2 + 0.03
    parts.append(("tail", _box((0.025, fin_h, fin_c), (0, 0.5 * R + fin_h / 2, tail_z))))
    parts.append(("tail", _box((stab, 0.02, 0.6 * fin_c), (0, 0.2 * R, tail_z))))
    xs = [xe] if n_eng == 2 else [xe, 1.8 * xe] if n_eng == 4 else []
    for x in (s * x for x in xs for s in (-1, 1)):
        parts.append(("engines", _zcyl(re, le, (x, y - 0.015 - re, z - sweep * abs(x) + 0.2 * chord), res)))
    return parts


def _chair(r, res) -> Labelled:
    S, T, H, Sd = r.uniform(0.4, 0.55), r.uniform(0.04, 0.08), r.uniform(0.4, 0.5), r.uniform(0.4, 0.6)
    s, round_legs = r.uniform(0.03, 0.06), r.random() < 0.5
    bh, bt = r.uniform(0.35, 0.7), r.uniform(0.03, 0.07)
    arms, ah, aw = r.random() < 0.5, r.uniform(0.15, 0.25), r.uniform(0.04, 0.07)
    parts = [("seat", _box((S, T, Sd), (0, H - T / 2, 0)))]
    parts += [("legs", p) for p in _legs(S / 2 - s / 2, Sd / 2 - s / 2, s, H - T, round_legs, res)]
    parts.append(("back", _box((S, bh, bt), (0, H + bh / 2, -Sd / 2 + bt / 2))))
    if arms:
        for x in (-1, 1):
            cx = x * (S / 2 + aw / 2)
            parts.append(("arms", _box((aw, 0.03, 0.85 * Sd), (cx, H + ah, 0.0))))
            parts.append(("arms", _box((0.6 * aw, ah + T, 0.6 * aw), (cx, H - T + (ah + T) / 2, 0.3 * Sd))))
    return parts


def _lamp(r, res) -> Labelled:
    rb, tb, rp, hp = r.uniform(0.2, 0.35), r.uniform(0.03, 0.08), r.uniform(0.015, 0.035), r.uniform(0.5, 1.0)
    sb, sh, t = r.uniform(0.25, 0.4), r.uniform(0.25, 0.4), r.uniform(0.015, 0.03)
    st, fb, j = r.uniform(0.5, 0.75) * sb, r.uniform(0.55, 0.8), r.uniform(0.0, 0.1)
    yc = tb + hp  # the bulb sits on the stem's top, wholly within the shade's height
    y0, rbulb = yc - (0.5 + j) * sh, fb * min(st - t, (0.5 - j) * sh)
    shade = _revolve([[sb, 0], [st, sh], [st - t, sh], [sb - t, 0], [sb, 0]], res, y0)
    return [("base", _cyl(rb, tb, (0, tb / 2, 0), res)), ("stem", _cyl(rp, hp, (0, tb + hp / 2, 0), res)),
            ("shade", shade), ("bulb", _ellipsoid((rbulb, rbulb, rbulb), (0, yc, 0), res))]


def _mug(r, res) -> Labelled:
    R, H = r.uniform(0.25, 0.5), r.uniform(0.6, 1.3)
    wall, bottom = r.uniform(0.04, 0.08), r.uniform(0.04, 0.1)
    major, minor, yc = r.uniform(0.2, 0.35) * H, r.uniform(0.03, 0.06), r.uniform(0.45, 0.55) * H
    full, level = r.random() < 0.8, r.uniform(0.35, 0.85)
    body = _revolve([[0, 0], [R, 0], [R, H], [R - wall, H], [R - wall, bottom], [0, bottom], [0, 0]], res)
    parts = [("body", body), ("handle", _arc_tube((R - wall / 2, yc, 0), major, minor, res))]
    if full:  # the liquid's surface: a thin disc just inside the inner wall, below the rim
        y = bottom + level * (H - bottom)
        parts.append(("contents", _cyl(0.97 * (R - wall), 0.015, (0, y - 0.0075, 0), res)))
    return parts


def _table(r, res) -> Labelled:
    W, D, T, H = r.uniform(1.0, 1.6), r.uniform(0.6, 1.0), r.uniform(0.04, 0.08), r.uniform(0.6, 0.9)
    s, e, round_legs = r.uniform(0.04, 0.09), r.uniform(0.0, 0.1), r.random() < 0.5
    shelf, sy, sth = r.random() < 0.6, r.uniform(0.15, 0.35) * H, r.uniform(0.02, 0.04)
    hx, hz = W / 2 - e - s / 2, D / 2 - e - s / 2
    parts = [("top", _box((W, T, D), (0, H - T / 2, 0)))]
    parts += [("legs", p) for p in _legs(hx, hz, s, H - T, round_legs, res)]
    if shelf:
        parts.append(("shelf", _box((2 * hx, sth, 2 * hz), (0, sy, 0))))
    return parts


BUILDERS = {"airplane": _airplane, "chair": _chair, "lamp": _lamp, "mug": _mug, "table": _table}
assert sorted(BUILDERS) == CLASSES


def _assemble(cls: str, parts: Labelled) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Labelled parts -> ``verts [V, 3] float64``, ``faces [F, 3] int64``, ``face_parts [F]`` (global
    ids), zero-area faces and unreferenced vertices dropped."""
    offsets = np.cumsum([0] + [len(v) for _, (v, _) in parts[:-1]])
    v = np.concatenate([p[0] for _, p in parts]).astype(np.float64)
    f = np.concatenate([p[1] + o for (_, p), o in zip(parts, offsets)]).astype(np.int64)
    fp = np.concatenate([np.full(len(p[1]), PART_NAMES.index(f"{cls}/{name}")) for name, p in parts]).astype(np.int64)
    keep = _areas(v, f) > 1e-12
    f, fp = f[keep], fp[keep]
    used = np.unique(f)
    remap = np.full(len(v), -1, np.int64)
    remap[used] = np.arange(len(used))
    return v[used], remap[f], fp


def build_parts(cls: str, rng, max_faces: int = 2000) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One raw instance of ``cls`` in its canonical pose (not normalised) -> ``verts [V, 3]
    float64``, ``faces [F, 3] int64``, ``face_parts [F] int64``. ``rng``: a seed or SeedSequence, or
    a Generator (copied, not advanced). Round parts start at 32 sections and are coarsened until
    the shape has at most ``max_faces`` faces (as ``synthetic.build_shape``)."""
    if cls not in BUILDERS:
        raise KeyError(f"synthetic_parts: unknown category {cls!r}; expected one of {CLASSES}")
    res = 32
    while True:  # a fresh copy of the generator per attempt: the same draws at every resolution
        r = copy.deepcopy(rng) if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        v, f, fp = _assemble(cls, BUILDERS[cls](r, res))
        if len(f) <= max_faces:
            return v, f, fp
        if res <= 6:
            raise ValueError(f"synthetic_parts: a {cls} needs {len(f)} faces even at {res} sections; max_faces={max_faces} is too small")
        res = max(6, int(res * 0.7))


def sample_faces(v: np.ndarray, f: np.ndarray, n: int, r: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``n`` area-weighted uniform surface samples -> ``points [n, 3]`` and the face each lies on,
    ``[n] int64`` (the same draws, hence the same points, as ``packed.sample_surface``)."""
    area = triangle_areas(v, f)
    idx = r.choice(len(f), size=n, p=area / area.sum())
    t = v[f[idx]]
    u, w = r.random(n), r.random(n)
    flip = u + w > 1  # fold the unit square onto the triangle
    u, w = np.where(flip, 1 - u, u), np.where(flip, 1 - w, w)
    return t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + w[:, None] * (t[:, 2] - t[:, 0]), idx.astype(np.int64)


# ----------------------------------------------------------------------------- generation + cache
def instance_seeds(seed: int, split: str, cls: str, k: int):
    """Shape k of ``cls`` in ``split``: seeds of its geometry, rotation and points (as ``synthetic``:
    ``[seed, split index, crc32(cls), k, 0 | 1 | 2]``)."""
    base = [int(seed), SPLITS.index(split), zlib.crc32(cls.encode()), int(k)]
    return np.random.SeedSequence(base + [0]), np.random.default_rng(base + [1]), np.random.default_rng(base + [2])


def make_shape(cls: str, split: str, k: int, seed: int, rotate: str, max_faces: int, num_points: int) -> dict:
    """Shape k of ``cls``: normalised, rotated mesh, face parts and point samples with their parts."""
    geometry, rot_rng, point_rng = instance_seeds(seed, split, cls, k)
    v, f, fp = build_parts(cls, geometry, max_faces)
    R = random_rotation(rotate, rot_rng)
    v = (normalize_unit_sphere(v) @ R.T).astype(np.float32)
    name = f"{cls}_{split}_{k:04d}"
    _check(name, v, f)
    pts, on = sample_faces(v.astype(np.float64), f, num_points, point_rng)
    return {"verts": v, "faces": f, "face_parts": fp, "points": pts.astype(np.float32), "part_labels": fp[on],
            "point_faces": on, "label": CLASSES.index(cls), "name": name, "rotations": R.astype(np.float32)}


def generate_split(split: str, count: int, seed: int, rotate: str, max_faces: int, num_points: int,
                   progress: bool = True) -> dict[str, np.ndarray]:
    """``count`` shapes per category -> packed arrays: ``packed.PACKED_ARRAYS`` plus ``rotations
    [N, 3, 3] float32``, ``part_labels [N, P] int64``, ``face_parts [sum F] int64`` (packed like
    ``faces``) and ``point_faces [N, P] int64`` (the shape-local face each point lies on)."""
    from tqdm.auto import tqdm

    shapes = []
    bar = tqdm(total=count * len(CLASSES), desc=f"synthetic_parts {split}", unit="shape", disable=None if progress else True, leave=False)
    for cls in CLASSES:
        for k in range(count):
            shapes.append(make_shape(cls, split, k, seed, rotate, max_faces, num_points))
            bar.update()
    bar.close()

    def cat(key, dtype, shape):
        return (np.concatenate([s[key] for s in shapes]) if shapes else np.zeros(0)).astype(dtype).reshape(shape)

    return {"verts": cat("verts", np.float32, (-1, 3)), "faces": cat("faces", np.int32, (-1, 3)),
            "verts_per_shape": np.asarray([len(s["verts"]) for s in shapes], np.int64),
            "faces_per_shape": np.asarray([len(s["faces"]) for s in shapes], np.int64),
            "points": np.asarray([s["points"] for s in shapes], np.float32).reshape(-1, num_points, 3),
            "labels": np.asarray([s["label"] for s in shapes], np.int64),
            "names": np.asarray([s["name"] for s in shapes], dtype=str),
            "rotations": np.asarray([s["rotations"] for s in shapes], np.float32).reshape(-1, 3, 3),
            "part_labels": np.asarray([s["part_labels"] for s in shapes], np.int64).reshape(-1, num_points),
            "point_faces": np.asarray([s["point_faces"] for s in shapes], np.int64).reshape(-1, num_points),
            "face_parts": cat("face_parts", np.int64, (-1,))}


def _allowed() -> np.ndarray:
    """``[categories, parts]`` bool: part p belongs to category c."""
    table = np.zeros((len(CLASSES), len(PART_NAMES)), bool)
    for c, ids in PARTS_OF.items():
        table[c, ids] = True
    return table


def _validate(a: dict[str, np.ndarray], n: int, num_points: int) -> None:
    """Raise ValueError unless the arrays form ``n`` well-formed shapes whose point and face parts
    all belong to their category (guards against misreads)."""
    validate(a, n, num_points, len(CLASSES))
    pl, fp, on = a["part_labels"], a["face_parts"], a["point_faces"]
    if (a["rotations"].shape != (n, 3, 3) or pl.shape != (n, num_points) or fp.shape != (len(a["faces"]),)
            or on.shape != (n, num_points) or (on.size and not (0 <= on.min() and (on < a["faces_per_shape"][:, None]).all()))
            or (pl.size and not 0 <= min(pl.min(), fp.min()) <= max(pl.max(), fp.max()) < len(PART_NAMES))):
        raise ValueError("inconsistent arrays")
    ok = _allowed()
    if not (ok[a["labels"][:, None], pl].all() and ok[np.repeat(a["labels"], a["faces_per_shape"]), fp].all()):
        raise ValueError("inconsistent arrays: a part outside its category")


class SyntheticParts(PackedShapes):
    """The embedded part-segmentation dataset (one split); arguments as ``synthetic.SyntheticShapes``
    (``num_per_class``: shapes per category for (train, val, test); the cache lives in
    ``root_cache_dir``; what is cached: the meshes, face parts, points and point parts).

    ``ds[i]`` -> dict: ``points [P, 3] float32`` (area-weighted surface samples, fixed per shape),
    ``part_labels [P] int64`` (global part ids: the part of the face each point lies on),
    ``label int`` (category index), ``name str`` (``"lamp_test_0003"``), ``rotation [3, 3] float32``
    (verts = canonical @ R^T) and, unless ``as_points``, ``verts [V, 3] float32``, ``faces [F, 3]
    int64``, ``face_parts [F] int64`` and ``point_faces [P] int64`` (the face each point lies on: the
    primitive its label is lifted from). ``classes``: sorted category names; ``part_names``: global
    part names (``"lamp/shade"``); ``parts_of``: category index -> sorted global part ids.
    """

    def __init__(self, root_cache_dir, split: str = "train", num_per_class=(16, 8, 16), seed: int = 0,
                 rotate: str = "none", num_points: int = 1024, as_points: bool = False, max_faces: int = 2000,
                 progress: bool = True):
        count = split_count(split, rotate, num_per_class, seed, num_points, max_faces, who="synthetic_parts")
        # everything that determines this split's content (other splits' counts do not)
        self.settings = {"version": GEOMETRY_VERSION, "parts": list(PART_NAMES), "split": split, "count": count,
                         "seed": int(seed), "rotate": rotate, "max_faces": int(max_faces), "num_points": int(num_points)}
        self.cache_path = cache_file(root_cache_dir, "synthetic_parts", self.settings)
        n = count * len(CLASSES)
        arrays = cached_arrays(self.cache_path, self.settings, PACKED_ARRAYS + EXTRA, lambda a: _validate(a, n, int(num_points)),
                               lambda: generate_split(split, count, int(seed), rotate, int(max_faces), int(num_points), progress))
        super().__init__(arrays, CLASSES, split, as_points)
        self.part_names = list(PART_NAMES)
        self.parts_of = {c: list(ids) for c, ids in PARTS_OF.items()}

    @property
    def num_parts(self) -> int:
        return len(self.part_names)

    def __getitem__(self, i: int) -> dict:
        item = self.item(i)
        i = i % len(self)
        item["rotation"] = torch.from_numpy(self._a["rotations"][i].copy())
        item["part_labels"] = torch.from_numpy(self._a["part_labels"][i].astype(np.int64))
        if not self.as_points:
            item["face_parts"] = torch.from_numpy(self._a["face_parts"][self._fo[i]:self._fo[i + 1]].astype(np.int64))
            item["point_faces"] = torch.from_numpy(self._a["point_faces"][i].astype(np.int64))
        return item
