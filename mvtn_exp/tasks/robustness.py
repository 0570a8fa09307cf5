"""Robustness transforms for evaluation: rotation about gravity (Y) and directional occlusion crops.

Every transform acts on a collated batch dict (see ``mvtn_exp.data.collate``): ``points [B, N, 3]``
and ``meshes`` (packed ``Meshes`` or ``None``) are transformed together, shape by shape, so the
selector / point encoder (``batch["points"]``) and the renderer (``batch["meshes"]`` or the points)
see the same shape. Inputs are never modified in place; a new dict is returned (other keys are
shared).

Rotation convention
    ``rotate_y(xyz, a)`` is the right-handed rotation about +Y by ``a`` degrees::

        x' =  x cos a + z sin a,   y' = y,   z' = -x sin a + z cos a

    so a positive angle turns +Z towards +X (+90: +Z -> +X, +X -> -Z). This is the azimuth
    convention of ``mvtn_exp.render.cameras`` (a camera at azimuth ``a`` sits at
    ``(sin a, 0, cos a)``): a shape rotated by ``a`` seen from azimuth ``a`` looks exactly like the
    unrotated shape seen from azimuth 0.

Occlusion convention
    Direction ``d`` in ``DIRECTIONS`` names an axis and a side, with the signed coordinate
    ``u = +coord`` for ``"+x"`` (``-coord`` for ``"-x"``). Ratio ``r`` in [0, 1) removes everything
    with ``u`` above the cut plane; points/surface exactly on the plane are kept. ``r = 0`` returns
    the inputs themselves (same tensor objects). Two frames for the plane (``FRAMES``):

    - ``unit_sphere`` (the paper's official code, the default): the plane is ``u = 1 - 2r`` in the
      frame of the unit sphere the shapes are normalised into, the same for every shape: the
      official rule keeps ``sign * x > 2|r| - 1``, the cap of height ``2r`` of the sphere's
      diameter on the other side, which is this rule with the side named by what is removed. On
      shapes that do not fill the sphere little goes at small ``r`` (synthetic shapes: 1% of the
      points at r = 0.1, 88% at r = 0.75).
    - ``extent``: the plane is ``max u - r (max u - min u)``, a share of each shape's own extent
      (18% / 69% of the synthetic shapes' points at r = 0.1 / 0.75).

    In ``crop_batch`` the ``extent`` plane of a shape is computed from its mesh vertices when the
    batch has meshes (the surface's extent; the points sampled on that surface are then cut by
    exactly the same plane), else from its points.

Floor rule (never empty; ``crop_batch`` flags the shapes it caught in ``occlusion_floored``)
    Points: if fewer than ``floor = max(1, ceil(POINT_FLOOR * N))`` points (``POINT_FLOOR = 0.01``)
    survive, the ``floor`` points with the smallest ``u`` are kept instead (all survivors plus the
    removed points nearest the cut plane). Meshes: if no face with positive area survives the cut,
    the ``max(1, ceil(FACE_FLOOR * F))`` faces (``FACE_FLOOR = 0.01``) whose nearest vertex is
    closest to the kept side (smallest min ``u``) are kept whole. With the ``extent`` frame neither
    floor triggers except for point clouds with very few survivors; with ``unit_sphere`` a shape
    lying wholly above the plane (large ``r``, a shape far from the sphere's rim) becomes that
    floor: the sliver of it nearest the kept side.
"""
from __future__ import annotations

import math

import torch

from ..data.shapes import Meshes
from ..data.synthetic import quaternion_rows

DIRECTIONS = ("+x", "-x", "+y", "-y", "+z", "-z")
FRAMES = ("unit_sphere", "extent")
POINT_FLOOR = 0.01
FACE_FLOOR = 0.01
# a triangle piece created by the cut is dropped when 2*area <= SLIVER * (longest edge)^2
SLIVER = 1e-7

__all__ = [
    "DIRECTIONS", "sample_angles", "rotate_y", "y_rotation_matrix", "rotate_batch", "random_rotations", "turn_batch",
    "FRAMES", "crop_plane", "crop_indices", "crop_points", "crop_mesh", "crop_batch",
]


