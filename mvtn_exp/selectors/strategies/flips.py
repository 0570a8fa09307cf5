"""View flips (``selector.flip_explore``): some training views rendered from their antipodes, the winners turned round.

From the end of the warm-up until ``flip_epochs`` each training view is rendered from its
antipode with probability ``flip_explore`` (draws from ``noise_generator(seed + 7_919, step)``);
each shape's loss is recorded per view as kept or flipped in the model's ``polarity`` module
(``selectors/polarity.py``: a ``ViewPolarity``, in checkpoints), and at the end of each of those
epochs a view whose antipode had the lower loss turns round for good. Per-shape statistics: one
process only.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from ...config.checks import at_least
from ...tasks import classification
from .. import view_gradient
from ..polarity import ViewPolarity
from .base import Strategy, StepContext, StrategyKeys, register_strategy

FLIP_SEED = 7_919  # the flip draws' stream: apart from the smoothed noise


def flip_generator(seed: int, step: int) -> torch.Generator:
    """The flip draws' own generator for global step ``step`` (a stream apart from the smoothed noise)."""
    return view_gradient.noise_generator(int(seed) + FLIP_SEED, step)


@dataclass
class FlipKeys(StrategyKeys):
    """``flip_explore``: the probability that a training view is rendered from its antipode (0: off),
    for the first ``flip_epochs`` epochs."""

    flip_explore: float = 0.0
    flip_epochs: int = 10

    def validate(self):
        super().validate()
        if self.grad == "search" and self.flip_explore > 0:
            raise ValueError("selector.grad=search with selector.flip_explore: the search already looks all round; "
                             "set selector.flip_explore=0")
        if not 0.0 <= self.flip_explore < 1.0:
            raise ValueError(f"selector.flip_explore={self.flip_explore!r}: expected a probability in [0, 1)")
        at_least("selector.flip_epochs", self.flip_epochs, 1)
        if self.from_ckpt and self.flip_explore > 0:
            raise ValueError("selector.from_ckpt with selector.flip_explore: a transferred G is frozen, its views are "
                             "not turned round")
        return self


@register_strategy
class Flips(Strategy):
    """Views explored from their antipodes and turned round where that side wins (the module docstring)."""

    name = "flips"
    keys = FlipKeys
    training_keys = ("flip_epochs",)
    multi_process = False
    switch = "flip_explore"

    def __init__(self, cfg) -> None:
        super().__init__(cfg)
        self.per_shape_loss = classification.loss_fn(cfg.task, reduction="none")
        self.exploring, self.mask = False, None

    @classmethod
    def enabled(cls, s) -> bool:
        return s.flip_explore > 0

    @classmethod
    def modules(cls, s, views: int) -> dict:
        return {"polarity": ViewPolarity(views)}

    def explores(self, epoch: int) -> bool:
        return self.s.warmup_epochs <= epoch < self.s.flip_epochs

    def start_epoch(self, model, epoch: int, ctx: StepContext) -> None:
        self.exploring = self.explores(epoch)

    def transform_views(self, ctx: StepContext) -> tuple:
        if not self.exploring:
            return ctx.views
        views, self.mask = ctx.model.polarity.explore(ctx.views, self.s.flip_explore,
                                                      flip_generator(self.cfg.seed, ctx.step))
        return views

    def after_forward(self, ctx: StepContext) -> None:
        if self.exploring:
            ctx.model.polarity.record(self.per_shape_loss(ctx.logits.detach(), ctx.labels), self.mask)

    def end_epoch(self, model, epoch: int) -> list[str]:
        if not self.explores(epoch):
            return []
        turned = model.polarity.decide()
        return [f"epoch {epoch + 1}: view(s) {turned} turned round (their antipodes had the lower loss)"] if turned else []

    def history(self, model) -> dict:
        return {"views_flipped": model.polarity.flipped.tolist()}
