"""Cameras: view-points u = (azimuth, elevation, distance) -> analytic camera frames and projection.

Conventions (see ../shared/DESIGN.md): world is Y-up; angles are degrees; azimuth turns about +Y
starting at +Z towards +X; elevation lifts from the XZ plane towards +Y. The camera sits at
``dist * (cos e sin a, sin e, cos e cos a)`` and looks at the origin.

The frame is built analytically (no look-at with a fixed up vector), so elevation exactly +-90
degrees and beyond is smooth and finite:

    right   = ( cos a,         0,      -sin a       )
    forward = (-cos e sin a,  -sin e,  -cos e cos a )   (unit vector towards the origin)
    up      = right x forward = (-sin e sin a, cos e, -sin e cos a)

Camera coordinates of a world point p: x = right.(p - c), y = up.(p - c), z = forward.(p - c)
(z is the depth in front of the camera). The rows (right, up, forward) form an orthonormal,
left-handed screen frame (det = -1) at every azimuth and elevation. Normalised device coordinates (NDC) have x to the right
and y up, in [-1, 1] across the image: perspective ``x / (z tan(fov/2))``, orthographic
``x / ortho_scale``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch


@dataclass
class Cameras:
    """A batch of B x M cameras looking at the origin.

    azim, elev, dist: ``[B, M]`` tensors, degrees / degrees / world units.
    fov: vertical = horizontal field of view in degrees (perspective only).
    orthographic: if True, NDC = camera xy / ortho_scale (distance changes depth only).
    """

    azim: torch.Tensor
    elev: torch.Tensor
    dist: torch.Tensor
    fov: float = 60.0
    orthographic: bool = False
    ortho_scale: float = 1.0

    def __post_init__(self) -> None:
        shapes = {tuple(t.shape) for t in (self.azim, self.elev, self.dist)}
        if len(shapes) != 1 or self.azim.dim() != 2:
            raise ValueError(
                "cameras: azim, elev and dist must share one shape [B, M]; got "
                f"{[tuple(t.shape) for t in (self.azim, self.elev, self.dist)]}"
            )
        if not (0.0 < self.fov < 180.0):
            raise ValueError(f"cameras: fov must be in (0, 180) degrees, got {self.fov}")
        if self.ortho_scale <= 0:
            raise ValueError(f"cameras: ortho_scale must be > 0, got {self.ortho_scale}")

    @property
    def batch_shape(self) -> tuple[int, int]:
        return tuple(self.azim.shape)  # type: ignore[return-value]

    def frames(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Rotation and position. Returns R ``[B, M, 3, 3]`` (rows: right, up, forward) and C ``[B, M, 3]``."""
        a = torch.deg2rad(self.azim)
        e = torch.deg2rad(self.elev)
        sa, ca, se, ce = torch.sin(a), torch.cos(a), torch.sin(e), torch.cos(e)
        zero = torch.zeros_like(a)
        right = torch.stack([ca, zero, -sa], -1)
        up = torch.stack([-se * sa, ce, -se * ca], -1)
        forward = torch.stack([-ce * sa, -se, -ce * ca], -1)
        position = -forward * self.dist.unsqueeze(-1)
        return torch.stack([right, up, forward], -2), position

    def focal(self) -> float:
        """NDC units per unit of (x / z) for perspective cameras."""
        return 1.0 / math.tan(math.radians(self.fov) / 2.0)


def to_camera_packed(points: torch.Tensor, counts: torch.Tensor, R: torch.Tensor, C: torch.Tensor,
                     shape_of: torch.Tensor | None = None) -> torch.Tensor:
    """World -> camera coordinates of packed shapes in every view of their own.

    points: ``[N, 3]`` packed (shape b owns ``counts[b]`` consecutive rows); R ``[B, M, 3, 3]``;
    C ``[B, M, 3]``; shape_of: ``[N]`` the shape of each point (derived from ``counts`` when None).
    Returns ``[N * M, 3]`` ordered point-major (row ``n * M + m``): ``R (p - C) = R p - R C``.
    Element-wise products gathered per point, no matmul: no loop over shapes, no host sync, and
    the same float32 result under TF32 or autocast settings that would round a matmul.
    """
    B, M = R.shape[:2]
    if len(points) == 0:
        return points.new_zeros(0, 3)
    if shape_of is None:
        shape_of = torch.repeat_interleave(torch.arange(B, device=points.device), counts, output_size=len(points))
    RC = (R * C.unsqueeze(-2)).sum(-1)  # [B, M, 3]
    rows = torch.cat([R.reshape(B, M, 9), RC], -1).permute(2, 0, 1)  # [12, B, M]: R_ij, then RC_i

    def g(k):  # entry k of each point's own views ``[N, M]`` (one at a time: memory of one [N, M])
        return rows[k].index_select(0, shape_of)

    p = points.unsqueeze(-1).unbind(1)  # 3 x [N, 1]
    out = [torch.addcmul(torch.addcmul(g(3 * i) * p[0], g(3 * i + 1), p[1]), g(3 * i + 2), p[2]) - g(9 + i)
           for i in range(3)]
    return torch.stack(out, -1).reshape(-1, 3)


def camera_to_ndc(cam: torch.Tensor, cameras: Cameras, znear: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Camera coordinates ``[..., 3]`` -> NDC xy ``[..., 2]`` and depth ``[...]``.

    Depth is clamped to ``znear`` inside the perspective divide only, so points behind the near
    plane stay finite (callers cull them by their true depth).
    """
    z = cam[..., 2]
    if cameras.orthographic:
        xy = cam[..., :2] / cameras.ortho_scale
    else:
        xy = cam[..., :2] * (cameras.focal() / z.clamp(min=znear)).unsqueeze(-1)
    return xy, z


def view_directions(azim: torch.Tensor, elev: torch.Tensor) -> torch.Tensor:
    """Degrees ``[...]`` -> unit directions from the origin to the camera ``[..., 3]`` (Y-up, as above)."""
    a, e = torch.deg2rad(azim), torch.deg2rad(elev)
    return torch.stack([torch.cos(e) * torch.sin(a), torch.sin(e), torch.cos(e) * torch.cos(a)], -1)


def direction_angles(d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit directions ``[..., 3]`` -> the azimuth, elevation in degrees of a camera there."""
    return torch.rad2deg(torch.atan2(d[..., 0], d[..., 2])), torch.rad2deg(torch.asin(d[..., 1].clamp(-1.0, 1.0)))