# ----------------------------------------------------------------------------------------------
# rotation about Y
# ----------------------------------------------------------------------------------------------
def sample_angles(n: int, theta_deg: float, generator: torch.Generator | None = None) -> torch.Tensor:
    """``[n]`` float32 angles (degrees) uniform in ``[-theta, theta]`` (theta = 180: the whole circle)."""
    if n < 0:
        raise ValueError(f"sample_angles: n must be >= 0, got {n}")
    if not 0.0 <= theta_deg <= 180.0:
        raise ValueError(f"sample_angles: theta must be in [0, 180] degrees, got {theta_deg}")
    device = generator.device if generator is not None else None
    u = torch.rand(n, generator=generator, device=device, dtype=torch.float64)
    return ((2.0 * u - 1.0) * float(theta_deg)).to(torch.float32)


def _angle_like(angle_deg, xyz: torch.Tensor) -> torch.Tensor:
    a = torch.as_tensor(angle_deg, device=xyz.device)
    dtype = xyz.dtype if xyz.is_floating_point() else torch.float32
    a = torch.deg2rad(a.to(torch.float64)).to(dtype)
    lead = xyz.dim() - 1
    if a.dim() > lead:
        raise ValueError(f"rotate_y: angles {tuple(a.shape)} do not fit coordinates {tuple(xyz.shape)}")
    return a.reshape(tuple(a.shape) + (1,) * (lead - a.dim()))


def rotate_y(xyz: torch.Tensor, angle_deg) -> torch.Tensor:
    """Rotate ``xyz [..., 3]`` about +Y (right-handed: positive turns +Z towards +X).

    ``angle_deg``: a number or a tensor matching the leading dims of ``xyz`` (e.g. ``[B]`` for
    ``[B, N, 3]``: one angle per shape). Returns a new tensor.
    """
    if xyz.shape[-1] != 3:
        raise ValueError(f"rotate_y: coordinates must be [..., 3], got {tuple(xyz.shape)}")
    a = _angle_like(angle_deg, xyz)
    c, s = torch.cos(a), torch.sin(a)
    x, y, z = xyz.unbind(-1)
    return torch.stack([x * c + z * s, y.clone(), z * c - x * s], -1)


def y_rotation_matrix(angle_deg) -> torch.Tensor:
    """``[..., 3, 3]`` matrices ``R`` with ``rotate_y(p, a) == R @ p``."""
    a = torch.deg2rad(torch.as_tensor(angle_deg, dtype=torch.float64))
    c, s = torch.cos(a), torch.sin(a)
    one, zero = torch.ones_like(a), torch.zeros_like(a)
    rows = [torch.stack([c, zero, s], -1), torch.stack([zero, one, zero], -1), torch.stack([-s, zero, c], -1)]
    return torch.stack(rows, -2)


def rotate_batch(batch: dict, angles_deg: torch.Tensor) -> dict:
    """New batch with shape ``b`` rotated about +Y by ``angles_deg[b]`` degrees (see ``turn_batch``)."""
    angles = torch.as_tensor(angles_deg).reshape(-1)
    if len(angles) != len(batch["points"]):
        raise ValueError(f"rotate_batch: {len(angles)} angles for a batch of {len(batch['points'])} shapes")
    return turn_batch(batch, y_rotation_matrix(angles))


def random_rotations(n: int, mode: str, generator: torch.Generator | None = None) -> torch.Tensor:
    """``[n, 3, 3]`` float64 rotations: identity (``none``), uniform about +Y (``y``) or uniform over
    SO(3) (``so3``: normalised Gaussian quaternions), drawn from ``generator`` (torch's global RNG if None)."""
    if mode == "none":
        return torch.eye(3, dtype=torch.float64).expand(n, 3, 3).clone()
    if mode == "y":
        return y_rotation_matrix(sample_angles(n, 180.0, generator).to(torch.float64))
    if mode != "so3":
        raise ValueError(f"random_rotations: mode={mode!r}; expected none, y or so3")
    q = torch.randn(n, 4, generator=generator, dtype=torch.float64)
    rows = quaternion_rows(*(q / q.norm(dim=1, keepdim=True).clamp_min(1e-12)).unbind(1))
    return torch.stack([torch.stack(r, -1) for r in rows], -2)


