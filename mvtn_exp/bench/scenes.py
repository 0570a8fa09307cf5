"""The benchmark's scenes and renderers: the tori and sampled point clouds every bench module
renders, the renderer of a grid row, and the forward / forward+backward calls that get timed.

Tori: ``trimesh.creation.torus(0.7, 0.3, n, n)``, n = 32 / 100 / 224 -> 2,048 / 20,000 / 100,352
faces; point clouds: points sampled (seeded) from the 20k torus surface.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from ..data.shapes import Meshes, PointClouds
from ..render import layouts
from ..render.renderer import MultiViewRenderer

TORUS_SECTIONS = {"torus-2k": 32, "torus-20k": 100, "torus-100k": 224}
POINT_SOURCE = "torus-20k"  # the surface point clouds are sampled from


def torus_of(sections: int, device, name: str) -> Meshes:
    """The benchmark torus (radii 0.7 / 0.3) with ``sections`` x ``sections`` quads: 2 sections^2 faces."""
    import trimesh

    t = trimesh.creation.torus(major_radius=0.7, minor_radius=0.3, major_sections=sections, minor_sections=sections)
    return Meshes.from_list([torch.tensor(np.asarray(t.vertices), dtype=torch.float32, device=device)],
                            [torch.tensor(np.asarray(t.faces), dtype=torch.long, device=device)], names=[name])


def torus(name: str, device) -> Meshes:
    return torus_of(TORUS_SECTIONS[name], device, name)


def torus_points(count: int, seed: int, device) -> PointClouds:
    import trimesh

    n = TORUS_SECTIONS[POINT_SOURCE]
    t = trimesh.creation.torus(major_radius=0.7, minor_radius=0.3, major_sections=n, minor_sections=n)
    pts, _ = trimesh.sample.sample_surface(t, count, seed=np.random.default_rng(seed))
    return PointClouds.from_list([torch.tensor(np.asarray(pts), dtype=torch.float32, device=device)], names=[f"points-{count}"])


def rotated_copies_y(verts: torch.Tensor, copies: int) -> list[torch.Tensor]:
    """``copies`` versions of ``[V, 3]`` vertices, copy k rotated by ``40 k`` degrees about Y."""
    out = []
    for k in range(copies):
        a = math.radians(40.0 * k)
        R = torch.tensor([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]],
                         dtype=verts.dtype, device=verts.device)
        out.append(verts @ R.T)
    return out


def shape_label(shape) -> str:
    return shape.names[0] if len(shape.names) else type(shape).__name__


def prims_of(shape) -> int:
    return int(shape.faces_per_shape[0]) if isinstance(shape, Meshes) else int(shape.points_per_shape[0])


# the time targets' renderer sides, timed against ResNet-18 in alternation: (shape, K, shading)
PAIRED_TARGETS = {"hard": ("torus-20k", 1), "smooth": ("torus-20k", 8, "smooth"), "flat": ("torus-20k", 8, "flat"),
                  "points": ("points-2048", 8)}

# LOD budgets measured: None is the renderer's default rule (faces per pixel row, silhouette-checked),
# the others the former rule (faces per image pixel)
LOD_FACES_PER_PIXEL = (None, 0.5, 0.25, 0.125)


def renderer_for(shape, size: int, K: int, shading: str = "flat", **extra) -> MultiViewRenderer:
    """The grid's renderer: eager unless ``compile=True`` is passed (the compiled rows are their own)."""
    extra.setdefault("compile", False)
    if isinstance(shape, Meshes):
        mode = dict(mode="hard") if K == 1 else dict(mode="soft", faces_per_pixel=K, shading=shading)
        return MultiViewRenderer(image_size=size, **mode, **extra).eval()
    return MultiViewRenderer(image_size=size, points_per_pixel=K, **extra).eval()


class Views:
    """Spherical views ``[B, M]``; ``grad`` copies of azim/elev are leaves that require grad."""

    def __init__(self, M: int, B: int, device):
        self.azim, self.elev, self.dist = layouts.spherical(M, batch=B, distance=2.2, device=device, sphere="fibonacci")
        self.azim_g = self.azim.clone().requires_grad_(True)
        self.elev_g = self.elev.clone().requires_grad_(True)


def render_fns(r: MultiViewRenderer, shape, v: Views):
    last = {}

    def fwd():
        with torch.no_grad():
            out = r(shape, v.azim, v.elev, v.dist)
        last["stats"] = out.stats

    def fwd_bwd():
        out = r(shape, v.azim_g, v.elev_g, v.dist)
        out.images.sum().backward()
        v.azim_g.grad = None
        v.elev_g.grad = None

    return fwd, fwd_bwd, last
