"""View-dependent synthetic dataset: 8 classes that differ only in a small detail inside a cup, under random poses.

Every shape is the same kind of body (raw units, before normalisation; Y-up, detail face +Z):

- a box ``W x H x D``, ``W, H ~ U(0.9, 1.3)``, ``D ~ U(0.4, 0.8)``;
- a cup on its +Z face: a tube of inner radius ``r ~ U(0.26, 0.32)``, wall ``U(0.04, 0.06)`` and
  depth ``h = r_in / tan(alpha)``, ``alpha ~ U(60, 66)`` deg, where ``r_in = r cos(pi / 24)`` is
  the radius of the circle inscribed in the 24-sided inner wall;
- the class: what stands centred on the cup's floor, inside the disc of radius
  ``rd ~ U(0.55, 0.65) r``, ``hd ~ U(0.55, 0.8) h < h`` high, so the rim hides it from the side:
  ``bar`` (a roof ridge 1.9 rd long, 0.6 rd wide), ``cone`` (radius 0.6 rd), ``cross`` (two
  crossing ridges 0.5 rd wide), ``empty`` (nothing), ``pair`` (two cones of radius 0.38 rd at
  +-0.6 rd), ``pyramid`` (square base inscribed in rd), ``ring`` (radii 0.55-1 rd, a roof-shaped
  section), ``tetra`` (three-sided pyramid inscribed in rd).

All classes draw the same numbers in the same order and nothing else, so one generator gives the
same body and cup for every class: the detail is the only class difference.

Families (``family``): ``cup`` (above, the default), ``decoys`` and ``slab``, kept to evaluate
finished recipes on places they were not tuned on. ``decoys``: a cube of side ``(W + H) / 2`` with the same
cup on each of its six faces; the class detail stands in one of them, drawn uniformly per shape
(one more draw after the dims), the other five stay empty. The global shape is the same whatever
the face, and near-isotropic (its principal frame is arbitrary), so neither a canonical pose nor a
class-mean view can know where to look; only the points inside the cups tell. ``slab`` (held out: no
recipe or setting is chosen on it): a slab ``(4 (r + wall) + 0.26) x H x 0.6 D`` with two cups on
each large face, their centres ``r + wall + 0.08`` either side of the middle (the same cup, so a
line that clears a cup's own rim clears its neighbour's); the detail stands in one of the four,
drawn uniformly per shape. The slab's principal frame is well defined (its normal is the least
spread axis), but a view down the normal sees the two cups of one face: which face, and which cup,
only the points inside the cups tell. The shape is centred
(bounding box) and scaled into the unit sphere, then turned by a rotation (``so3`` by default:
uniform over SO(3), so the cup points anywhere). Determinism, splits and the ``.npz`` cache work
as in ``synthetic.py``.

Visibility (``sees_detail``): a camera sees the detail when the straight line from the centre of
the cup's floor to the camera clears the rim, i.e. the camera is above the rim plane and inside
the cone of half-angle ``atan(r_in / h)`` (= alpha) around the cup axis with its apex at the floor
centre (exact for the polygonal cup, up to the slivers between the inscribed circle and the
polygon; the box lies behind the floor plane and cannot block that line). ``full=True`` asks the
same of every point of the footprint disc (cone ``atan((r_in - rd) / h)``): the whole detail
shows. ``python -m mvtn_exp.data.synthetic_views --report`` prints how often fixed layouts see it.
"""
from __future__ import annotations

import argparse
import math
import zlib
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
import trimesh

from .mesh_io import normalize_unit_sphere
from .packed import PACKED_ARRAYS, PackedShapes, cached_arrays, pack, sample_surface, validate
from .view_detail import camera_positions, detail_angles, layout_views, rendered_traces, sees_detail, visibility_table
from .synthetic import Part, _box, _check, _outward, _tm, build_shape, random_rotation
from .synthetic_cache import SPLITS, cache_file, split_count

GEOMETRY_VERSION = "1"  # bump whenever a builder changes: old caches then miss
CUP_SECTIONS = 24
EXTRA = ("rotations", "detail_anchor", "detail_axis", "detail_size")
EXTRA_SHAPES = {"rotations": (3, 3), "detail_anchor": (3,), "detail_axis": (3,), "detail_size": (3,)}


class Dims(NamedTuple):
    """One instance's proportions (raw units): box, cup (inner radius, inscribed radius, depth, wall), detail."""

    W: float
    H: float
    D: float
    r: float
    r_in: float
    h: float
    wall: float
    rd: float
    hd: float


