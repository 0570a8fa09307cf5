"""Small tensor ops with fast backward passes on CPU."""
from __future__ import annotations

import torch


def take(t: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """``t[idx]`` for a long index of any shape, via ``index_select``.

    Advanced indexing's backward is an accumulating ``index_put_`` (slow and serial on CPU);
    ``index_select``'s backward is ``index_add_``. Returns ``[*idx.shape, *t.shape[1:]]``.
    """
    return t.index_select(0, idx.reshape(-1)).view(*idx.shape, *t.shape[1:])


# Per-(pixel, slot) vector maths in components: ``[..., 3]`` tensors are unbound into three
# ``[...]`` ones and put back together with ``stack``. On CPU a reduction over a last dimension of
# 3 costs about ten times the fused adds (measured: ``x.sum(-1)`` 0.78 ms, ``x0 + x1 + x2`` 0.07 ms
# on 83k x 3), and broadcasting a ``[..., 1]`` factor over xyz makes the backward pass reduce over
# it again; these run once per slot in every soft render.
def dot(a: tuple, b: tuple) -> torch.Tensor:
    """Dot product of two vectors given as component triples (each ``[...]``)."""
    return torch.addcmul(torch.addcmul(a[0] * b[0], a[1], b[1]), a[2], b[2])


def scale(a: tuple, s: torch.Tensor) -> tuple:
    return tuple(c * s for c in a)


def normalized(a: tuple, eps: float = 1e-12) -> tuple:
    """``F.normalize`` of a component triple (clamped before the square root: a zero vector gets a
    zero gradient, not NaN)."""
    return scale(a, dot(a, a).clamp(min=eps * eps).rsqrt())


def weighted3(w: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """``(w[..., None] * v).sum(-2)``: weights ``[..., 3]``, values ``[..., 3, 3]`` -> ``[..., 3]``."""
    w0, w1, w2 = w.unbind(-1)
    v0, v1, v2 = (c.unbind(-1) for c in v.unbind(-2))
    return torch.stack([torch.addcmul(torch.addcmul(w0 * v0[d], w1, v1[d]), w2, v2[d]) for d in range(3)], -1)
