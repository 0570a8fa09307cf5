"""BatchNorm over the whole global batch when several processes train one run (``sync_bn=true``).

Without it each process normalises over its own share of the batch (on 32 GPUs G's BatchNorm saw
2-3 shapes per process) and keeps running statistics of its share alone. ``SyncBatchNorm`` here
computes the batch mean and variance over every process's share, in two all-reduces (the sums and
the count, then the squared deviations from that mean: no E[x^2] - E[x]^2 cancellation), through
an all-reduce whose backward all-reduces the gradient, so the gradient of
every process's share reaches every other process. It runs on CPU (gloo) as on CUDA (NCCL);
``torch.nn.SyncBatchNorm`` refuses CPU tensors.

The trainer backpropagates each process's loss weighted by its share of the global batch and sums
the gradients over the processes, so the step is the gradient of the whole batch's mean loss
through the shared statistics (``tests/test_sync_bn.py`` checks it against one process holding the
whole batch, in float64; ``models/pooled_layer.py`` runs the plain layers
while synchronising). With one process, in eval mode or outside a process group it is exactly
``torch.nn.BatchNorm*d``; parameter and buffer names are BatchNorm's, so checkpoints move between
runs with and without it.
"""
from __future__ import annotations

import torch
import torch.distributed as dist
from torch import Tensor, nn


class _SumOverProcesses(torch.autograd.Function):
    """``t`` summed over the processes; the backward sums the gradient over them likewise (every
    process's loss depends on every process's ``t``)."""

    @staticmethod
    def forward(ctx, t: Tensor) -> Tensor:
        t = t.clone(memory_format=torch.contiguous_format)
        dist.all_reduce(t)
        return t

    @staticmethod
    def backward(ctx, grad: Tensor) -> Tensor:
        grad = grad.clone(memory_format=torch.contiguous_format)
        dist.all_reduce(grad)
        return grad


def all_reduce_with_grad(t: Tensor) -> Tensor:
    return _SumOverProcesses.apply(t)


def synchronising() -> bool:
    """True inside a process group of more than one process."""
    return dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1


class SyncBatchNorm(nn.modules.batchnorm._BatchNorm):
    """BatchNorm over ``[N, C, *]`` inputs whose training statistics are the global batch's."""

    def _check_input_dim(self, x: Tensor) -> None:
        if x.dim() < 2:
            raise ValueError(f"expected at least 2D input [N, C, ...] (got {x.dim()}D input)")

    def forward(self, x: Tensor) -> Tensor:
        if not (self.training and synchronising()):
            return super().forward(x)
        self._check_input_dim(x)
        dims = [0, *range(2, x.dim())]
        shape = [1, x.shape[1]] + [1] * (x.dim() - 2)
        xf = x.float() if x.dtype in (torch.float16, torch.bfloat16) else x
        count = torch.tensor([float(xf.numel() // xf.shape[1])], dtype=xf.dtype, device=xf.device)
        dist.all_reduce(count)
        if float(count) < 2:
            raise ValueError(f"BatchNorm needs more than 1 value per channel over all processes (got {int(count)})")
        mean = all_reduce_with_grad(xf.sum(dims)) / count
        centred = xf - mean.view(shape)
        var = all_reduce_with_grad((centred * centred).sum(dims)) / count  # biased, as BatchNorm normalises
        y = centred * torch.rsqrt(var + self.eps).view(shape)
        if self.affine:
            y = y * self.weight.view(shape) + self.bias.view(shape)
        if self.track_running_stats:
            self._update_running(mean.detach(), var.detach() * count / (count - 1))
        return y.to(x.dtype)

    @torch.no_grad()
    def _update_running(self, mean: Tensor, unbiased_var: Tensor) -> None:
        """BatchNorm's running statistics (momentum, or the cumulative mean with ``momentum=None``)."""
        self.num_batches_tracked.add_(1)
        factor = self.momentum if self.momentum is not None else 1.0 / float(self.num_batches_tracked)
        self.running_mean.mul_(1 - factor).add_(mean.to(self.running_mean.dtype), alpha=factor)
        self.running_var.mul_(1 - factor).add_(unbiased_var.to(self.running_var.dtype), alpha=factor)


def convert(module: nn.Module) -> nn.Module:
    """``module`` with every ``BatchNorm1d/2d/3d`` replaced by a ``SyncBatchNorm`` holding the same
    parameters and buffers (in place for children; returns the new module when ``module`` is one)."""
    if isinstance(module, (nn.BatchNorm1d, nn.BatchNorm2d, nn.BatchNorm3d)):
        ref = module.running_mean if module.running_mean is not None else module.weight
        new = SyncBatchNorm(module.num_features, module.eps, module.momentum, module.affine, module.track_running_stats,
                            **({"device": ref.device, "dtype": ref.dtype} if ref is not None else {}))
        new.load_state_dict(module.state_dict())
        new.train(module.training)
        if module.affine:
            new.weight.requires_grad_(module.weight.requires_grad)
            new.bias.requires_grad_(module.bias.requires_grad)
        return new
    for name, child in module.named_children():
        setattr(module, name, convert(child))
    return module
