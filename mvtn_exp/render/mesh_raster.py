"""Mesh rasterizer: K nearest faces per pixel (no autograd), then differentiable fragments.

Search (``search_faces``): all faces of all views are projected at once; faces behind the near
plane, outside the frustum, of zero screen area, and (optionally) back-facing are culled; the
rest go through the tile search of ``tiles.py`` (soft mode: ``soft_search.py``, built on the
pieces here). Only the winners are then recomputed with autograd (``face_fragments``): screen and
perspective-correct barycentrics, depth and the signed squared distance used for soft edges.
Backward memory therefore grows with the kept (pixel, face) pairs, not with pixels x faces.

Faces crossing the near plane are culled, not clipped (documented limitation).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from . import nearest, tiles
from .accel import fused
from .edge_distance import barycentric_signs, covers, edge_function, segment_sqdist, signed_sqdist
from .ops import take

# hard mode: face boxes of at most this many pixels are tested whole, larger ones go row by row
SMALL_BOX_HARD = 2


@dataclass
class ProjectedFaces:
    """Faces of every view in screen space. Face-view index ``fv = face * M + view``.

    cols: ``[9, F*M]`` rows x0, y0, z0, x1, y1, z1, x2, y2, z2: NDC x, y and depth of each corner,
    detached (for the search; one contiguous row per coordinate keeps the per-face work cheap);
    alive: ``[F*M]`` bool (survived culling); facing: ``[F*M]`` +1 front (counter-clockwise on
    screen), -1 back, 0 culled; vert_xy ``[V*M, 2]``, vert_z ``[V*M]``: differentiable vertex-view
    projections (vertex-view index ``v * M + view``); faces ``[F, 3]``; shape_of_face ``[F]``;
    views: M; num_images: B * M. Per-face-view indices are derived on demand for the faces that
    need them (``image_of``, ``corners_of``), never stored for all F*M.
    """

    cols: torch.Tensor
    alive: torch.Tensor
    facing: torch.Tensor
    vert_xy: torch.Tensor
    vert_z: torch.Tensor
    faces: torch.Tensor
    shape_of_face: torch.Tensor
    views: int
    num_images: int

    def image_of(self, fv: torch.Tensor) -> torch.Tensor:
        """Flat image index ``b * M + m`` of face-views ``fv`` (any shape)."""
        f = torch.div(fv, self.views, rounding_mode="floor")
        return take(self.shape_of_face, f) * self.views + (fv - f * self.views)

    def corners_of(self, fv: torch.Tensor) -> torch.Tensor:
        """Vertex-view indices ``[..., 3]`` of the corners of face-views ``fv``."""
        f = torch.div(fv, self.views, rounding_mode="floor")
        return take(self.faces, f) * self.views + (fv - f * self.views).unsqueeze(-1)

    @property
    def image(self) -> torch.Tensor:
        """``[F*M]`` flat image index of every face-view."""
        return self.image_of(torch.arange(self.cols.shape[1], device=self.cols.device))

    @property
    def xyz(self) -> torch.Tensor:
        """``[F*M, 3, 3]`` view: corner, (x, y, depth)."""
        return self.cols.t().view(-1, 3, 3)

    @property
    def xy(self) -> torch.Tensor:
        return self.xyz[..., :2]

    @property
    def z(self) -> torch.Tensor:
        return self.xyz[..., 2]


@dataclass
class Fragments:
    """Differentiable per-pixel data for the K winners of the active pixels.

    pix: ``[P]`` flat pixel index; fv: ``[P, K]`` face-view index (-1 empty); valid: ``[P, K]``;
    bary: ``[P, K, 3]`` perspective-correct barycentrics (None if not requested);
    zbuf: ``[P, K]`` depth (None when neither barycentrics nor distances are needed);
    dist: ``[P, K]`` signed squared NDC distance (None in hard mode).
    """

    pix: torch.Tensor
    fv: torch.Tensor
    valid: torch.Tensor
    bary: torch.Tensor | None
    zbuf: torch.Tensor | None
    dist: torch.Tensor | None


def area_eps(dtype: torch.dtype, H: int, W: int) -> float:
    """Smallest screen area (twice, NDC^2) treated as a real face: far below one pixel."""
    return 1e-4 * 4.0 / (H * W) if dtype == torch.float32 else 1e-9 * 4.0 / (H * W)


def cull(cols: torch.Tensor, *, znear: float, cull_backfaces: bool, H: int, W: int):
    """Culling mask and facing sign for face-views from corner rows ``[9, N]`` (see ProjectedFaces).

    Faces outside the frustum need no test here: their pixel boxes are empty in the search.
    """
    with torch.no_grad():
        x0, y0, z0, x1, y1, z1, x2, y2, z2 = cols
        area2 = edge_function(x0, y0, x1, y1, x2, y2)
        alive = (z0 >= znear) & (z1 >= znear) & (z2 >= znear)
        alive &= area2.abs() > area_eps(cols.dtype, H, W)
        if cull_backfaces:
            alive &= area2 > 0
        facing = torch.where(alive, torch.sign(area2), torch.zeros_like(area2)).to(torch.int8)
    return alive, facing


def face_planes(x0, y0, x1, y1, x2, y2) -> list[torch.Tensor]:
    """Screen barycentrics as planes: lambda_k = A_k x + B_k y + C_k for the corners k = 0, 1, 2.

    Inputs are ``[N]`` corner coordinates; returns [A0, B0, C0, A1, B1, C1, A2, B2, C2], each ``[N]``.
    Faces must have non-zero area (culled otherwise).
    """
    inv = 1.0 / edge_function(x0, y0, x1, y1, x2, y2)
    out = []
    for (ax, ay), (bx, by) in (((x1, y1), (x2, y2)), ((x2, y2), (x0, y0)), ((x0, y0), (x1, y1))):
        ex, ey = (bx - ax) * inv, (by - ay) * inv
        out += [-ey, ex, ey * ax - ex * ay]
    return out


# rows of a face table (``face_table``): barycentric planes, inverse corner depths, corners
TABLE_PLANES, TABLE_INV_Z, TABLE_CORNERS = 0, 9, 12


def face_table(cols: torch.Tensor) -> torch.Tensor:
    """Corner rows ``[9, N]`` (see ProjectedFaces) -> ``[18, N]``, one contiguous row per quantity:
    A0, B0, C0, A1, B1, C1, A2, B2, C2 (``face_planes``), 1/z0, 1/z1, 1/z2, x0, y0, x1, y1, x2, y2.

    Candidates gather from it row by row (``barycentrics``, ``inverse_depth``, ``triangle_sqdist``):
    on CPU a 1-D ``index_select`` costs about a third per value of one over an ``[N, 12]`` table.
    """
    x0, y0, z0, x1, y1, z1, x2, y2, z2 = cols
    return torch.stack(face_planes(x0, y0, x1, y1, x2, y2) + [1.0 / z0, 1.0 / z1, 1.0 / z2, x0, y0, x1, y1, x2, y2])


def table_planes(table: torch.Tensor) -> list[torch.Tensor]:
    """The nine plane rows of a face table, as ``face_planes`` returns them."""
    return list(table[TABLE_PLANES:TABLE_PLANES + 9].unbind(0))


@fused
def barycentrics(table: torch.Tensor, prim: torch.Tensor, x: torch.Tensor, y: torch.Tensor) -> list[torch.Tensor]:
    """Screen barycentrics ``[lambda_0, lambda_1, lambda_2]``, each ``[C]``, of the points x, y ``[C]``
    (NDC) in faces ``prim`` ``[C]`` (columns of ``table``)."""
    def g(r):
        return table[r].index_select(0, prim)

    return [torch.addcmul(torch.addcmul(g(3 * k + 2), g(3 * k), x), g(3 * k + 1), y) for k in range(3)]


@fused
def inverse_depth(table: torch.Tensor, prim: torch.Tensor, lam: list[torch.Tensor]) -> torch.Tensor:
    """``sum_k lambda_k / z_k`` ``[C]``: the inverse depth at screen barycentrics ``lam`` in faces ``prim``."""
    iz = [table[TABLE_INV_Z + k].index_select(0, prim) for k in range(3)]
    return torch.addcmul(torch.addcmul(lam[0] * iz[0], lam[1], iz[1]), lam[2], iz[2])


@fused
def triangle_sqdist(table: torch.Tensor, prim: torch.Tensor, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Squared NDC distance ``[C]`` from the points x, y ``[C]`` to the triangles ``prim`` (their edges;
    callers tell inside from outside by the barycentrics)."""
    c = [table[TABLE_CORNERS + r].index_select(0, prim) for r in range(6)]
    d = segment_sqdist(c[2], c[3], c[4], c[5], x, y)
    d = torch.minimum(d, segment_sqdist(c[4], c[5], c[0], c[1], x, y))
    return torch.minimum(d, segment_sqdist(c[0], c[1], c[2], c[3], x, y))


