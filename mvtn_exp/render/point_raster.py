"""Point rasterizer: K nearest points in depth within a screen radius per pixel.

Each point of each view is a disc of ``radius`` (NDC units, constant on screen). The search runs
without autograd through ``tiles.py``; the squared screen distances of the winners are then
recomputed differentiably, so gradients reach point positions and the camera.
"""
from __future__ import annotations

import torch

from . import tiles
from .ops import take


def search_points(xy: torch.Tensor, z: torch.Tensor, image: torch.Tensor, alive: torch.Tensor, *, H: int, W: int,
                  K: int, radius: float, num_images: int, tile_size: int, max_candidates: int,
                  overflow=None) -> tiles.Selection:
    """xy ``[N, 2]`` NDC, z ``[N]`` depth, image ``[N]``, alive ``[N]`` bool -> Selection over point-views."""
    with torch.no_grad():
        pv = torch.nonzero(alive).squeeze(1)
        x, y = xy.detach()[pv, 0], xy.detach()[pv, 1]
        boxes = tiles.pixel_boxes(x - radius, x + radius, y - radius, y + radius, image[pv], H, W)
        zz = z.detach()[pv]
        r2 = radius * radius

        def span(p, yy):  # the disc's chord at height yy (slightly widened: candidates are re-tested)
            cx = x.index_select(0, p)
            half = (r2 - (yy - y.index_select(0, p)) ** 2).clamp(min=0).sqrt() + 1e-6
            return tiles.columns(cx - half, cx + half, W)

        picks = []
        for parts in tiles.candidate_chunks(boxes, H, W, tile_size, max_candidates, xy.dtype, span, overflow=overflow):
            cand = tiles.concat(parts)
            d2 = (cand.x - x.index_select(0, cand.prim)) ** 2 + (cand.y - y.index_select(0, cand.prim)) ** 2
            keep = torch.nonzero(d2 < r2).squeeze(1)
            c = cand.prim[keep]
            picks.append(tiles.select_nearest(cand.pix[keep], zz.index_select(0, c), pv.index_select(0, c), K, num_images * H * W))
        return tiles.merge(picks, K, xy.device)


def point_alphas(xy: torch.Tensor, sel: tiles.Selection, *, H: int, W: int, radius: float,
                 opacity: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Differentiable alphas of the occupied slots only: (slot ``[S]``, flat indices into
    ``sel.prim.view(-1)``, ascending (pixel by pixel, nearest first); alpha ``[S]``).

    Alpha falls off smoothly with the squared screen distance d^2 to the point's centre:
    ``opacity * (1 - d^2/r^2)^2``, C1 at the rim so camera gradients stay bounded.
    """
    K = sel.prim.shape[1]
    slot = sel.occupied()
    px, py = tiles.pixel_centres(sel.pix.index_select(0, torch.div(slot, K, rounding_mode="floor")), H, W, xy.dtype)
    p = take(xy, sel.prim.reshape(-1).index_select(0, slot))
    d2 = (p[:, 0] - px) ** 2 + (p[:, 1] - py) ** 2
    t = (1 - d2 / (radius * radius)).clamp(min=0)
    return slot, opacity * t * t
