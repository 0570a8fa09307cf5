"""Per-pixel predictions of M views lifted to a shape's points, and back: the labels a view shows.

A view's pixel shows one primitive (``MultiViewRenderer.primitive_index``: the front-most face of
a mesh or point of a cloud, shape-local, -1 on the background). ``lift`` averages the logits of
the pixels that show a primitive within each view, then fuses the views that saw it:

- ``mean``: the mean of those per-view logits (differentiable: the lifted 3D loss trains through it);
- ``mode``: the paper's rule (as in Voint Cloud): each view votes for its argmax, the most votes win
  (ties go to the larger mean logit).

A point takes its primitive's result (a cloud's points are its primitives; a mesh's point takes
the face it lies on, ``prim_of_point``). A point no view saw has ``seen`` False; ``fill_unseen``
gives it the result of its nearest seen point of the same shape. ``pixel_labels`` is the other
direction: the part label each pixel shows, the target of the 2D segmentation loss.
"""
from __future__ import annotations

import torch

FUSIONS = ("mean", "mode")
IGNORE = -1  # a pixel that shows no primitive (the 2D loss's ignore_index)


def pixel_labels(index: torch.Tensor, prim_labels: torch.Tensor) -> torch.Tensor:
    """``index [B, M, H, W]`` (primitive per pixel, -1 background) and ``prim_labels [B, N]`` (the
    label of each primitive) -> ``[B, M, H, W]`` long labels, ``IGNORE`` on the background."""
    B, M, H, W = index.shape
    flat = index.reshape(B, -1)
    labels = torch.gather(prim_labels, 1, flat.clamp(min=0))
    return torch.where(flat >= 0, labels, torch.full_like(labels, IGNORE)).view(B, M, H, W)


def per_shape(packed: torch.Tensor, counts: torch.Tensor, fill: int = IGNORE) -> torch.Tensor:
    """Values packed shape after shape (``face_parts [sum F]``) -> ``[B, max F]``, ``fill`` past
    each shape's own count (what ``pixel_labels`` takes for a mesh batch)."""
    B, width = len(counts), int(counts.max()) if len(counts) else 0
    out = torch.full((B, width), fill, dtype=packed.dtype, device=packed.device)
    column = torch.arange(width, device=packed.device)
    out[column[None] < counts[:, None].to(packed.device)] = packed
    return out


def lift(logits: torch.Tensor, index: torch.Tensor, num_prims: int, prim_of_point: torch.Tensor | None = None,
         fuse: str = "mean") -> tuple[torch.Tensor, torch.Tensor]:
    """``logits [B, M, C, H, W]``, ``index [B, M, H, W]`` -> ``(scores [B, P, C], seen [B, P] bool)``.

    ``num_prims``: primitives per shape (N, indices ``< N``); ``prim_of_point [B, P]``: each point's
    primitive (None: the points are the primitives, P = N). ``scores``: the fused logits (``mean``)
    or the votes (``mode``); zero where unseen. Views are handled one at a time: memory ``[B, N, C]``."""
    if fuse not in FUSIONS:
        raise ValueError(f"lift: fuse={fuse!r}; expected one of {list(FUSIONS)}")
    B, M, C = logits.shape[:3]
    total = logits.new_zeros(B, num_prims, C)
    votes = logits.new_zeros(B, num_prims, C) if fuse == "mode" else None
    views = logits.new_zeros(B, num_prims)
    for m in range(M):
        mean, seen = _view_mean(logits[:, m], index[:, m], num_prims)
        total = total + mean  # (zero where this view did not see the primitive)
        views = views + seen
        if votes is not None:
            votes = votes + torch.nn.functional.one_hot(mean.argmax(-1), C) * seen[..., None]
    seen = views > 0
    scores = total / views.clamp(min=1)[..., None]
    if votes is not None:  # the tie-break stays below one vote: softmax in (0, 1), scaled by 1/2
        scores = votes + 0.5 * scores.detach().softmax(-1) * seen[..., None]
    if prim_of_point is None:
        return scores, seen
    return torch.gather(scores, 1, prim_of_point[..., None].expand(-1, -1, C)), torch.gather(seen, 1, prim_of_point)


def _view_mean(logits: torch.Tensor, index: torch.Tensor, num_prims: int) -> tuple[torch.Tensor, torch.Tensor]:
    """One view: ``logits [B, C, H, W]``, ``index [B, H, W]`` -> the mean logits of the pixels that
    show each primitive ``[B, N, C]`` and whether any does ``[B, N]`` (float 0/1)."""
    B, C = logits.shape[:2]
    flat = index.reshape(B, -1)
    shown = flat >= 0
    rows = torch.arange(B, device=index.device)[:, None].expand_as(flat)[shown]
    slot = rows * num_prims + flat[shown]  # (batch, primitive) flat
    values = logits.reshape(B, C, -1).transpose(1, 2)[shown]  # [S, C]
    sums = logits.new_zeros(B * num_prims, C).index_add(0, slot, values)
    count = logits.new_zeros(B * num_prims).index_add(0, slot, torch.ones_like(slot, dtype=logits.dtype))
    mean = sums / count.clamp(min=1)[:, None]
    return mean.view(B, num_prims, C), (count > 0).to(logits.dtype).view(B, num_prims)


def fill_unseen(points: torch.Tensor, scores: torch.Tensor, seen: torch.Tensor) -> torch.Tensor:
    """``points [B, P, 3]``, ``scores [B, P, C]``, ``seen [B, P]`` -> scores where each unseen
    point takes those of its nearest seen point of the same shape (a shape no view saw is left
    as it is)."""
    out = scores.clone()
    for b in range(points.shape[0]):
        hit, miss = seen[b].nonzero().squeeze(1), (~seen[b]).nonzero().squeeze(1)
        if len(hit) and len(miss):
            nearest = torch.cdist(points[b, miss], points[b, hit]).argmin(1)
            out[b, miss] = scores[b, hit[nearest]]
    return out


def coverage(seen: torch.Tensor) -> torch.Tensor:
    """The share of each shape's points that some view saw: ``[B]`` in [0, 1]."""
    return seen.float().mean(1)
