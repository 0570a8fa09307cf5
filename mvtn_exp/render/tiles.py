"""Screen tiles: primitives' pixel boxes -> (primitive, pixel) candidates -> K nearest per pixel.

Shared by the mesh and the point rasterizer. Everything here runs without autograd: it only
decides *which* primitives cover *which* pixels; callers recompute the differentiable quantities
for the winners.

How a scene is searched:
1. each primitive (a face or point in one view) gives an inclusive pixel box, clipped to the image;
   empty boxes (off-screen, between pixel centres) cost nothing after this step;
2. candidates are the pixel centres inside each box, enumerated with ``repeat_interleave``;
3. if the whole scene has more candidates than ``max_candidates``, primitives are binned into
   ``tile_size`` square screen tiles (packed bins: a tile holds as many primitives as cover it, so
   nothing is ever dropped) and processed in chunks of whole tiles, each under the budget; a
   single tile over budget is processed alone and reported once with a warning;
4. per pixel, the K candidates of smallest score win (ties: smaller primitive index first); the
   score is the depth in hard mode and minus the blend logit in soft mode.

Pixel convention: image row i (top = 0), column j; pixel centre in NDC is
``x = (2j + 1) / W - 1``, ``y = 1 - (2i + 1) / H``. Flat pixel index: ``(image * H + i) * W + j``.
"""
from __future__ import annotations

import contextlib
import warnings
from dataclasses import dataclass
from typing import Iterator

import torch

from .accel import fused


@dataclass
class PixelBoxes:
    """Inclusive pixel boxes of primitives. All ``[N]`` long (image may be None until known); empty when
    ``j1 < j0`` or ``i1 < i0``."""

    image: torch.Tensor
    j0: torch.Tensor
    j1: torch.Tensor
    i0: torch.Tensor
    i1: torch.Tensor

    def sizes(self) -> torch.Tensor:
        return (self.j1 - self.j0 + 1).clamp(min=0) * (self.i1 - self.i0 + 1).clamp(min=0)


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


def pixel_boxes(xmin, xmax, ymin, ymax, image, H: int, W: int) -> PixelBoxes:
    """NDC extents ``[N]`` -> inclusive pixel-centre index boxes clipped to the ``H x W`` image."""
    j0 = torch.ceil(((xmin + 1) * W - 1) / 2).clamp(-1, W).long().clamp(min=0)
    j1 = torch.floor(((xmax + 1) * W - 1) / 2).clamp(-1, W).long().clamp(max=W - 1)
    i0 = torch.ceil(((1 - ymax) * H - 1) / 2).clamp(-1, H).long().clamp(min=0)
    i1 = torch.floor(((1 - ymin) * H - 1) / 2).clamp(-1, H).long().clamp(max=H - 1)
    return PixelBoxes(image, j0, j1, i0, i1)


