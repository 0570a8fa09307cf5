"""How G trains inside the one loop: the interface ``engine/trainer.py`` calls for every selector.

A selector config's ``training()`` names the class; the trainer builds it once per run and calls

- ``start(model, cfg_dict, resumed)`` once, after the model is built (view transfer loads and
  freezes G here);
- ``param_group(params)`` / ``clip``: G's AdamW group (only if G has parameters; its schedule
  multiplier is the selector config's ``lr_scale``);
- ``start_epoch(model, epoch, g_lr, hold_views)`` before an epoch's first step (``hold_views``:
  the multi-view net asks for G's initial views this epoch, e.g. ViewGCN's single-view stage);
- ``train_step(model, batch, step, loss_fn, timer) -> Step`` for every training batch: the forward
  pass shape -> G -> R -> C and the objective whose backward trains G and C;
- ``end_epoch(model, epoch) -> lines`` after the epoch's steps (decisions taken, for the log);
- ``before_validation(model, batches) -> state | None`` / ``after_validation(model, state)``;
- ``history(model) -> dict``: what the epoch's record keeps of G's training state.

``SelectorTraining`` is the fixed views' (nothing to train) and holds the one ``train_step``;
``LearnedTraining`` the paper's (autograd through the differentiable renderer on C's loss, an
optional warm-up with G frozen, ``move_every``, ``stop_epoch``) plus the training strategies its
config turns on (``selectors/strategies/``: the smoothed gradient, view flips, raced hypotheses,
the view search), whose hooks run in the config's order inside that step.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
from torch import Tensor

from ..render import layouts
from .canonical import pca_frames, world_views
from . import view_transfer
from .fixed import random_directions
from .hypotheses import split_images, split_views
from .strategies import StepContext


@dataclass
class Step:
    """One training step's forward: ``views`` (each ``[B', M]``), ``images [B', M, 3, H, W]``,
    ``logits [B', K]`` and ``labels [B']`` (B' = B, or B x H while hypotheses race), C's ``loss``
    (what the epoch reports) and the ``objective`` whose backward trains G and C."""

    views: tuple
    images: Tensor
    logits: Tensor
    labels: Tensor
    loss: Tensor
    objective: Tensor


def task_targets(loss_fn, model, batch: dict, views):
    """What C's output is compared with for ``views``: the task head's ``targets`` (e.g. the
    views' label images of segmentation), or the batch's class labels ``[B]``."""
    targets = getattr(loss_fn, "targets", None)
    return targets(model, batch, views) if targets is not None else batch["labels"].to(model.device)


class SelectorTraining:
    """Fixed views: every step renders the selector's views; there is no G to train.

    ``train_step`` is the one training step of every selector: the phase flags (``warm``,
    ``frozen``, ``learning``; all False here) and the enabled ``strategies`` (none here) shape it
    through their hooks (``selectors/strategies/__init__.py``)."""

    clip: Optional[float] = None

    def __init__(self, cfg) -> None:
        self.cfg, self.s = cfg, cfg.selector
        self.warm = self.frozen = self.learning = False
        self.strategies: list = []

    def start(self, model, cfg_dict: dict, resumed: bool) -> None:
        """Called once after the model is built, before the optimizer; ``resumed``: the weights come
        from the run's own checkpoint next."""

    def param_group(self, params: list) -> dict:
        raise ValueError(f"selector={self.s.name}: a fixed selector has no parameters to train")

    def start_epoch(self, model, epoch: int, g_lr: Optional[float], hold_views: bool) -> None:
        """Called before the first step of 0-based ``epoch``; ``g_lr``: G's learning rate now."""

    def context(self, model, batch: dict, step: int, loss_fn, timer) -> StepContext:
        """A step's context, carrying the epoch's phase."""
        return StepContext(model, batch, step, loss_fn, timer, warm=self.warm, frozen=self.frozen,
                           learning=self.learning)

    def select(self, model, batch: dict, ctx: StepContext):
        """G's views of the step, each ``[B, M]`` (``[B, H * M]`` for H hypotheses)."""
        return model.select(batch)

    def forward(self, ctx: StepContext) -> None:
        """R then C on ``ctx.seen``: fills ``ctx.labels`` (``task_targets``), ``images``, ``logits``
        and C's ``loss``.
        With S = ``ctx.sets`` > 1 each shape is S rows for C (its views split into S sets); R is
        differentiated unless a strategy says otherwise."""
        model, batch, S = ctx.model, ctx.batch, ctx.sets
        grad = all(s.differentiates_render(ctx) for s in self.strategies)
        with ctx.timer.stage("render"), torch.set_grad_enabled(grad):
            labels = task_targets(ctx.loss_fn, model, batch, ctx.seen)
            ctx.labels = labels if S == 1 else labels.repeat_interleave(S)  # [B * S]
            images = model.render(batch, *ctx.seen)
            ctx.images = images if S == 1 else split_images(images, S)  # [B * S, M', 3, h, w]
        with ctx.timer.stage("backbone"):
            if S == 1:
                ctx.logits, _ = model.classify(ctx.images, ctx.seen, batch)
            else:
                ctx.logits, _ = model.classify(ctx.images, split_views(ctx.seen, S))
            ctx.loss = model.mvnet.training_loss(ctx.logits, ctx.labels, ctx.loss_fn)

    def train_step(self, model, batch: dict, step: int, loss_fn, timer) -> Step:
        """G's views (after the strategies' ``transform_views``), C's views (``training_views``),
        R and C, the strategies' records (``after_forward``), and the objective: C's loss plus
        every strategy's ``g_term``."""
        ctx = self.context(model, batch, step, loss_fn, timer)
        for strategy in self.strategies:
            strategy.begin_step(ctx)
        with timer.stage("selector"), torch.set_grad_enabled(not self.frozen):
            ctx.views = self.select(model, batch, ctx)
            for strategy in self.strategies:
                ctx.views = strategy.transform_views(ctx)
        ctx.seen = ctx.views
        for strategy in self.strategies:
            ctx.seen = strategy.training_views(ctx)
        self.forward(ctx)
        for strategy in self.strategies:
            strategy.after_forward(ctx)
        objective = ctx.loss
        for strategy in self.strategies:
            term = strategy.g_term(ctx)
            if term is not None:
                objective = objective + term
        return Step(ctx.views, ctx.images, ctx.logits, ctx.labels, ctx.loss, objective)

    def end_epoch(self, model, epoch: int) -> list[str]:
        """The strategies' decisions after the epoch's steps, their log lines in order."""
        return [line for strategy in self.strategies for line in strategy.end_epoch(model, epoch)]

    def before_validation(self, model, batches) -> Optional[dict]:
        """``bn_recalibrate > 0``: re-estimate C's BatchNorm statistics on the selector's current
        views (fixed, or G's); with scope ``eval`` return training's own statistics
        (``after_validation`` puts them back)."""
        from ..models import precise_bn

        if not self.s.bn_recalibrate:
            return None
        state = precise_bn.running_statistics(model) if self.s.bn_recalibrate_scope == "eval" else None
        precise_bn.recalibrate(model, batches(), self.s.bn_recalibrate)
        return state

    def after_validation(self, model, state: Optional[dict]) -> None:
        from ..models import precise_bn

        if state is not None:
            precise_bn.restore(model, state)

    def history(self, model) -> dict:
        """The strategies' entries of the epoch's record."""
        return {k: v for strategy in self.strategies for k, v in strategy.history(model).items()}


class LearnedTraining(SelectorTraining):
    """The paper's: G trains by autograd through R on C's loss, in its own AdamW group (``lr``,
    ``beta1``), its gradient clipped to ``clip``; with ``move_every`` k it moves in one epoch of
    every k only. For the first ``warmup_epochs`` epochs (and
    whenever the multi-view net holds the views) G is frozen and C trains on ``warmup_views``; from
    ``stop_epoch`` on, or at learning rate 0, C trains on G's views without G's gradient.
    ``strategies``: the config's enabled training strategies, built once per run, in its order."""

    def __init__(self, cfg) -> None:
        super().__init__(cfg)
        self.clip = self.s.clip
        self.strategies = [strategy(cfg) for strategy in self.s.enabled_strategies()]

    def start(self, model, cfg_dict: dict, resumed: bool) -> None:
        """``selector.from_ckpt``: G from another run, frozen (a resumed run has it in its own state)."""
        if self.s.from_ckpt and not resumed:
            view_transfer.load_frozen_selector(model, cfg_dict, self.s.from_ckpt)
        elif self.s.from_ckpt:
            view_transfer.freeze_selector(model)

    def param_group(self, params: list) -> dict:
        return {"params": params, "lr": self.s.lr, "name": "selector", "betas": (self.s.beta1, 0.999)}

    def start_epoch(self, model, epoch: int, g_lr: Optional[float], hold_views: bool) -> None:
        trains = bool(model.parameter_groups()["selector"])
        self.warm = trains and (epoch < self.s.warmup_epochs or hold_views)
        # G's learning rate is 0, or G holds its views this epoch (move_every): C trains on G's views,
        # and G's gradient is not computed
        holding = (epoch - self.s.warmup_epochs) % self.s.move_every != 0
        self.frozen = trains and not self.warm and (g_lr == 0.0 or holding)
        self.learning = trains and not self.warm and not self.frozen
        phase = StepContext(model, {}, -1, None, None, warm=self.warm, frozen=self.frozen, learning=self.learning)
        for strategy in self.strategies:
            strategy.start_epoch(model, epoch, phase)

    def warmup_views(self, model, batch: dict):
        """Views of a warm-up step, each ``[B, warmup_num_views or views]``: G's initial views u0,
        new uniform random views per shape, the fixed spherical layout, or a ring in each shape's
        principal frame (``canonical``: world directions of the shapes as posed)."""
        B, M = batch["points"].shape[0], self.s.warmup_num_views or self.cfg.views
        if self.s.warmup_views == "random":
            azim, elev = random_directions((B, M))
            azim, elev = azim.float().to(model.device), elev.float().to(model.device)
            return azim, elev, torch.full_like(azim, self.s.distance)
        if self.s.warmup_views == "spherical":
            return layouts.spherical(M, B, self.s.distance, device=model.device, sphere=self.s.sphere)
        if self.s.warmup_views == "canonical":  # a ring in each shape's principal frame, as world views
            ring = layouts.circular(M, B, self.s.warmup_elevation, self.s.distance, device=model.device)
            return world_views(ring, pca_frames(batch["points"].to(model.device)))
        return tuple(t.to(model.device) for t in model.selector.initial_views(B))

    def select(self, model, batch: dict, ctx: StepContext):
        """Warm-up views while warm, else G's (all H hypotheses' when ``ctx.hypotheses`` > 1)."""
        if self.warm:
            return self.warmup_views(model, batch)
        return model.select(batch, all_hypotheses=True) if ctx.hypotheses > 1 else model.select(batch)

