"""Per pixel, the K nearest of its (primitive, pixel) candidates: the ``Selection`` the rasterizers
shade, chunk selections merged, and the K = 1 winners that combine across chunks of any partition.

Like ``tiles.py`` it runs without autograd: the score ranks candidates (the depth in hard mode,
minus the blend logit in soft mode), ties go to the smaller primitive index, and the sizes it needs
are read from the device together (``tiles.read_ints``; index lists by ``tiles.where_true``).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from .tiles import read_ints, where_true


@dataclass
class Selection:
    """K best primitives for every pixel that has at least one.

    pix: ``[P]`` flat pixel index, ascending; prim: ``[P, K]`` primitive index, -1 in unused slots.
    rest_pix, rest_prim: ``[R]`` the candidates that did not get a slot (only when asked for:
    soft coverage counts them); most: the largest number of candidates any pixel had (0 if empty; a
    0-dim tensor when counted on the device, read only when asked);
    base_log_miss: ``[P]`` soft coverage the search counted itself and left out of the slots and the
    rest, as a constant ``sum log(1 - p)`` (fully covered pixels: their covering faces' bound).
    used: the number of used slots when the search knows it on the host (else None: counted when asked).
    """

    pix: torch.Tensor
    prim: torch.Tensor
    rest_pix: torch.Tensor | None = None
    rest_prim: torch.Tensor | None = None
    most: int | torch.Tensor = 0
    base_log_miss: torch.Tensor | None = None
    used: int | None = None

    def occupied(self) -> torch.Tensor:
        """Flat indices into ``prim.view(-1)`` of the used slots ``[S]``, ascending (a host read
        only when ``used`` is unknown)."""
        mask = self.prim.reshape(-1) >= 0
        return torch.nonzero(mask).squeeze(1) if self.used is None else where_true(mask, self.used)


def _sortable(score: torch.Tensor) -> torch.Tensor:
    """float32 ``[C]`` -> int64 in [0, 2^32) with the same order (negative values included)."""
    bits = score.contiguous().view(torch.int32).long()
    return (bits ^ ((bits >> 31) & 0x7FFFFFFF)) + (1 << 31)


def select_nearest(pix: torch.Tensor, score: torch.Tensor, prim: torch.Tensor, K: int, num_pixels: int,
                   keep_rest: bool = False, rest_mask: torch.Tensor | None = None,
                   slot_mask: torch.Tensor | None = None) -> Selection:
    """K candidates of smallest ``score`` per pixel (ties: smaller ``prim`` first).

    pix, score, prim: ``[C]`` candidates (score any finite float: depth in hard mode, minus the
    blend logit in soft mode), enumerated in ascending ``prim`` order within each pixel.
    keep_rest: also return the candidates beyond the K slots (``rest_pix``, ``rest_prim``), only
    those where ``rest_mask`` ``[C]`` is True when given. slot_mask: ``[C]``, False for candidates
    that may not hold a slot (they must rank after every candidate that may, in their pixel).
    Returns a Selection over the pixels with at least one candidate.
    """
    device = pix.device
    empty = torch.zeros(0, dtype=torch.long, device=device)
    if len(pix) == 0:
        return Selection(empty, torch.zeros(0, K, dtype=torch.long, device=device), empty if keep_rest else None,
                         empty if keep_rest else None, 0, used=0)
    if K == 1 and not keep_rest:
        active, _, best = nearest_one(pix, score, prim, num_pixels)
        return Selection(active, best.unsqueeze(1), used=len(active))
    if score.dtype == torch.float32:
        # one int64 key (pixel, order-preserving score bits): a single sort
        order = torch.sort((pix << 32) | _sortable(score), stable=True).indices
    else:
        order = torch.sort(score, stable=True).indices
        order = order[torch.sort(pix[order], stable=True).indices]
    sp = pix.index_select(0, order)
    first = torch.ones_like(sp, dtype=torch.bool)
    first[1:] = sp[1:] != sp[:-1]
    idx = torch.arange(len(sp), device=device)
    seg_start = torch.where(first, idx, torch.zeros_like(idx)).cummax(0).values
    rank = idx - seg_start
    keep = rank < K
    if slot_mask is not None:
        keep &= slot_mask.index_select(0, order)
    seg = torch.cumsum(first.long(), 0) - 1
    rest = None
    if keep_rest:
        rest = ~keep if rest_mask is None else ~keep & rest_mask.index_select(0, order)
    # the sizes below in one host read
    n_active, n_kept, n_rest = read_ints(first.sum(), keep.sum(), (rest if keep_rest else keep[:0]).sum())
    active = sp.index_select(0, where_true(first, n_active))
    out = torch.full((n_active * K,), -1, dtype=torch.long, device=device)
    kept = where_true(keep, n_kept)
    out.index_copy_(0, seg.index_select(0, kept) * K + rank.index_select(0, kept), prim.index_select(0, order.index_select(0, kept)))
    rest_pix = rest_prim = None
    if keep_rest:
        rest = where_true(rest, n_rest)
        rest_pix, rest_prim = sp.index_select(0, rest), prim.index_select(0, order.index_select(0, rest))
    return Selection(active, out.view(-1, K), rest_pix, rest_prim, rank.max() + 1, used=n_kept)


def nearest_one(pix: torch.Tensor, score: torch.Tensor, prim: torch.Tensor, num_pixels: int):
    """Per pixel the candidate of smallest ``score`` (ties: smaller ``prim``): ``(pix, score, prim)``,
    each ``[P]``, pixels ascending. Winners of disjoint candidate sets, concatenated and passed
    through again, give the winners of their union (so chunks of any partition combine)."""
    zmin = torch.full((num_pixels,), float("inf"), dtype=score.dtype, device=pix.device)
    zmin.scatter_reduce_(0, pix, score, "amin")
    win = score == zmin.index_select(0, pix)
    none = torch.iinfo(torch.long).max
    best = torch.full((num_pixels,), none, dtype=torch.long, device=pix.device)
    best.scatter_reduce_(0, pix[win], prim[win], "amin")
    active = torch.nonzero(best != none).squeeze(1)
    return active, zmin.index_select(0, active), best.index_select(0, active)


def largest(values: list):
    """The largest of ints and 0-dim tensors, without reading a tensor on the host."""
    out = max((v for v in values if not torch.is_tensor(v)), default=0)
    for v in values:
        if torch.is_tensor(v):
            out = torch.clamp(v, min=out) if not torch.is_tensor(out) else torch.maximum(out, v)
    return out


def merge(selections: list[Selection], K: int, device) -> Selection:
    """Concatenate chunk selections (chunks never share a pixel), sorted by pixel."""
    if not selections:
        return Selection(torch.zeros(0, dtype=torch.long, device=device), torch.zeros(0, K, dtype=torch.long, device=device))
    if len(selections) == 1:
        return selections[0]
    pix = torch.cat([s.pix for s in selections])
    order = torch.argsort(pix)
    rest_pix = rest_prim = None
    if selections[0].rest_pix is not None:
        rest_pix = torch.cat([s.rest_pix for s in selections])
        rest_prim = torch.cat([s.rest_prim for s in selections])
    used = None if any(s.used is None for s in selections) else sum(s.used for s in selections)
    return Selection(pix[order], torch.cat([s.prim for s in selections])[order], rest_pix, rest_prim,
                     largest([s.most for s in selections]), used=used)
