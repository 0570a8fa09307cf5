"""Embedded synthetic dataset: procedurally built meshes in 12 classes, deterministic, cached on disk.

Classes come in look-alike groups that differ in details, some of which only show from some
directions (Y-up, the front is +Z, where azimuth 0 looks from):

- ``box`` / ``cabinet`` / ``shelf``: same outer proportions; a handle on the +Z face only; an open
  +Z face showing 1-3 shelves (a box in silhouette from every direction).
- ``can`` / ``mug``: same body; the mug is open at the top and has a handle on +X, hidden behind
  the body in silhouettes taken along the X axis.
- ``table`` / ``desk`` / ``bench``: a top on 4 legs vs on 2 full-depth side panels (alike from the
  front, different from the side); a bench is a long, shallow, low desk.
- ``chair`` / ``stool``: seat on 4 legs, with or without a backrest on the -Z side.
- ``bottle``, ``lamp``: revolved profiles (shoulder and neck; base, pole and open shade).

Every instance draws its proportions from a numpy Generator seeded by (seed, split, class,
index); the shape is centred (bounding box at the origin) and scaled into the unit sphere, then
optionally rotated about the origin (so rotation never changes the scale). Each split is
generated once and cached as an ``.npz`` whose name hashes every setting that determines it.
"""
from __future__ import annotations

import copy
import zlib

import numpy as np
import torch
import trimesh

from .mesh_io import normalize_unit_sphere, zup_to_yup
from .synthetic_cache import ROTATIONS, SPLITS, cache_file, split_count  # noqa: F401 (SPLITS, ROTATIONS: the dataset's names)
from .packed import CacheWarning, PackedShapes, cached_arrays, sample_surface, validate  # noqa: F401 (CacheWarning re-exported)

GEOMETRY_VERSION = "1"  # bump whenever a builder changes: old caches then miss
Part = tuple[np.ndarray, np.ndarray]  # (verts [V, 3] float64, faces [F, 3] int64)


# ----------------------------------------------------------------------------- primitives
def _outward(v: np.ndarray, f: np.ndarray) -> Part:
    """Flip the winding of a closed part whose signed volume is negative (normals point out)."""
    t = v[f]
    vol = np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum()
    return v, (f[:, ::-1].copy() if vol < 0 else f)


def _tm(m, centre, yup: bool) -> Part:
    v = np.asarray(m.vertices, np.float64)
    return _outward((zup_to_yup(v) if yup else v) + centre, np.asarray(m.faces, np.int64))


def _box(ext, centre=(0.0, 0.0, 0.0)) -> Part:
    return _tm(trimesh.creation.box(extents=ext), centre, False)


def _cyl(radius, height, centre, res) -> Part:
    """Closed cylinder with its axis along Y."""
    return _tm(trimesh.creation.cylinder(radius=radius, height=height, sections=res), centre, True)


def _revolve(profile, res, y0=0.0) -> Part:
    """Revolve a closed (radius, height) polyline about the Y axis; the base sits at ``y0``."""
    return _tm(trimesh.creation.revolve(np.asarray(profile, np.float64), sections=res), (0.0, y0, 0.0), True)


