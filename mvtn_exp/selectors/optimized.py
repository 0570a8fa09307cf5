"""Scene-parameter optimisation (``selector=optimized``): the paper's alternative to learning G.

Instead of a network predicting the views, each batch's views start from a fixed layout
(circular or spherical) and take ``steps`` gradient steps on azimuth and elevation against an
objective of the current C through the differentiable renderer R:

    u_0 = layout;  u_{t+1} = u_t - lr * sign * d objective(C(R(S, u_t)), y) / d u_t

Objectives (``objective``, while training): ``min_ce`` (views that help C: lowest cross-entropy),
``max_ce`` (views that hurt it), ``max_coverage`` / ``min_coverage`` (mean soft coverage of the
images), ``margin`` (the paper's: the widest gap between C's two highest logits, no labels), and
``attack_margin`` (adversarial, with labels: raise the best wrong logit over the true one). The
paper: 10 steps, learning rate 50 for cross-entropy, 25 for coverage and the margin, on a
pretrained C.

Labels never reach evaluation: ``MVTN.select`` hands an evaluating selector the batch without its
labels, and at evaluation the steps follow ``eval_objective``, a label-free objective (``margin``,
``max_coverage``, ``min_coverage``) or ``none`` (the starting layout). Its default is the training
objective when that one is label-free, else ``margin``. During the inner steps C runs in evaluation
mode (its BatchNorm statistics do not move) and no gradient reaches any weight; the final views are
detached. It needs a renderer with a camera gradient (soft mode).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
import torch.nn.functional as F
from torch import Tensor

from mvtn_exp.config.checks import at_least, one_of
from mvtn_exp.selectors.config import register
from mvtn_exp.selectors.fixed import BASE_LAYOUTS, LayoutConfig, ViewSelector, Views, base_layout

LABEL_FREE = ("margin", "max_coverage", "min_coverage")
OBJECTIVES = ("min_ce", "max_ce", "attack_margin", *LABEL_FREE)
EVAL_OBJECTIVES = ("none", *LABEL_FREE)
# eval_objective=if_label_free: the training objective at evaluation when it needs no labels, else
# none -- the paper's rule ("The CE loss optimization is only applied during training, while the
# coverage and adversarial losses are optimized during both training and test time", L501)
IF_LABEL_FREE = "if_label_free"
# step_size=null: the paper's step for the objective ("a learning rate of 50 ... using the cross
# entropy loss. For the coverage and adversarial losses, ... a learning rate of 25", L507)
PAPER_STEP = {"min_ce": 50.0, "max_ce": 50.0, "attack_margin": 25.0, "margin": 25.0, "max_coverage": 25.0,
              "min_coverage": 25.0}


def eval_objective_for(objective: str, setting: str | None) -> str:
    """The objective an evaluating selector follows: ``setting``, with null meaning ``objective``
    when label-free else ``margin`` (this project's default) and ``if_label_free`` meaning
    ``objective`` when label-free else ``none`` (the paper's)."""
    if setting is None:
        return objective if objective in LABEL_FREE else "margin"
    if setting == IF_LABEL_FREE:
        return objective if objective in LABEL_FREE else "none"
    return setting


class OptimizedSelector(ViewSelector):
    """The starting layout (``forward``) and the settings of ``optimize_views``; no parameters."""

    LAYOUTS = BASE_LAYOUTS

    def __init__(self, views: int, layout: str = "circular", steps: int = 10, lr: float = 50.0,
                 objective: str = "min_ce", elevation: float = 30.0, distance: float = 2.2,
                 sphere: str = "equal_area", eval_objective: str | None = None) -> None:
        super().__init__(views)
        self.base = base_layout("OptimizedSelector", views, layout, elevation, distance, sphere)
        if objective not in OBJECTIVES:
            raise ValueError(f"selector.objective={objective!r}: expected one of {', '.join(OBJECTIVES)}")
        eval_objective = eval_objective_for(objective, eval_objective)
        if eval_objective not in EVAL_OBJECTIVES:
            raise ValueError(f"selector.eval_objective={eval_objective!r}: expected one of {', '.join(EVAL_OBJECTIVES)} "
                             "(evaluation reads no labels)")
        self.eval_objective = eval_objective
        if steps < 0 or not lr > 0:
            raise ValueError(f"selector.steps={steps} must be >= 0 and selector.lr={lr} > 0")
        self.layout, self.steps, self.lr, self.objective = layout, int(steps), float(lr), objective

    def forward(self, points: Tensor) -> Views:
        """``[B, N, 3] -> (azim, elev, dist)``: the starting layout, each ``[B, M]``."""
        return self.base(points)

    def refine(self, model, batch: dict, views: Views) -> Views:
        """``steps`` gradient steps on the batch's views (``optimize_views``) against ``objective``
        while training, ``eval_objective`` when evaluating (a batch without labels)."""
        objective = self.objective if self.training and "labels" in batch else self.eval_objective
        return optimize_views(model, batch, views, self, objective)

    def extra_repr(self) -> str:
        return (f"views={self.views}, layout={self.layout}, steps={self.steps}, lr={self.lr}, "
                f"objective={self.objective}, eval_objective={self.eval_objective}")


def objective_value(objective: str, logits: Tensor, labels: Tensor | None, coverage: Tensor) -> Tensor:
    """The quantity the steps *decrease*: ``[B]`` per shape (so every shape moves on its own).

    logits ``[B, K]``, labels ``[B]`` (None for the label-free objectives), coverage ``[B]`` (mean
    soft coverage of the shape's views).
    """
    if objective == "margin":  # the paper's: widen the gap between the two highest logits
        top = logits.topk(2, dim=1).values if logits.shape[1] > 1 else torch.cat([logits, logits], 1)
        return top[:, 1] - top[:, 0]
    if objective == "max_coverage":
        return -coverage
    if objective == "min_coverage":
        return coverage
    if labels is None:
        raise ValueError(f"selector.objective={objective}: needs the labels, which only training has")
    if objective == "min_ce":
        return F.cross_entropy(logits, labels, reduction="none")
    if objective == "max_ce":
        return -F.cross_entropy(logits, labels, reduction="none")
    true = logits.gather(1, labels[:, None])[:, 0]
    wrong = logits.masked_fill(F.one_hot(labels, logits.shape[1]).bool(), float("-inf")).amax(1)
    return true - wrong  # attack_margin: decreasing it pushes the best wrong class above the true one


def optimize_views(model, batch: dict, views: Views, selector: OptimizedSelector, objective: str) -> Views:
    """``steps`` gradient steps on the views of ``batch`` against ``objective`` (see the module
    docstring); the labels are read only by an objective that needs them."""
    azim, elev, dist = (v.detach() for v in views)
    if selector.steps == 0 or objective == "none":
        return azim, elev, dist
    labels = None if objective in LABEL_FREE else batch["labels"].to(azim.device)
    was_training = model.mvnet.training
    model.mvnet.eval()
    try:
        with torch.enable_grad():
            for _ in range(selector.steps):
                azim, elev = azim.requires_grad_(True), elev.requires_grad_(True)
                out = model.render_output(batch, azim, elev, dist)
                logits, _ = model.mvnet(out.images, (azim, elev, dist))
                coverage = out.alpha.reshape(len(logits), -1).mean(1)
                value = objective_value(objective, logits, labels, coverage).sum()
                g_azim, g_elev = torch.autograd.grad(value, (azim, elev))
                azim = (azim - selector.lr * g_azim).detach()
                elev = (elev - selector.lr * g_elev).detach()
    finally:
        model.mvnet.train(was_training)
    return azim, elev, dist


# ----------------------------------------------------------------------------- config option
@register("optimized")
@dataclass
class OptimizedConfig(LayoutConfig):
    """The paper's scene-parameter optimisation: the base layout, then ``steps`` gradient steps of
    ``step_size`` on each batch's views against ``objective`` of the current C while training, and
    against the label-free ``eval_objective`` at evaluation (null: ``objective`` when it is
    label-free, else ``margin``; ``if_label_free``: ``objective`` when it is label-free, else
    ``none``, the paper's rule). ``step_size`` null: the paper's step for the objective
    (``PAPER_STEP``: 50 for cross-entropy, 25 for coverage and the margins)."""

    name: str = "optimized"
    steps: int = 10
    step_size: Optional[float] = 50.0
    objective: str = "min_ce"
    eval_objective: Optional[str] = None

    def validate(self) -> "OptimizedConfig":
        super().validate()
        one_of("selector.objective", self.objective, OBJECTIVES)
        if self.eval_objective is not None:
            one_of("selector.eval_objective", self.eval_objective, (*EVAL_OBJECTIVES, IF_LABEL_FREE))
        at_least("selector.steps", self.steps, 0)
        if self.step_size is not None:
            at_least("selector.step_size", self.step_size, 0.0, strict=True)
        return self

    def segmentation_problem(self) -> Optional[str]:
        if self.steps == 0:
            return None
        return (f"its steps optimise objective={self.objective} on a classifier's logits; use selector.steps=0 "
                f"(the base layout) or a learned selector")

    @property
    def step(self) -> float:
        """``step_size``, or the paper's for ``objective`` when null."""
        return PAPER_STEP[self.objective] if self.step_size is None else float(self.step_size)

    def uses_camera_gradient(self) -> bool:
        return self.steps > 0

    def build(self, views: int, seed: int, point_encoder=None) -> ViewSelector:
        return OptimizedSelector(views, layout=self.base_layout, steps=self.steps, lr=self.step,
                                 objective=self.objective, elevation=self.elevation, distance=self.distance,
                                 sphere=self.sphere, eval_objective=self.eval_objective)