def turn_batch(batch: dict, R: torch.Tensor) -> dict:
    """New batch with shape ``b`` turned by the rotation ``R[b]`` (``[B, 3, 3]``, ``p -> R p``).

    Turns ``points [B, N, 3]``, every shape's mesh vertices (same matrix) and, when present,
    ``rotations [B, 3, 3]`` (composed: ``R @ rotations``, so ``verts = canonical @ R^T`` still holds)
    and the detail frame of ``synthetic_views`` (``detail_anchor``, ``detail_axis`` ``[B, 3]``).
    """
    points = batch["points"]
    if R.shape != (len(points), 3, 3):
        raise ValueError(f"turn_batch: rotations {tuple(R.shape)} for a batch of {len(points)} shapes")
    out = dict(batch)
    out["points"] = torch.einsum("bij,bnj->bni", R.to(points), points)
    meshes = batch.get("meshes")
    if meshes is not None:
        if len(meshes) != len(points):
            raise ValueError(f"turn_batch: {len(meshes)} meshes but {len(points)} point clouds")
        v = meshes.verts
        per_vert = torch.repeat_interleave(R.to(device=v.device, dtype=v.dtype), meshes.verts_per_shape, dim=0)
        out["meshes"] = meshes.with_verts(torch.einsum("vij,vj->vi", per_vert, v))
    for key in ("rotations", "detail_anchor", "detail_axis"):
        x = batch.get(key)
        if x is not None:
            Rx = R.to(device=x.device, dtype=x.dtype)
            out[key] = Rx @ x if x.dim() == 3 else torch.einsum("bij,bj->bi", Rx, x)
    return out


# ----------------------------------------------------------------------------------------------
# occlusion crop
# ----------------------------------------------------------------------------------------------
def _axis_sign(direction: str) -> tuple[int, float]:
    if direction not in DIRECTIONS:
        raise ValueError(f"direction {direction!r}: must be one of {DIRECTIONS}")
    return "xyz".index(direction[1]), (1.0 if direction[0] == "+" else -1.0)


def _check_ratio(ratio: float) -> float:
    ratio = float(ratio)
    if not 0.0 <= ratio < 1.0:
        raise ValueError(f"occlusion ratio {ratio!r}: must be in [0, 1)")
    return ratio


def _signed(xyz: torch.Tensor, direction: str) -> torch.Tensor:
    axis, sign = _axis_sign(direction)
    return xyz[..., axis] * sign


def crop_plane(xyz: torch.Tensor, direction: str, ratio: float, frame: str = "unit_sphere") -> torch.Tensor:
    """Cut position in signed coordinates ``u`` (see module doc) of each shape.

    ``xyz [..., N, 3]`` -> ``[...]``: ``1 - 2 ratio`` (``frame="unit_sphere"``) or
    ``max u - ratio * (max u - min u)`` (``"extent"``); points with ``u`` above it are removed. In
    world coordinates the plane is ``coord = sign * plane``.
    """
    ratio = _check_ratio(ratio)
    if frame not in FRAMES:
        raise ValueError(f"occlusion frame {frame!r}: must be one of {FRAMES}")
    u = _signed(xyz, direction)
    if u.shape[-1] == 0:
        raise ValueError("crop_plane: a shape has no points/vertices")
    if frame == "unit_sphere":
        return torch.full(u.shape[:-1], 1.0 - 2.0 * ratio, dtype=u.dtype, device=u.device)
    hi, lo = u.max(-1).values, u.min(-1).values
    return hi - ratio * (hi - lo)


def _floor(n: int, frac: float) -> int:
    return max(1, math.ceil(frac * n)) if n else 0


def crop_indices(points: torch.Tensor, direction: str, ratio: float, generator: torch.Generator | None = None,
                 planes: torch.Tensor | None = None, frame: str = "unit_sphere") -> tuple[torch.Tensor, torch.Tensor]:
    """Index form of ``crop_points``: ``(index [B, N] long, survivors [B] long)``.

    Row ``b`` lists its ``survivors[b]`` kept points first (in their original order), then
    ``N - survivors[b]`` draws made uniformly with replacement among those kept points.
    ``planes [B]`` overrides the per-shape cut (signed coordinates, see ``crop_plane``), else
    ``crop_plane(points, direction, ratio, frame)``.
    """
    index, count, _ = _crop_indices(points, direction, ratio, generator, planes, frame)
    return index, count


