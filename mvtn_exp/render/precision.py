"""The renderer's numbers: float32 whatever autocast surrounds it, and torch's deterministic
algorithms when asked (``renderer.deterministic``)."""
from __future__ import annotations

import contextlib

import torch

from ..data.shapes import Meshes

LOW_PRECISION = (torch.float16, torch.bfloat16)


@contextlib.contextmanager
def deterministic_algorithms(on: bool):
    """Within the block, torch's deterministic algorithms (warn-only) when ``on`` and not already set."""
    if not on or torch.are_deterministic_algorithms_enabled():
        yield
        return
    torch.use_deterministic_algorithms(True, warn_only=True)
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(False)


def full_precision(shapes, azim, elev, dist):
    """Shapes and views with float16 / bfloat16 tensors cast to float32 (others unchanged)."""
    def up(t):
        return t.float() if t.dtype in LOW_PRECISION else t

    ref = shapes.verts if isinstance(shapes, Meshes) else shapes.points
    if ref.dtype in LOW_PRECISION:
        shapes = shapes.to(dtype=torch.float32)
    return shapes, up(azim), up(elev), up(dist)
