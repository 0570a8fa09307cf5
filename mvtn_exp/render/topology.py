"""Mesh topology used by the renderer: the neighbour of each face across each of its edges."""
from __future__ import annotations

import torch


def edge_neighbours(faces: torch.Tensor, num_verts: int | None = None) -> torch.Tensor:
    """Neighbour face across each edge. faces ``[F, 3]`` (global vertex indices) -> ``[F, 3]`` long.

    Edge i of a face is the one opposite vertex i: (v1, v2), (v2, v0), (v0, v1). -1 where the edge
    is a border. num_verts: more than the largest vertex index (read from ``faces`` when None). On non-manifold edges (three or more faces) faces are paired in index order.
    """
    F_ = len(faces)
    if F_ == 0:
        return torch.full((0, 3), -1, dtype=torch.long, device=faces.device)
    a = faces[:, [1, 2, 0]].reshape(-1)
    b = faces[:, [2, 0, 1]].reshape(-1)
    lo, hi = torch.minimum(a, b), torch.maximum(a, b)
    # (num_verts: any bound above every index, given to spare a host read of the largest one)
    key = lo * (num_verts if num_verts is not None else int(faces.max()) + 1) + hi
    order = torch.sort(key, stable=True).indices
    k = key[order]
    same = k[1:] == k[:-1]
    # pair consecutive equal keys, starting at the first of each run: (0,1), (2,3), ...
    run_start = torch.ones(len(k), dtype=torch.bool, device=faces.device)
    run_start[1:] = ~same
    idx = torch.arange(len(k), device=faces.device)
    pos_in_run = idx - torch.where(run_start, idx, torch.zeros_like(idx)).cummax(0).values
    left = same & (pos_in_run[:-1] % 2 == 0)  # [3F - 1]: sorted position i pairs with i + 1
    # written without a host read: the unpaired positions go to a spare slot past the end
    spare = 3 * F_
    flat = torch.full((3 * F_ + 1,), -1, dtype=torch.long, device=faces.device)
    flat.scatter_(0, torch.where(left, order[:-1], spare), torch.div(order[1:], 3, rounding_mode="floor"))
    flat.scatter_(0, torch.where(left, order[1:], spare), torch.div(order[:-1], 3, rounding_mode="floor"))
    return flat[:-1].view(F_, 3)
