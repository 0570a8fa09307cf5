"""PointNet's last shared layer and its global max-pool, without the ``[B, C, N]`` activations.

PointNet ends with ``max_n ReLU(BN(W h))``: a ``Cin -> C`` layer (C = 1024) over every point,
BatchNorm, ReLU, then a max over the N points. Run module by module, autograd keeps the
``[B, C, N]`` tensor three times (convolution, BatchNorm and ReLU outputs) and the backward
makes two dense ``[B, C, N]`` gradients and two matrix products as large as the forward's.
On this project's CPU that layer is about 80% of G's time (16 shapes x 256 points: 87 ms forward
and backward at C = 1024 against 15 ms at C = 256).

``pooled_layer(h, conv, bn)`` computes the same function exactly (up to rounding):

* BatchNorm is per channel affine, ``a_c z + d_c``, and ReLU is monotone, so the max over the
  points is ``ReLU(a_c e_bc + d_c)`` with ``e_bc`` the largest ``z`` of the channel where
  ``a_c >= 0`` and the smallest where ``a_c < 0``. The forward needs ``z`` only for that one
  max, taken on ``sign(a) z``.
* The batch statistics of ``z = W h`` follow from those of ``h``: mean ``W mu_h`` and variance
  ``w_c^T S w_c`` with ``S`` the ``Cin x Cin`` covariance of ``h`` (centred first, so nothing
  cancels).
* The gradient of the statistics is ``alpha_c + beta_c (z - mu_c)`` over all points, plus one
  entry per ``(b, c)`` at the chosen point. Its products with ``h`` and ``W`` reduce to
  ``Cin x Cin`` sums and a gather at the chosen points: the backward never forms a ``[B, C, N]``
  tensor.

Training mode updates the running statistics as ``nn.BatchNorm1d`` does (momentum, or a
cumulative average with ``momentum=None``; unbiased variance). Evaluation mode, a BatchNorm
without running statistics in evaluation, or a single value per channel (where BatchNorm raises)
run the plain modules instead. Tested against the plain modules in float64 (outputs, every
gradient, running statistics) and by ``gradcheck`` (``tests/test_point_encoders.py``).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .sync_bn import SyncBatchNorm, synchronising


def _plain(h: Tensor, conv: nn.Conv1d, bn: nn.BatchNorm1d) -> Tensor:
    return F.relu(bn(conv(h))).amax(dim=2)


class _PooledLayer(torch.autograd.Function):
    """``(h [B, Cin, N], weight [C, Cin], gamma [C], beta [C], eps) -> (out [B, C], mean [C],
    var [C])``: training-mode BatchNorm statistics (biased variance) of ``weight @ h`` come back
    for the running averages."""

    @staticmethod
    def forward(ctx, h, weight, gamma, beta, eps):
        B, Cin, N = h.shape
        n = B * N
        mu_h = h.mean(dim=(0, 2))  # [Cin]
        centred = h - mu_h[None, :, None]
        cov = torch.matmul(centred, centred.transpose(1, 2)).sum(0) / n  # [Cin, Cin]
        w_cov = weight @ cov  # [C, Cin]
        mean = weight @ mu_h  # [C]
        var = (w_cov * weight).sum(1).clamp_min(0.0)  # [C]
        rstd = (var + eps).rsqrt()
        a = gamma * rstd
        sign = torch.where(a < 0, -1.0, 1.0).to(h.dtype)
        # the point each (shape, channel) takes its max from: argmax of sign(a) * z
        best, idx = torch.matmul(weight * sign[:, None], h).max(dim=2)  # [B, C]
        e = best * sign
        xhat = (e - mean) * rstd
        pre = gamma * xhat + beta
        ctx.save_for_backward(h, centred, w_cov, weight, gamma, rstd, xhat, pre, idx)
        return pre.clamp_min(0.0), mean, var

    @staticmethod
    def backward(ctx, g_out, _g_mean, _g_var):
        h, centred, w_cov, weight, gamma, rstd, xhat, pre, idx = ctx.saved_tensors
        B, Cin, N = h.shape
        n = B * N
        s = g_out * (pre > 0).to(g_out.dtype)  # dL/d(BN output) at the chosen points [B, C]
        g_beta = s.sum(0)
        g_gamma = (s * xhat).sum(0)
        q = s * (gamma * rstd)  # dL/dz at the chosen point [B, C]
        g_var = -0.5 * rstd * rstd * gamma * g_gamma  # dL/dvar: xhat = (e - mean) rstd
        # dL/dz over all points: c_mean + c_dev (z - mean), plus q at the chosen points
        c_mean = -q.sum(0) / n  # through the batch mean
        c_dev = 2.0 * g_var / n
        rows = (idx + torch.arange(B, device=idx.device)[:, None] * N).flatten()  # [B * C] chosen points
        points = h.transpose(1, 2).reshape(n, Cin)  # points-major rows
        h_at = points.index_select(0, rows).view(B, -1, Cin)  # [B, C, Cin]
        g_weight = (c_mean[:, None] * points.sum(0)[None, :] + (c_dev[:, None] * n) * w_cov
                    + (h_at * q[:, :, None]).sum(0))
        g_h = None
        if ctx.needs_input_grad[0]:
            dense = (weight.T @ c_mean)[None, :, None] + torch.matmul(weight.T @ (c_dev[:, None] * weight), centred)
            sparse = torch.zeros_like(points).index_add_(0, rows, (q[:, :, None] * weight[None]).view(-1, Cin))
            g_h = dense + sparse.view(B, N, Cin).transpose(1, 2)
        return g_h, g_weight, g_gamma, g_beta, None


def pooled_layer(h: Tensor, conv: nn.Conv1d, bn: nn.BatchNorm1d) -> Tensor:
    """``max_n ReLU(bn(conv(h)))`` for ``h [B, Cin, N]`` -> ``[B, C]`` (see the module docstring).

    ``conv``: ``Conv1d(Cin, C, 1, bias=False)``; ``bn``: ``BatchNorm1d(C)`` with affine weights.
    """
    batch_stats = bn.training or not bn.track_running_stats
    if (not batch_stats or h.shape[0] * h.shape[2] <= 1 or conv.bias is not None or not bn.affine
            or (isinstance(bn, SyncBatchNorm) and synchronising())):  # statistics over every process's share
        return _plain(h, conv, bn)
    weight = conv.weight[:, :, 0]
    out, mean, var = _PooledLayer.apply(h, weight, bn.weight, bn.bias, bn.eps)
    if bn.training and bn.track_running_stats:
        with torch.no_grad():
            bn.num_batches_tracked.add_(1)
            f = 1.0 / float(bn.num_batches_tracked) if bn.momentum is None else bn.momentum
            n = h.shape[0] * h.shape[2]
            bn.running_mean.mul_(1 - f).add_(mean.detach(), alpha=f)
            bn.running_var.mul_(1 - f).add_(var.detach() * (n / (n - 1)), alpha=f)
    return out
