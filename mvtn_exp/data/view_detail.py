"""What a camera sees of the view-dependent dataset's class detail: camera positions and angles
(degrees, Y-up, as ``render/cameras.py``), the detail's visibility from a camera, the fixed
layouts' visibility table, and the check that a render differs from the detail-less twin."""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch

from .synthetic import random_rotation

if TYPE_CHECKING:  # pragma: no cover
    from .synthetic_views import SyntheticViews


def detail_angles(anchor, axis, cams) -> np.ndarray:
    """``[N, M]`` degrees between ``axis [N, 3]`` and ``cams [N, M, 3] - anchor [N, 3]``."""
    d = np.asarray(cams, np.float64) - np.asarray(anchor, np.float64)[:, None]
    cos = (d * np.asarray(axis, np.float64)[:, None]).sum(-1) / np.maximum(np.linalg.norm(d, axis=-1), 1e-12)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def camera_positions(azim, elev, dist=2.2) -> np.ndarray:
    """Degrees -> ``[..., 3]`` positions ``dist * (cos e sin a, sin e, cos e cos a)`` (looking at the origin)."""
    a, e = np.radians(np.asarray(azim, np.float64)), np.radians(np.asarray(elev, np.float64))
    return np.asarray(dist, np.float64)[..., None] * np.stack([np.cos(e) * np.sin(a), np.sin(e), np.cos(e) * np.cos(a)], -1)


def view_angles(direction) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions ``[..., 3]`` from the origin -> the azimuth, elevation (degrees) of a camera there."""
    d = np.asarray(direction, np.float64)
    return np.degrees(np.arctan2(d[..., 0], d[..., 2])), np.degrees(np.arcsin(np.clip(d[..., 1], -1.0, 1.0)))


def sees_detail(anchor, axis, size, cams, full: bool = False) -> np.ndarray:
    """``[N, M]`` bool: camera m sees shape n's detail (criterion in the module docstring).

    ``anchor``, ``axis``, ``size``: ``[N, 3]`` (the dataset's ``detail_*`` arrays); ``cams``:
    camera positions ``[M, 3]`` (shared) or ``[N, M, 3]``.
    """
    anchor, axis, size = (np.asarray(x, np.float64) for x in (anchor, axis, size))
    cams = np.asarray(cams, np.float64)
    d = (cams if cams.ndim == 3 else cams[None]) - anchor[:, None]  # [N, M, 3] floor centre -> camera
    up = (d * axis[:, None]).sum(-1)  # height of the camera above the floor plane
    lateral = np.linalg.norm(d - up[..., None] * axis[:, None], axis=-1)
    r_in, h, rd = size[:, 0:1], size[:, 1:2], size[:, 2:3]
    room = r_in - rd if full else r_in  # how far the line may drift sideways by the rim's height
    return (up > h) & (h * lateral < room * up)


def layout_views(layout: str, M: int) -> tuple[np.ndarray, np.ndarray]:
    """Azimuths, elevations ``[M]`` (degrees) of the fixed layouts of ``render/layouts.py``:
    ``circular`` (elevation 30, azimuth 0 first) or ``spherical`` (Fibonacci)."""
    from ..render import layouts

    if layout not in ("circular", "spherical"):
        raise ValueError(f"layout={layout!r}: expected circular or spherical")
    azim, elev, _ = layouts.circular(M, elevation=30.0) if layout == "circular" else layouts.spherical(M)
    return azim[0].double().numpy(), elev[0].double().numpy()


def visibility_table(ds: "SyntheticViews", views=(1, 4, 12), poses: int = 200, seed: int = 0, dist: float = 2.2) -> list[dict]:
    """Per fixed layout and M: the fraction of ``ds``'s shapes of which at least one view sees the
    detail (``seen``; ``seen_full``: the whole detail), and ``seen_mc``: the same over ``poses``
    further uniform SO(3) poses of every shape (seeded by ``seed``): the dataset's expectation."""
    a = ds._a
    frame = (a["detail_anchor"], a["detail_axis"], a["detail_size"])
    rng = np.random.default_rng([seed, 7])
    Q = np.stack([random_rotation("so3", rng) for _ in range(poses)])  # [P, 3, 3]
    mc = [np.einsum("pij,nj->pni", Q, x).reshape(-1, 3) for x in frame[:2]] + [np.tile(frame[2], (poses, 1))]
    rows = []
    for layout in ("circular", "spherical"):
        for M in views:
            cams = camera_positions(*layout_views(layout, M), dist)
            rows.append({"layout": layout, "M": M, "seen": sees_detail(*frame, cams).any(1).mean(),
                         "seen_full": sees_detail(*frame, cams, full=True).any(1).mean(),
                         "seen_mc": sees_detail(*mc, cams).any(1).mean()})
    return rows


def rendered_traces(ds: "SyntheticViews", azim, elev, dist: float = 2.2, image_size: int = 64, batch: int = 16) -> np.ndarray:
    """``[N, M]`` pixels in which a hard, flat-shaded ``image_size`` render of each shape of ``ds``
    (meshes) differs from its ``empty`` twin (same seeds: same body, cup and pose, no detail), seen
    from ``azim``, ``elev`` (degrees, ``[M]`` shared or ``[N, M]`` per shape): what the renderer
    shows of the detail, to check ``sees_detail`` against (0 for the ``empty`` class itself)."""
    from ..render.renderer import MultiViewRenderer
    from .synthetic_views import instance_seeds, make_shape
    from .shapes import Meshes

    if ds.as_points:
        raise ValueError("rendered_traces: needs meshes (as_points=False)")
    renderer, cfg, out = MultiViewRenderer(image_size=image_size, mode="hard", shading="flat"), ds.settings, []
    azim, elev = (torch.as_tensor(np.asarray(x, np.float32)) for x in (azim, elev))
    azim, elev = (x.reshape(1, -1).expand(len(ds), -1) if x.dim() == 1 else x for x in (azim, elev))
    for lo in range(0, len(ds), batch):
        verts, faces = [], []
        for i in range(lo, min(lo + batch, len(ds))):
            cls, split, k = ds.names[i].rsplit("_", 2)
            geometry, rot_rng, _ = instance_seeds(cfg["seed"], split, cls, int(k))
            v, f, *_ = make_shape("empty", geometry, random_rotation(cfg["rotate"], rot_rng), cfg["max_faces"],
                                  cfg.get("family", "cup"))
            item = ds.item(i)
            verts += [item["verts"], torch.from_numpy(v)]
            faces += [item["faces"], torch.from_numpy(f)]
        views = [x[lo:lo + len(verts) // 2].repeat_interleave(2, 0) for x in (azim, elev)]  # shape, twin, ...
        with torch.no_grad():
            img = renderer(Meshes.from_list(verts, faces), *views, dist).images
        out.append(((img[0::2] - img[1::2]).abs() > 1e-4).any(2).flatten(2).sum(-1).numpy())
    return np.concatenate(out)
