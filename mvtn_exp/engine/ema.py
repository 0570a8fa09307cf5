"""An exponential moving average of the whole model's weights (``optim.ema_decay``).

After every optimizer step: ``ema_p <- decay * ema_p + (1 - decay) * p`` for every parameter of
G and C; buffers (BatchNorm statistics, G's frozen state) are copied from the live model. The
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

    @torch.no_grad()
    def update(self, model: nn.Module) -> None:
        """One step of the average towards ``model``'s current weights."""
        live = dict(model.named_parameters())
        for name, p in self.model.named_parameters():
            p.lerp_(live[name].detach(), 1.0 - self.decay)
        bufs = dict(model.named_buffers())
        for name, b in self.model.named_buffers():
            b.copy_(bufs[name])

    def state_dict(self) -> dict:
        return self.model.state_dict()

    def load_state_dict(self, state: dict) -> None:
        self.model.load_state_dict(state)
