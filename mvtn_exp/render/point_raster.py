"""Point rasterizer: K nearest points in depth within a screen radius per pixel.

Each point of each view is a disc of ``radius`` (NDC units, constant on screen). The search runs
without autograd through ``tiles.py``; the squared screen distances of the winners are then
recomputed differentiably, so gradients reach point positions and the camera.
"""
from __future__ import annotations

import torch

from . import tiles


def search_points(xy: torch.Tensor, z: torch.Tensor, image: torch.Tensor, alive: torch.Tensor, *, H: int, W: int,
                  K: int, radius: float, num_images: int, tile_size: int, max_candidates: int) -> tiles.Selection:
    """xy ``[N, 2]`` NDC, z ``[N]`` depth, image ``[N]``, alive ``[N]`` bool -> Selection over point-views."""
    with torch.no_grad():
        pv = torch.nonzero(alive).squeeze(1)
        x, y = xy.detach()[pv, 0], xy.detach()[pv, 1]
        boxes = tiles.pixel_boxes(x - radius, x + radius, y - radius, y + radius, image[pv], H, W)
        picks = []
        for c, pix in tiles.candidate_chunks(boxes, H, W, tile_size, max_candidates):
            px, py = tiles.pixel_centres(pix, H, W, xy.dtype)
            d2 = (px - x[c]) ** 2 + (py - y[c]) ** 2
            keep = torch.nonzero(d2 < radius * radius).squeeze(1)
            picks.append(tiles.select_nearest(pix[keep], z.detach()[pv[c[keep]]], pv[c[keep]], K, num_images * H * W))
        return tiles.merge(picks, K, xy.device)


def point_sqdist(xy: torch.Tensor, sel: tiles.Selection, *, H: int, W: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Differentiable squared NDC distance ``[P, K]`` from each active pixel to its points, and validity."""
    valid = sel.prim >= 0
    px, py = tiles.pixel_centres(sel.pix, H, W, xy.dtype)
    p = xy[sel.prim.clamp(min=0)]
    d2 = (p[..., 0] - px[:, None]) ** 2 + (p[..., 1] - py[:, None]) ** 2
    return d2, valid
