"""Signed squared distance from pixel centres to triangles, with a hand-written backward.

Soft coverage needs, for every (pixel, face) pair the search keeps (a few hundred thousand slots and
up to a million rim entries per batch), the squared NDC distance to the nearest edge, negative
inside. Through autograd that is about fifty small ops per pair, each saving its inputs; here the
forward runs without a graph and keeps, per pair, only the nearest edge's end points, its
parameter t and the residual r, which is all the gradient needs:

    d = s |p - a - t (b - a)|^2,  t in [0, 1] the nearest point of the segment ab,
    dd/da = -2 s (1 - t) r,  dd/db = -2 s t r,  r = p - a - t (b - a)

(the derivative through t vanishes: at an interior optimum r is normal to the edge, at a clamped end
t is constant). s is +1 outside the triangle, -1 inside, 0 where d is the constant ``FAR_SQ``.
"""
from __future__ import annotations

import torch

from .accel import fused

# far beyond any on-screen squared NDC distance: "no boundary edge near this pixel"
FAR_SQ = 1.0e4

# edge k joins corners EDGES[k] (the edge opposite corner k)
EDGES = ((1, 2), (2, 0), (0, 1))


def edge_function(ax, ay, bx, by, px, py):
    """Twice the signed area of (a, b, p): positive when p is left of a->b."""
    return (bx - ax) * (py - ay) - (by - ay) * (px - ax)


def triangle_area2(X, Y):
    """Twice the signed area of triangles given as corner lists ``X, Y`` (3 x ``[...]``); an
    exactly zero area (only empty slots: real zero-area faces are culled) becomes 1."""
    area = edge_function(X[0], Y[0], X[1], Y[1], X[2], Y[2])
    return torch.where(area.abs() > 1e-30, area, torch.ones_like(area))


def barycentric_signs(X, Y, px, py) -> list:
    """Screen barycentrics ``[lambda_0, lambda_1, lambda_2]`` of p in triangles ``X, Y`` (differentiable)."""
    area = triangle_area2(X, Y)
    return [edge_function(X[a], Y[a], X[b], Y[b], px, py) / area for a, b in EDGES]


def covers(lam: list) -> torch.Tensor:
    """True where all three barycentrics are >= 0 (the point is inside or on the triangle)."""
    return (lam[0] >= 0) & (lam[1] >= 0) & (lam[2] >= 0)


def nearest_on_segment(ax, ay, bx, by, px, py):
    """The nearest point of segment ab to p as (t, r): t ``[...]`` in [0, 1] along ab and the residual
    r = p - a - t (b - a) as (rx, ry); safe for a == b."""
    ex, ey = bx - ax, by - ay
    qx, qy = px - ax, py - ay
    t = (torch.addcmul(qx * ex, qy, ey) / torch.addcmul(ex * ex, ey, ey).clamp(min=1e-30)).clamp(0, 1)
    return t, qx - t * ex, qy - t * ey


def segment_sqdist(ax, ay, bx, by, px, py):
    """Squared distance from p to segment ab (all ``[...]``); safe for a == b."""
    _, rx, ry = nearest_on_segment(ax, ay, bx, by, px, py)
    return torch.addcmul(rx * rx, ry, ry)


@fused
def _nearest_edge(vx, vy, corners, px, py, interior, valid):
    """The forward maths of ``signed_sqdist`` (no autograd): (dist, and for the backward the
    nearest edge's end point ids a, b, its t, residual rx, ry and the sign), each ``[N]``."""
    ids = [corners[:, k].contiguous() for k in range(3)]
    X = [vx.index_select(0, i) for i in ids]
    Y = [vy.index_select(0, i) for i in ids]
    area = triangle_area2(X, Y)
    inside = None
    d, t, rx, ry = [], [], [], []
    for a, b in EDGES:
        # barycentric k has the sign of the edge function of edge k over the area
        lk = edge_function(X[a], Y[a], X[b], Y[b], px, py) / area
        inside = lk >= 0 if inside is None else inside & (lk >= 0)
        tk, rxk, ryk = nearest_on_segment(X[a], Y[a], X[b], Y[b], px, py)
        d.append(torch.addcmul(rxk * rxk, ryk, ryk))
        t.append(tk)
        rx.append(rxk)
        ry.append(ryk)
    # outside: the nearest of the three edges; inside: of the edges that are not interior
    d_in = d if interior is None else [torch.where(interior[:, k], FAR_SQ, d[k]) for k in range(3)]
    d_use = [torch.where(inside, d_in[k], d[k]) for k in range(3)]
    best = torch.zeros_like(ids[0], dtype=torch.uint8)
    dmin = d_use[0]
    for k in (1, 2):
        closer = d_use[k] < dmin
        best = torch.where(closer, k, best)
        dmin = torch.where(closer, d_use[k], dmin)
    sign = torch.where(inside, -1.0, 1.0).to(dmin.dtype)
    dist = sign * dmin
    flat = dmin >= FAR_SQ  # inside with every edge interior: a constant
    if valid is not None:
        dist = torch.where(valid, dist, FAR_SQ)
        flat = flat | ~valid
    sign = torch.where(flat, 0.0, sign)

    def pick(vals):
        return torch.where(best == 0, vals[0], torch.where(best == 1, vals[1], vals[2]))

    return dist, pick([ids[a] for a, _ in EDGES]), pick([ids[b] for _, b in EDGES]), pick(t), pick(rx), pick(ry), sign


class _SignedSqDist(torch.autograd.Function):
    @staticmethod
    def forward(ctx, vert_xy, corners, px, py, interior, valid):  # runs without autograd
        dist, *saved = _nearest_edge(vert_xy[:, 0].contiguous(), vert_xy[:, 1].contiguous(), corners, px, py,
                                     interior, valid)
        ctx.save_for_backward(*saved)
        ctx.num_verts = vert_xy.shape[0]
        return dist

    @staticmethod
    def backward(ctx, grad):
        a_id, b_id, t, rx, ry, sign = ctx.saved_tensors
        coef = -2.0 * grad * sign
        ca, cb = coef * (1 - t), coef * t
        V = ctx.num_verts
        gx = torch.zeros(V, dtype=grad.dtype, device=grad.device).index_add_(0, a_id, ca * rx).index_add_(0, b_id, cb * rx)
        gy = torch.zeros(V, dtype=grad.dtype, device=grad.device).index_add_(0, a_id, ca * ry).index_add_(0, b_id, cb * ry)
        return torch.stack([gx, gy], 1), None, None, None, None, None


def signed_sqdist(vert_xy: torch.Tensor, corners: torch.Tensor, px: torch.Tensor, py: torch.Tensor,
                  interior: torch.Tensor | None = None, valid: torch.Tensor | None = None) -> torch.Tensor:
    """Signed squared NDC distance ``[N]`` from pixel centres to triangles.

    vert_xy: ``[V, 2]`` NDC vertex positions (differentiable); corners: ``[N, 3]`` long, the
    triangle of each pair (rows of ``vert_xy``); px, py: ``[N]`` pixel centres; interior: ``[N, 3]``
    bool, True where edge k (opposite corner k) is shared with a neighbour facing the same way:
    ignored by the inside distance, so a closed surface's coverage does not dip at its internal
    edges; valid: ``[N]`` bool, False for empty slots (they get ``FAR_SQ``).
    Outside: +(distance to the nearest edge)^2; inside: -(distance to the nearest non-interior
    edge)^2, ``-FAR_SQ`` when every edge is interior. Zero-area triangles are culled before here.
    """
    return _SignedSqDist.apply(vert_xy, corners, px, py, interior, valid)
