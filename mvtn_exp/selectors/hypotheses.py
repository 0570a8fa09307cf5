"""Several sets of views tried side by side early in training, the one with the lowest loss kept.

Why (the measurements: docs/results/finding-the-detail.md): on view-dependent data, whether G
finds the class detail is decided in the first epochs, before C reads anything, so a single set
of views finds it in some seeds only; and C learns the detail within a few epochs once one
consistent view shows it. So a G that holds H
hypotheses (``selector.hypotheses``; H sets of M views, each starting from its own part of the
spherical layout and moving on its own share of the smoothed gradient) has H chances, and C,
trained on every hypothesis's render of every shape, learns the detail from whichever shows it.

During the exploring epochs the trainer renders all H x M views, C classifies each hypothesis's
M views as a shape of its own (so a shape's H renders count as H samples of the batch), and each
shape's loss under each hypothesis is recorded: G's own loss (``selector.loss``; with the
centered logit a C that ignores the label scores every hypothesis 0 on average, so the race is
not won by views where C's output is merely flat). At the end of each exploring epoch the
hypothesis with the lowest mean loss becomes the selector's ``active`` one; validation,
checkpoints and test use only the active one. Exploration ends, and only the active hypothesis is
rendered from then on, once it leads every other by more than ``selector.race_z`` standard
errors of the paired per-shape differences (the same shapes seen under both: a randomised
comparison), or after ``selector.race_epochs`` epochs. The sums are cleared every epoch,
since C changes. The cost is H x the render and C of a step while exploring.
"""
from __future__ import annotations

import torch
from torch import Tensor, nn


class HypothesisRace(nn.Module):
    """Per-hypothesis loss sums of one epoch, and whether the race is over (buffers, in checkpoints).

    ``record(loss [B, H])``: each shape's loss under each hypothesis. ``decide(z)`` -> (index of
    the lowest mean loss, the means as a list, whether it leads every other by more than ``z``
    paired standard errors; ``z=None``: never) and clears the sums; with nothing recorded it
    returns ``(None, [], False)``. ``finish()`` ends the race for good (``done``).
    """

    def __init__(self, hypotheses: int) -> None:
        super().__init__()
        if int(hypotheses) < 2:
            raise ValueError(f"HypothesisRace: needs at least 2 hypotheses, got {hypotheses!r}")
        H = int(hypotheses)
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))
        self.register_buffer("sums", torch.zeros(H, dtype=torch.float64))
        self.register_buffer("products", torch.zeros(H, H, dtype=torch.float64))  # sum over shapes of l_h l_k
        self.register_buffer("done", torch.zeros((), dtype=torch.bool))

    @property
    def hypotheses(self) -> int:
        return self.sums.numel()

    def record(self, loss: Tensor) -> None:
        if loss.dim() != 2 or loss.shape[1] != self.hypotheses:
            raise ValueError(f"HypothesisRace.record: expected losses [B, {self.hypotheses}], got {list(loss.shape)}")
        loss = loss.detach().to(self.sums)  # the buffers' device and dtype (float64), wherever the model is
        self.count += loss.shape[0]
        self.sums += loss.sum(0)
        self.products += loss.T @ loss

    def decide(self, z: float | None = None) -> tuple[int | None, list[float], bool]:
        n = float(self.count)
        if n == 0:
            return None, [], False
        means = self.sums / n
        a = int(means.argmin())
        clear = False
        if z is not None and n > 1:
            second = self.products / n  # E[l_h l_k]
            diff = means - means[a]  # mean of l_b - l_a per b
            var = (second.diag() - 2 * second[a] + second[a, a] - diff ** 2).clamp_min(0) * n / (n - 1)
            se = (var / n).sqrt()
            others = torch.arange(self.hypotheses, device=means.device) != a
            clear = bool((diff[others] > z * se[others]).all())
        self.count.zero_()
        self.sums.zero_()
        self.products.zero_()
        return a, [float(m) for m in means], clear

    def finish(self) -> None:
        self.done.fill_(True)

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
