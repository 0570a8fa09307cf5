"""Re-estimate C's BatchNorm statistics before each validation (``selector.bn_recalibrate``).

Why (the measurements: docs/results/finding-the-detail.md): with learned views, validation
accuracy can fall to chance (one class for every shape) for single epochs while training accuracy
keeps rising. The weights are fine; the running statistics of C's BatchNorm layers are not:
re-estimated on the training shapes from that epoch's checkpoint, validation recovers. The
running averages follow
the last training batches with momentum 0.1, rendered from G's training-mode views with
training-time light and colour, while validation renders G's eval-mode views.

So with ``selector.bn_recalibrate=N`` (N > 0) the running statistics of every BatchNorm layer of C
are reset and set to the plain average over the first N batches of the epoch's training order,
rendered as validation renders them (the whole model in eval mode but C's BatchNorm layers, no
augmentation, no gradients). G, C's weights and every random stream are untouched; the epoch's
checkpoint (and so the test) carries the re-estimated statistics.

``selector.bn_recalibrate_scope``: ``all`` lets training go on from the re-estimated statistics,
which changes a learned G's trajectory where G's smoothed probes run C in eval mode; ``eval``
keeps them for
validation, the checkpoints' ``model`` and the test only, and puts training's own running
averages back after each validation (``running_statistics`` / ``restore``; checkpoints carry them
as ``train_bn`` for an exact resume), so training is bit-identical to a run without re-estimation.
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
                views = model.select(batch)
                model.mvnet_forward(model.render(batch, *views), views, batch)
                used += 1
    finally:
        for m, momentum in zip(bns, momenta):
            m.momentum = momentum
        for m, flag in flags:
            m.training = flag
    return used


def running_statistics(model: nn.Module) -> dict[str, torch.Tensor]:
    """Copies of the running statistics of every BatchNorm layer of ``model.mvnet``, keyed as in
    ``model.state_dict()`` (``mvnet.<layer>.running_mean`` / ``running_var`` / ``num_batches_tracked``)."""
    layers = {id(m) for m in batchnorms(model.mvnet)}
    out = {}
    for name, m in model.mvnet.named_modules():
        if id(m) in layers:
            for key in ("running_mean", "running_var", "num_batches_tracked"):
                out[f"mvnet.{name}.{key}"] = getattr(m, key).detach().clone()
    return out


def restore(model: nn.Module, stats: dict[str, torch.Tensor]) -> None:
    """Put ``running_statistics`` back in place (a key that ``model`` lacks is an error)."""
    buffers = dict(model.named_buffers())
    missing = sorted(set(stats) - set(buffers))
    if missing:
        raise KeyError(f"BatchNorm statistics for layers this model does not have: {missing[:3]}")
    with torch.no_grad():
        for key, value in stats.items():
            buffers[key].copy_(value)
