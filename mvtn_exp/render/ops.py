"""Small tensor ops with fast backward passes on CPU."""
from __future__ import annotations

import torch


def take(t: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """``t[idx]`` for a long index of any shape, via ``index_select``.

    Advanced indexing's backward is an accumulating ``index_put_`` (slow and serial on CPU);
    ``index_select``'s backward is ``index_add_``. Returns ``[*idx.shape, *t.shape[1:]]``.
    """
    return t.index_select(0, idx.reshape(-1)).view(*idx.shape, *t.shape[1:])


def scatter_rows(base: torch.Tensor, idx: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """Out-of-place ``base[idx] = rows`` for unique ``idx`` (backward: gathers only)."""
    return base.index_copy(0, idx, rows)


# Reductions over a last dimension of 3 (xyz, barycentrics) as unbind + fused adds: on CPU
# ``x.sum(-1)`` over such a small dimension costs about ten times as much (measured: 0.78 vs
# 0.07 ms on 83k x 3), and these run once per (pixel, slot) in every soft render.
def sum3(x: torch.Tensor) -> torch.Tensor:
    """``x.sum(-1, keepdim=True)`` for ``[..., 3]``."""
    x0, x1, x2 = x.unbind(-1)
    return (x0 + x1 + x2).unsqueeze(-1)


def dot3(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``(a * b).sum(-1, keepdim=True)`` for ``[..., 3]`` (broadcasting)."""
    a, b = torch.broadcast_tensors(a, b)
    a0, a1, a2 = a.unbind(-1)
    b0, b1, b2 = b.unbind(-1)
    return torch.addcmul(torch.addcmul(a0 * b0, a1, b1), a2, b2).unsqueeze(-1)


def normalize3(x: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """``F.normalize(x, dim=-1, eps=eps)`` for ``[..., 3]`` (clamped before the square root, so a
    zero vector has a zero gradient, not NaN)."""
    return x / dot3(x, x).clamp(min=eps * eps).sqrt()


def weighted3(w: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """``(w[..., None] * v).sum(-2)``: weights ``[..., 3]``, values ``[..., 3, D]`` -> ``[..., D]``."""
    w0, w1, w2 = w.unsqueeze(-1).unbind(-2)
    v0, v1, v2 = v.unbind(-2)
    return torch.addcmul(torch.addcmul(w0 * v0, w1, v1), w2, v2)
