"""Re-estimate C's BatchNorm statistics before each validation (``optim.bn_recalibrate``).

Why (measured on ``synthetic_views``, learned M = 4, seed 2): validation accuracy fell to exactly
chance (0.125: one class for every shape) for single epochs while training accuracy kept rising
(for example epoch 9: train 0.41, validation 0.125, loss 3.92). The weights were fine; the
running statistics of C's BatchNorm layers were not: re-estimated on the training shapes from the
checkpoint of that epoch, validation accuracy is 0.417 (loss 1.46). The running averages follow
the last training batches with momentum 0.1, rendered from G's training-mode views with
training-time light and colour, while validation renders G's eval-mode views.

So with ``optim.bn_recalibrate=N`` (N > 0) the running statistics of every BatchNorm layer of C
are reset and set to the plain average over the first N batches of the epoch's training order,
rendered as validation renders them (the whole model in eval mode but C's BatchNorm layers, no
augmentation, no gradients). G, C's weights and every random stream are untouched; the epoch's
checkpoint (and so the test) carries the re-estimated statistics.
"""
from __future__ import annotations

from typing import Iterable

import torch
from torch import nn


def batchnorms(module: nn.Module) -> list[nn.modules.batchnorm._BatchNorm]:
    return [m for m in module.modules() if isinstance(m, nn.modules.batchnorm._BatchNorm) and m.track_running_stats]


def recalibrate(model, batches: Iterable[dict], n: int) -> int:
    """Reset and re-estimate ``model.mvnet``'s BatchNorm statistics over ``n`` of ``batches`` (see
    the module docstring); returns the number of batches used. Every module's train/eval flag is
    restored afterwards."""
    bns = batchnorms(model.mvnet)
    if not bns or n <= 0:
        return 0
    flags = [(m, m.training) for m in model.modules()]
    momenta = [m.momentum for m in bns]
    used = 0
    try:
        model.eval()
        for m in bns:
            m.reset_running_stats()
            m.momentum = None  # cumulative moving average: the plain mean over the batches
            m.train()
        with torch.no_grad():
            for batch in batches:
                if used >= n:
                    break
                model.mvnet(model.render(batch, *model.select(batch)))
                used += 1
    finally:
        for m, momentum in zip(bns, momenta):
            m.momentum = momentum
        for m, flag in flags:
            m.training = flag
    return used