# the hole of a ring (``row_spans(hole=...)``): pixels at least this far (NDC) inside every edge of
# the triangle, far above the rounding of the span arithmetic while edges are not near-horizontal
HOLE_MARGIN = 1e-3
HOLE_MAX_SLOPE = 1e2


def row_spans(planes: list[torch.Tensor], boxes: tiles.PixelBoxes, radius: float, small_box: int, W: int,
              hole: tuple[torch.Tensor, torch.Tensor] | None = None):
    """``span(prim, y) -> (j0, j1)`` for ``tiles.candidate_chunks``: per face and box row, the pixel
    columns within ``radius`` (NDC) of the triangle. planes: ``face_planes`` of the boxes' faces.

    Edge k (moved outward by the radius plus rounding slack) bounds x at height y by
    x = s_k y + t_k, from the left when A_k > 0, from the right when A_k < 0; edges with A_k = 0
    are horizontal and never bound a row inside the face's box. Only faces whose box has more
    than ``small_box`` pixels go row by row.

    hole: the faces' own vertical extent (ymin, ymax) ``[N]``: then ``span`` also returns the
    columns (h0, h1) surely inside the triangle (``HOLE_MARGIN`` inside every edge; empty for
    faces with a near-horizontal side edge), which a search for the faces *near* a pixel but not
    covering it can skip: it then enumerates a ring, not the whole dilated triangle.
    """
    n = len(boxes.j0)
    big = torch.nonzero(boxes.sizes() > small_box).squeeze(1)
    row_of = torch.full((n,), -1, dtype=torch.long, device=big.device)
    row_of[big] = torch.arange(len(big), device=big.device)
    A = torch.stack([planes[k].index_select(0, big) for k in (0, 3, 6)], 1)
    Bp = torch.stack([planes[k].index_select(0, big) for k in (1, 4, 7)], 1)
    Cp = torch.stack([planes[k].index_select(0, big) for k in (2, 5, 8)], 1)
    norm = torch.sqrt(A * A + Bp * Bp)
    safe = torch.where(A == 0, torch.ones_like(A), A)
    slope = -Bp / safe
    inf = torch.full_like(A, float("inf"))
    zero = torch.zeros_like(A)

    def intercepts(r):  # left bounds of the three edges, then right bounds, moved out by r
        icpt = -(Cp + r * norm) / safe
        return [torch.where(A > 0, icpt, -inf), torch.where(A < 0, icpt, inf)]

    left, right = intercepts(radius + 1e-5)
    # per face: left bounds (slope, intercept) of the three edges, then right bounds; one contiguous
    # row each, so a box row gathers 1-D values (see ``face_table``)
    rowtab = torch.cat([torch.where(A > 0, slope, zero), left, torch.where(A < 0, slope, zero), right], 1).t().contiguous()
    if hole is not None:
        hl, hr = intercepts(-HOLE_MARGIN)
        steep = ((slope.abs() <= HOLE_MAX_SLOPE) | (A == 0)).all(1)
        ylo = torch.where(steep, hole[0].index_select(0, big) + HOLE_MARGIN, inf[:, 0])
        holetab = torch.cat([hl, hr, ylo[:, None], hole[1].index_select(0, big)[:, None] - HOLE_MARGIN], 1).t().contiguous()

    def bounds(g, lo_rows, hi_rows, yy):
        lo = torch.maximum(torch.maximum(torch.addcmul(lo_rows[0], g[0], yy), torch.addcmul(lo_rows[1], g[1], yy)),
                           torch.addcmul(lo_rows[2], g[2], yy))
        hi = torch.minimum(torch.minimum(torch.addcmul(hi_rows[0], g[6], yy), torch.addcmul(hi_rows[1], g[7], yy)),
                           torch.addcmul(hi_rows[2], g[8], yy))
        return lo, hi

    def span(p, yy):
        r = row_of.index_select(0, p)
        g = [rowtab[k].index_select(0, r) for k in range(12)]
        j0, j1 = tiles.columns(*bounds(g, g[3:6], g[9:12], yy), W)
        if hole is None:
            return j0, j1
        h = [holetab[k].index_select(0, r) for k in range(8)]
        lo, hi = bounds(g, h[0:3], h[3:6], yy)
        lo = torch.where((yy < h[6]) | (yy > h[7]), float("inf"), lo)  # rows outside the face: no hole
        return (j0, j1, *tiles.columns(lo, hi, W))

    return span


