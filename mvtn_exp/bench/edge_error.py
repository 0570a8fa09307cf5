"""Soft-edge error: coverage and colour at K slots against a reference that keeps every face.

The reference is the same renderer with ``faces_per_pixel=REF_K`` colour slots (beyond them a
softmax weight is negligible: the ``faces`` column says how many faces the fullest pixel has within
the blur radius), coverage over every face and no pruning (``coverage_tol=0``, ``depth_window=null``), so any difference comes from
which faces hold the K slots and from the pruning of the search. Edge pixels are those whose reference
coverage lies in ``[EDGE_LO, 1 - EDGE_LO]``; a pixel is "off" when its coverage (or any colour
channel) differs from the reference by more than ``TOL``.

Run: ``python -m mvtn_exp.bench.edge_error`` (Markdown table on stdout).
"""
from __future__ import annotations

import argparse
import math
from dataclasses import dataclass

import numpy as np
import torch

from ..data.shapes import Meshes
from ..render import layouts
from ..render.renderer import MultiViewRenderer

EDGE_LO = 1e-3
TOL = 0.02
REF_K = 128


def torus_mesh(sections: int, open_half: bool = False) -> Meshes:
    """Torus (major 0.7, minor 0.3) with ``2 * sections^2`` faces; ``open_half`` keeps the faces
    with z >= 0 only (an open mesh with a boundary)."""
    import trimesh

    t = trimesh.creation.torus(major_radius=0.7, minor_radius=0.3, major_sections=sections, minor_sections=sections)
    return _meshes(np.asarray(t.vertices), np.asarray(t.faces), open_half, f"torus-{len(t.faces)}")


def icosphere_mesh(subdivisions: int, open_half: bool = False) -> Meshes:
    import trimesh

    t = trimesh.creation.icosphere(subdivisions=subdivisions, radius=0.9)
    return _meshes(np.asarray(t.vertices), np.asarray(t.faces), open_half, f"icosphere-{len(t.faces)}")


def _meshes(v, f, open_half, name) -> Meshes:
    if open_half:
        f = f[(v[f][:, :, 2].mean(1) >= 0)]
        name += "-open"
    return Meshes.from_list([torch.tensor(v, dtype=torch.float32)], [torch.tensor(f, dtype=torch.long)], names=[name])


@dataclass
class EdgeError:
    shape: str
    size: int
    shading: str
    K: int
    edge_pixels: int
    cov_off: float  # fraction of edge pixels with |coverage - ref| > TOL
    cov_max: float
    rgb_off: float
    rgb_max: float
    faces: int = 0  # most faces within the blur radius of one pixel


def measure(meshes: Meshes, *, size: int, shading: str, K: int, views: int = 4, **renderer) -> EdgeError:
    """Render ``views`` spherical views at K slots and at the reference; compare on edge pixels."""
    azim, elev, dist = layouts.spherical(views, batch=len(meshes), distance=2.2, sphere="fibonacci")
    kw = dict(image_size=size, mode="soft", shading=shading, **renderer)
    with torch.no_grad():
        out = MultiViewRenderer(faces_per_pixel=K, **kw).eval()(meshes, azim, elev, dist)
        ref = MultiViewRenderer(faces_per_pixel=REF_K, **{**kw, "coverage_tol": 0.0, "depth_window": None}).eval()(meshes, azim, elev, dist)
    most = int(ref.stats.get("max_candidates", 0))
    a, ar = out.alpha[:, :, 0], ref.alpha[:, :, 0]
    edge = (ar >= EDGE_LO) & (ar <= 1 - EDGE_LO)
    dc = (a - ar).abs()[edge]
    drgb = (out.images - ref.images).abs().amax(2)[edge]
    n = int(edge.sum())
    frac = (lambda d: float((d > TOL).float().mean()) if n else 0.0)
    return EdgeError(meshes.names[0], size, shading, K, n, frac(dc), float(dc.max()) if n else 0.0,
                     frac(drgb), float(drgb.max()) if n else 0.0, most)


def default_cases() -> list[tuple[Meshes, int]]:
    return [
        (icosphere_mesh(4), 224),
        (torus_mesh(100), 224),
        (torus_mesh(32), 64),
        (torus_mesh(32, open_half=True), 64),
        (torus_mesh(32, open_half=True), 224),
    ]


def to_markdown(rows: list[EdgeError]) -> str:
    head = ("| shape | px | shading | K | edge pixels | coverage off > 0.02 | max coverage error | colour off > 0.02 | "
            "max colour error | most faces in a pixel |\n")
    head += "|---|---|---|---|---|---|---|---|---|---|\n"
    return head + "".join(
        f"| {r.shape} | {r.size} | {r.shading} | {r.K} | {r.edge_pixels} | {100 * r.cov_off:.2f}% | {r.cov_max:.1e} | "
        f"{100 * r.rgb_off:.2f}% | {r.rgb_max:.1e} | {r.faces} |\n" for r in rows)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--K", type=int, nargs="+", default=[8])
    p.add_argument("--shading", nargs="+", default=["silhouette", "flat", "smooth"])
    p.add_argument("--views", type=int, default=4)
    args = p.parse_args(argv)
    rows = []
    for meshes, size in default_cases():
        for shading in args.shading:
            for K in args.K:
                rows.append(measure(meshes, size=size, shading=shading, K=K, views=args.views))
                print(to_markdown(rows[-1:]).splitlines()[-1], flush=True)
    print(to_markdown(rows))


if __name__ == "__main__":
    main()
