"""Which side of its axis each learned view looks from: a per-view polarity chosen by trying both.

Why (measured on ``synthetic_views``, ``python scripts/studies/view_landscape.py --thetas ...``
on the C of epoch 1 of learned runs): before C can read the class detail, its loss is lowest
where its predictions are most uniform, which is on the cup axis *from either side*: 2.16 /
2.19 / 2.22 / 2.21 / 2.23 / 2.18 / 2.14 at 0 / 30 / 60 / 90 / 120 / 150 / 180 degrees from the
axis (seed 1). The view into the cup (0) and the view of its outside bottom (180) are two basins
of equal depth that no gradient can tell apart, since only the first shows the detail once C
has learned it. A G on the losing side never lets C see the detail, so C never learns it and
the other basin never gets deeper: in 3 of 6 runs G settled behind the cup in the first epochs.

So during the first ``selector.flip_epochs`` epochs each training view is, with probability
``selector.flip_explore``, rendered from its antipode ``(azim + 180, -elev)`` instead (an
independent draw per shape and view). C thereby trains on both sides of G's axis; the shape's
loss is recorded per view as "kept" or "flipped", and at the end of each of those epochs a view
whose flipped renders had a lower mean loss than its kept ones, by more than two standard
errors, turns round for good (its polarity toggles). The comparison is a randomised
experiment, so with M > 1 the other views' flips only add noise to it. Validation and test
views use the polarity, never the exploration.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor, nn


def antipode(azim: Tensor, elev: Tensor) -> tuple[Tensor, Tensor]:
    """The opposite camera direction: ``(azim + 180, -elev)`` in degrees, azimuth kept in
    [-180, 180); differentiable (gradient +1 / -1)."""
    return torch.remainder(azim + 360.0, 360.0) - 180.0, -elev


class ViewPolarity(nn.Module):
    """Per-view polarity of M views with its exploration statistics (all buffers, in checkpoints).

    ``forward(views)``: each ``[B, M]``; views whose polarity is flipped are replaced by their
    antipodes. ``explore(views, prob, generator)`` -> (views, mask ``[B, M]`` bool) also flips
    the masked entries; ``record(loss [B], mask)`` adds each shape's loss to its views' kept /
    flipped sums; ``decide()`` toggles the views whose flipped side won (see the module docstring)
    and clears the sums; returns the indices of the views turned round.
    """

    transforms_views = True  # the model maps G's views through it at every selection (``MVTN.select``)

    def __init__(self, views: int, min_count: int = 8, z: float = 2.0) -> None:
        super().__init__()
        self.min_count, self.z = int(min_count), float(z)
        self.register_buffer("flipped", torch.zeros(views, dtype=torch.bool))
        # [side (0 kept, 1 flipped), M]: count, sum and sum of squares of the shapes' losses
        self.register_buffer("stats", torch.zeros(3, 2, views, dtype=torch.float64))

    def _apply_flips(self, views: tuple, flip: Tensor) -> tuple:
        azim, elev, dist = views
        a, e = antipode(azim, elev)
        return torch.where(flip, a, azim), torch.where(flip, e, elev), dist

    def forward(self, views: tuple) -> tuple:
        return self._apply_flips(views, self.flipped.expand_as(views[0]))

    def explore(self, views: tuple, prob: float, generator: torch.Generator) -> tuple[tuple, Tensor]:
        """``views`` after the polarity (``forward``'s output); returns them with a random share
        ``prob`` of the entries turned to their antipodes, and that mask ``[B, M]``."""
        mask = (torch.rand(views[0].shape, generator=generator) < prob).to(views[0].device)
        return self._apply_flips(views, mask), mask

    def record(self, loss: Tensor, mask: Tensor) -> None:
        loss = loss.detach().double()[:, None].expand_as(mask)
        for side, sel in enumerate((~mask, mask)):
            w = sel.double()
            self.stats[0, side] += w.sum(0)
            self.stats[1, side] += (w * loss).sum(0)
            self.stats[2, side] += (w * loss * loss).sum(0)

    def decide(self) -> list[int]:
        n, s, ss = self.stats.unbind(0)  # each [2, M]
        turned = []
        for m in range(self.flipped.numel()):
            if min(n[0, m], n[1, m]) < self.min_count:
                continue
            mean = s[:, m] / n[:, m]
            var = (ss[:, m] / n[:, m] - mean ** 2).clamp_min(0) * n[:, m] / (n[:, m] - 1)
            se = math.sqrt(float((var / n[:, m]).sum()))
            if float(mean[0] - mean[1]) > self.z * se:
                self.flipped[m] = ~self.flipped[m]
                turned.append(m)
        self.stats.zero_()
        return turned

    def extra_repr(self) -> str:
        return f"views={self.flipped.numel()}, min_count={self.min_count}, z={self.z}"