def pixel_centres(pix: torch.Tensor, H: int, W: int, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """Flat pixel index ``[N]`` -> NDC centre x, y ``[N]``."""
    j = pix % W
    i = (pix // W) % H
    x = (2 * j + 1).to(dtype) / W - 1
    y = 1 - (2 * i + 1).to(dtype) / H
    return x, y


@dataclass
class Candidates:
    """(primitive, pixel) pairs: prim, pix ``[C]`` long; x, y ``[C]`` NDC pixel centres."""

    prim: torch.Tensor
    pix: torch.Tensor
    x: torch.Tensor
    y: torch.Tensor


# boxes of at most this many pixels are enumerated whole; larger ones row by row through ``span``
SMALL_BOX = 4


def read_ints(*values: torch.Tensor) -> list[int]:
    """0-dim integer tensors -> Python ints in one host read (one sync on CUDA, however many values)."""
    return torch.stack([v.reshape(()).long() for v in values]).tolist() if values else []


# where_true's form: "auto" is the sync-free one on CUDA and ``nonzero`` on the CPU (faster there,
# where a host read costs nothing); "sync_free" everywhere, which ``gpu_path`` sets so that a CPU
# run counts the operators a GPU runs (``bench.kernel_ops``)
_WHERE = "auto"


@contextlib.contextmanager
def gpu_path():
    """Within the block the search takes its CUDA form on every device (for counting kernel ops)."""
    global _WHERE
    old, _WHERE = _WHERE, "sync_free"
    try:
        yield
    finally:
        _WHERE = old


def where_true(mask: torch.Tensor, count: int) -> torch.Tensor:
    """The indices ``[count]`` of True in the 1-d ``mask``, ascending, without a host read on CUDA
    (``count = mask.sum()``, read by the caller, e.g. with other counts in one ``read_ints``)."""
    if _WHERE == "auto" and mask.device.type == "cpu":
        return torch.nonzero(mask).squeeze(1)
    n = mask.numel()
    dest = torch.where(mask, torch.cumsum(mask, 0) - 1, count)  # the False ones to a spare slot
    out = torch.empty(count + 1, dtype=torch.long, device=mask.device)
    return out.scatter_(0, dest, torch.arange(n, device=mask.device))[:count]


def columns(xlo: torch.Tensor, xhi: torch.Tensor, W: int) -> tuple[torch.Tensor, torch.Tensor]:
    """NDC interval -> inclusive range of pixel-centre columns inside it (empty when j1 < j0)."""
    return (torch.ceil(((xlo + 1) * W - 1) / 2).clamp(-1, W).long(),
            torch.floor(((xhi + 1) * W - 1) / 2).clamp(-1, W).long())


def _count_terms(boxes: PixelBoxes, small_box: int) -> torch.Tensor:
    """Per box ``[4, N]``: its candidates, whether it has at most ``small_box`` pixels, its
    candidates if so, its rows if not (summed: what ``_enumerate`` needs to size its outputs)."""
    sizes = boxes.sizes()
    small = sizes <= small_box
    rows = (boxes.i1 - boxes.i0 + 1).clamp(min=0)
    return torch.stack([sizes, small.long(), sizes * small, rows * ~small])


def _counts(boxes: PixelBoxes, sel: torch.Tensor, small_box: int) -> list[int]:
    """One host read for the boxes ``sel``: [candidates in all, boxes of at most ``small_box``
    pixels, their candidates, the rows of the larger ones]."""
    return _count_terms(boxes, small_box).index_select(1, sel).sum(1).tolist()


def _enumerate(boxes: PixelBoxes, sel: torch.Tensor, H: int, W: int, span, dtype, owner=None,
               small_box=SMALL_BOX, counts: list[int] | None = None) -> tuple[Candidates, Candidates]:
    """Pixel centres of the boxes ``sel``: (from whole boxes, from row spans).

    span: optional ``span(prim [R], y [R]) -> (j0, j1)``: per box row at NDC height y, the
    inclusive pixel columns the primitive can reach there (see ``columns``); it trims large boxes
    to the primitive's own shape. It may return ``(j0, j1, h0, h1)``: columns h0..h1 are then
    skipped (a hole, ``mesh_raster.row_spans``). Boxes of at most ``small_box`` pixels skip it and are enumerated
    whole: there the row pass would cost more than the candidates it saves.
    owner: maps box index -> primitive index (tile-clipped boxes); identity when None.
    counts: ``_counts(boxes, sel, small_box)`` when the caller has read them (else read here, once).
    Host syncs: that read, and the row spans' candidate count.
    """
    total, n_small, small_total, large_rows = counts or _counts(boxes, sel, small_box)
    if span is None:
        return (_enumerate_boxes(boxes, sel, H, W, dtype, owner, total),
                _enumerate_boxes(boxes, sel[:0], H, W, dtype, owner, 0))
    small = boxes.sizes().index_select(0, sel) <= small_box
    # small boxes first, then the others, each in their order (a partition without a host read)
    dest = torch.where(small, torch.cumsum(small, 0) - 1, n_small + torch.cumsum(~small, 0) - 1)
    parted = torch.empty_like(sel).index_copy_(0, dest, sel)
    return (_enumerate_boxes(boxes, parted[:n_small], H, W, dtype, owner, small_total),
            _enumerate_rows(boxes, parted[n_small:], H, W, span, dtype, owner, large_rows))


def concat(parts: tuple[Candidates, ...]) -> Candidates:
    return Candidates(*(torch.cat([getattr(a, k) for a in parts]) for k in ("prim", "pix", "x", "y")))


@fused
def _enumerate_boxes(boxes: PixelBoxes, sel: torch.Tensor, H: int, W: int, dtype, owner, total: int) -> Candidates:
    """Every pixel centre of the boxes ``sel`` (``total`` of them)."""
    dev = sel.device
    j0, i0 = boxes.j0.index_select(0, sel), boxes.i0.index_select(0, sel)
    w = (boxes.j1.index_select(0, sel) - j0 + 1).clamp(min=0)
    n = w * (boxes.i1.index_select(0, sel) - i0 + 1).clamp(min=0)
    own = torch.repeat_interleave(torch.arange(len(sel), device=dev), n, output_size=total)
    local = torch.arange(len(own), device=dev) - (torch.cumsum(n, 0) - n).index_select(0, own)
    wo = w.index_select(0, own)
    di = torch.div(local, wo, rounding_mode="floor")
    i = i0.index_select(0, own) + di
    j = j0.index_select(0, own) + local - di * wo
    b = sel.index_select(0, own)
    pix = (boxes.image.index_select(0, b) * H + i) * W + j
    p = b if owner is None else owner.index_select(0, b)
    return Candidates(p, pix, (2 * j + 1).to(dtype) / W - 1, 1 - (2 * i + 1).to(dtype) / H)


@fused
def _enumerate_rows(boxes: PixelBoxes, sel: torch.Tensor, H: int, W: int, span, dtype, owner, rows: int) -> Candidates:
    """The pixel centres of the boxes ``sel`` (``rows`` box rows in all) that ``span`` keeps."""
    dev = sel.device
    i0 = boxes.i0.index_select(0, sel)
    nrows = (boxes.i1.index_select(0, sel) - i0 + 1).clamp(min=0)
    rown = torch.repeat_interleave(torch.arange(len(sel), device=dev), nrows, output_size=rows)
    i = (i0 - (torch.cumsum(nrows, 0) - nrows)).index_select(0, rown) + torch.arange(len(rown), device=dev)
    b = sel.index_select(0, rown)
    p = b if owner is None else owner.index_select(0, b)
    y = 1 - (2 * i + 1).to(dtype) / H
    cols = span(p, y)
    j0 = torch.maximum(boxes.j0.index_select(0, b), cols[0])
    j1 = torch.minimum(boxes.j1.index_select(0, b), cols[1])
    if len(cols) == 4:  # a hole (h0, h1) to skip: each row becomes two runs, the second empty without one
        h0, h1 = cols[2], cols[3]
        has = h0 <= h1
        j0 = torch.stack([j0, torch.where(has, torch.maximum(j0, h1 + 1), j1 + 1)], 1).view(-1)
        j1 = torch.stack([torch.where(has, torch.minimum(j1, h0 - 1), j1), j1], 1).view(-1)
        b, p, i, y = (t.repeat_interleave(2) for t in (b, p, i, y))
    n = (j1 - j0 + 1).clamp(min=0)
    own = torch.repeat_interleave(torch.arange(len(n), device=dev), n)
    j = (j0 - (torch.cumsum(n, 0) - n)).index_select(0, own) + torch.arange(len(own), device=dev)
    pix = ((boxes.image.index_select(0, b) * H + i) * W).index_select(0, own) + j
    return Candidates(p.index_select(0, own), pix, (2 * j + 1).to(dtype) / W - 1, y.index_select(0, own))


def _split_box_by_tiles(boxes: PixelBoxes, tile: int, H: int, W: int):
    """Bin boxes into tiles (empty boxes into none). Returns per (box, tile) pair: a PixelBoxes
    clipped to the tile, the box index and the global tile id, pairs sorted by tile (stable); and
    the number of tile ids. One host read (the pair count and the number of images)."""
    ty0, ty1 = boxes.i0 // tile, boxes.i1 // tile
    tx0, tx1 = boxes.j0 // tile, boxes.j1 // tile
    ntx = (W + tile - 1) // tile
    nty = (H + tile - 1) // tile
    wt = (tx1 - tx0 + 1).clamp(min=0)
    n = torch.where(boxes.sizes() > 0, wt * (ty1 - ty0 + 1).clamp(min=0), 0)
    total, last_image = read_ints(n.sum(), boxes.image.max())
    dev = n.device
    owner = torch.repeat_interleave(torch.arange(len(n), device=dev), n, output_size=total)
    local = torch.arange(total, device=dev) - (torch.cumsum(n, 0) - n).index_select(0, owner)
    w = wt.index_select(0, owner)
    ty = ty0.index_select(0, owner) + torch.div(local, w, rounding_mode="floor")
    tx = tx0.index_select(0, owner) + local % w
    tile_id = (boxes.image.index_select(0, owner) * nty + ty) * ntx + tx
    order = torch.sort(tile_id, stable=True).indices
    p, ty, tx, tile_id = owner[order], ty[order], tx[order], tile_id[order]
    clipped = PixelBoxes(
        boxes.image[p],
        torch.maximum(boxes.j0[p], tx * tile), torch.minimum(boxes.j1[p], tx * tile + tile - 1),
        torch.maximum(boxes.i0[p], ty * tile), torch.minimum(boxes.i1[p], ty * tile + tile - 1),
    )
    return clipped, p, tile_id, (last_image + 1) * nty * ntx


def _tile_counts(tiles: PixelBoxes, tile_id: torch.Tensor, num_tiles: int, small_box: int) -> list[list[int]]:
    """One host read: per tile id, cumulative (pairs, then ``_counts``' four numbers), ``[5][num_tiles]``."""
    terms = _count_terms(tiles, small_box)
    per_pair = torch.cat([torch.ones_like(terms[:1]), terms])
    per_tile = torch.zeros(5, num_tiles, dtype=torch.long, device=terms.device).index_add_(1, tile_id, per_pair)
    return torch.cumsum(per_tile, 1).tolist()


_warned_tile_budget = False


def candidate_chunks(boxes: PixelBoxes, H: int, W: int, tile_size: int, max_candidates: int, dtype=torch.float32,
                     span=None, small_box: int = SMALL_BOX, by_primitive: bool = False,
                     overflow=None) -> Iterator[tuple[Candidates, Candidates]]:
    """Yield candidate chunks, each as (from whole boxes, from row spans) (see ``_enumerate``);
    every pixel's candidates lie in exactly one chunk.

    by_primitive: chunks are runs of consecutive primitives instead (a pixel's candidates may then
    span chunks): for a search whose per-chunk winners combine (``nearest_one``), it skips the
    binning into tiles, the dearest step of a dense scene.
    overflow: called with the candidate count of a tile (or primitive box) over ``max_candidates``
    (an explicit memory budget raises there); None: it is processed alone, with one warning.
    """
    global _warned_tile_budget
    sizes = boxes.sizes()
    every = torch.arange(len(sizes), device=sizes.device)
    counts = _counts(boxes, every, small_box)  # (empty boxes add no candidate: no need to drop them first)
    if counts[0] == 0:
        return
    if counts[0] <= max_candidates:
        yield _enumerate(boxes, every, H, W, span, dtype, None, small_box, counts)
        return
    if by_primitive:
        prim = torch.nonzero(sizes > 0).squeeze(1)
        ends = torch.cumsum(sizes.index_select(0, prim), 0)
        largest = int(sizes.max())
        if largest > max_candidates and overflow is not None:
            overflow(largest)
        if largest > max_candidates and not _warned_tile_budget:
            _warned_tile_budget = True
            warnings.warn(f"renderer: one primitive's box holds {largest} candidates, over the chunk budget "
                          f"max_candidates={max_candidates}; it is processed alone (budget grown, nothing dropped). "
                          "Raise max_candidates to silence this.", RuntimeWarning, stacklevel=3)
        start = 0
        while start < len(prim):  # each run within the budget; a single primitive over it alone
            base = int(ends[start - 1]) if start else 0
            stop = max(start + 1, int(torch.searchsorted(ends, base + max_candidates, right=True)))
            yield _enumerate(boxes, prim[start:stop], H, W, span, dtype, None, small_box)
            start = stop
        return
    tiles, owner, tile_id, num_tiles = _split_box_by_tiles(boxes, tile_size, H, W)
    cum = _tile_counts(tiles, tile_id, num_tiles, small_box)  # (the chunks' counts below: no read per chunk)
    most = max(b - a for a, b in zip([0] + cum[1][:-1], cum[1]))
    if most > max_candidates and overflow is not None:
        overflow(most)
    if most > max_candidates and not _warned_tile_budget:
        _warned_tile_budget = True
        warnings.warn(
            f"renderer: one {tile_size}px tile holds {most} candidates, over the chunk budget "
            f"max_candidates={max_candidates}; it is processed alone (budget grown, nothing dropped). "
            "Lower tile_size or raise max_candidates to silence this.",
            RuntimeWarning,
            stacklevel=3,
        )
    start = 0  # the first tile of the chunk being gathered
    for t in range(num_tiles):
        base = cum[1][start - 1] if start else 0
        if t == num_tiles - 1 or cum[1][t + 1] - base > max_candidates:
            lo = [c[start - 1] if start else 0 for c in cum]
            if cum[0][t] > lo[0]:
                sel = torch.arange(lo[0], cum[0][t], device=tiles.j0.device)
                yield _enumerate(tiles, sel, H, W, span, dtype, owner, small_box, [c[t] - a for c, a in zip(cum[1:], lo[1:])])
            start = t + 1


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
