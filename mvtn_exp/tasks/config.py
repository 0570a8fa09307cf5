"""The task schema (``task=NAME``): the head's loss and its settings."""
from __future__ import annotations

from dataclasses import dataclass

from ..config.checks import fraction, one_of
from .lifting import FUSIONS

TASKS = ("classification", "segmentation")
SEG_LOSSES = ("pixels", "points")
CONDITIONS = ("category", "none")
BALANCES = ("none", "inverse_sqrt")


@dataclass
class TaskConfig:
    """The task head and its loss.

    ``classification``: cross-entropy over the dataset's classes (``label_smoothing``).
    ``segmentation``: part labels per point (a dataset with part labels). C predicts every pixel's
    part or the background; ``loss=pixels`` is the paper's 2D loss (per-pixel cross-entropy against
    the rendered label images, background included), ``loss=points`` the cross-entropy of the
    logits lifted to the points the views saw (mean fusion). ``fuse``: how the views' predictions
    are fused on a point at evaluation, ``mode`` (the paper's: each view votes its argmax) or
    ``mean`` (of the logits); a point no view saw takes its nearest seen point's prediction.
    ``condition``: ``category`` (the shape's category is known, as the benchmark's evaluation
    assumes: C's scores are restricted to that category's parts and the background in training as
    at test) or ``none`` (C chooses among all parts; evaluation still restricts its argmax)."""

    name: str = "classification"
    label_smoothing: float = 0.0
    fuse: str = "mode"
    loss: str = "pixels"
    condition: str = "category"
    balance: str = "none"

    def validate(self) -> "TaskConfig":
        one_of("task", self.name, TASKS)
        fraction("task.label_smoothing", self.label_smoothing)
        one_of("task.fuse", self.fuse, FUSIONS)
        one_of("task.loss", self.loss, SEG_LOSSES)
        one_of("task.condition", self.condition, CONDITIONS)
        one_of("task.balance", self.balance, BALANCES)
        return self
