"""The smoothed gradient (``selector.grad=smoothed``): G's gradient from probe renders, and C's jittered views.

While G learns, R is not differentiated: every ``probe_every`` steps G's gradient is the loss
smoothed over the views, estimated from ``probe_pairs`` antithetic pairs of renders ``probe_sigma``
degrees apart (``selectors/view_gradient.py``) of G's own ``loss`` (``task`` or
``centered_logit``), added to the objective as ``view_gradient.surrogate``; with ``probe_batched``
every probe of a step is rendered in one call (not while hypotheses race: ``sets`` > 1). No probes
in a step whose ``hold_g`` is set (a race without probes). ``train_jitter``: C trains on G's views
moved by Gaussian noise of that many degrees (the probes stay at G's views), so that C does not
adapt to G's exact view. Random streams: the probes' noise ``noise_generator(seed, step)``, the
jitter's ``noise_generator(seed + 15_485_863, step)``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
from torch import Tensor

from ...config.checks import at_least
from ...tasks import classification
from .. import view_gradient
from ..hypotheses import join_views, split_views
from .base import Strategy, StepContext, StrategyKeys, register_strategy

JITTER_SEED = 15_485_863  # the jitter's stream: apart from the probes'


def jittered(views: tuple, degrees: float, generator: torch.Generator) -> tuple:
    """``(azim, elev, dist)`` each ``[B, M]`` -> the same views moved by ``N(0, degrees^2)`` in azimuth
    and elevation (detached: C's training views, not G's)."""
    azim, elev, dist = (v.detach() for v in views)
    noise = torch.randn((2, *azim.shape), generator=generator, dtype=torch.float64).to(azim)
    return azim + degrees * noise[0], elev + degrees * noise[1], dist


@dataclass
class SmoothedKeys(StrategyKeys):
    """``probe_pairs`` antithetic pairs ``probe_sigma`` degrees apart every ``probe_every`` steps,
    rendered in one call with ``probe_batched``; ``train_jitter``: C's views moved off G's by this
    many degrees (0: G's views; needs ``grad=smoothed``)."""

    probe_pairs: int = 2
    probe_sigma: float = 10.0
    train_jitter: float = 0.0
    probe_every: int = 1
    probe_batched: bool = False

    def validate(self):
        super().validate()
        at_least("selector.probe_pairs", self.probe_pairs, 1)
        at_least("selector.probe_sigma", self.probe_sigma, 0.0, strict=True)
        at_least("selector.train_jitter", self.train_jitter, 0.0)
        if self.train_jitter > 0 and self.grad != "smoothed":
            raise ValueError(f"selector.train_jitter={self.train_jitter}: C's views are moved off G's only with "
                             "selector.grad=smoothed (G's gradient from probes at its own views)")
        at_least("selector.probe_every", self.probe_every, 1)
        return self


@register_strategy
class Smoothed(Strategy):
    """G's gradient from antithetic probe renders, C on jittered views (the module docstring)."""

    name = "smoothed"
    keys = SmoothedKeys
    training_keys = ("probe_pairs", "probe_sigma", "probe_every", "train_jitter", "probe_batched")
    switch = "grad"
    grad = "smoothed"

    def __init__(self, cfg) -> None:
        super().__init__(cfg)
        self.selector_loss = classification.selector_loss_fn(self.s.loss, cfg.task)
        self.active = False

    def start_epoch(self, model, epoch: int, ctx: StepContext) -> None:
        self.active = ctx.learning  # probes only while G learns

    def training_views(self, ctx: StepContext) -> tuple:
        if not (self.active and self.s.train_jitter > 0):
            return ctx.seen
        return jittered(ctx.seen, self.s.train_jitter,
                        view_gradient.noise_generator(self.cfg.seed + JITTER_SEED, ctx.step))

    def differentiates_render(self, ctx: StepContext) -> bool:
        return not self.active

    def g_term(self, ctx: StepContext) -> Optional[Tensor]:
        """``surrogate(views, g)`` with ``g`` the smoothed estimate at G's views (split per
        hypothesis when C sees each alone)."""
        if not self.active or ctx.step % self.s.probe_every or ctx.hold_g:
            return None
        S = ctx.sets
        with ctx.timer.stage("selector"):
            g = view_gradient.smoothed_view_gradient(
                view_gradient.model_render_loss(ctx.model, ctx.batch, ctx.labels, self.selector_loss, hypotheses=S),
                split_views(ctx.views, S) if S > 1 else ctx.views,
                self.s.probe_pairs, self.s.probe_sigma, view_gradient.noise_generator(self.cfg.seed, ctx.step),
                batched=self.s.probe_batched and S == 1)
            return view_gradient.surrogate(ctx.views, *(join_views(g, S) if S > 1 else g))
