"""An exponential moving average of the whole model's weights (``optim.ema_decay``).

After optimizer step t (0-based): ``ema_p <- d_t * ema_p + (1 - d_t) * p`` with
``d_t = min(decay, (1 + t) / (10 + t))`` (a warm-up, as timm's EMA: the first steps follow the
weights closely, so the random initial weights fade at once) for every parameter of
G and C and every floating-point buffer (BatchNorm running statistics: the average's statistics
follow its weights, as timm's ModelEmaV2 does); other buffers (step counters, G's frozen state)
are copied from the live model. Copying the live statistics instead was measured: with the
averaged weights they gave 0.08-0.38 validation accuracy where the raw model had 0.92-0.95. The
trainer evaluates the average on validation beside the raw weights every epoch and keeps whichever
is better as ``best.pt``; the average travels in ``last.pt`` so resume stays exact.
"""
from __future__ import annotations

import copy

import torch
from torch import nn


class ModelEMA:
    """``model``'s weight average; ``self.model`` is a frozen copy in eval mode, used like the original."""

    def __init__(self, model: nn.Module, decay: float) -> None:
        if not 0.0 < decay < 1.0:
            raise ValueError(f"optim.ema_decay={decay}: expected a number in (0, 1), e.g. 0.999")
        self.decay = float(decay)
        self.model = copy.deepcopy(model).eval()
        for p in self.model.parameters():
            p.requires_grad_(False)

    def decay_at(self, step: int) -> float:
        """The decay of the update after optimizer step ``step`` (0-based): the warm-up, then ``decay``."""
        return min(self.decay, (1.0 + step) / (10.0 + step))

    @torch.no_grad()
    def update(self, model: nn.Module, step: int) -> None:
        """One step of the average towards ``model``'s current weights, after optimizer step ``step``."""
        d = self.decay_at(step)
        live = dict(model.named_parameters())
        for name, p in self.model.named_parameters():
            p.lerp_(live[name].detach(), 1.0 - d)
        bufs = dict(model.named_buffers())
        for name, b in self.model.named_buffers():
            if b.is_floating_point():
                b.lerp_(bufs[name], 1.0 - d)
            else:
                b.copy_(bufs[name])

    def state_dict(self) -> dict:
        return self.model.state_dict()

    def load_state_dict(self, state: dict) -> None:
        self.model.load_state_dict(state)
