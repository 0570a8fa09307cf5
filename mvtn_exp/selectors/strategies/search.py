"""G trained on a view search (``selector.grad=search``): C's loss is read at candidate views over
the whole sphere, and each of G's views is pulled towards the best candidate near it.

The paper's G learns from the gradient of C's loss through R. Where the class shows from a narrow
set of views only, that gradient is zero almost everywhere: from a view that does not see the
detail, no small move changes what C sees of it (``docs/results/finding-the-detail.md``). A G
that *can* express the right view (``scripts/studies/g_capacity.py``) then never finds it. The
search gives G a target instead of a slope; the formulation of G is untouched (``u = u0 + u_bound
tanh(G(S))`` for ``mvtn_spherical``), only its training differs. Every ``search_every`` steps
while G learns:

1. candidates: ``search_views`` directions spread over the sphere (the equal-area layout, turned
   by a fresh random rotation each search, from ``noise_generator(seed + 104_729, step)``, so that
   the candidates cover the sphere over time), at the selector's distance, plus G's own M views;
2. each candidate rendered and classified *alone* by C (eval mode, no gradient), scored by G's
   per-shape loss (``selector.loss``: ``task`` or ``centered_logit``), ``[B, K + M]``;
3. G's view m is assigned the candidates nearer to it than to G's other views (its own among them)
   and its target is the lowest-scoring of those (for M = 1: the best of all);
4. G's loss: ``search_weight x mean (1 - cos(view, target))`` over shapes and views, added to C's
   loss; R is not differentiated, so this is G's only gradient.

C keeps training on G's views as usual. With ``warmup_epochs`` (and ``warmup_views=spherical``,
``warmup_num_views``) C first learns the classes from many fixed views while G waits, so that its
scores of single views mean something when the search starts. The labels are read while
training only (the loss needs them); evaluation is G alone.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
from torch import Tensor

from ...config.checks import at_least
from ...render import layouts
from ...render.cameras import direction_angles as to_angles
from ...render.cameras import view_directions as unit_directions
from ...tasks import classification
from ...tasks.robustness import random_rotations
from .. import view_gradient
from .base import Strategy, StepContext, StrategyKeys, register_strategy

SEARCH_SEED = 104_729  # the candidates' rotations: a stream apart from the smoothed noise


def candidates(K: int, B: int, distance: float, generator: torch.Generator, device) -> tuple:
    """``K`` equal-area directions turned by one random rotation (from ``generator``), the same for
    the ``B`` shapes of the batch -> ``(azim, elev, dist)`` each ``[B, K]``."""
    azim, elev, _ = layouts.spherical(K, 1, distance, dtype=torch.float64)
    R = random_rotations(1, "so3", generator)[0]
    a, e = to_angles(unit_directions(azim[0], elev[0]) @ R.T)
    a, e = (x.float().to(device).expand(B, K) for x in (a, e))
    return a, e, torch.full_like(a, float(distance))


def targets(views_dir: Tensor, cand_dir: Tensor, scores: Tensor) -> Tensor:
    """Each view's target: the lowest-scoring candidate among those nearest to it.

    ``views_dir [B, M, 3]`` G's views (unit), ``cand_dir [B, C, 3]`` the candidates (unit; G's own
    views among them), ``scores [B, C]`` -> target directions ``[B, M, 3]``.
    """
    owner = torch.einsum("bmi,bci->bmc", views_dir, cand_dir).argmax(1)  # [B, C]: the view nearest to each candidate
    M = views_dir.shape[1]
    mine = owner[:, None, :] == torch.arange(M, device=owner.device)[None, :, None]  # [B, M, C]
    masked = scores[:, None, :].expand(-1, M, -1).masked_fill(~mine, float("inf"))
    best = masked.argmin(-1)  # [B, M]; a view owning no candidate gets candidate 0's score inf: see below
    target = torch.gather(cand_dir, 1, best[..., None].expand(-1, -1, 3))
    owns = mine.any(-1, keepdim=True)
    return torch.where(owns, target, views_dir)  # a view with no candidate of its own stays


def search_loss(views: tuple, target: Tensor) -> Tensor:
    """``mean (1 - cos(view, target))`` over shapes and views; ``target [B, M, 3]`` unit, detached."""
    return (1.0 - (unit_directions(views[0], views[1]) * target.detach()).sum(-1)).mean()


@dataclass
class SearchKeys(StrategyKeys):
    """``search_views`` candidates every ``search_every`` steps, G pulled with weight ``search_weight``."""

    search_views: int = 12
    search_every: int = 1
    search_weight: float = 1.0

    def validate(self):
        super().validate()
        at_least("selector.search_views", self.search_views, 1)
        at_least("selector.search_every", self.search_every, 1)
        at_least("selector.search_weight", self.search_weight, 0.0, strict=True)
        return self


@register_strategy
class Search(Strategy):
    """G's gradient from the view search of the module docstring; R is never differentiated."""

    name = "search"
    keys = SearchKeys
    training_keys = ("search_views", "search_every", "search_weight")
    switch = "grad"
    grad = "search"

    def __init__(self, cfg) -> None:
        super().__init__(cfg)
        self.selector_loss = classification.selector_loss_fn(self.s.loss, cfg.task)
        self.learning = False

    def start_epoch(self, model, epoch: int, ctx: StepContext) -> None:
        self.learning = ctx.learning

    def differentiates_render(self, ctx: StepContext) -> bool:
        return False

    def score(self, model, batch: dict, views: tuple, labels: Tensor) -> Tensor:
        """G's loss of every view of ``views`` (each ``[B, C]``) seen alone by C -> ``[B, C]``."""
        B, C = views[0].shape
        with torch.no_grad(), view_gradient.eval_mode(model):
            images = model.render(batch, *views)  # [B, C, 3, h, w]
            alone = tuple(v.reshape(B * C, 1) for v in views)
            logits, _ = model.mvnet(images.reshape(B * C, 1, *images.shape[2:]), alone)
        return self.selector_loss(logits.float(), labels.repeat_interleave(C)).reshape(B, C)

    def g_term(self, ctx: StepContext) -> Optional[Tensor]:
        if not self.learning or ctx.step % self.s.search_every or ctx.hold_g:
            return None
        views = ctx.views
        with ctx.timer.stage("selector"):
            B, device = views[0].shape[0], views[0].device
            gen = view_gradient.noise_generator(self.cfg.seed + SEARCH_SEED, ctx.step)
            cand = candidates(self.s.search_views, B, self.s.distance, gen, device)
            own = tuple(v.detach() for v in views)
            pool = tuple(torch.cat([c, o], 1) for c, o in zip(cand, own))  # [B, K + M]
            scores = self.score(ctx.model, ctx.batch, pool, ctx.labels)
            target = targets(unit_directions(own[0], own[1]), unit_directions(pool[0], pool[1]), scores)
            return self.s.search_weight * search_loss(views, target)
