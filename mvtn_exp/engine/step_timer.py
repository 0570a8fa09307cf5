"""Wall time of one training step split into its stages: data, selector G, renderer R, backbone C
(multi-view net and loss), optimizer. Forward and backward of each stage are both counted: the
backward is split with gradient hooks at the stage boundaries (views u and images X)."""
from __future__ import annotations

import time
from contextlib import contextmanager

import torch

STAGES = ("data", "selector", "render", "backbone", "optimizer")


class StepTimer:
    """Accumulates seconds per stage over steps; ``means()`` -> seconds per step per stage (+ total)."""

    def __init__(self, device: torch.device) -> None:
        self.device = device
        self.sync = device.type == "cuda"
        self.seconds = dict.fromkeys(STAGES, 0.0)
        self.steps = 0

    def now(self) -> float:
        if self.sync:
            torch.cuda.synchronize(self.device)  # the run's own GPU (a sweep job may hold cuda:N)
        return time.perf_counter()

    @contextmanager
    def stage(self, name: str):
        t0 = self.now()
        yield
        self.seconds[name] += self.now() - t0

    def backward(self, loss: torch.Tensor, views: tuple, images: torch.Tensor) -> None:
        """``loss.backward()``, charging C's part to backbone, R's to render and G's to selector."""
        marks: dict[str, float] = {}

        def mark(name):
            def hook(grad):
                marks.setdefault(name, self.now())
                return grad
            return hook

        if images.requires_grad:
            images.register_hook(mark("images"))
        for v in views:
            if v.requires_grad:
                v.register_hook(mark("views"))
        t0 = self.now()
        loss.backward()
        t1 = self.now()
        t_img = marks.get("images", t1)
        t_views = marks.get("views", t1)
        self.seconds["backbone"] += t_img - t0
        self.seconds["render"] += max(t_views - t_img, 0.0)
        self.seconds["selector"] += max(t1 - max(t_views, t_img), 0.0)

    def step_done(self) -> None:
        self.steps += 1

    def means(self) -> dict[str, float]:
        n = max(self.steps, 1)
        out = {k: v / n for k, v in self.seconds.items()}
        out["total"] = sum(out.values())
        return out
