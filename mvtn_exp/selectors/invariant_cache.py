"""A bounded cache of a rotation-invariant function of point clouds, keyed by the cloud's content.

``mvtn_poi`` scores every point from rotation-invariant neighbourhood descriptors (kNN,
neighbourhood PCA): most of G's time per training step (docs/results/training-cost.md), spent
again at every step although the shape's points only turn
(``augment.rotate``). Since the descriptors do not change under a rotation (or a reflection) of the
centred cloud, they are computed once per shape and looked up afterwards.

Key: the cloud's point count and its centred radii ``|p_i - mean p|``, relative to their mean and
rounded to 1/256 (unchanged by a rotation, which moves each radius by float rounding only). A hit
must also match the stored radii to ``1e-4`` of their mean, so two different clouds never share an
entry; a radius that rounds the other way after a rotation (about 1% of lookups at 256 points)
is a miss, which computes the descriptors again. The order of the points is part of the key (the
same samples in another order are another cloud). At most ``capacity`` clouds are kept, the least
recently used dropped first; ``capacity = 0`` calls the function every time.
"""
from __future__ import annotations

from collections import OrderedDict
from typing import Callable

import torch
from torch import Tensor

KEY_STEPS = 256.0  # radii rounded to 1/KEY_STEPS of their mean for the key
MATCH_TOL = 1e-4  # a hit's radii agree with the stored ones to this fraction of their mean


class InvariantCache:
    """``cache(points [B, N, 3], centred) -> fn(points) [B, N, F]``, each cloud's rows computed at most
    once while it stays among the ``capacity`` most recently used (module docstring).

    fn: a function of a batch of centred clouds whose value does not change when a cloud is turned
    about its centre; it is called on the clouds that miss, batched. ``hits`` / ``misses`` count
    lookups of single clouds.
    """

    def __init__(self, fn: Callable[[Tensor], Tensor], capacity: int) -> None:
        if capacity < 0:
            raise ValueError(f"InvariantCache: capacity must be >= 0, got {capacity!r}")
        self.fn, self.capacity = fn, int(capacity)
        self.entries: OrderedDict[bytes, tuple[Tensor, Tensor]] = OrderedDict()  # key -> (radii [N], value [N, F])
        self.hits = self.misses = 0

    def __len__(self) -> int:
        return len(self.entries)

    def __call__(self, points: Tensor) -> Tensor:
        if self.capacity == 0:
            return self.fn(points)
        B, N, _ = points.shape
        radii = points.detach().norm(dim=-1)  # [B, N]
        rel = radii / radii.mean(1, keepdim=True).clamp_min(1e-12)
        keys = [N.to_bytes(4, "little") + row.tobytes()
                for row in torch.round(rel * KEY_STEPS).to(torch.int32).cpu().numpy()]
        values: list[Tensor | None] = [None] * B
        missing = []
        for b, key in enumerate(keys):
            entry = self.entries.get(key)
            if entry is not None and entry[1].dtype == points.dtype and entry[1].device == points.device and \
                    float((entry[0] - rel[b]).abs().max()) <= MATCH_TOL:
                self.entries.move_to_end(key)
                values[b] = entry[1]
            else:
                missing.append(b)
        self.hits += B - len(missing)
        self.misses += len(missing)
        if missing:
            fresh = self.fn(points.index_select(0, torch.tensor(missing, device=points.device)))
            for i, b in enumerate(missing):
                values[b] = fresh[i]
                self.entries[keys[b]] = (rel[b].clone(), fresh[i].clone())
                self.entries.move_to_end(keys[b])
            while len(self.entries) > self.capacity:
                self.entries.popitem(last=False)
        return torch.stack(values)  # type: ignore[arg-type]
