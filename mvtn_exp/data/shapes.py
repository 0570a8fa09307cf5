"""Shape containers: one packed layout for batches of meshes and point clouds of different sizes.

A batch of B shapes is stored *packed*: all vertices (or points) of all shapes concatenated, with
per-shape counts. Face indices are global (already offset into the packed vertex array). Every
part of the project (readers, collate, renderer, selectors) uses these two types.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import torch


class ShapeError(ValueError):
    """A shape that cannot be rendered (NaN/Inf coordinates, bad indices, ...); names the shape."""


def _shape_index(counts: torch.Tensor, total: int) -> torch.Tensor:
    """``[total]`` the shape of each packed row (``total = counts.sum()``, given: no host sync)."""
    return torch.repeat_interleave(torch.arange(len(counts), device=counts.device), counts, output_size=total)


def trusted(cls, **fields):
    """An instance of ``cls`` from fields already checked (a copy of a checked one): no ``__post_init__``."""
    obj = cls.__new__(cls)
    obj.__dict__.update(fields)
    return obj


def _check_finite(name: str, tensor: torch.Tensor, counts: torch.Tensor, names: Sequence[str]) -> None:
    bad = ~torch.isfinite(tensor).all(-1)
    if bool(bad.any()):
        shape = int(_shape_index(counts, len(tensor))[bad.nonzero()[0, 0]])
        raise ShapeError(
            f"shape '{names[shape]}' (batch index {shape}) has {int(bad.sum())} non-finite {name} "
            "(NaN or Inf); fix or drop it before rendering"
        )


@dataclass
class Meshes:
    """Packed triangle meshes.

    verts: ``[V, 3]`` float, all shapes' vertices concatenated (world units, Y-up).
    faces: ``[F, 3]`` long, global indices into ``verts``.
    verts_per_shape, faces_per_shape: ``[B]`` long counts.
    names: one label per shape, used in error messages.
    """

    verts: torch.Tensor
    faces: torch.Tensor
    verts_per_shape: torch.Tensor
    faces_per_shape: torch.Tensor
    names: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        if not self.names:
            self.names = [f"mesh{i}" for i in range(len(self.verts_per_shape))]
        if self.verts.dim() != 2 or self.verts.shape[-1] != 3:
            raise ShapeError(f"meshes: verts must be [V, 3], got {tuple(self.verts.shape)}")
        if self.faces.dim() != 2 or self.faces.shape[-1] != 3:
            raise ShapeError(f"meshes: faces must be [F, 3], got {tuple(self.faces.shape)}")
        _check_finite("vertices", self.verts, self.verts_per_shape, self.names)
        if self.faces.numel():
            nf = len(self.faces)
            lo = torch.repeat_interleave(self.vert_offsets(), self.faces_per_shape, output_size=nf)
            hi = lo + torch.repeat_interleave(self.verts_per_shape, self.faces_per_shape, output_size=nf)
            bad = ((self.faces < lo[:, None]) | (self.faces >= hi[:, None])).any(-1)
            if bool(bad.any()):
                shape = int(self.shape_of_face()[bad.nonzero()[0, 0]])
                raise ShapeError(
                    f"shape '{self.names[shape]}' has face indices outside its own vertices "
                    f"({int(bad.sum())} faces)"
                )

    @staticmethod
    def from_list(verts: Sequence[torch.Tensor], faces: Sequence[torch.Tensor], names: Sequence[str] | None = None) -> "Meshes":
        """Pack per-shape ``[V_i, 3]`` vertices and ``[F_i, 3]`` local face indices."""
        if len(verts) != len(faces):
            raise ShapeError(f"meshes: {len(verts)} vertex arrays but {len(faces)} face arrays")
        nv = torch.tensor([len(v) for v in verts], dtype=torch.long)
        nf = torch.tensor([len(f) for f in faces], dtype=torch.long)
        offsets = torch.cumsum(nv, 0) - nv
        device = verts[0].device if len(verts) else torch.device("cpu")
        packed_faces = [f.to(device=device, dtype=torch.long).reshape(-1, 3) + int(o) for f, o in zip(faces, offsets)]
        return Meshes(
            verts=torch.cat([v.reshape(-1, 3) for v in verts]) if len(verts) else torch.zeros(0, 3),
            faces=torch.cat(packed_faces) if packed_faces else torch.zeros(0, 3, dtype=torch.long),
            verts_per_shape=nv.to(device),
            faces_per_shape=nf.to(device),
            names=list(names) if names is not None else [],
        )

    def __len__(self) -> int:
        return len(self.verts_per_shape)

    def vert_offsets(self) -> torch.Tensor:
        return torch.cumsum(self.verts_per_shape, 0) - self.verts_per_shape

    def shape_of_vert(self) -> torch.Tensor:
        return _shape_index(self.verts_per_shape, len(self.verts))

    def shape_of_face(self) -> torch.Tensor:
        return _shape_index(self.faces_per_shape, len(self.faces))

    def to(self, device=None, dtype=None) -> "Meshes":
        """The same meshes on ``device`` / in ``dtype`` (not checked again: no host sync)."""
        return trusted(Meshes, verts=self.verts.to(device=device, dtype=dtype), faces=self.faces.to(device),
                        verts_per_shape=self.verts_per_shape.to(device), faces_per_shape=self.faces_per_shape.to(device),
                        names=list(self.names))

    def with_verts(self, verts: torch.Tensor) -> "Meshes":
        """Same topology, new (e.g. transformed, requires-grad) vertex positions ``[V, 3]``."""
        return Meshes(verts, self.faces, self.verts_per_shape, self.faces_per_shape, list(self.names))


@dataclass
class PointClouds:
    """Packed point clouds.

    points: ``[P, 3]`` all shapes' points concatenated; points_per_shape: ``[B]`` counts;
    colors: optional ``[P, 3]`` in [0, 1] (default white).
    """

    points: torch.Tensor
    points_per_shape: torch.Tensor
    colors: torch.Tensor | None = None
    names: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        if not self.names:
            self.names = [f"points{i}" for i in range(len(self.points_per_shape))]
        if self.points.dim() != 2 or self.points.shape[-1] != 3:
            raise ShapeError(f"point clouds: points must be [P, 3], got {tuple(self.points.shape)}")
        _check_finite("points", self.points, self.points_per_shape, self.names)

    @staticmethod
    def from_list(points: Sequence[torch.Tensor], names: Sequence[str] | None = None) -> "PointClouds":
        counts = torch.tensor([len(p) for p in points], dtype=torch.long)
        device = points[0].device if len(points) else torch.device("cpu")
        return PointClouds(
            points=torch.cat([p.reshape(-1, 3) for p in points]) if len(points) else torch.zeros(0, 3),
            points_per_shape=counts.to(device),
            names=list(names) if names is not None else [],
        )

    @staticmethod
    def from_padded(points: torch.Tensor) -> "PointClouds":
        """``[B, N, 3]`` dense clouds of equal size."""
        B, N, _ = points.shape
        return PointClouds(points.reshape(-1, 3), torch.full((B,), N, dtype=torch.long, device=points.device))

    def __len__(self) -> int:
        return len(self.points_per_shape)

    def shape_of_point(self) -> torch.Tensor:
        return _shape_index(self.points_per_shape, len(self.points))

    def to(self, device=None, dtype=None) -> "PointClouds":
        """The same clouds on ``device`` / in ``dtype`` (not checked again: no host sync)."""
        colors = None if self.colors is None else self.colors.to(device=device, dtype=dtype)
        return trusted(PointClouds, points=self.points.to(device=device, dtype=dtype),
                        points_per_shape=self.points_per_shape.to(device), colors=colors, names=list(self.names))

    def with_points(self, points: torch.Tensor) -> "PointClouds":
        return PointClouds(points, self.points_per_shape, self.colors, list(self.names))


def host_counts(shapes) -> tuple[list, ...]:
    """The per-shape counts on the host (one read): (vertices, faces) of Meshes, (points,) of PointClouds."""
    if isinstance(shapes, Meshes):
        return tuple(torch.stack([shapes.verts_per_shape, shapes.faces_per_shape]).tolist())
    return (shapes.points_per_shape.tolist(),)


def subset(shapes, a: int, b: int, counts: tuple | None = None):
    """Shapes ``a:b`` of packed Meshes or PointClouds (not checked again); counts: ``host_counts(shapes)``
    (read when None)."""
    counts = counts or host_counts(shapes)
    if isinstance(shapes, Meshes):
        nv, nf = counts
        v0, v1, f0, f1 = sum(nv[:a]), sum(nv[:b]), sum(nf[:a]), sum(nf[:b])
        return trusted(Meshes, verts=shapes.verts[v0:v1], faces=shapes.faces[f0:f1] - v0,
                       verts_per_shape=shapes.verts_per_shape[a:b], faces_per_shape=shapes.faces_per_shape[a:b],
                       names=list(shapes.names[a:b]))
    (n,) = counts
    p0, p1 = sum(n[:a]), sum(n[:b])
    return trusted(PointClouds, points=shapes.points[p0:p1], points_per_shape=shapes.points_per_shape[a:b],
                   colors=None if shapes.colors is None else shapes.colors[p0:p1], names=list(shapes.names[a:b]))
