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

``SelectorTraining`` is the fixed views' (nothing to train); ``LearnedTraining`` the paper's
(autograd through the differentiable renderer on C's loss, an optional warm-up with G frozen);
``probes.ProbeTraining`` adds the smoothed gradient, G's own loss, view flips and raced hypotheses.
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


class SelectorTraining:
    """Fixed views: every step renders the selector's views; there is no G to train."""

    clip: Optional[float] = None

    def __init__(self, cfg) -> None:
        self.cfg, self.s = cfg, cfg.selector

    def start(self, model, cfg_dict: dict, resumed: bool) -> None:
        """Called once after the model is built, before the optimizer; ``resumed``: the weights come
        from the run's own checkpoint next."""

    def param_group(self, params: list) -> dict:
        raise ValueError(f"selector={self.s.name}: a fixed selector has no parameters to train")

    def start_epoch(self, model, epoch: int, g_lr: Optional[float], hold_views: bool) -> None:
        """Called before the first step of 0-based ``epoch``; ``g_lr``: G's learning rate now."""

    def select(self, model, batch: dict):
        return model.select(batch)

    def forward(self, model, batch: dict, views, loss_fn, grad_render: bool = True) -> Step:
        """R then C on ``views``: the task loss is the objective."""
        labels = batch["labels"].to(model.device)
        with self.timer.stage("render"), torch.set_grad_enabled(grad_render):
            images = model.render(batch, *views)
        with self.timer.stage("backbone"):
            logits, _ = model.classify(images, views, batch)
            loss = model.mvnet.training_loss(logits, labels, loss_fn)
        return Step(views, images, logits, labels, loss, loss)

    def train_step(self, model, batch: dict, step: int, loss_fn, timer) -> Step:
        self.timer = timer
        with timer.stage("selector"):
            views = self.select(model, batch)
        return self.forward(model, batch, views, loss_fn)

    def end_epoch(self, model, epoch: int) -> list[str]:
        return []

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
        return {}


class LearnedTraining(SelectorTraining):
    """The paper's: G trains by autograd through R on C's loss, in its own AdamW group (``lr``,
    ``beta1``), its gradient clipped to ``clip``; with ``move_every`` k it moves in one epoch of
    every k only. For the first ``warmup_epochs`` epochs (and
    whenever the multi-view net holds the views) G is frozen and C trains on ``warmup_views``; from
    ``stop_epoch`` on, or at learning rate 0, C trains on G's views without G's gradient."""

    def __init__(self, cfg) -> None:
        super().__init__(cfg)
        self.clip = self.s.clip
        self.warm = self.frozen = False

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

    def select(self, model, batch: dict):
        with torch.set_grad_enabled(not self.frozen):
            return self.warmup_views(model, batch) if self.warm else model.select(batch)

