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
