"""Raced hypotheses (``selector.hypotheses`` H > 1): H sets of views trained side by side, the one of lowest G loss kept.

For at most ``race_epochs`` epochs after the warm-up G gives all H sets of M views, C trains on
each (``race_mode``: ``separate``, each set a shape of its own, or ``pooled``, all H x M views as
one), each shape's G loss under each set is recorded in the model's ``hypotheses`` module
(``selectors/hypotheses.py``: a ``HypothesisRace``, in checkpoints) and at the end of each racing
epoch the set of lowest mean loss becomes G's ``active`` one; the race ends once it leads every
other by ``race_z`` paired standard errors, at its last epoch, or (``race_batches`` N) after N
batches of a racing epoch. ``race_probes=false``: no G term in racing steps (``hold_g``). Needs a
G that holds hypotheses (``PoiConfig``) and a multi-view net that classifies any view set.
Per-shape statistics: one process only.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Optional

import torch

from ...config.checks import at_least, one_of
from ...tasks import classification
from .. import view_gradient
from ..hypotheses import HypothesisRace, split_images
from .base import Strategy, StepContext, StrategyKeys, register_strategy

if TYPE_CHECKING:  # pragma: no cover
    from ...config.schema import TrainConfig

RACE_MODES = ("separate", "pooled")  # how C sees the hypotheses while they race
ONE_SET = "selector.hypotheses=1 selector.race_epochs=0 selector.antipodes=false"  # one set of views, no race
ENDS = {"batches": " (after {n} batches: kept from now on)", "lead": " (a clear lead: kept from now on)",
        "cap": " (the race's last epoch, no clear lead: kept from now on)", None: ""}


def hypothesis_losses(model, logits, images, labels, H: int, S: int, selector_loss):
    """Each shape's G loss under each of the H hypotheses, ``[B, H]``. Separate (S = H): read off
    the training logits ``[B * H, classes]``; pooled (S = 1): C in eval mode, without gradients, on
    each hypothesis's M views alone (``images [B, H * M, 3, h, w]``)."""
    if S == H:
        return selector_loss(logits.detach(), labels).reshape(-1, H)
    with torch.no_grad(), view_gradient.eval_mode(model.mvnet):
        alone, _ = model.mvnet(split_images(images.detach(), H))
    return selector_loss(alone, labels.repeat_interleave(H)).reshape(-1, H)


@dataclass
class RaceKeys(StrategyKeys):
    """``hypotheses`` H sets of M views raced for at most ``race_epochs`` epochs (both or neither),
    decided early at a lead of ``race_z`` paired standard errors (null: never) or after
    ``race_batches`` batches (null: whole epochs); ``race_mode``: separate | pooled;
    ``race_probes``: false holds G while they race."""

    hypotheses: int = 1
    race_epochs: int = 0
    race_z: Optional[float] = 3.0
    race_batches: Optional[int] = None
    race_mode: str = "separate"
    race_probes: bool = True

    def validate(self):
        super().validate()
        at_least("selector.hypotheses", self.hypotheses, 1)
        at_least("selector.race_epochs", self.race_epochs, 0)
        if self.race_z is not None:
            at_least("selector.race_z", self.race_z, 0.0)
        if self.race_batches is not None:
            at_least("selector.race_batches", self.race_batches, 1)
        one_of("selector.race_mode", self.race_mode, RACE_MODES)
        if (self.hypotheses > 1) != (self.race_epochs > 0):
            raise ValueError(f"selector.hypotheses={self.hypotheses} with selector.race_epochs={self.race_epochs}: "
                             f"set both (hypotheses >= 2 and race_epochs >= 1) or neither (one set of views: {ONE_SET})")
        if self.hypotheses > 1 and (self.flip_explore > 0 or self.grad == "search"):
            raise ValueError(f"selector.hypotheses={self.hypotheses} with selector.flip_explore or selector.grad=search: "
                             f"choose one way to explore (one set of views: {ONE_SET})")
        if not self.race_probes and self.hypotheses < 2:
            raise ValueError("selector.race_probes=false with selector.hypotheses=1: nothing races (it holds G only "
                             "while hypotheses race)")
        if self.from_ckpt and self.hypotheses > 1:
            raise ValueError(f"selector.from_ckpt with selector.hypotheses={self.hypotheses}: a transferred G is "
                             f"frozen, it races nothing; add {ONE_SET}")
        return self

    def check(self, cfg: "TrainConfig") -> None:
        super().check(cfg)
        if self.hypotheses > 1 and not cfg.mvnet.any_view_set:
            raise ValueError(f"selector.hypotheses={self.hypotheses} with mvnet={cfg.mvnet.name}: racing hypotheses is "
                             f"for MVCNN-style networks; use {ONE_SET}")


