"""Several sets of views tried side by side early in training, the one with the lowest loss kept.

Why (measured on ``synthetic_views`` at M = 1, 2026-12-02): whether G finds the class detail is
decided in the first two to four epochs, before C reads anything, so it is a coin flip per run
(7 of 15 seeds); and C learns the detail within a few epochs once one consistent view shows it
(cameras on the cup axis: validation 0.30 after 2 epochs, 0.42 after 3). So a G that holds H
hypotheses (``selector.hypotheses``; H sets of M views, each starting from its own part of the
spherical layout and moving on its own share of the smoothed gradient) has H chances, and C,
trained on every hypothesis's render of every shape, learns the detail from whichever shows it.

During the first ``optim.hypothesis_epochs`` epochs the trainer renders all H x M views, C
classifies each hypothesis's M views as a shape of its own (so a shape's H renders count as H
samples of the batch), and each shape's loss is recorded per hypothesis. At the end of each of
those epochs the hypothesis with the lowest mean training loss becomes the selector's ``active``
one (and the sums are cleared); validation, checkpoints and test use only the active one, and
after the last exploring epoch only it is rendered. The cost is H x the render and C of a step
during exploration.
"""
from __future__ import annotations

import torch
from torch import Tensor, nn


class HypothesisRace(nn.Module):
    """Per-hypothesis loss sums of one epoch (buffers, in checkpoints).

    ``record(loss [B, H])``: each shape's loss under each hypothesis; ``decide()`` -> (index of the
    lowest mean loss, the means as a list) and clears the sums. An epoch with nothing recorded
    keeps nothing to decide: ``decide`` then returns ``(None, [])``.
    """

    def __init__(self, hypotheses: int) -> None:
        super().__init__()
        if int(hypotheses) < 2:
            raise ValueError(f"HypothesisRace: needs at least 2 hypotheses, got {hypotheses!r}")
        self.register_buffer("stats", torch.zeros(2, int(hypotheses), dtype=torch.float64))  # count, sum

    @property
    def hypotheses(self) -> int:
        return self.stats.shape[1]

    def record(self, loss: Tensor) -> None:
        if loss.dim() != 2 or loss.shape[1] != self.hypotheses:
            raise ValueError(f"HypothesisRace.record: expected losses [B, {self.hypotheses}], got {list(loss.shape)}")
        loss = loss.detach().double().cpu()
        self.stats[0] += loss.shape[0]
        self.stats[1] += loss.sum(0)

    def decide(self) -> tuple[int | None, list[float]]:
        n, s = self.stats
        if float(n.min()) == 0:
            return None, []
        means = s / n
        self.stats.zero_()
        return int(means.argmin()), [float(m) for m in means]

    def extra_repr(self) -> str:
        return f"hypotheses={self.hypotheses}"


def split_images(images: Tensor, hypotheses: int) -> Tensor:
    """Images of all hypotheses ``[B, H * M, C, h, w]`` (hypothesis-major) -> ``[B * H, M, C, h, w]``:
    each hypothesis's M views as a shape of its own, shape b's hypotheses at rows ``b * H ... b * H + H - 1``."""
    B, HM = images.shape[:2]
    if HM % hypotheses:
        raise ValueError(f"split_images: {HM} views do not split into {hypotheses} hypotheses")
    return images.reshape(B * hypotheses, HM // hypotheses, *images.shape[2:])


def split_views(views: tuple, hypotheses: int) -> tuple:
    """``(azim, elev, dist)`` each ``[B, H * M]`` -> each ``[B * H, M]`` (the rows of ``split_images``)."""
    return tuple(v.reshape(v.shape[0] * hypotheses, v.shape[1] // hypotheses) for v in views)


def join_views(views: tuple, hypotheses: int) -> tuple:
    """The inverse of ``split_views``: each ``[B * H, M]`` -> ``[B, H * M]``."""
    return tuple(v.reshape(v.shape[0] // hypotheses, v.shape[1] * hypotheses) for v in views)