def face_boxes(cols: torch.Tensor, image: torch.Tensor, radius: float, H: int, W: int) -> tiles.PixelBoxes:
    """Pixel boxes of faces (corner rows ``[9, N]``, see ProjectedFaces) dilated by ``radius`` (NDC)."""
    x0, y0, _, x1, y1, _, x2, y2, _ = cols
    return tiles.pixel_boxes(
        torch.minimum(torch.minimum(x0, x1), x2) - radius, torch.maximum(torch.maximum(x0, x1), x2) + radius,
        torch.minimum(torch.minimum(y0, y1), y2) - radius, torch.maximum(torch.maximum(y0, y1), y2) + radius,
        image, H, W,
    )


def search_faces(pf: ProjectedFaces, *, H: int, W: int, K: int, blur_radius: float, tile_size: int, max_candidates: int,
                 ranking: "soft_search.SoftRanking | None" = None, overflow=None) -> nearest.Selection:
    """K best faces per pixel among faces whose triangle is within ``blur_radius`` (NDC).

    Hard mode (``blur_radius == 0``): the K nearest covering faces. Soft mode: ``soft_search.search``
    (the K faces of largest blend logit, and the rest for coverage).
    """
    with torch.no_grad():
        if blur_radius > 0:
            from . import soft_search  # it builds on this module

            if ranking is None:
                raise ValueError("search_faces: soft mode (blur_radius > 0) needs a SoftRanking")
            return soft_search.search(pf, H=H, W=W, K=K, blur_radius=blur_radius, tile_size=tile_size,
                                      max_candidates=max_candidates, ranking=ranking, overflow=overflow)
        num_pixels = pf.num_images * H * W
        if K > 1:
            return nearest.merge(list(_hard_picks(pf, 0, pf.cols.shape[1], H, W, K, tile_size, max_candidates, num_pixels,
                                                overflow)), K, pf.cols.device)
        # K = 1: winners of runs of face-views combine (``nearest.nearest_one``), so the per-face work
        # (boxes, face tables, row spans) is done a slice at a time: memory bounded for any batch
        n, step = pf.cols.shape[1], max(1, max_candidates // 8)
        picks = [p for a in range(0, n, step) for p in _hard_picks(pf, a, min(n, a + step), H, W, 1, tile_size,
                                                                      max_candidates, num_pixels, overflow)]
        if len(picks) != 1:
            picks = [nearest.nearest_one(*(torch.cat(t) for t in zip(*picks)), num_pixels)] if picks else []
        empty = torch.zeros(0, dtype=torch.long, device=pf.cols.device)
        pix, _, best = picks[0] if picks else (empty, None, empty)
        return nearest.Selection(pix, best.unsqueeze(1), used=len(pix))  # (every pixel's one slot is used)


def _hard_picks(pf: ProjectedFaces, start: int, stop: int, H: int, W: int, K: int, tile_size: int, max_candidates: int,
                num_pixels: int, overflow=None):
    """The nearest covering faces among face-views ``start:stop``, per candidate chunk: K = 1
    ``nearest.nearest_one`` triples (chunks of consecutive faces), else ``nearest.select_nearest``
    selections (whole pixels per chunk)."""
    cols = pf.cols[:, start:stop]
    boxes = face_boxes(cols, None, 0.0, H, W)
    # culled faces, and faces whose box holds no pixel centre (off-screen, or tiny between
    # centres), stop here
    keep = torch.nonzero(pf.alive[start:stop] & (boxes.sizes() > 0)).squeeze(1)
    fv = keep + start
    cols = cols.index_select(1, keep)
    boxes = tiles.PixelBoxes(pf.image_of(fv), *(t.index_select(0, keep) for t in (boxes.j0, boxes.j1, boxes.i0, boxes.i1)))
    table = face_table(cols)
    span = row_spans(table_planes(table), boxes, 0.0, SMALL_BOX_HARD, W)
    # faces covering each pixel, depth from the barycentric planes
    for parts in tiles.candidate_chunks(boxes, H, W, tile_size, max_candidates, cols.dtype, span, SMALL_BOX_HARD,
                                        by_primitive=K == 1, overflow=overflow):
        cand = tiles.concat(parts)
        lam = barycentrics(table, cand.prim, cand.x, cand.y)
        inside = torch.nonzero(covers(lam)).squeeze(1)
        prim = cand.prim.index_select(0, inside)
        depth = 1.0 / inverse_depth(table, prim, [l.index_select(0, inside) for l in lam]).clamp(min=1e-12)
        pix, ids = cand.pix.index_select(0, inside), fv.index_select(0, prim)
        yield (nearest.nearest_one(pix, depth, ids, num_pixels) if K == 1
               else nearest.select_nearest(pix, depth, ids, K, num_pixels))


@fused
def _depth_and_bary(X, Y, Z, px, py, valid, need_bary: bool):
    """Perspective-correct depth ``[P, K]`` and barycentrics ``[P, K, 3]`` (None unless ``need_bary``)
    of pixel centres px, py ``[P, 1]`` in triangles with corners X, Y (NDC) and depths Z, each a
    triple of ``[P, K]``; outside a triangle (soft edges) at its nearest point. Empty slots
    (``valid`` False) get depth 0."""
    lam = barycentric_signs(X, Y, px, py)
    with torch.no_grad():
        inside = covers(lam)
    # outside the triangle (soft edges) attributes come from the nearest point of the triangle;
    # in components (``ops.dot``): no size-3 reductions
    lam = [torch.where(inside, lk, lk.clamp(min=0)) for lk in lam]
    total = (lam[0] + lam[1] + lam[2]).clamp(min=1e-12)
    zinv = [lk / total / zk.clamp(min=1e-12) for lk, zk in zip(lam, Z)]
    zsum = (zinv[0] + zinv[1] + zinv[2]).clamp(min=1e-12)
    zbuf = torch.where(valid, 1.0 / zsum, torch.zeros_like(zsum))
    return zbuf, (torch.stack([zk / zsum for zk in zinv], -1) if need_bary else None)


def face_fragments(pf: ProjectedFaces, sel: nearest.Selection, *, H: int, W: int, need_bary: bool,
                   need_dist: bool, interior_edge: torch.Tensor | None, need_depth: bool = True) -> Fragments:
    """Differentiable barycentrics / depth / signed distance for the selected (pixel, face) pairs.

    interior_edge: ``[F*M, 3]`` bool, True where an edge is shared with a neighbour facing the same
    way in that view; such edges are ignored by the inside distance (no wireframe in soft
    silhouettes: the coverage of a closed surface does not dip at its internal edges).
    need_depth: False with ``need_bary=False`` gives the distances alone (``zbuf`` None; soft
    coverage of the rest faces). Distances come from ``edge_distance.signed_sqdist`` (its own backward).
    """
    valid = sel.prim >= 0
    if not (need_bary or need_dist):
        # hard flat shading needs no per-pixel geometry at all: colours are per face
        return Fragments(sel.pix, sel.prim, valid, None, None, None)
    fv = sel.prim.clamp(min=0)
    px, py = tiles.pixel_centres(sel.pix, H, W, pf.cols.dtype)
    px, py = px[:, None], py[:, None]
    vv = pf.corners_of(fv)  # [P, K, 3] vertex-view ids
    dist = None
    if need_dist:
        dist = signed_sqdist(pf.vert_xy, vv.reshape(-1, 3), px.expand_as(valid).reshape(-1), py.expand_as(valid).reshape(-1),
                             None if interior_edge is None else take(interior_edge, fv).reshape(-1, 3),
                             valid.reshape(-1)).view(valid.shape)
    if not (need_bary or need_depth):
        return Fragments(sel.pix, sel.prim, valid, None, None, dist)
    X = take(pf.vert_xy[:, 0], vv).unbind(-1)  # corner x, y, each [P, K]
    Y = take(pf.vert_xy[:, 1], vv).unbind(-1)
    zbuf, bary = _depth_and_bary(X, Y, take(pf.vert_z, vv).unbind(-1), px, py, valid, need_bary)
    return Fragments(sel.pix, sel.prim, valid, bary, zbuf, dist)
