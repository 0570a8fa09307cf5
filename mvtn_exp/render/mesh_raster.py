"""Mesh rasterizer: K nearest faces per pixel (no autograd), then differentiable fragments.

Search (``search_faces``): all faces of all views are projected at once; faces behind the near
plane, outside the frustum, of zero screen area, and (optionally) back-facing are culled; the
rest go through the tile search of ``tiles.py``. Only the winners are then recomputed with
autograd (``face_fragments``): screen and perspective-correct barycentrics, depth and the signed
squared distance used for soft edges. Backward memory therefore grows with pixels x K, not with
pixels x faces.

Faces crossing the near plane are culled, not clipped (documented limitation).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from . import tiles
from .ops import take

# far beyond any on-screen squared NDC distance: "no boundary edge near this pixel"
FAR_SQ = 1.0e4
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


def _edge(ax, ay, bx, by, px, py):
    """Twice the signed area of (a, b, p): positive when p is left of a->b."""
    return (bx - ax) * (py - ay) - (by - ay) * (px - ax)


def area_eps(dtype: torch.dtype, H: int, W: int) -> float:
    """Smallest screen area (twice, NDC^2) treated as a real face: far below one pixel."""
    return 1e-4 * 4.0 / (H * W) if dtype == torch.float32 else 1e-9 * 4.0 / (H * W)


def cull(cols: torch.Tensor, *, znear: float, cull_backfaces: bool, H: int, W: int):
    """Culling mask and facing sign for face-views from corner rows ``[9, N]`` (see ProjectedFaces).

    Faces outside the frustum need no test here: their pixel boxes are empty in the search.
    """
    with torch.no_grad():
        x0, y0, z0, x1, y1, z1, x2, y2, z2 = cols
        area2 = _edge(x0, y0, x1, y1, x2, y2)
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
    inv = 1.0 / _edge(x0, y0, x1, y1, x2, y2)
    out = []
    for (ax, ay), (bx, by) in (((x1, y1), (x2, y2)), ((x2, y2), (x0, y0)), ((x0, y0), (x1, y1))):
        ex, ey = (bx - ax) * inv, (by - ay) * inv
        out += [-ey, ex, ey * ax - ex * ay]
    return out


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


def search_faces(pf: ProjectedFaces, *, H: int, W: int, K: int, blur_radius: float, tile_size: int, max_candidates: int,
                 ranking: SoftRanking | None = None) -> tiles.Selection:
    """K best faces per pixel among faces whose triangle is within ``blur_radius`` (NDC).

    Hard mode (``blur_radius == 0``): the K nearest covering faces. Soft mode: the K faces of
    largest blend logit (``ranking``), i.e. the K largest colour weights; the other candidates
    come back as ``rest_pix`` / ``rest_prim`` so that coverage can count every face within the
    blur radius, whatever K is.
    """
    with torch.no_grad():
        x0, y0, z0, x1, y1, z1, x2, y2, z2 = pf.cols
        boxes = tiles.pixel_boxes(
            torch.minimum(torch.minimum(x0, x1), x2) - blur_radius, torch.maximum(torch.maximum(x0, x1), x2) + blur_radius,
            torch.minimum(torch.minimum(y0, y1), y2) - blur_radius, torch.maximum(torch.maximum(y0, y1), y2) + blur_radius,
            None, H, W,
        )
        # culled faces, and faces whose box holds no pixel centre (off-screen, or tiny between
        # centres), stop here
        fv = torch.nonzero(pf.alive & (boxes.sizes() > 0)).squeeze(1)
        cols = pf.cols.index_select(1, fv)
        boxes = tiles.PixelBoxes(pf.image_of(fv), *(t.index_select(0, fv) for t in (boxes.j0, boxes.j1, boxes.i0, boxes.i1)))
        x0, y0, z0, x1, y1, z1, x2, y2, z2 = cols
        planes = face_planes(x0, y0, x1, y1, x2, y2)
        iz = [1.0 / z0, 1.0 / z1, 1.0 / z2]
        # row spans, for the faces whose box goes row by row: edge k (moved outward by the blur
        # radius plus rounding slack) bounds x at height y by x = s_k y + t_k, from the left when
        # A_k > 0, from the right when A_k < 0; edges with A_k = 0 are horizontal and never bound
        # a row inside the face's box
        small_box = SMALL_BOX_HARD if blur_radius == 0 else tiles.SMALL_BOX
        big = torch.nonzero(boxes.sizes() > small_box).squeeze(1)
        row_of = torch.full((len(fv),), -1, dtype=torch.long, device=fv.device)
        row_of[big] = torch.arange(len(big), device=fv.device)
        A = torch.stack([planes[k].index_select(0, big) for k in (0, 3, 6)], 1)
        Bp = torch.stack([planes[k].index_select(0, big) for k in (1, 4, 7)], 1)
        Cp = torch.stack([planes[k].index_select(0, big) for k in (2, 5, 8)], 1)
        Cp = Cp + (blur_radius + 1e-5) * torch.sqrt(A * A + Bp * Bp)
        safe = torch.where(A == 0, torch.ones_like(A), A)
        slope, icpt = -Bp / safe, -Cp / safe
        inf = torch.full_like(A, float("inf"))
        zero = torch.zeros_like(A)
        rowtab = torch.cat([torch.where(A > 0, slope, zero), torch.where(A > 0, icpt, -inf),
                            torch.where(A < 0, slope, zero), torch.where(A < 0, icpt, inf)], 1)  # [Fbig, 12]

        def span(p, yy):
            r = rowtab.index_select(0, row_of.index_select(0, p))
            yc = yy[:, None]
            return tiles.columns((r[:, 0:3] * yc + r[:, 3:6]).amax(1), (r[:, 6:9] * yc + r[:, 9:12]).amin(1), W)

        num_pixels = pf.num_images * H * W
        picks = []
        table = torch.stack(planes + iz, 1)  # [Fs, 12]: barycentric planes, inverse corner depths
        if blur_radius == 0:
            # hard mode: faces covering each pixel, depth from the barycentric planes
            for parts in tiles.candidate_chunks(boxes, H, W, tile_size, max_candidates, cols.dtype, span, small_box):
                cand = tiles.concat(parts)
                t = table.index_select(0, cand.prim)
                lam = t[:, 0:9:3] * cand.x[:, None] + t[:, 1:9:3] * cand.y[:, None] + t[:, 2:9:3]
                keep = torch.nonzero((lam >= 0).all(1)).squeeze(1)
                depth = 1.0 / (lam[keep] * t[keep, 9:12]).sum(1).clamp(min=1e-12)
                picks.append(tiles.select_nearest(cand.pix[keep], depth, fv.index_select(0, cand.prim[keep]), K, num_pixels))
            return tiles.merge(picks, K, pf.cols.device)
        # soft mode: candidates within the dilated span, tested exactly against the blur radius
        if ranking is None:
            raise ValueError("search_faces: soft mode (blur_radius > 0) needs a SoftRanking")
        xy = torch.stack([x0, y0, x1, y1, x2, y2], 1).view(-1, 3, 2)
        for parts in tiles.candidate_chunks(boxes, H, W, tile_size, max_candidates, cols.dtype, span, small_box):
            cand = tiles.concat(parts)
            picks.append(_soft_chunk(cand, table, xy, fv, ranking, blur_radius, K, H * W, num_pixels))
        return tiles.merge(picks, K, pf.cols.device)


def _soft_chunk(cand: tiles.Candidates, table, xy, fv, ranking: SoftRanking, blur_radius: float, K: int,
                image_pixels: int, num_pixels: int) -> tiles.Selection:
    """One chunk of the soft search: blur-radius test, pruning, K best by logit, and the rest.

    Pruning, in pixels whose covering faces alone leave less than ``ranking.coverage_tol``
    uncovered (a conservative bound: the distance to an edge's line never exceeds the distance
    to the edge): faces that do not cover the pixel and trail its nearest covering face by more
    than ``ranking.depth_window`` in logit are dropped before any distance is computed (hidden, they add
    neither colour nor coverage), and those that do not get a slot are not returned as rest.
    Elsewhere (rims) every face within the blur radius is kept for coverage. Everywhere, a slot
    goes only to faces whose logit is within ``depth_window`` of the pixel's largest: the others
    would weigh less than ``exp(-depth_window)`` of it in the colour and count only for coverage.
    """
    t = table.index_select(0, cand.prim)
    lam = t[:, 0:9:3] * cand.x[:, None] + t[:, 1:9:3] * cand.y[:, None] + t[:, 2:9:3]  # [C, 3]
    inside = (lam >= 0).all(1)
    lc = lam.clamp(min=0)
    depth = 1.0 / ((lc / lc.sum(1, keepdim=True)) * t[:, 9:12]).sum(1).clamp(min=1e-12)
    fvc = fv.index_select(0, cand.prim)
    image = torch.div(cand.pix, image_pixels, rounding_mode="floor")
    zl = ranking.depth_logit(image, depth)
    outside = torch.nonzero(~inside).squeeze(1)
    sat = None
    if not ranking.by_depth:
        ins = torch.nonzero(inside).squeeze(1)
        base = cand.pix.min() if len(cand.pix) else 0
        local = cand.pix - base
        n = int(local.max()) + 1 if len(local) else 0
        ti = t.index_select(0, ins)
        dl = lam.index_select(0, ins) / torch.sqrt(ti[:, 0:9:3] ** 2 + ti[:, 1:9:3] ** 2)  # [n, 3] to edge lines
        if ranking.interior is not None:
            dl = torch.where(ranking.interior.index_select(0, fvc.index_select(0, ins)), torch.full_like(dl, 1e2), dl)
        dmin = dl.amin(1).clamp(max=1e2)
        miss = torch.zeros(n, dtype=lam.dtype, device=lam.device).index_add_(
            0, local.index_select(0, ins), torch.nn.functional.logsigmoid(-dmin * dmin / ranking.sigma))
        best = torch.full((n,), float("-inf"), dtype=lam.dtype, device=lam.device).scatter_reduce_(
            0, local.index_select(0, ins), zl.index_select(0, ins), "amax")
        sat = miss < ranking.log_tol(lam.dtype)
        lo = local.index_select(0, outside)
        hidden = sat.index_select(0, lo) & (zl.index_select(0, outside) < best.index_select(0, lo) - (math.log(2.0) + ranking.depth_window))
        outside = outside[~hidden]
    sqd = torch.full_like(cand.x, -FAR_SQ)  # covering: log p taken as 0 in the ranking
    fo = xy.index_select(0, cand.prim.index_select(0, outside))
    sqd[outside] = point_triangle_sqdist(fo[..., 0], fo[..., 1], cand.x.index_select(0, outside), cand.y.index_select(0, outside))
    near = inside.clone()
    near[outside] = sqd.index_select(0, outside) <= blur_radius**2
    keep = torch.nonzero(near).squeeze(1)
    pk = cand.pix.index_select(0, keep)
    if ranking.by_depth:
        return tiles.select_nearest(pk, depth.index_select(0, keep), fvc.index_select(0, keep), K, num_pixels)
    score = -(zl.index_select(0, keep) + torch.nn.functional.logsigmoid(-sqd.index_select(0, keep) / ranking.sigma))
    lk = local.index_select(0, keep)
    # a slot only for faces whose colour weight is within exp(-depth_window) of the pixel's largest
    least = torch.full((n,), float("inf"), dtype=score.dtype, device=score.device).scatter_reduce_(0, lk, score, "amin")
    slot_ok = score <= least.index_select(0, lk) + ranking.depth_window
    rest_ok = inside.index_select(0, keep) | ~sat.index_select(0, lk)
    return tiles.select_nearest(pk, score, fvc.index_select(0, keep), K, num_pixels, keep_rest=True,
                                rest_mask=rest_ok, slot_mask=slot_ok)


def _segment_sqdist(ax, ay, bx, by, px, py):
    """Squared distance from p to segment ab (all ``[...]``); safe for a == b."""
    ex, ey = bx - ax, by - ay
    ll = (ex * ex + ey * ey).clamp(min=1e-30)
    t = (((px - ax) * ex + (py - ay) * ey) / ll).clamp(0, 1)
    dx, dy = px - ax - t * ex, py - ay - t * ey
    return dx * dx + dy * dy


def edge_sqdists(fx, fy, px, py) -> torch.Tensor:
    """Squared distances to the three edges (v1v2, v2v0, v0v1), stacked on the last dim."""
    return torch.stack([
        _segment_sqdist(fx[..., 1], fy[..., 1], fx[..., 2], fy[..., 2], px, py),
        _segment_sqdist(fx[..., 2], fy[..., 2], fx[..., 0], fy[..., 0], px, py),
        _segment_sqdist(fx[..., 0], fy[..., 0], fx[..., 1], fy[..., 1], px, py),
    ], -1)


def point_triangle_sqdist(fx, fy, px, py) -> torch.Tensor:
    return edge_sqdists(fx, fy, px, py).min(-1).values


def face_fragments(pf: ProjectedFaces, sel: tiles.Selection, *, H: int, W: int, need_bary: bool,
                   need_dist: bool, interior_edge: torch.Tensor | None) -> Fragments:
    """Differentiable barycentrics / depth / signed distance for the selected (pixel, face) pairs.

    interior_edge: ``[F*M, 3]`` bool, True where an edge is shared with a neighbour facing the same
    way in that view; such edges are ignored by the inside distance (no wireframe in soft
    silhouettes: the coverage of a closed surface does not dip at its internal edges).
    """
    valid = sel.prim >= 0
    if not (need_bary or need_dist):
        # hard flat shading needs no per-pixel geometry at all: colours are per face
        return Fragments(sel.pix, sel.prim, valid, None, None, None)
    fv = sel.prim.clamp(min=0)
    px, py = tiles.pixel_centres(sel.pix, H, W, pf.cols.dtype)
    px, py = px[:, None], py[:, None]
    vv = pf.corners_of(fv)  # [P, K, 3] vertex-view ids
    xy = take(pf.vert_xy, vv)  # [P, K, 3, 2]
    fx, fy = xy[..., 0], xy[..., 1]
    a = _edge(fx[..., 0], fy[..., 0], fx[..., 1], fy[..., 1], fx[..., 2], fy[..., 2])
    a = torch.where(a.abs() > 1e-30, a, torch.ones_like(a))  # empty slots only (real faces: culled if ~0)
    l0 = _edge(fx[..., 1], fy[..., 1], fx[..., 2], fy[..., 2], px, py) / a
    l1 = _edge(fx[..., 2], fy[..., 2], fx[..., 0], fy[..., 0], px, py) / a
    l2 = _edge(fx[..., 0], fy[..., 0], fx[..., 1], fy[..., 1], px, py) / a
    lam = torch.stack([l0, l1, l2], -1)
    with torch.no_grad():
        inside = (lam >= 0).all(-1)
    dist = None
    if need_dist:
        d = edge_sqdists(fx, fy, px, py)
        outside_d = d.min(-1).values
        if interior_edge is not None:
            d = torch.where(interior_edge[fv], torch.full_like(d, FAR_SQ), d)
        dist = torch.where(inside, -d.min(-1).values, outside_d)
        dist = torch.where(valid, dist, torch.full_like(dist, FAR_SQ))
    # outside the triangle (soft edges) attributes come from the nearest point of the triangle
    lam = torch.where(inside.unsqueeze(-1), lam, lam.clamp(min=0))
    lam = lam / lam.sum(-1, keepdim=True).clamp(min=1e-12)
    zinv = lam / take(pf.vert_z, vv).clamp(min=1e-12)
    zsum = zinv.sum(-1).clamp(min=1e-12)
    zbuf = torch.where(valid, 1.0 / zsum, torch.zeros_like(zsum))
    bary = zinv / zsum.unsqueeze(-1) if need_bary else None
    return Fragments(sel.pix, sel.prim, valid, bary, zbuf, dist)


def saturated_log_miss(dtype: torch.dtype) -> float:
    """``log prod (1 - p)`` below which soft coverage ``1 - prod (1 - p)`` rounds to exactly 1."""
    return math.log(torch.finfo(dtype).eps) - 1.0


def rest_log_miss(pf: ProjectedFaces, sel: tiles.Selection, slots_log_miss: torch.Tensor, ranking: SoftRanking, *,
                  H: int, W: int) -> torch.Tensor:
    """Coverage of the candidates beyond the K slots: ``sum log(1 - p)`` per active pixel ``[P]``.

    Soft coverage is ``1 - prod (1 - p)`` over *every* face within the blur radius, not only the
    K that hold colour slots, so it does not depend on K. Only pixels whose slots
    (``slots_log_miss`` ``[P]``, their ``sum log(1 - p)``) leave more than
    ``ranking.coverage_tol`` uncovered need the rest (silhouette rims, occlusion contours); there
    the rest is recomputed differentiably, flat (one face per entry). Elsewhere it is 0, which
    changes coverage by less than ``coverage_tol``.
    """
    P = len(sel.pix)
    out = torch.zeros(P, dtype=pf.vert_xy.dtype, device=pf.vert_xy.device)
    if sel.rest_pix is None or len(sel.rest_pix) == 0:
        return out
    with torch.no_grad():
        rim = slots_log_miss.detach() > ranking.log_tol(slots_log_miss.dtype)
        owner = torch.searchsorted(sel.pix, sel.rest_pix)
        keep = torch.nonzero(rim.index_select(0, owner)).squeeze(1)
    if len(keep) == 0:
        return out
    rest = tiles.Selection(sel.rest_pix.index_select(0, keep), sel.rest_prim.index_select(0, keep).unsqueeze(1))
    d = face_fragments(pf, rest, H=H, W=W, need_bary=False, need_dist=True, interior_edge=ranking.interior).dist[:, 0]
    return out.index_add(0, owner.index_select(0, keep), torch.nn.functional.logsigmoid(d / ranking.sigma))


def packed_slots(sel: tiles.Selection) -> tuple[tiles.Selection, torch.Tensor]:
    """The used slots of ``sel`` one per row: (Selection with pix ``[S]``, prim ``[S, 1]``; owner ``[S]``,
    the active-pixel index of each row). Soft mode shades and blends only these."""
    K = sel.prim.shape[1]
    used = sel.occupied()
    owner = torch.div(used, K, rounding_mode="floor")
    return tiles.Selection(sel.pix.index_select(0, owner), sel.prim.reshape(-1).index_select(0, used).unsqueeze(1)), owner
