"""Which primitive each pixel shows (``MultiViewRenderer.primitive_index``): the front-most face
covering a pixel's centre, or the front-most point whose splat covers it, as a shape-local index
per pixel; what lifts per-pixel predictions back to the points (``tasks/lifting.py``)."""
from __future__ import annotations

import torch

from ..data.shapes import Meshes, host_counts, subset
from . import budget, mesh_raster, point_raster


def front_index(renderer, shapes, azim: torch.Tensor, elev: torch.Tensor, dist: torch.Tensor) -> torch.Tensor:
    """``[B, M, H, W]`` long: the shape-local face (meshes) or point (clouds) index each pixel shows,
    -1 on the background; shapes in the groups the memory budget allows, one K = 1 search each."""
    c = renderer.cfg
    H = W = c.image_size
    B, M = azim.shape
    mesh = isinstance(shapes, Meshes)
    counts = shapes.faces_per_shape if mesh else shapes.points_per_shape
    work = budget.plan("hard" if mesh else "points", counts, M, H, c.max_candidates, c.memory_budget_mb, azim.device)
    out = torch.full((B * M * H * W,), -1, dtype=torch.long, device=azim.device)
    host = host_counts(shapes) if len(work.groups) > 1 else None
    for a, b in work.groups:
        group = shapes if (a, b) == (0, B) else subset(shapes, a, b, host)
        pix, prim = _front(renderer, group, azim[a:b], elev[a:b], dist[a:b], work.max_candidates)
        sizes = group.faces_per_shape if mesh else group.points_per_shape
        first = torch.cumsum(sizes, 0) - sizes  # each shape's first primitive in the packed batch
        shape = torch.div(pix, M * H * W, rounding_mode="floor")
        packed = torch.div(prim, M, rounding_mode="floor")  # (primitive-views are primitive * M + view)
        out[pix + a * M * H * W] = packed - first[shape]
    return out.view(B, M, H, W)


def _front(renderer, shapes, azim, elev, dist, max_candidates) -> tuple[torch.Tensor, torch.Tensor]:
    """One group's covered pixels ``[P]`` (flat over its B*M images) and the front-most
    primitive-view of each ``[P]``."""
    c = renderer.cfg
    H = W = c.image_size
    B, M = azim.shape
    if isinstance(shapes, Meshes):
        pf, _, _ = renderer.project_faces(shapes, azim, elev, dist)
        sel = mesh_raster.search_faces(pf, H=H, W=W, K=1, blur_radius=0.0, tile_size=c.tile_size,
                                       max_candidates=max_candidates)
    else:
        cams = renderer._cameras(azim, elev, dist)
        xy, z, image = renderer._project(shapes.points, shapes.points_per_shape, cams)
        r = c.point_radius
        alive = (z >= c.znear) & (xy.abs() <= 1 + r).all(-1)
        sel = point_raster.search_points(xy, z, image, alive, H=H, W=W, K=1, radius=r, num_images=B * M,
                                         tile_size=c.tile_size, max_candidates=max_candidates)
    seen = sel.prim[:, 0] >= 0
    return sel.pix[seen], sel.prim[seen, 0]
