"""Point rasterizer: K nearest points in depth within a screen radius per pixel.

Each point of each view is a disc of ``radius`` (NDC units, constant on screen). The search runs
without autograd through ``tiles.py``; the squared screen distances of the winners are then
recomputed differentiably, so gradients reach point positions and the camera.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from . import nearest, tiles
from .ops import take


def search_points(xy: torch.Tensor, z: torch.Tensor, image: torch.Tensor, alive: torch.Tensor, *, H: int, W: int,
                  K: int, radius: float, num_images: int, tile_size: int, max_candidates: int,
                  overflow=None) -> nearest.Selection:
    """xy ``[N, 2]`` NDC, z ``[N]`` depth, image ``[N]``, alive ``[N]`` bool -> Selection over point-views."""
    with torch.no_grad():
        pv = torch.nonzero(alive).squeeze(1)
        seen = xy.detach().index_select(0, pv)
        x, y = seen[:, 0].contiguous(), seen[:, 1].contiguous()
        boxes = tiles.pixel_boxes(x - radius, x + radius, y - radius, y + radius, image.index_select(0, pv), H, W)
        zz = z.detach().index_select(0, pv)
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
            c = cand.prim.index_select(0, keep)
            picks.append(nearest.select_nearest(cand.pix.index_select(0, keep), zz.index_select(0, c), pv.index_select(0, c), K,
                                              num_images * H * W))
        return nearest.merge(picks, K, xy.device)


@dataclass
class PackedSlots:
    """The used slots of a point Selection, what the differentiable part needs of it: slot ``[S]``
    flat indices into ``[P, K]``, ascending; point ``[S]`` the point-view in each; pix ``[P]`` the
    active pixels. ``compact(num_point_views)`` stores slot and point as int32 (half the memory a recomputed group
    keeps for the backward pass) when they fit; ``long()`` gives int64 ones back."""

    slot: torch.Tensor
    point: torch.Tensor
    pix: torch.Tensor
    K: int

    @staticmethod
    def of(sel: nearest.Selection) -> "PackedSlots":
        slot = sel.occupied()
        return PackedSlots(slot, sel.prim.reshape(-1).index_select(0, slot), sel.pix, sel.prim.shape[1])

    def compact(self, num_point_views: int) -> "PackedSlots":
        if max(len(self.pix) * self.K, num_point_views) >= 2**31:
            return self
        return PackedSlots(self.slot.int(), self.point.int(), self.pix, self.K)

    def long(self) -> "PackedSlots":
        return PackedSlots(self.slot.long(), self.point.long(), self.pix, self.K)


def point_alphas(xy: torch.Tensor, packed: PackedSlots, *, H: int, W: int, radius: float, opacity: float) -> torch.Tensor:
    """Differentiable alphas of the used slots ``packed`` (pixel by pixel, nearest first): ``[S]``.

    Alpha falls off smoothly with the squared screen distance d^2 to the point's centre:
    ``opacity * (1 - d^2/r^2)^2``, C1 at the rim so camera gradients stay bounded.
    """
    px, py = tiles.pixel_centres(packed.pix.index_select(0, torch.div(packed.slot, packed.K, rounding_mode="floor")),
                                 H, W, xy.dtype)
    p = take(xy, packed.point)
    d2 = (p[:, 0] - px) ** 2 + (p[:, 1] - py) ** 2
    t = (1 - d2 / (radius * radius)).clamp(min=0)
    return opacity * t * t