def _crop_indices(points, direction, ratio, generator, planes, frame):
    """``crop_indices`` plus ``floored [B]`` bool: the shapes the floor rule kept from becoming empty."""
    _check_ratio(ratio)
    if points.dim() != 3 or points.shape[-1] != 3:
        raise ValueError(f"crop_points: points must be [B, N, 3], got {tuple(points.shape)}")
    B, N, _ = points.shape
    u = _signed(points, direction)
    if planes is None:
        planes = crop_plane(points, direction, ratio, frame)
    keep = u <= planes.to(u)[:, None]
    count = keep.sum(1)
    floor = _floor(N, POINT_FLOOR)
    low = count < floor
    if bool(low.any()):
        # floor rule: the `floor` points with the smallest u (survivors + nearest removed ones)
        rank = torch.empty_like(u, dtype=torch.long)
        order_u = u.argsort(dim=1, stable=True)
        rank.scatter_(1, order_u, torch.arange(N, device=u.device).expand(B, N))
        keep = torch.where(low[:, None], rank < floor, keep)
        count = keep.sum(1)
    order = (~keep).long().argsort(dim=1, stable=True)  # survivors first, original order
    gdev = generator.device if generator is not None else points.device
    draw = torch.rand(B, N, generator=generator, device=gdev, dtype=torch.float64).to(points.device)
    pick = (draw * count[:, None]).long().clamp(max=N - 1)
    pick = torch.minimum(pick, (count[:, None] - 1).clamp(min=0))
    pos = torch.arange(N, device=points.device).expand(B, N)
    src = torch.where(pos < count[:, None], pos, pick)
    return order.gather(1, src), count, low


def crop_points(points: torch.Tensor, direction: str, ratio: float, generator: torch.Generator | None = None,
                planes: torch.Tensor | None = None, frame: str = "unit_sphere") -> torch.Tensor:
    """Occlusion crop of dense clouds ``[B, N, 3]`` -> ``[B, N, 3]``.

    Keeps each shape's points on the kept side of its cut plane (see module doc; ``planes [B]``
    overrides the planes) and refills to ``N`` by drawing kept points uniformly with replacement
    (``generator`` seeds the draws). ``ratio = 0`` returns ``points`` itself.
    """
    if _check_ratio(ratio) == 0.0 and planes is None:
        _axis_sign(direction)
        return points
    index, _ = crop_indices(points, direction, ratio, generator, planes, frame)
    return points.gather(1, index[..., None].expand(-1, -1, 3))


