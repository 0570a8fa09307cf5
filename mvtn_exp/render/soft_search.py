"""Soft-mode face search: per pixel, the faces that hold colour slots and the rest that only count for coverage.

Two passes, both without autograd:

1. covering faces (``_covering``): each face's undilated row spans, the pixels it covers; from them
   every pixel's best (largest) depth logit and a conservative bound on how fully its covering
   faces alone cover it (distances to the edge lines never exceed those to the edges);
2. faces within the blur radius that do not cover the pixel (``_near``): the dilated row spans
   less each face's inside (a ring; ``mesh_raster.row_spans(hole=...)``), where a candidate from
   a face whose nearest corner lies more than ``depth_window`` (in logit) behind the best covering
   face of a fully covered pixel is dropped before anything else is computed (hidden: it adds
   neither colour nor coverage); the others are tested exactly against the blur radius.

Then per pixel the K candidates of largest blend logit ``log p + zinv / gamma`` (the K largest
softmax weights, only those within ``depth_window`` of the largest) hold the slots; every other
candidate comes back as the rest (``Selection.rest_pix`` / ``rest_prim``), so that coverage counts
every face within the blur radius whatever K is (``rest_log_miss``), except in fully covered
pixels: there the covering faces' bound stands for all of them (``Selection.base_log_miss``).
``SoftRanking.by_depth`` keeps PyTorch3D's choice instead: the K nearest by depth among the faces
within the blur radius, coverage from those K alone.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from . import accel, nearest, tiles
from .accel import fused
from .edge_distance import covers
from .mesh_raster import (SMALL_BOX_HARD, TABLE_CORNERS, ProjectedFaces, barycentrics, face_boxes, face_fragments,
                          face_table, inverse_depth, row_spans, table_planes, triangle_sqdist)

# soft search: a candidate whose depth logit trails the best covering face of a pixel by more than
# this much has a colour weight below exp(-DEPTH_WINDOW) of that face's (and log p <= 0 cannot help it)
DEPTH_WINDOW = 12.0


@dataclass
class SoftRanking:
    """How soft mode ranks a pixel's candidates: by the blend logit ``log p + zinv / gamma``
    (or by depth alone when ``by_depth``, PyTorch3D's choice: the K nearest, no rest).

    zfar, znear: ``[num_images]`` the scene depth range of each image (as in ``softmax_blend``);
    sigma, gamma: the blend's. In the search, ``log p`` of a covering face is taken as 0 (its
    true value lies in [log 1/2, 0]); for the others it is ``logsigmoid(-d^2 / sigma)``.
    interior: ``[F*M, 3]`` interior-edge flags (see ``face_fragments``); coverage_tol: coverage
    closer to 1 than this counts as full (0: only where it rounds to 1); depth_window: how far
    (in logit) behind a fully covering face a face may lie and still be searched (inf: no pruning).
    """

    zfar: torch.Tensor
    znear: torch.Tensor
    sigma: float
    gamma: float
    by_depth: bool = False
    interior: torch.Tensor | None = None
    coverage_tol: float = 0.0
    depth_window: float = DEPTH_WINDOW

    def depth_logit(self, image: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
        """``zinv / gamma`` of candidates ``[C]`` in images ``image`` ``[C]``."""
        zf = self.zfar.index_select(0, image)
        return (zf - depth) / ((zf - self.znear.index_select(0, image)).clamp(min=1e-12) * self.gamma)

    def log_tol(self, dtype: torch.dtype) -> float:
        """``log prod (1 - p)`` below which a pixel counts as fully covered."""
        return math.log(self.coverage_tol) if self.coverage_tol > 0 else saturated_log_miss(dtype)


@dataclass
class _Faces:
    """The searched face-views: ids ``fv`` and images ``[Fs]``, corner rows ``cols`` ``[9, Fs]``,
    ``mesh_raster.face_table`` ``[18, Fs]``, its planes (list of 9 ``[Fs]``), the largest depth
    logit (nearest corner) ``zl_max`` ``[Fs]``."""

    fv: torch.Tensor
    image: torch.Tensor
    cols: torch.Tensor
    table: torch.Tensor
    planes: list
    zl_max: torch.Tensor


def search(pf: ProjectedFaces, *, H: int, W: int, K: int, blur_radius: float, tile_size: int, max_candidates: int,
           ranking: SoftRanking, overflow=None) -> nearest.Selection:
    """The soft search (see the module docstring) -> Selection with slots ``[P, K]`` and the rest."""
    with torch.no_grad():
        dilated = face_boxes(pf.cols, None, blur_radius, H, W)
        seen = pf.alive & (dilated.sizes() > 0)
        # (with the widest box, which the near pass's row minimum needs: one host read for both)
        width = torch.where(seen, dilated.j1 - dilated.j0 + 1, 1)
        n_seen, widest = tiles.read_ints(seen.sum(), width.max() if width.numel() else width.new_ones(()))
        fv = tiles.where_true(seen, n_seen)
        image = pf.image_of(fv)
        cols = pf.cols.index_select(1, fv)
        table = face_table(cols)
        faces = _Faces(fv, image, cols, table, table_planes(table),
                       ranking.depth_logit(image, torch.minimum(torch.minimum(cols[2], cols[5]), cols[8])))
        dilated = tiles.PixelBoxes(image, *(t.index_select(0, fv) for t in (dilated.j0, dilated.j1, dilated.i0, dilated.i1)))
        num_pixels = pf.num_images * H * W
        chunks = dict(H=H, W=W, tile_size=tile_size, max_candidates=max_candidates, dtype=cols.dtype, overflow=overflow)
        if ranking.by_depth:
            pix, prim, depth, _ = _near(faces, dilated, blur_radius, None, ranking, chunks, keep_inside=True, widest=widest)
            return nearest.select_nearest(pix, depth, prim, K, num_pixels)
        pix1, prim1, zl1, miss1 = _covering(faces, ranking, chunks)
        miss = torch.zeros(num_pixels, dtype=cols.dtype, device=cols.device).index_add_(0, pix1, miss1)
        best = torch.full((num_pixels,), float("-inf"), dtype=cols.dtype, device=cols.device).scatter_reduce_(0, pix1, zl1, "amax")
        full = miss < ranking.log_tol(cols.dtype)
        hidden_below = torch.where(full, best - (math.log(2.0) + ranking.depth_window), torch.full_like(best, float("-inf")))
        pix2, prim2, zl2, sqd2 = _near(faces, dilated, blur_radius, hidden_below, ranking, chunks, keep_inside=False,
                                       widest=widest)
        pix = torch.cat([pix1, pix2])
        score = torch.cat([-zl1, -(zl2 + F.logsigmoid(-sqd2 / ranking.sigma))])
        # a slot only for faces whose colour weight is within exp(-depth_window) of the pixel's largest
        least = torch.full((num_pixels,), float("inf"), dtype=score.dtype, device=score.device).scatter_reduce_(0, pix, score, "amin")
        slot_ok = score <= least.index_select(0, pix) + ranking.depth_window
        # fully covered pixels keep no rest: their coverage is within coverage_tol of 1 whatever
        # the other faces add (``rest_log_miss`` counts them with their covering faces' bound)
        rest_ok = ~full.index_select(0, pix)
        prim = torch.cat([prim1, prim2])
        # only the few slot candidates are ranked (every pixel's best is one of them); the others
        # join the rest unsorted
        other = ~slot_ok & rest_ok
        n_ok, n_other = tiles.read_ints(slot_ok.sum(), other.sum())
        ok = tiles.where_true(slot_ok, n_ok)
        sel = nearest.select_nearest(pix.index_select(0, ok), score.index_select(0, ok), prim.index_select(0, ok), K,
                                   num_pixels, keep_rest=True, rest_mask=rest_ok.index_select(0, ok))
        sel.base_log_miss = torch.where(full.index_select(0, sel.pix), miss.index_select(0, sel.pix), 0.0)
        other = tiles.where_true(other, n_other)
        sel.rest_pix = torch.cat([sel.rest_pix, pix.index_select(0, other)])
        sel.rest_prim = torch.cat([sel.rest_prim, prim.index_select(0, other)])
        # (a count per pixel, not bincount: no host sync; a 0-dim tensor, read when asked)
        sel.most = torch.zeros(num_pixels, dtype=torch.int32, device=pix.device).index_add_(
            0, pix, torch.ones_like(pix, dtype=torch.int32)).max() if len(pix) else 0
        return sel


def _covering(faces: _Faces, ranking: SoftRanking, chunks: dict):
    """Pass 1: (pixel, face) pairs where the face covers the pixel centre -> pix, face-view, depth
    logit, and the conservative ``log(1 - p)`` from the distance to the nearest non-interior edge
    line, each ``[C1]``."""
    H, W = chunks["H"], chunks["W"]
    boxes = face_boxes(faces.cols, faces.image, 0.0, H, W)
    span = row_spans(faces.planes, boxes, 0.0, SMALL_BOX_HARD, W)
    out = []
    # per face and edge: 1 / |grad lambda_k| (lambda_k times it is the distance to the edge line), or
    # -1 for interior edges, which do not bound coverage
    grad = [torch.sqrt(faces.planes[3 * k] ** 2 + faces.planes[3 * k + 1] ** 2) for k in range(3)]
    inv_grad = torch.stack([1.0 / g for g in grad])
    if ranking.interior is not None:
        inv_grad = torch.where(ranking.interior.index_select(0, faces.fv).t(), -1.0, inv_grad)
    for parts in tiles.candidate_chunks(boxes, span=span, small_box=SMALL_BOX_HARD, **chunks):
        cand = tiles.concat(parts)
        lam = barycentrics(faces.table, cand.prim, cand.x, cand.y)
        keep = torch.nonzero(covers(lam)).squeeze(1)
        prim = cand.prim.index_select(0, keep)
        lam = [l.index_select(0, keep) for l in lam]
        depth = 1.0 / inverse_depth(faces.table, prim, lam).clamp(min=1e-12)
        dmin = None
        for k in range(3):  # distance to the nearest non-interior edge line
            ig = inv_grad[k].index_select(0, prim)
            dl = torch.where(ig < 0, 1e2, lam[k] * ig)
            dmin = dl if dmin is None else torch.minimum(dmin, dl)
        dmin = dmin.clamp(max=1e2)
        out.append((cand.pix.index_select(0, keep), faces.fv.index_select(0, prim),
                    ranking.depth_logit(faces.image.index_select(0, prim), depth), F.logsigmoid(-dmin * dmin / ranking.sigma)))
    return _cat(out, 4, faces)


def _near(faces: _Faces, boxes: tiles.PixelBoxes, radius: float, hidden_below, ranking: SoftRanking, chunks: dict,
          keep_inside: bool, widest: int):
    """Pass 2: faces within ``radius`` of the pixel centre. Candidates whose face's largest depth
    logit is below ``hidden_below[pix]`` are skipped first; covering pairs are left to pass 1 unless
    ``keep_inside``. Returns pix, face-view, then depth logit and squared distance (or depth and
    None when ``keep_inside``, PyTorch3D's ranking), each ``[C2]``. widest: at least the widest box,
    in pixels (bounds the row minimum's ranges)."""
    W = chunks["W"]
    if hidden_below is not None:
        hidden = _hidden_faces(faces, boxes, hidden_below, chunks["H"], W)
        boxes = tiles.PixelBoxes(boxes.image, boxes.j0, torch.where(hidden, boxes.j0 - 1, boxes.j1), boxes.i0, boxes.i1)
    # pairs that cover the pixel are pass 1's: skip each triangle's inside, enumerate a ring
    hole = None
    if not keep_inside:
        ys = faces.table[TABLE_CORNERS + 1:TABLE_CORNERS + 6:2]
        hole = (ys.amin(0), ys.amax(0))
    span = row_spans(faces.planes, boxes, radius, tiles.SMALL_BOX, W, hole=hole)
    if hidden_below is not None:
        span = _unhidden_rows(span, faces, boxes, RowMin(hidden_below, chunks["H"], W, widest), chunks["H"])
    out = []
    r2 = radius**2
    for parts in tiles.candidate_chunks(boxes, span=span, small_box=tiles.SMALL_BOX, **chunks):
        cand = tiles.concat(parts)  # (both parts in one pass: half the kernels and host reads)
        hb = hidden_below
        if hb is not None and not accel.enabled():
            # eager: drop the hidden candidates before the maths (compiled, one fused loop tests them)
            idx = torch.nonzero(faces.zl_max.index_select(0, cand.prim) >= hb.index_select(0, cand.pix)).squeeze(1)
            cand, hb = tiles.Candidates(*(getattr(cand, k).index_select(0, idx) for k in ("prim", "pix", "x", "y"))), None
        keep, depth, sqd = _near_values(faces.table, faces.zl_max, hb, cand.prim, cand.pix, cand.x, cand.y, r2, keep_inside)
        keep = torch.nonzero(keep).squeeze(1)
        prim, pix, depth = cand.prim.index_select(0, keep), cand.pix.index_select(0, keep), depth.index_select(0, keep)
        fvk = faces.fv.index_select(0, prim)
        if keep_inside:
            out.append((pix, fvk, depth, depth))
        else:
            out.append((pix, fvk, ranking.depth_logit(faces.image.index_select(0, prim), depth), sqd.index_select(0, keep)))
    pix, prim, a, b = _cat(out, 4, faces)
    return pix, prim, a, (None if keep_inside else b)


class RowMin:
    """Range minimum over image rows: ``query(row, j0, j1)`` is the least of ``values`` over columns
    j0..j1 of each ``row`` (a sparse table: level k holds the minimum of 2^k consecutive columns;
    a query takes two overlapping blocks). values: ``[num_images * H * W]``; rows ``[R]`` are
    ``image * H + i``; an empty range (j1 < j0) gives +inf."""

    def __init__(self, values: torch.Tensor, H: int, W: int, longest: int | None = None):
        """``longest``: the widest range that will be queried (levels beyond it are not built, and a
        longer query would miss its middle columns: callers clip their ranges); None: W."""
        self.W, self.n = W, values.numel()
        self.longest = max(1, min(W, W if longest is None else int(longest)))
        levels = self.longest.bit_length()
        table = torch.empty(levels, self.n // W, W, dtype=values.dtype, device=values.device)
        table[0] = values.view(-1, W)
        for k in range(1, levels):  # level k: the minimum of columns j .. j + 2^k - 1 (clipped at W)
            half = 1 << (k - 1)
            torch.minimum(table[k - 1, :, :W - half], table[k - 1, :, half:], out=table[k, :, :W - half])
            table[k, :, W - half:] = table[k - 1, :, W - half:]
        self.table = table.view(-1)
        # floor(log2(n)) for n = 1..longest (index 0 unused)
        self.log2 = torch.tensor([0] + [n.bit_length() - 1 for n in range(1, self.longest + 1)], device=values.device)

    def query(self, row: torch.Tensor, j0: torch.Tensor, j1: torch.Tensor) -> torch.Tensor:
        empty = j1.clamp(max=self.W - 1) < j0.clamp(min=0)
        j0, j1 = j0.clamp(0, self.W - 1), j1.clamp(0, self.W - 1)  # (in range even where empty)
        length = (j1 - j0 + 1).clamp(min=1)
        k = self.log2.index_select(0, length)
        base = k * self.n + row * self.W
        least = torch.minimum(self.table.index_select(0, base + j0),
                              self.table.index_select(0, base + j1 - (1 << k) + 1))
        return torch.where(empty, float("inf"), least)


def _unhidden_rows(span, faces: _Faces, boxes: tiles.PixelBoxes, row_min: RowMin, H: int):
    """``span`` with the rows where a face is hidden in every pixel of its columns emptied: its
    largest depth logit ``faces.zl_max`` is below the least ``hidden_below`` there (the columns
    clipped to the face's box ``boxes``, as they are enumerated). Each such pixel would be dropped
    by the per-candidate test in ``_near`` anyway; this drops it before it is enumerated (the same
    candidates survive)."""
    def rows(p, yy):
        cols = span(p, yy)
        i = torch.round(((1 - yy) * H - 1) / 2).long()
        row = faces.image.index_select(0, p) * H + i
        j0 = torch.maximum(cols[0], boxes.j0.index_select(0, p))
        j1 = torch.minimum(cols[1], boxes.j1.index_select(0, p))
        hidden = faces.zl_max.index_select(0, p) < row_min.query(row, j0, j1)
        return (cols[0], torch.where(hidden, -2, cols[1]), *cols[2:])

    return rows


@fused
def _near_values(table, zl_max, hidden_below, prim, pix, x, y, r2: float, keep_inside: bool):
    """Pass 2's maths for candidates ``[C]``: (keep mask, depth at the face's nearest point, squared
    distance to the triangle), each ``[C]``. Kept: within ``r2`` (squared NDC) and, unless
    ``keep_inside``, not covering the pixel; and, with ``hidden_below`` ``[num_pixels]``, not
    hidden (the face's largest depth logit ``zl_max[prim]`` at least ``hidden_below[pix]``)."""
    lam = barycentrics(table, prim, x, y)
    inside = covers(lam)
    sqd = triangle_sqdist(table, prim, x, y)
    near = sqd <= r2
    keep = (inside | near) if keep_inside else (~inside & near)
    if hidden_below is not None:
        keep = keep & (zl_max.index_select(0, prim) >= hidden_below.index_select(0, pix))
    # outside the triangle: depth at the nearest point (negative barycentrics clamped)
    lam = [lk.clamp(min=0) for lk in lam]
    total = lam[0] + lam[1] + lam[2]
    depth = total / inverse_depth(table, prim, lam).clamp(min=1e-12 * total)
    return keep, depth, sqd


# screen tiles of the hidden-face test: a face is skipped when it is hidden in every tile its box touches
HIDDEN_TILE = 8


def _hidden_faces(faces: _Faces, boxes: tiles.PixelBoxes, hidden_below: torch.Tensor, H: int, W: int) -> torch.Tensor:
    """``[Fs]`` True for faces hidden in every pixel of their (dilated) box: the face's largest depth
    logit is below ``hidden_below`` ``[num_images * H * W]`` everywhere there. Tested per
    ``HIDDEN_TILE`` tile (the minimum over its pixels) for boxes of up to 3 x 3 tiles; larger
    boxes are never skipped here."""
    T = HIDDEN_TILE
    nty, ntx = -(-H // T), -(-W // T)
    hb = hidden_below.view(-1, H, W)
    hb = F.pad(hb, (0, ntx * T - W, 0, nty * T - H), value=float("-inf"))
    tile_min = hb.view(-1, nty, T, ntx, T).amin((2, 4))  # [images, nty, ntx]
    ty0, ty1 = torch.div(boxes.i0, T, rounding_mode="floor"), torch.div(boxes.i1, T, rounding_mode="floor")
    tx0, tx1 = torch.div(boxes.j0, T, rounding_mode="floor"), torch.div(boxes.j1, T, rounding_mode="floor")
    flat = tile_min.reshape(-1)
    base = boxes.image * (nty * ntx)
    least = torch.full_like(faces.zl_max, float("inf"))
    for dy in range(3):
        ty = torch.minimum(ty0 + dy, ty1)
        for dx in range(3):
            tx = torch.minimum(tx0 + dx, tx1)
            least = torch.minimum(least, flat.index_select(0, base + ty * ntx + tx))
    small = (ty1 - ty0 <= 2) & (tx1 - tx0 <= 2)
    return small & (faces.zl_max < least)


def _cat(parts: list[tuple], n: int, faces: _Faces) -> tuple:
    if not parts:
        ref = faces.table
        return (torch.zeros(0, dtype=torch.long, device=ref.device), torch.zeros(0, dtype=torch.long, device=ref.device),
                *(torch.zeros(0, dtype=ref.dtype, device=ref.device) for _ in range(n - 2)))
    return tuple(torch.cat([p[i] for p in parts]) for i in range(n))


def saturated_log_miss(dtype: torch.dtype) -> float:
    """``log prod (1 - p)`` below which soft coverage ``1 - prod (1 - p)`` rounds to exactly 1."""
    return math.log(torch.finfo(dtype).eps) - 1.0


def rest_log_miss(pf: ProjectedFaces, sel: nearest.Selection, slots_log_miss: torch.Tensor, ranking: SoftRanking, *,
                  H: int, W: int) -> torch.Tensor:
    """Coverage of the candidates beyond the K slots: ``sum log(1 - p)`` per active pixel ``[P]``.

    Soft coverage is ``1 - prod (1 - p)`` over *every* face within the blur radius, not only the
    K that hold colour slots, so it does not depend on K. Only pixels whose slots
    (``slots_log_miss`` ``[P]``, their ``sum log(1 - p)``) leave more than
    ``ranking.coverage_tol`` uncovered need the rest (silhouette rims, occlusion contours); there
    the rest is recomputed differentiably, flat (one face per entry). Elsewhere it is 0, which
    changes coverage by less than ``coverage_tol``. Pixels the search found fully covered
    (``sel.base_log_miss``) get their covering faces' conservative bound instead, a constant: their
    coverage, exact or not, is within ``coverage_tol`` of 1.
    """
    P = len(sel.pix)
    out = torch.zeros(P, dtype=pf.vert_xy.dtype, device=pf.vert_xy.device)
    if sel.base_log_miss is not None:
        out = sel.base_log_miss.to(out.dtype)
    if sel.rest_pix is None or len(sel.rest_pix) == 0:
        return out
    with torch.no_grad():
        rim = slots_log_miss.detach() > ranking.log_tol(slots_log_miss.dtype)
        # the active-pixel index of each rest entry: a dense pixel -> row table (cheaper than a search)
        row = torch.full((pf.num_images * H * W,), -1, dtype=torch.long, device=sel.pix.device)
        row.index_copy_(0, sel.pix, torch.arange(P, device=sel.pix.device))
        owner = row.index_select(0, sel.rest_pix)
        keep = torch.nonzero(rim.index_select(0, owner)).squeeze(1)
    if len(keep) == 0:
        return out
    rest = nearest.Selection(sel.rest_pix.index_select(0, keep), sel.rest_prim.index_select(0, keep).unsqueeze(1))
    d = face_fragments(pf, rest, H=H, W=W, need_bary=False, need_dist=True, interior_edge=ranking.interior,
                       need_depth=False).dist[:, 0]
    return out.index_add(0, owner.index_select(0, keep), torch.nn.functional.logsigmoid(d / ranking.sigma))


def packed_slots(sel: nearest.Selection) -> tuple[nearest.Selection, torch.Tensor]:
    """The used slots of ``sel`` one per row: (Selection with pix ``[S]``, prim ``[S, 1]``; owner ``[S]``,
    the active-pixel index of each row). Soft mode shades and blends only these."""
    K = sel.prim.shape[1]
    used = sel.occupied()
    owner = torch.div(used, K, rounding_mode="floor")
    return nearest.Selection(sel.pix.index_select(0, owner), sel.prim.reshape(-1).index_select(0, used).unsqueeze(1)), owner