def draw_dims(r: np.random.Generator) -> Dims:
    """The only draws any class makes, always in this order (see the module docstring)."""
    W, H, D = r.uniform(0.9, 1.3), r.uniform(0.9, 1.3), r.uniform(0.4, 0.8)
    cup_r, wall, alpha = r.uniform(0.26, 0.32), r.uniform(0.04, 0.06), math.radians(r.uniform(60.0, 66.0))
    r_in = cup_r * math.cos(math.pi / CUP_SECTIONS)
    h = r_in / math.tan(alpha)
    return Dims(W, H, D, cup_r, r_in, h, wall, r.uniform(0.55, 0.65) * cup_r, r.uniform(0.55, 0.8) * h)


def _zcone(radius, height, xy, z0, sections) -> Part:
    """Closed cone (``sections`` = 3, 4: a pyramid), axis +Z, base on the plane z = z0 at (x, y) = xy."""
    return _tm(trimesh.creation.cone(radius=radius, height=height, sections=sections), (*xy, z0), False)


def _ridge(length, width, height, z0, along_x: bool = True) -> Part:
    """Closed triangular prism lying on the plane z = z0 (a roof ridge of ``height``), centred on the axis."""
    L, w = length / 2, width / 2
    v = np.array([[-L, -w, 0], [-L, w, 0], [-L, 0, height], [L, -w, 0], [L, w, 0], [L, 0, height]], np.float64)
    f = np.array([[0, 2, 1], [3, 4, 5], [0, 1, 4], [0, 4, 3], [0, 3, 5], [0, 5, 2], [1, 2, 5], [1, 5, 4]], np.int64)
    v = v if along_x else v[:, [1, 0, 2]] * (-1.0, 1.0, 1.0)  # turned 90 deg about Z
    return _outward(v + (0.0, 0.0, z0), f)


def _ring(d: Dims, sections) -> Part:
    """Ring of radii 0.55-1 rd with a triangular (roof) section ``hd`` high, on the cup's floor."""
    profile = [[0.55 * d.rd, 0.0], [d.rd, 0.0], [0.775 * d.rd, d.hd], [0.55 * d.rd, 0.0]]
    return _tm(trimesh.creation.revolve(np.array(profile), sections=sections), (0.0, 0.0, d.D / 2), False)


# class -> parts on the cup's floor (z = D/2), given the dims and the round-part sections. No part
# has a face parallel to the floor on top: under a light from the camera such a face would shade
# exactly like the floor, and the detail would vanish when seen straight down the cup.
DETAILS = {
    "bar": lambda d, n: [_ridge(1.9 * d.rd, 0.6 * d.rd, d.hd, d.D / 2)],
    "cone": lambda d, n: [_zcone(0.6 * d.rd, d.hd, (0.0, 0.0), d.D / 2, n)],
    "cross": lambda d, n: [_ridge(1.9 * d.rd, 0.5 * d.rd, d.hd, d.D / 2), _ridge(1.9 * d.rd, 0.5 * d.rd, d.hd, d.D / 2, False)],
    "empty": lambda d, n: [],
    "pair": lambda d, n: [_zcone(0.38 * d.rd, d.hd, (s * 0.6 * d.rd, 0.0), d.D / 2, n) for s in (-1, 1)],
    "pyramid": lambda d, n: [_zcone(d.rd, d.hd, (0.0, 0.0), d.D / 2, 4)],
    "ring": lambda d, n: [_ring(d, n)],
    "tetra": lambda d, n: [_zcone(d.rd, d.hd, (0.0, 0.0), d.D / 2, 3)],
}
CLASSES: list[str] = sorted(DETAILS)


FAMILIES = ("cup", "decoys", "slab")
# the six faces of the decoys' cube: rotations taking +Z to +Z, -Z, +X, -X, +Y, -Y
FACES = np.array([np.eye(3), np.diag([1.0, -1.0, -1.0]), [[0, 0, 1], [0, 1, 0], [-1, 0, 0]],
                  [[0, 0, -1], [0, 1, 0], [1, 0, 0]], [[1, 0, 0], [0, 0, 1], [0, -1, 0]],
                  [[1, 0, 0], [0, 0, -1], [0, 1, 0]]], np.float64)
SLAB_GAP = 0.08  # between a slab cup's outer wall and the slab's middle