@register_strategy
class Race(Strategy):
    """H hypotheses rendered and raced, the winner kept as G's ``active`` set (the module docstring).

    State per epoch: ``H`` / ``S`` (hypotheses rendered, rows per shape for C), ``race_steps``
    (racing steps so far), ``race_losses`` (the last decision's mean losses), ``race_lines`` (log
    lines of its decisions), ``race_end`` (how the race ended this epoch: batches | lead | cap)."""

    name = "race"
    keys = RaceKeys
    training_keys = ("race_epochs", "race_z", "race_batches", "race_mode", "race_probes")
    multi_process = False
    switch = "hypotheses"

    def __init__(self, cfg) -> None:
        super().__init__(cfg)
        self.selector_loss = classification.selector_loss_fn(self.s.loss, cfg.task)
        self.H = self.S = 1
        self.epoch, self.race_steps, self.race_losses, self.race_lines, self.race_end = 0, 0, None, [], None

    @classmethod
    def enabled(cls, s) -> bool:
        return s.hypotheses > 1

    @classmethod
    def modules(cls, s, views: int) -> dict:
        return {"hypotheses": HypothesisRace(s.hypotheses)}

    def racing(self, model, epoch: int) -> bool:
        return not bool(model.hypotheses.done) and self.s.warmup_epochs <= epoch < self.s.race_epochs

    def start_epoch(self, model, epoch: int, ctx: StepContext) -> None:
        self.epoch = epoch
        # all H hypotheses are rendered; C classifies each as a shape of its own (S = H: race_mode=separate)
        # or all H x M views of a shape pooled as one (S = 1: pooled)
        self.H = model.hypotheses.hypotheses if self.racing(model, epoch) else 1
        self.S = self.H if self.H == 1 or self.s.race_mode == "separate" else 1
        self.race_steps, self.race_losses, self.race_lines, self.race_end = 0, None, [], None

    def decide(self, model, epoch: int, final: bool) -> None:
        """The hypothesis of lowest mean G loss so far becomes the active one; the race ends when it
        leads clearly (``race_end`` "lead"), at its last epoch ("cap": the pick may be chance), or
        when ``final`` ("batches"); a line for the log."""
        active, self.race_losses, clear = model.hypotheses.decide(self.s.race_z)
        if active is not None:
            model.selector.active.fill_(active)
        last = epoch + 1 == self.s.race_epochs
        self.race_end = "batches" if final else "lead" if clear else "cap" if last else None
        if self.race_end:
            model.hypotheses.finish()
        how = ENDS[self.race_end].format(n=self.race_steps)
        self.race_lines.append(f"epoch {epoch + 1}: hypotheses' mean {self.s.loss} loss "
                               f"{' / '.join(f'{x:.4f}' for x in self.race_losses)}: hypothesis {active} active{how}")

    def begin_step(self, ctx: StepContext) -> None:
        if self.H > 1 and self.s.race_batches is not None and self.race_steps >= self.s.race_batches:
            self.decide(ctx.model, self.epoch, final=True)  # decided on the batches so far
            self.H = self.S = 1
        self.race_steps += self.H > 1
        ctx.hypotheses, ctx.sets = self.H, self.S
        ctx.hold_g = ctx.hold_g or (self.H > 1 and not self.s.race_probes)

    def after_forward(self, ctx: StepContext) -> None:
        if self.H > 1:  # each shape's loss under each hypothesis: G's own loss
            with ctx.timer.stage("selector"):
                ctx.model.hypotheses.record(hypothesis_losses(ctx.model, ctx.logits, ctx.images, ctx.labels,
                                                              self.H, self.S, self.selector_loss))

    def end_epoch(self, model, epoch: int) -> list[str]:
        if self.racing(model, epoch):
            self.decide(model, epoch, final=False)
        return self.race_lines

    def history(self, model) -> dict:
        return {"hypothesis_active": int(model.selector.active), "hypothesis_losses": self.race_losses,
                "race_end": self.race_end}