def _tri_area2(v: torch.Tensor, f: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Twice the area of each face and its longest squared edge."""
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    area2 = torch.linalg.cross(b - a, c - a).norm(dim=-1)
    edge2 = torch.stack([(b - a).square().sum(-1), (c - b).square().sum(-1), (a - c).square().sum(-1)], -1)
    return area2, edge2.max(-1).values


def crop_mesh(verts: torch.Tensor, faces: torch.Tensor, direction: str, ratio: float,
              plane: float | torch.Tensor | None = None, frame: str = "unit_sphere") -> tuple[torch.Tensor, torch.Tensor]:
    """Occlusion crop of one mesh: ``verts [V, 3]``, ``faces [F, 3]`` (local) -> ``(verts, faces)``.

    Triangles are clipped against the cut plane (see module doc; ``plane`` overrides it, signed
    coordinates): fully kept ones stay as they are, fully removed ones go, straddling ones are
    split so the kept part ends exactly on the plane (new vertices interpolated linearly along
    the cut edges, one per edge, shared by both neighbouring faces; their coordinate along the
    axis is set exactly to the plane). Degenerate pieces produced by the cut are dropped and
    unreferenced vertices are removed. ``ratio = 0`` returns the inputs themselves.
    """
    axis, sign = _axis_sign(direction)
    if _check_ratio(ratio) == 0.0 and plane is None:
        return verts, faces
    if verts.dim() != 2 or verts.shape[-1] != 3 or faces.dim() != 2 or faces.shape[-1] != 3:
        raise ValueError(f"crop_mesh: need verts [V, 3] and faces [F, 3], got {tuple(verts.shape)}, {tuple(faces.shape)}")
    faces = faces.long()
    V, F = len(verts), len(faces)
    if F == 0 or V == 0:
        return verts, faces
    u = verts[:, axis] * sign
    t = crop_plane(verts, direction, ratio, frame) if plane is None else torch.as_tensor(plane).to(u)
    keep = u <= t
    kf = keep[faces]                      # [F, 3]
    nk = kf.sum(1)

    # --- one new vertex per cut edge ------------------------------------------------------
    e0 = faces                             # edge i goes from corner i to corner i+1
    e1 = faces.roll(-1, 1)
    crossing = keep[e0] != keep[e1]        # [F, 3]
    inner = torch.where(keep[e0], e0, e1)  # the kept end
    outer = torch.where(keep[e0], e1, e0)  # the removed end
    key = inner * V + outer
    uniq, inv = torch.unique(key[crossing], return_inverse=True)
    a_idx, b_idx = uniq // V, uniq % V
    lam = ((t - u[a_idx]) / (u[b_idx] - u[a_idx])).clamp(0.0, 1.0)
    new_v = verts[a_idx] + lam[:, None] * (verts[b_idx] - verts[a_idx])
    new_v[:, axis] = sign * t
    new_v[lam == 0] = verts[a_idx[lam == 0]]   # cut through a kept vertex: reuse it exactly
    ev = torch.full((F, 3), -1, dtype=torch.long, device=faces.device)
    ev[crossing] = V + inv
    all_v = torch.cat([verts, new_v.to(verts.dtype)])

    ar = torch.arange(F, device=faces.device)
    pieces_new = []
    # one kept corner i: (A, P_AB, P_CA) with A = corner i; P_AB = edge i, P_CA = edge i+2
    one = nk == 1
    if bool(one.any()):
        i = kf[one].to(torch.uint8).argmax(1)
        r = ar[one]
        pieces_new.append(torch.stack([faces[r, i], ev[r, i], ev[r, (i + 2) % 3]], -1))
    # two kept corners, removed corner i = C: A = i+1, B = i+2; (A, B, P_BC), (A, P_BC, P_CA)
    two = nk == 2
    if bool(two.any()):
        i = (~kf[two]).to(torch.uint8).argmax(1)
        r = ar[two]
        A, B = faces[r, (i + 1) % 3], faces[r, (i + 2) % 3]
        P_bc, P_ca = ev[r, (i + 2) % 3], ev[r, i]
        pieces_new.append(torch.stack([A, B, P_bc], -1))
        pieces_new.append(torch.stack([A, P_bc, P_ca], -1))
    new_faces = torch.cat(pieces_new) if pieces_new else faces.new_zeros(0, 3)
    if len(new_faces):
        area2, edge2 = _tri_area2(all_v, new_faces)
        ok = (area2 > SLIVER * edge2) & (area2 > 0)
        new_faces = new_faces[ok]
    out_faces = torch.cat([faces[nk == 3], new_faces])

    if len(out_faces) == 0 or not bool((_tri_area2(all_v, out_faces)[0] > 0).any()):
        # floor rule: keep whole the faces that reach furthest into the kept side
        n = _floor(F, FACE_FLOOR)
        out_faces = faces[u[faces].min(1).values.argsort(stable=True)[:n]]
        all_v = verts

    used, local = torch.unique(out_faces, return_inverse=True)
    return all_v[used], local.reshape(-1, 3)


def crop_batch(batch: dict, direction: str, ratio: float, generator: torch.Generator | None = None,
               frame: str = "unit_sphere") -> dict:
    """New batch with every shape cut along ``direction`` at ``ratio`` in ``frame`` (module doc).

    ``points`` go through ``crop_points``; each mesh through ``crop_mesh`` and the packed
    ``Meshes`` is rebuilt. When the batch has meshes, the cut plane of shape ``b`` comes from its
    mesh vertices and cuts both its mesh and its points (consistent shapes); otherwise from its
    points. ``occlusion_floored [B]`` (bool) marks the shapes of which fewer than the floor of
    points survived (the floor rule kept them from becoming empty). ``ratio = 0`` returns a new
    dict sharing the original tensors (nothing floored).
    """
    _axis_sign(direction)
    ratio = _check_ratio(ratio)
    if frame not in FRAMES:
        raise ValueError(f"occlusion frame {frame!r}: must be one of {FRAMES}")
    out = dict(batch)
    out["occlusion_floored"] = torch.zeros(len(batch["points"]), dtype=torch.bool)
    if ratio == 0.0:
        return out
    points = batch["points"]
    meshes = batch.get("meshes")
    planes = None
    if meshes is not None:
        if len(meshes) != len(points):
            raise ValueError(f"crop_batch: {len(meshes)} meshes but {len(points)} point clouds")
        vs = torch.split(meshes.verts, meshes.verts_per_shape.tolist())
        offsets = meshes.vert_offsets().tolist()
        fs = torch.split(meshes.faces, meshes.faces_per_shape.tolist())
        new_v, new_f, plist = [], [], []
        for v, f, o in zip(vs, fs, offsets):
            p = crop_plane(v, direction, ratio, frame)
            cv, cf = crop_mesh(v, f - o, direction, ratio, plane=p)
            new_v.append(cv)
            new_f.append(cf)
            plist.append(p)
        planes = torch.stack(plist).to(points.device)
        out["meshes"] = Meshes.from_list(new_v, new_f, names=list(meshes.names))
    index, _, floored = _crop_indices(points, direction, ratio, generator, planes, frame)
    out["points"] = points.gather(1, index[..., None].expand(-1, -1, 3))
    out["occlusion_floored"] = floored.cpu()
    return out