class Placement(NamedTuple):
    """Where a cup built on the +Z face at the origin goes: ``p -> p @ R.T + t`` (``R [3, 3]``, ``t [3]``)."""

    R: np.ndarray
    t: np.ndarray


ON_FACE = [Placement(F, np.zeros(3)) for F in FACES]  # the decoys' six cups; ON_FACE[0]: the cup family's


def slab_cups(d: Dims) -> list[Placement]:
    """The slab's four cups: x = -s, +s on the +Z face, then on the -Z face (``s = r + wall + gap``)."""
    s = d.r + d.wall + SLAB_GAP
    return [Placement(F, np.array([x, 0.0, 0.0])) for F in FACES[:2] for x in (-s, s)]


def draw_family(family: str, r: np.random.Generator) -> tuple[Dims, Placement]:
    """A family's draws: the dims (``D``: the decoys' cube side, the slab's thickness) and the
    placement of the cup holding the detail (the identity for ``cup``)."""
    d = draw_dims(r)
    if family == "cup":
        return d, ON_FACE[0]
    if family == "decoys":
        return d._replace(D=(d.W + d.H) / 2), ON_FACE[int(r.integers(len(FACES)))]
    d = d._replace(W=4 * (d.r + d.wall) + 2 * SLAB_GAP + 0.1, D=0.6 * d.D)
    return d, slab_cups(d)[int(r.integers(4))]


def _placed(part: Part, at: Placement) -> Part:
    return part[0] @ at.R.T + at.t, part[1]


