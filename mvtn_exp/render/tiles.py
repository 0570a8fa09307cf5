"""Screen tiles: primitives' pixel boxes -> (primitive, pixel) candidates, in chunks under a budget.

Shared by the mesh and the point rasterizer. Everything here runs without autograd: it only
decides *which* primitives cover *which* pixels; ``nearest.py`` keeps the K nearest of each
pixel's candidates, and callers recompute the differentiable quantities for the winners.

How a scene is searched:
1. each primitive (a face or point in one view) gives an inclusive pixel box, clipped to the image;
   empty boxes (off-screen, between pixel centres) cost nothing after this step;
2. candidates are the pixel centres inside each box, enumerated with ``repeat_interleave``;
3. if the whole scene has more candidates than ``max_candidates``, primitives are binned into
   ``tile_size`` square screen tiles (packed bins: a tile holds as many primitives as cover it, so
   nothing is ever dropped) and processed in chunks of whole tiles, each under the budget; a
   single tile over budget is processed alone and reported once with a warning;
4. per pixel, the K candidates of smallest score win (``nearest.select_nearest``; ties: smaller
   primitive index first); the score is the depth in hard mode and minus the blend logit in soft mode.

Pixel convention: image row i (top = 0), column j; pixel centre in NDC is
``x = (2j + 1) / W - 1``, ``y = 1 - (2i + 1) / H``. Flat pixel index: ``(image * H + i) * W + j``.
The host-read helpers (``read_ints``, ``where_true`` and its CUDA form on any device, ``gpu_path``)
live here too: the search of both modules reads its sizes through them.
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
    span chunks): for a search whose per-chunk winners combine (``nearest.nearest_one``), it skips the
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
        yield from _primitive_runs(boxes, prim, ends, H, W, max_candidates, span, dtype, small_box)
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
    yield from _tile_runs(tiles, owner, cum, num_tiles, H, W, max_candidates, span, dtype, small_box)


def _primitive_runs(boxes: PixelBoxes, prim: torch.Tensor, ends: torch.Tensor, H: int, W: int, max_candidates: int,
                    span, dtype, small_box: int) -> Iterator[tuple[Candidates, Candidates]]:
    """``candidate_chunks(by_primitive=True)``'s chunks: runs of consecutive primitives ``prim`` (the
    non-empty boxes; ``ends``: their cumulative sizes), each within ``max_candidates``; a single
    primitive over it alone."""
    start = 0
    while start < len(prim):  # each run within the budget; a single primitive over it alone
        base = int(ends[start - 1]) if start else 0
        stop = max(start + 1, int(torch.searchsorted(ends, base + max_candidates, right=True)))
        yield _enumerate(boxes, prim[start:stop], H, W, span, dtype, None, small_box)
        start = stop


def _tile_runs(tiles: PixelBoxes, owner: torch.Tensor, cum: list[list[int]], num_tiles: int, H: int, W: int,
               max_candidates: int, span, dtype, small_box: int) -> Iterator[tuple[Candidates, Candidates]]:
    """``candidate_chunks``' chunks of whole tiles (``_split_box_by_tiles``, cumulative counts
    ``cum`` from ``_tile_counts``), each within ``max_candidates``; a single tile over it alone."""
    start = 0  # the first tile of the chunk being gathered
    for t in range(num_tiles):
        base = cum[1][start - 1] if start else 0
        if t == num_tiles - 1 or cum[1][t + 1] - base > max_candidates:
            lo = [c[start - 1] if start else 0 for c in cum]
            if cum[0][t] > lo[0]:
                sel = torch.arange(lo[0], cum[0][t], device=tiles.j0.device)
                yield _enumerate(tiles, sel, H, W, span, dtype, owner, small_box, [c[t] - a for c, a in zip(cum[1:], lo[1:])])
            start = t + 1
