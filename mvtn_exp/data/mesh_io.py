"""Reading shapes from files: meshes (OFF, OBJ, PLY, STL via trimesh) and point clouds (.npy, .txt, .ply).

OFF files whose header glues ``OFF`` to the counts (``OFF9278 6940 0``, common in ModelNet) are
read by our own OFF parser, which also tolerates blank and ``#`` comment lines.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

POINT_SUFFIXES = {".npy", ".txt", ".xyz", ".csv"}


class ShapeFileError(ValueError):
    """A shape file that cannot be read; the message names the file and what was expected."""


class DatasetNotFound(FileNotFoundError):
    """A dataset folder is missing or not laid out as expected; the message names both."""


def _content_lines(path: Path):
    with open(path, "r", errors="replace") as fh:
        for line in fh:
            line = line.split("#", 1)[0].strip()
            if line:
                yield line


def read_off(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """OFF -> vertices ``[V, 3]`` float64, triangles ``[F, 3]`` int64 (polygons fan-triangulated)."""
    path = Path(path)
    lines = _content_lines(path)
    try:
        head = next(lines)
    except StopIteration:
        raise ShapeFileError(f"{path}: empty file, expected an OFF header") from None
    if not head.upper().startswith("OFF"):
        raise ShapeFileError(f"{path}: expected an OFF header, got {head[:40]!r}")
    rest = head[3:].strip()
    counts = rest.split() if rest else next(lines, "").split()
    try:
        nv, nf = int(counts[0]), int(counts[1])
    except (IndexError, ValueError):
        raise ShapeFileError(f"{path}: expected 'OFF' then vertex and face counts, got {head[:40]!r}") from None
    verts = np.empty((nv, 3), dtype=np.float64)
    try:
        for i in range(nv):
            verts[i] = [float(t) for t in next(lines).split()[:3]]
    except (StopIteration, ValueError) as exc:
        raise ShapeFileError(f"{path}: expected {nv} vertex lines of 3 numbers ({exc})") from None
    tris = []
    try:
        for _ in range(nf):
            vals = [int(t) for t in next(lines).split()]
            n = vals[0]
            poly = vals[1:1 + n]
            if len(poly) != n or n < 3:
                raise ValueError(f"face with {n} indices has {len(poly)}")
            tris.extend((poly[0], poly[k], poly[k + 1]) for k in range(1, n - 1))
    except (StopIteration, ValueError) as exc:
        raise ShapeFileError(f"{path}: expected {nf} face lines 'n i1 .. in' ({exc})") from None
    faces = np.asarray(tris, dtype=np.int64).reshape(-1, 3)
    return verts, faces


def read_mesh(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Any supported mesh file -> ``([V, 3] float64, [F, 3] int64)``; materials are ignored."""
    path = Path(path)
    if not path.is_file():
        raise ShapeFileError(f"{path}: no such file")
    if path.suffix.lower() == ".off":
        verts, faces = read_off(path)
    else:
        import trimesh

        try:
            mesh = trimesh.load(path, force="mesh", process=False, skip_materials=True)
        except Exception as exc:
            raise ShapeFileError(f"{path}: trimesh could not read it as a mesh ({exc})") from None
        verts, faces = np.asarray(mesh.vertices, np.float64).reshape(-1, 3), np.asarray(mesh.faces, np.int64)
        if len(faces) == 0:  # forced to a mesh, a file of bare vertices comes back with none: count them
            verts = _bare_vertices(path)
    check_mesh(path, verts, faces.reshape(-1, 3))
    return verts, faces.reshape(-1, 3)


def _bare_vertices(path: Path) -> np.ndarray:
    """The vertices ``[V, 3]`` of a mesh file that has no faces (trimesh reads it as a point cloud,
    or a scene of them), so a refusal can say how many there are."""
    import trimesh

    try:
        obj = trimesh.load(path, process=False, skip_materials=True)
    except Exception:
        return np.zeros((0, 3))
    parts = obj.geometry.values() if isinstance(obj, trimesh.Scene) else [obj]
    verts = [np.asarray(getattr(g, "vertices", np.zeros((0, 3))), np.float64).reshape(-1, 3) for g in parts]
    return np.concatenate(verts) if verts else np.zeros((0, 3))


def check_mesh(name, verts: np.ndarray, faces: np.ndarray) -> None:
    """Refuse meshes that would render empty or wrong: ShapeFileError naming the file and what it
    holds (``<file>: 3 vertices and no faces; expected a triangle mesh``)."""
    if len(verts) == 0:
        raise ShapeFileError(f"{name}: empty mesh (0 vertices, {len(faces)} faces)")
    if len(faces) == 0:
        raise ShapeFileError(f"{name}: {len(verts)} vertices and no faces; expected a triangle mesh "
                             "(a point cloud? use a point file)")
    if not np.isfinite(verts).all():
        raise ShapeFileError(f"{name}: {int((~np.isfinite(verts)).any(1).sum())} vertices are NaN or Inf")
    if faces.min() < 0 or faces.max() >= len(verts):
        raise ShapeFileError(f"{name}: face indices out of range [0, {len(verts)}) (min {faces.min()}, max {faces.max()})")
    tri = verts[faces]
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    if not (area > 0).any():
        raise ShapeFileError(f"{name}: all {len(faces)} faces have zero area")


def read_points(path: str | Path) -> np.ndarray:
    """Point cloud file -> ``[N, 3]`` float64 (extra columns such as normals are dropped)."""
    path = Path(path)
    if not path.is_file():
        raise ShapeFileError(f"{path}: no such file")
    suffix = path.suffix.lower()
    try:
        if suffix == ".npy":
            pts = np.load(path)
        elif suffix == ".ply":
            import trimesh

            pts = np.asarray(trimesh.load(path, process=False).vertices)
        else:
            pts = np.loadtxt(path, delimiter="," if "," in open(path).readline() else None, ndmin=2)
    except Exception as exc:
        raise ShapeFileError(f"{path}: could not read points ({exc})") from None
    pts = np.asarray(pts, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise ShapeFileError(f"{path}: expected an [N, >=3] array of points, got shape {pts.shape}")
    pts = pts[:, :3]
    if not np.isfinite(pts).all():
        raise ShapeFileError(f"{path}: {int((~np.isfinite(pts)).any(1).sum())} points are NaN or Inf")
    return pts


def is_point_file(path: str | Path) -> bool:
    """.ply files count as point clouds when they hold no faces."""
    path = Path(path)
    s = path.suffix.lower()
    if s in POINT_SUFFIXES:
        return True
    if s == ".ply":
        import trimesh

        obj = trimesh.load(path, process=False)
        return not hasattr(obj, "faces") or len(getattr(obj, "faces", [])) == 0
    return False


def zup_to_yup(xyz: np.ndarray) -> np.ndarray:
    """Rotate -90 degrees about X: (x, y, z) -> (x, z, -y) (Z-up files such as ModelNet to Y-up)."""
    return np.stack([xyz[:, 0], xyz[:, 2], -xyz[:, 1]], 1)


def normalize_unit_sphere(xyz: np.ndarray) -> np.ndarray:
    """Centre the bounding box at the origin and scale the farthest point to radius 1."""
    centre = (xyz.max(0) + xyz.min(0)) / 2
    out = xyz - centre
    r = np.linalg.norm(out, axis=1).max()
    return out / r if r > 0 else out