def _builder(cls: str, family: str = "cup"):
    def build(r: np.random.Generator, res: int) -> list[Part]:
        d, at = draw_family(family, r)
        cup = _tm(trimesh.creation.annulus(d.r, d.r + d.wall, d.h, sections=CUP_SECTIONS), (0.0, 0.0, d.D / 2 + d.h / 2), False)
        detail = [_placed(p, at) for p in DETAILS[cls](d, max(res // 2, 8))]
        if family == "cup":
            return [_box((d.W, d.H, d.D)), cup] + detail
        if family == "decoys":
            return [_box((d.D, d.D, d.D))] + [_placed(cup, c) for c in ON_FACE] + detail
        return [_box((d.W, d.H, d.D))] + [_placed(cup, c) for c in slab_cups(d)] + detail
    return build


BUILDERS = {c: _builder(c) for c in CLASSES}
FAMILY_BUILDERS = {f: {c: _builder(c, f) for c in CLASSES} for f in FAMILIES}


def frame_points(d: Dims, at: Placement = ON_FACE[0]) -> np.ndarray:
    """``[3, 3]`` points that travel with the mesh: floor centre, rim-plane centre, inscribed wall
    point of the cup holding the detail (placed by ``at``)."""
    return np.array([[0.0, 0.0, d.D / 2], [0.0, 0.0, d.D / 2 + d.h], [d.r_in, 0.0, d.D / 2]]) @ at.R.T + at.t


def make_shape(cls: str, seq, rotation: np.ndarray, max_faces: int = 2000, family: str = "cup"):
    """One normalised, rotated instance -> ``verts [V, 3] float32``, ``faces [F, 3] int64``, and the
    detail frame: ``anchor [3]`` (floor centre), ``axis [3]`` (unit, out of the cup), ``size [3]``
    (``r_in``, ``h``, ``rd`` in unit-sphere units). ``seq``: the geometry seed (SeedSequence or int)."""
    if family not in FAMILIES:
        raise ValueError(f"dataset.family={family!r}: expected one of {', '.join(FAMILIES)}")
    v, f = build_shape(cls, seq, max_faces, builders=FAMILY_BUILDERS[family])
    d, at = draw_family(family, np.random.default_rng(seq))  # the builder's draws again, from a fresh generator
    # the frame points lie inside the bounding box and nearer the centre than the farthest
    # vertex, so normalising them with the mesh leaves the mesh's normalisation unchanged
    both = normalize_unit_sphere(np.concatenate([v, frame_points(d, at)])) @ rotation.T
    v, (a, m, w) = both[:-3], both[-3:]
    h = np.linalg.norm(m - a)
    size = np.array([np.linalg.norm(w - a), h, d.rd * h / d.h])
    return v.astype(np.float32), f, a, (m - a) / h, size


# ----------------------------------------------------------------------------- generation + cache
def instance_seeds(seed: int, split: str, cls: str, k: int):
    """Shape k of class ``cls`` in ``split``: seeds of its geometry, rotation and points (as in
    ``synthetic.generate_split``: ``[seed, split index, crc32(cls), k, 0 | 1 | 2]``)."""
    base = [int(seed), SPLITS.index(split), zlib.crc32(cls.encode()), int(k)]
    return np.random.SeedSequence(base + [0]), np.random.default_rng(base + [1]), np.random.default_rng(base + [2])


def generate_split(split: str, count: int, seed: int, rotate: str, max_faces: int, num_points: int,
                   progress: bool = True, family: str = "cup") -> dict[str, np.ndarray]:
    """``count`` shapes per class -> packed arrays (``packed.PACKED_ARRAYS`` plus ``EXTRA``)."""
    from tqdm.auto import tqdm

    shapes = []
    bar = tqdm(total=count * len(CLASSES), desc=f"synthetic_views {family} {split}", unit="shape", disable=None if progress else True, leave=False)
    for label, cls in enumerate(CLASSES):
        for k in range(count):
            name = f"{cls}_{split}_{k:04d}"
            geometry, rot_rng, point_rng = instance_seeds(seed, split, cls, k)
            R = random_rotation(rotate, rot_rng)
            v, f, anchor, axis, size = make_shape(cls, geometry, R, max_faces, family)
            _check(name, v, f)
            pts = sample_surface(v.astype(np.float64), f, num_points, point_rng)
            shapes.append({"verts": v, "faces": f, "points": pts, "label": label, "name": name, "rotations": R,
                           "detail_anchor": anchor, "detail_axis": axis, "detail_size": size})
            bar.update()
    bar.close()
    arrays = pack(shapes, num_points, EXTRA)
    return {**arrays, **{k: arrays[k].reshape(-1, *EXTRA_SHAPES[k]) for k in EXTRA}}


def _validate(a: dict[str, np.ndarray], n: int, num_points: int) -> None:
    validate(a, n, num_points, len(CLASSES))
    if any(a[k].shape != (n, *EXTRA_SHAPES[k]) or not np.isfinite(a[k]).all() for k in EXTRA):
        raise ValueError("inconsistent arrays")


class SyntheticViews(PackedShapes):
    """The view-dependent synthetic dataset (one split); arguments as ``synthetic.SyntheticShapes``
    (``rotate`` none | y | so3 is honoured, default so3; the cache lives in ``root_cache_dir``).

    ``ds[i]`` -> the ``SyntheticShapes`` item (``verts``, ``faces`` unless ``as_points``, ``points``,
    ``label``, ``name`` like ``"ring_test_0003"``, ``rotation [3, 3]``: verts = canonical @ R^T) plus
    the detail frame, float32: ``detail_anchor [3]``, ``detail_axis [3]``, ``detail_size [3]``
    (see ``make_shape``; what ``sees_detail`` takes).
    """

    VIEW_HEADLINE = ("detail_seen",)  # the training log's number for each epoch's validation views

    def __init__(self, root_cache_dir, split: str = "train", num_per_class=(24, 12, 24), seed: int = 0,
                 rotate: str = "so3", num_points: int = 1024, as_points: bool = False, max_faces: int = 2000,
                 progress: bool = True, family: str = "cup"):
        count = split_count(split, rotate, num_per_class, seed, num_points, max_faces, who="synthetic_views")
        if family not in FAMILIES:
            raise ValueError(f"dataset.family={family!r}: expected one of {', '.join(FAMILIES)}")
        self.settings = {"version": GEOMETRY_VERSION, "classes": list(CLASSES), "split": split, "count": count,
                         "seed": int(seed), "rotate": rotate, "max_faces": int(max_faces), "num_points": int(num_points)}
        if family != "cup":  # the cup family keeps the cache files it always had
            self.settings["family"] = family
        self.cache_path = cache_file(root_cache_dir, "synthetic_views", self.settings)
        n = count * len(CLASSES)
        arrays = cached_arrays(self.cache_path, self.settings, PACKED_ARRAYS + EXTRA, lambda a: _validate(a, n, int(num_points)),
                               lambda: generate_split(split, count, int(seed), rotate, int(max_faces), int(num_points),
                                                      progress, family))
        super().__init__(arrays, CLASSES, split, as_points)

    def __getitem__(self, i: int) -> dict:
        item = self.item(i)
        i = i % len(self)
        item["rotation"] = torch.from_numpy(self._a["rotations"][i].copy())
        for k in EXTRA[1:]:
            item[k] = torch.from_numpy(self._a[k][i].copy())
        return item


    def detail_seen(self, azim, elev, dist) -> np.ndarray:
        """``[N, M]`` bool: view m of shape n (``[N, M]`` degrees / world units, dataset order and
        poses) sees the detail (``sees_detail``)."""
        a = self._a
        cams = camera_positions(np.asarray(azim), np.asarray(elev), np.asarray(dist))
        return sees_detail(a["detail_anchor"], a["detail_axis"], a["detail_size"], cams)


    def detail_angles(self, azim, elev, dist) -> np.ndarray:
        """``[N, M]`` degrees between shape n's cup axis and the line from its floor centre to camera m
        (0: looking straight down the cup; the detail shows below about ``alpha`` = 60-66 degrees)."""
        a = self._a
        cams = camera_positions(np.asarray(azim), np.asarray(elev), np.asarray(dist))
        return detail_angles(a["detail_anchor"], a["detail_axis"], cams)

    def view_report(self, res: dict) -> dict:
        """Where the class detail shows: the share of shapes of which some predicted view sees it,
        the accuracy on those and on the rest, the median angle of the nearest view to the cup
        axis. ``res``: a ``classification.evaluate`` result on this split (same order)."""
        if res["azim"].numel() == 0:
            return {}
        views = [res[k].double().numpy() for k in ("azim", "elev", "dist")]
        seen = torch.from_numpy(self.detail_seen(*views).any(1))
        right = res["pred"] == res["labels"]

        def acc(mask):
            return float(right[mask].float().mean()) if bool(mask.any()) else None

        nearest = self.detail_angles(*views).min(1)
        return {"detail_seen": float(seen.float().mean()), "acc_detail_seen": acc(seen),
                "acc_detail_unseen": acc(~seen), "detail_angle_median": float(np.median(nearest))}

    def view_figures(self, res: dict, run_dir) -> None:
        """``detail_angles.png`` in ``run_dir``: the angles of the predicted views to the cup axis."""
        from ..viz.views import detail_angles_png

        if res["azim"].numel():
            views = [res[k].double().numpy() for k in ("azim", "elev", "dist")]
            detail_angles_png(self.detail_angles(*views), Path(run_dir) / "detail_angles.png")


def main(argv=None) -> None:
    p = argparse.ArgumentParser(prog="python -m mvtn_exp.data.synthetic_views", description=__doc__.splitlines()[0])
    p.add_argument("--report", action="store_true", help="print the fixed-view visibility table (Markdown)")
    p.add_argument("--root", default="outputs/cache/synthetic_views", help="cache folder")
    p.add_argument("--split", default="test", choices=SPLITS)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--num-per-class", type=int, nargs=3, default=(24, 12, 24))
    p.add_argument("--rotate", default="so3")
    p.add_argument("--family", default="cup", choices=FAMILIES)
    p.add_argument("--poses", type=int, default=200, help="random poses per shape for the expectation")
    p.add_argument("--render", action="store_true", help="also render every shape and its empty twin (64 px)")
    args = p.parse_args(argv)
    if not args.report:
        p.error("nothing to do: pass --report")
    ds = SyntheticViews(args.root, args.split, args.num_per_class, args.seed, args.rotate, num_points=1024,
                        family=args.family)
    print(f"synthetic_views ({args.family}) {args.split}: {len(ds)} shapes, rotate={args.rotate}, seed={args.seed}, cameras at "
          "distance 2.2. Seen: the line from the cup's floor centre to a camera clears the rim.\n")
    cols = ["layout", "M", f"seen ({len(ds)} shapes)", "whole detail seen", f"seen ({args.poses} random poses per shape)"]
    cols += ["render differs from the empty twin (>= 1 px, 64 px)"] if args.render else []
    print("| " + " | ".join(cols) + " |\n" + "|---" * len(cols) + "|")
    keep = np.asarray(ds.labels) != CLASSES.index("empty")
    for row in visibility_table(ds, poses=args.poses):
        cells = [row["layout"], str(row["M"])] + [f"{row[k]:.3f}" for k in ("seen", "seen_full", "seen_mc")]
        if args.render:
            cells.append(f"{(rendered_traces(ds, *layout_views(row['layout'], row['M']))[keep] >= 1).any(1).mean():.3f}")
        print("| " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