def _arc_tube(centre, major, minor, res) -> Part:
    """Half torus in the XY plane bulging towards +X (a mug handle), capped at both ends."""
    nt, nm = max(res // 2, 4), max(res // 4, 4)
    t = np.linspace(-np.pi / 2, np.pi / 2, nt + 1)
    p = np.linspace(0, 2 * np.pi, nm, endpoint=False)
    radial = np.stack([np.cos(t), np.sin(t), np.zeros_like(t)], 1)[:, None]  # [T, 1, 3]
    ring = major * radial + minor * (np.cos(p)[None, :, None] * radial + np.sin(p)[None, :, None] * np.array([0, 0, 1.0]))
    ends = major * radial[[0, -1], 0]
    verts = np.concatenate([ring.reshape(-1, 3), ends]) + centre
    i, j = np.meshgrid(np.arange(nt), np.arange(nm), indexing="ij")
    a, b = i * nm + j, i * nm + (j + 1) % nm
    c, d = a + nm, b + nm
    side = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    k = np.arange(nm)
    e0, e1 = len(verts) - 2, len(verts) - 1
    cap0 = np.stack([np.full(nm, e0), (k + 1) % nm, k], 1)
    cap1 = np.stack([np.full(nm, e1), nt * nm + k, nt * nm + (k + 1) % nm], 1)
    return _outward(verts, np.concatenate([side, cap0, cap1]).astype(np.int64))


def _legs(half_x, half_z, thick, height, round_legs, res) -> list[Part]:
    """Four legs from y=0 to y=height with centres at (+-half_x, +-half_z)."""
    centres = [(sx * half_x, height / 2, sz * half_z) for sx in (-1, 1) for sz in (-1, 1)]
    return [_cyl(thick / 2, height, c, res) if round_legs else _box((thick, height, thick), c) for c in centres]


# ----------------------------------------------------------------------------- class builders
# Each builder draws its proportions from ``r`` (always in the same order, whatever ``res``) and
# returns parts in a canonical Y-up pose with the floor at y=0 where it has one.
def _box_dims(r):
    return r.uniform(0.6, 1.4, 3)


def _box_shape(r, res):
    return [_box(_box_dims(r))]


def _cabinet(r, res):
    w, h, d = _box_dims(r)  # same first draws as a box: same body from the same generator
    hw, hh, hd = r.uniform(0.3, 0.5) * w, r.uniform(0.15, 0.25), r.uniform(0.18, 0.26)
    cx, cy = r.uniform(-0.1, 0.1) * w, r.uniform(0.0, 0.2) * h
    return [_box((w, h, d)), _box((hw, hh, hd), (cx, cy, d / 2 + hd / 2))]


def _shelf(r, res):
    w, h, d = _box_dims(r)
    t, n, inset = r.uniform(0.04, 0.07), int(r.integers(1, 4)), r.uniform(0.0, 0.1) * d
    parts = [_box((t, h, d), (s * (w - t) / 2, 0, 0)) for s in (-1, 1)]
    parts += [_box((w - 2 * t, t, d), (0, s * (h - t) / 2, 0)) for s in (-1, 1)]
    parts.append(_box((w - 2 * t, h - 2 * t, t), (0, 0, -(d - t) / 2)))
    for k in range(1, n + 1):
        y = -h / 2 + k * h / (n + 1)
        parts.append(_box((w - 2 * t, t, d - t - inset), (0, y, (t - inset) / 2)))
    return parts


def _top_dims(r):
    return r.uniform(1.0, 1.6), r.uniform(0.6, 1.0), r.uniform(0.04, 0.08), r.uniform(0.6, 0.9)


def _table(r, res):
    W, D, T, H = _top_dims(r)
    s, e, round_legs = r.uniform(0.04, 0.09), r.uniform(0.0, 0.1), r.random() < 0.5
    top = _box((W, T, D), (0, H - T / 2, 0))
    return [top] + _legs(W / 2 - e - s / 2, D / 2 - e - s / 2, s, H - T, round_legs, res)


def _panels(W, D, T, H, s, e, depth):
    top = _box((W, T, D), (0, H - T / 2, 0))
    return [top] + [_box((s, H - T, depth), (x * (W / 2 - e - s / 2), (H - T) / 2, 0)) for x in (-1, 1)]


def _desk(r, res):
    W, D, T, H = _top_dims(r)
    s, e, frac = r.uniform(0.04, 0.09), r.uniform(0.0, 0.1), r.uniform(0.85, 1.0)
    return _panels(W, D, T, H, s, e, frac * D)


def _bench(r, res):
    W, D, T, H = r.uniform(1.4, 2.0), r.uniform(0.35, 0.55), r.uniform(0.05, 0.09), r.uniform(0.4, 0.55)
    s, e, frac = r.uniform(0.05, 0.1), r.uniform(0.05, 0.2), r.uniform(0.8, 1.0)
    return _panels(W, D, T, H, s, e, frac * D)


def _seat_dims(r):
    return (r.uniform(0.4, 0.55), r.uniform(0.04, 0.08), r.uniform(0.45, 0.75), r.uniform(0.03, 0.06),
            r.uniform(0.0, 0.06), r.random() < 0.5)


def _stool(r, res):
    S, T, H, s, e, round_legs = _seat_dims(r)
    round_seat = r.random() < 0.5
    k = 0.7 if round_seat else 1.0
    seat = _cyl(S / 2, T, (0, H - T / 2, 0), res) if round_seat else _box((S, T, S), (0, H - T / 2, 0))
    return [seat] + _legs(k * (S / 2 - e - s / 2), k * (S / 2 - e - s / 2), s, H - T, round_legs, res)


def _chair(r, res):
    S, T, H, s, e, round_legs = _seat_dims(r)
    bh, bt, posts = r.uniform(0.35, 0.7), r.uniform(0.03, 0.07), r.random() < 0.5
    parts = [_box((S, T, S), (0, H - T / 2, 0))]
    parts += _legs(S / 2 - e - s / 2, S / 2 - e - s / 2, s, H - T, round_legs, res)
    z = -S / 2 + bt / 2
    if posts:  # two posts and a top rail
        rail = bh * 0.35
        parts += [_box((s, bh - rail, bt), (x * (S / 2 - s / 2), H + (bh - rail) / 2, z)) for x in (-1, 1)]
        parts.append(_box((S, rail, bt), (0, H + bh - rail / 2, z)))
    else:
        parts.append(_box((S, bh, bt), (0, H + bh / 2, z)))
    return parts


def _can_dims(r):
    return r.uniform(0.25, 0.5), r.uniform(0.6, 1.3)


def _can(r, res):
    R, H = _can_dims(r)
    return [_cyl(R, H, (0, H / 2, 0), res)]


def _mug(r, res):
    R, H = _can_dims(r)
    wall, bottom = r.uniform(0.04, 0.08), r.uniform(0.04, 0.1)
    major, minor, yc = r.uniform(0.2, 0.35) * H, r.uniform(0.025, 0.05), r.uniform(0.45, 0.55) * H
    body = _revolve([[0, 0], [R, 0], [R, H], [R - wall, H], [R - wall, bottom], [0, bottom], [0, 0]], res)
    return [body, _arc_tube((R - wall / 2, yc, 0), major, minor, res)]


def _bottle(r, res):
    R, hb, hs = r.uniform(0.2, 0.4), r.uniform(0.5, 0.9), r.uniform(0.1, 0.25)
    rn, hn = r.uniform(0.25, 0.45) * R, r.uniform(0.15, 0.3)
    top = hb + hs + hn
    return [_revolve([[0, 0], [R, 0], [R, hb], [rn, hb + hs], [rn, top], [0, top], [0, 0]], res)]


def _lamp(r, res):
    rb, tb, rp, hp = r.uniform(0.2, 0.35), r.uniform(0.03, 0.08), r.uniform(0.015, 0.035), r.uniform(0.5, 1.0)
    sb, sh, t = r.uniform(0.25, 0.4), r.uniform(0.2, 0.4), r.uniform(0.015, 0.03)
    st, y0 = r.uniform(0.4, 0.7) * sb, tb + hp - r.uniform(0.6, 0.9) * sh
    shade = _revolve([[sb, 0], [st, sh], [st - t, sh], [sb - t, 0], [sb, 0]], res, y0)
    return [_cyl(rb, tb, (0, tb / 2, 0), res), _cyl(rp, hp, (0, tb + hp / 2, 0), res), shade]


BUILDERS = {
    "bench": _bench, "bottle": _bottle, "box": _box_shape, "cabinet": _cabinet, "can": _can,
    "chair": _chair, "desk": _desk, "lamp": _lamp, "mug": _mug, "shelf": _shelf, "stool": _stool,
    "table": _table,
}
CLASSES: list[str] = sorted(BUILDERS)


def _concat(parts: list[Part]) -> Part:
    offsets = np.cumsum([0] + [len(v) for v, _ in parts[:-1]])
    return (np.concatenate([v for v, _ in parts]).astype(np.float64),
            np.concatenate([f + o for (_, f), o in zip(parts, offsets)]).astype(np.int64))


def _areas(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Twice the area of each triangle, ``[F]`` (float64)."""
    t = v.astype(np.float64)[f]
    return np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)


def _clean(v: np.ndarray, f: np.ndarray) -> Part:
    """Drop zero-area faces and unreferenced vertices."""
    f = f[_areas(v, f) > 1e-12]
    used = np.unique(f)
    remap = np.full(len(v), -1, np.int64)
    remap[used] = np.arange(len(used))
    return v[used], remap[f]


def build_shape(name: str, rng: np.random.Generator | int, max_faces: int = 2000, builders=None) -> Part:
    """One raw instance of class ``name`` in its canonical pose (Y-up, front +Z, not normalised).

    ``rng``: a seed (int or SeedSequence) or a Generator (copied, not advanced). Round parts start
    at 32 sections and are coarsened until the shape has at most ``max_faces`` faces.
    ``builders``: class name -> builder ``(rng, res) -> list of parts`` (default: ``BUILDERS``).
    Returns ``([V, 3] float64, [F, 3] int64)``.
    """
    builders = BUILDERS if builders is None else builders
    if name not in builders:
        raise KeyError(f"synthetic: unknown class {name!r}; expected one of {sorted(builders)}")
    res = 32
    while True:  # a fresh copy of the generator per attempt: the same draws at every resolution
        r = copy.deepcopy(rng) if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        v, f = _clean(*_concat(builders[name](r, res)))
        if len(f) <= max_faces:
            return v, f
        if res <= 6:
            raise ValueError(f"synthetic: a {name} needs {len(f)} faces even at {res} sections; max_faces={max_faces} is too small")
        res = max(6, int(res * 0.7))


def quaternion_rows(w, x, y, z) -> tuple:
    """The rotation matrix of the unit quaternion ``(w, x, y, z)`` as 3 rows of 3 entries; works
    elementwise on numbers, numpy arrays and tensors alike (the caller stacks them)."""
    return ((1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)),
            (2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)),
            (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)))


def random_rotation(mode: str, r: np.random.Generator) -> np.ndarray:
    """``[3, 3]`` rotation: identity (``none``), uniform about +Y (``y``) or uniform over SO(3) (``so3``)."""
    if mode == "none":
        return np.eye(3)
    if mode == "y":
        a = r.uniform(0, 2 * np.pi)
        c, s = np.cos(a), np.sin(a)
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    if mode == "so3":
        w, x, y, z = (q := r.normal(size=4)) / np.linalg.norm(q)
        return np.array(quaternion_rows(w, x, y, z))
    raise ValueError(f"synthetic: rotate={mode!r}; expected one of {list(ROTATIONS)}")


def _check(name: str, v: np.ndarray, f: np.ndarray) -> None:
    assert len(v) and len(f), f"synthetic shape {name}: empty mesh"
    assert np.isfinite(v).all(), f"synthetic shape {name}: non-finite vertices"
    assert f.min() >= 0 and f.max() < len(v), f"synthetic shape {name}: face index out of range"
    area = _areas(v, f)
    assert (area > 1e-12).all(), f"synthetic shape {name}: {int((area <= 1e-12).sum())} degenerate faces"


# ----------------------------------------------------------------------------- generation + cache
ARRAYS = ("verts", "faces", "verts_per_shape", "faces_per_shape", "points", "labels", "names", "rotations")


def generate_split(split: str, count: int, seed: int, rotate: str, max_faces: int, num_points: int,
                   progress: bool = True) -> dict[str, np.ndarray]:
    """Build ``count`` shapes per class for one split -> packed arrays (see ``ARRAYS``).

    Shape k of class c in split s is fully determined by (seed, s, c, k): its geometry, rotation
    and point samples each use their own generator, so e.g. ``rotate`` never changes the geometry
    and the counts of one split never change another split's shapes.
    """
    from tqdm.auto import tqdm

    sid = SPLITS.index(split)
    out = {k: [] for k in ARRAYS}
    bar = tqdm(total=count * len(CLASSES), desc=f"synthetic {split}", unit="shape", disable=None if progress else True, leave=False)
    for label, cls in enumerate(CLASSES):
        code = zlib.crc32(cls.encode())
        for k in range(count):
            name = f"{cls}_{split}_{k:04d}"
            v, f = build_shape(cls, np.random.SeedSequence([seed, sid, code, k, 0]), max_faces)
            R = random_rotation(rotate, np.random.default_rng([seed, sid, code, k, 1]))
            v = (normalize_unit_sphere(v) @ R.T).astype(np.float32)
            _check(name, v, f)
            pts = sample_surface(v.astype(np.float64), f, num_points, np.random.default_rng([seed, sid, code, k, 2]))
            for key, val in (("verts", v), ("faces", f.astype(np.int32)), ("verts_per_shape", len(v)),
                             ("faces_per_shape", len(f)), ("points", pts.astype(np.float32)), ("labels", label),
                             ("names", name), ("rotations", R.astype(np.float32))):
                out[key].append(val)
            bar.update()
    bar.close()
    shapes = {"verts": (-1, 3), "faces": (-1, 3), "points": (-1, num_points, 3), "rotations": (-1, 3, 3)}
    types = {"verts": np.float32, "faces": np.int32, "points": np.float32, "rotations": np.float32, "names": str}

    def pack(k):
        arr = np.concatenate(out[k]) if k in ("verts", "faces") and out[k] else np.asarray(out[k])
        return arr.astype(types.get(k, np.int64)).reshape(shapes.get(k, (-1,)))

    return {k: pack(k) for k in ARRAYS}


def _validate(a: dict[str, np.ndarray], n: int, num_points: int) -> None:
    """Raise ValueError unless the arrays form ``n`` well-formed shapes (guards against misreads)."""
    validate(a, n, num_points, len(CLASSES))
    if a["rotations"].shape != (n, 3, 3):
        raise ValueError("inconsistent arrays")


class SyntheticShapes(PackedShapes):
    """The embedded synthetic dataset (one split), as meshes and as fixed surface point samples.

    ``num_per_class``: shapes per class for (train, val, test). ``rotate``: ``none``, ``y``
    (uniform about the vertical axis) or ``so3``; the rotation is about the origin after
    normalisation, so every shape keeps max vertex norm 1. ``max_faces``: face budget per shape.

    ``ds[i]`` -> dict: ``verts [V, 3] float32`` (unit sphere, Y-up), ``faces [F, 3] int64``,
    ``points [num_points, 3] float32`` (area-weighted, fixed per shape), ``label int``,
    ``name str`` (``"mug_test_0007"``), ``rotation [3, 3] float32`` (verts = canonical @ R^T).
    With ``as_points=True`` the mesh is left out. ``classes``: sorted class names (label = index).
    """

    def __init__(self, root_cache_dir, split: str = "train", num_per_class=(40, 10, 20), seed: int = 0,
                 rotate: str = "none", num_points: int = 1024, as_points: bool = False, max_faces: int = 2000,
                 progress: bool = True):
        count = split_count(split, rotate, num_per_class, seed, num_points, max_faces)
        # everything that determines this split's content (other splits' counts do not)
        self.settings = {"version": GEOMETRY_VERSION, "classes": list(CLASSES), "split": split, "count": count,
                         "seed": int(seed), "rotate": rotate, "max_faces": int(max_faces), "num_points": int(num_points)}
        self.cache_path = cache_file(root_cache_dir, "synthetic", self.settings)
        n = count * len(CLASSES)
        arrays = cached_arrays(self.cache_path, self.settings, ARRAYS, lambda a: _validate(a, n, int(num_points)),
                               lambda: generate_split(split, count, int(seed), rotate, int(max_faces), int(num_points), progress))
        super().__init__(arrays, CLASSES, split, as_points)

    def __getitem__(self, i: int) -> dict:
        item = self.item(i)
        item["rotation"] = torch.from_numpy(self._a["rotations"][i % len(self)].copy())
        return item
