"""Scene-parameter optimisation (``selector=optimized``): the paper's alternative to learning G.

Instead of a network predicting the views, each batch's views start from a fixed layout
(circular or spherical) and take ``steps`` gradient steps on azimuth and elevation against an
objective of the current C through the differentiable renderer R:

    u_0 = layout;  u_{t+1} = u_t - lr * sign * d objective(C(R(S, u_t)), y) / d u_t

Objectives (``objective``): ``min_ce`` (views that help C: lowest cross-entropy), ``max_ce``
(views that hurt it), ``max_coverage`` / ``min_coverage`` (mean soft coverage of the images),
``margin`` (adversarial: raise the best wrong logit over the true one). The paper: 10 steps,
learning rate 50 for cross-entropy, 25 for coverage and the margin, on a pretrained C.

The cross-entropy and margin objectives read the labels, at evaluation too: this is an analysis
of how far views alone move a given C (an oracle, or an attack), not a deployable selector.
During the inner steps C runs in evaluation mode (its BatchNorm statistics do not move) and no
gradient reaches any weight; the final views are detached. It needs a renderer with a camera
gradient (soft mode).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from mvtn_exp.checks import at_least, one_of
from mvtn_exp.selectors.config import register
from mvtn_exp.selectors.fixed import BASE_LAYOUTS, LayoutConfig, ViewSelector, Views, base_layout

OBJECTIVES = ("min_ce", "max_ce", "max_coverage", "min_coverage", "margin")


class OptimizedSelector(ViewSelector):
    """The starting layout (``forward``) and the settings of ``optimize_views``; no parameters."""

    LAYOUTS = BASE_LAYOUTS

    def __init__(self, views: int, layout: str = "circular", steps: int = 10, lr: float = 50.0,
                 objective: str = "min_ce", elevation: float = 30.0, distance: float = 2.2,
                 sphere: str = "equal_area") -> None:
        super().__init__(views)
        self.base = base_layout("OptimizedSelector", views, layout, elevation, distance, sphere)
        if objective not in OBJECTIVES:
            raise ValueError(f"selector.objective={objective!r}: expected one of {', '.join(OBJECTIVES)}")
        if steps < 0 or not lr > 0:
            raise ValueError(f"selector.steps={steps} must be >= 0 and selector.lr={lr} > 0")
        self.layout, self.steps, self.lr, self.objective = layout, int(steps), float(lr), objective

    def forward(self, points: Tensor) -> Views:
        """``[B, N, 3] -> (azim, elev, dist)``: the starting layout, each ``[B, M]``."""
        return self.base(points)

    def refine(self, model, batch: dict, views: Views) -> Views:
        """``steps`` gradient steps on the batch's views against the objective (``optimize_views``)."""
        return optimize_views(model, batch, views, self)

    def extra_repr(self) -> str:
        return f"views={self.views}, layout={self.layout}, steps={self.steps}, lr={self.lr}, objective={self.objective}"


def objective_value(objective: str, logits: Tensor, labels: Tensor, coverage: Tensor) -> Tensor:
    """The quantity the steps *decrease*: ``[B]`` per shape (so every shape moves on its own).

    logits ``[B, K]``, labels ``[B]``, coverage ``[B]`` (mean soft coverage of the shape's views).
    """
    if objective == "min_ce":
        return F.cross_entropy(logits, labels, reduction="none")
    if objective == "max_ce":
        return -F.cross_entropy(logits, labels, reduction="none")
    if objective == "max_coverage":
        return -coverage
    if objective == "min_coverage":
        return coverage
    true = logits.gather(1, labels[:, None])[:, 0]
    wrong = logits.masked_fill(F.one_hot(labels, logits.shape[1]).bool(), float("-inf")).amax(1)
    return true - wrong  # margin: decreasing it pushes the best wrong class above the true one


def optimize_views(model, batch: dict, views: Views, selector: OptimizedSelector) -> Views:
    """``steps`` gradient steps on the views of ``batch`` (see the module docstring)."""
    azim, elev, dist = (v.detach() for v in views)
    if selector.steps == 0:
        return azim, elev, dist
    labels = batch["labels"].to(azim.device)
    was_training = model.mvnet.training
    model.mvnet.eval()
    try:
        with torch.enable_grad():
            for _ in range(selector.steps):
                azim, elev = azim.requires_grad_(True), elev.requires_grad_(True)
                out = model.render_output(batch, azim, elev, dist)
                logits, _ = model.mvnet(out.images, (azim, elev, dist))
                B = len(labels)
                coverage = out.alpha.reshape(B, -1).mean(1)
                value = objective_value(selector.objective, logits, labels, coverage).sum()
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
    ``step_size`` on each batch's views against ``objective`` of the current C (labels included:
    an analysis of what views alone do to C, not a deployable G)."""

    name: str = "optimized"
    steps: int = 10
    step_size: float = 50.0
    objective: str = "min_ce"

    def validate(self) -> "OptimizedConfig":
        super().validate()
        one_of("selector.objective", self.objective, OBJECTIVES)
        at_least("selector.steps", self.steps, 0)
        at_least("selector.step_size", self.step_size, 0.0, strict=True)
        return self

    def uses_camera_gradient(self) -> bool:
        return self.steps > 0

    def build(self, views: int, seed: int, point_encoder=None) -> ViewSelector:
        return OptimizedSelector(views, layout=self.base_layout, steps=self.steps, lr=self.step_size,
                                 objective=self.objective, elevation=self.elevation, distance=self.distance,
                                 sphere=self.sphere)
