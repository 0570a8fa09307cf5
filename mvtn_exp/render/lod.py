"""Level of detail: simplify meshes to a face budget the image can show, and keep a simplification
only where the image cannot tell it from the mesh (cached).

The budget (``face_budget``) grows with the image side, not its area: a surface simplified to
faces of edge e deviates from the original by about e^2 / R (R: its curvature radius), which is a
fixed number of pixels when the faces per pixel row are fixed (``lod_faces_per_row``, 32: 2,048
faces at 64 px, 7,168 at 224 px). ``lod_faces_per_pixel`` (faces per pixel of the image's area)
is the former rule, kept as an option.

Simplification (fast-simplification, quadric error) does not always keep a shape: on real CAD
meshes with thin parts it can remove a table's legs at budgets the image could still show. So a
simplification is kept only if the silhouettes of the simplified mesh at the image size, from the
six axis directions, match the mesh's with an IoU of at least ``lod_min_iou`` (0.99); otherwise the
next budget up (x 2, x 4, ...) is tried, and the mesh itself is kept when none passes. The budget is
a request: fast-simplification does not always reach it on open or non-manifold meshes; what was
reached is recorded.
"""
from __future__ import annotations

import hashlib
import logging
from dataclasses import dataclass

import numpy as np
import torch

log = logging.getLogger(__name__)

# the six axis directions (azimuth, elevation in degrees) of the silhouette check
CHECK_VIEWS = ((0.0, 0.0), (90.0, 0.0), (180.0, 0.0), (270.0, 0.0), (0.0, 89.0), (0.0, -89.0))


@dataclass
class LodResult:
    verts: np.ndarray
    faces: np.ndarray
    faces_in: int
    budget: int
    iou: float = 1.0  # silhouette IoU of the kept mesh against the input (1: the input itself)

    @property
    def faces_out(self) -> int:
        return len(self.faces)


_CACHE: dict[tuple, LodResult] = {}


def face_budget(image_size: int, faces_per_row: float = 32.0, faces_per_pixel: float | None = None) -> int:
    """Faces a mesh keeps at ``image_size``: ``faces_per_pixel * size^2`` when given, else
    ``faces_per_row * size``; at least 16."""
    if faces_per_pixel is not None:
        return max(16, int(faces_per_pixel * image_size * image_size))
    return max(16, int(faces_per_row * image_size))


def _simplify_to(verts: np.ndarray, faces: np.ndarray, budget: int):
    """fast-simplification towards ``budget`` faces: (verts, faces), or None if it fails or corrupts."""
    import fast_simplification

    try:
        v, f = fast_simplification.simplify(
            np.ascontiguousarray(verts, dtype=np.float32), np.ascontiguousarray(faces, dtype=np.int32),
            target_reduction=1.0 - budget / len(faces),
        )
    except Exception as exc:  # keep the original mesh: LOD must never lose a shape
        log.warning("lod: simplification failed (%s); keeping %d faces", exc, len(faces))
        return None
    if len(f) == 0 or not np.isfinite(v).all() or f.min() < 0 or f.max() >= len(v):
        return None
    return v.astype(verts.dtype), f.astype(np.int64)


def silhouette_iou(verts_a: np.ndarray, faces_a: np.ndarray, verts_b: np.ndarray, faces_b: np.ndarray,
                   image_size: int) -> float:
    """IoU of the hard silhouettes of two meshes (same frame) over ``CHECK_VIEWS`` at ``image_size``,
    framed together (both scaled by the first mesh's bounding radius, camera at 2.2)."""
    from ..data.shapes import Meshes
    from .renderer import MultiViewRenderer

    centre = (verts_a.max(0) + verts_a.min(0)) / 2
    scale = float(np.linalg.norm(verts_a - centre, axis=1).max()) or 1.0
    meshes = Meshes.from_list([torch.tensor((v - centre) / scale, dtype=torch.float32) for v in (verts_a, verts_b)],
                              [torch.tensor(f, dtype=torch.long) for f in (faces_a, faces_b)])
    azim = torch.tensor([[a for a, _ in CHECK_VIEWS]] * 2)
    elev = torch.tensor([[e for _, e in CHECK_VIEWS]] * 2)
    with torch.no_grad():
        alpha = MultiViewRenderer(image_size=image_size, mode="hard", shading="silhouette")(meshes, azim, elev).alpha > 0.5
    union = int((alpha[0] | alpha[1]).sum())
    return float(int((alpha[0] & alpha[1]).sum()) / union) if union else 1.0


def simplify(verts: np.ndarray, faces: np.ndarray, budget: int, image_size: int | None = None,
             min_iou: float = 0.0) -> LodResult:
    """Simplify ``[V, 3]`` / ``[F, 3]`` to about ``budget`` faces (module docstring). With ``min_iou``
    > 0 a simplification is kept only if its silhouettes at ``image_size`` keep that IoU; budgets
    x 2, x 4, ... are tried next. Returns the input when it fits, every attempt fails, or none passes."""
    if len(faces) <= budget:
        return LodResult(verts, faces, len(faces), budget)
    key = (hashlib.sha1(np.ascontiguousarray(verts, dtype=np.float32).tobytes()
                        + np.ascontiguousarray(faces, dtype=np.int64).tobytes()).hexdigest(), budget,
           image_size if min_iou > 0 else None, min_iou)
    hit = _CACHE.get(key)
    if hit is not None:
        return hit
    res = LodResult(verts, faces, len(faces), budget)
    ask = budget
    while ask < len(faces):
        out = _simplify_to(verts, faces, ask)
        if out is not None:
            iou = silhouette_iou(verts, faces, *out, image_size) if min_iou > 0 else 1.0
            if iou >= min_iou:
                res = LodResult(out[0], out[1], len(faces), budget, iou)
                break
            log.info("lod: %d -> %d faces keeps silhouette IoU %.4f < %.4f at %d px; trying %d",
                     len(faces), len(out[1]), iou, min_iou, image_size, 2 * ask)
        ask *= 2
    _CACHE[key] = res
    return res


# per mesh fingerprint (counts and two fixed random projections of its vertices and faces) and device:
# the simplified mesh there, so a hit costs no copy to the host, no hash and no upload
# (at most DEVICE_CACHE_SIZE entries, the oldest dropped first: augmented shapes are new every epoch)
_DEVICE_CACHE: dict[tuple, tuple[torch.Tensor, torch.Tensor]] = {}
DEVICE_CACHE_SIZE = 8192
_PROBE_SEED = 20211


def fingerprints(meshes) -> list[tuple]:
    """One key per shape of packed Meshes, computed where the mesh lives with a single host sync:
    (vertex count, face count, and float64 sums of the vertices and of the local face indices
    weighted by fixed pseudo-random vectors). Two meshes share a key only if these sums coincide
    to the last bit: a moved, rotated, scaled or re-indexed mesh gets a new one."""
    dev = meshes.verts.device
    gen = torch.Generator().manual_seed(_PROBE_SEED)
    wv = torch.rand(2, 3, generator=gen, dtype=torch.float64).to(dev)
    wf = torch.rand(2, 3, generator=gen, dtype=torch.float64).to(dev)
    B = len(meshes)
    v = meshes.verts.detach().to(torch.float64)
    shape_of_vert = meshes.shape_of_vert()
    # the order of the vertices counts too: a weight per position within its own shape
    pos = (torch.arange(len(v), device=dev) - meshes.vert_offsets().index_select(0, shape_of_vert)).to(torch.float64)
    vsum = torch.zeros(B, 3, dtype=torch.float64, device=dev).index_add_(
        0, shape_of_vert, torch.stack([v @ wv[0], v @ wv[1], (v @ wv[0]) * torch.sin(pos)], 1))
    local = (meshes.faces - meshes.vert_offsets().index_select(0, meshes.shape_of_face())[:, None]).to(torch.float64)
    fsum = torch.zeros(B, 2, dtype=torch.float64, device=dev).index_add_(
        0, meshes.shape_of_face(), torch.stack([local @ wf[0], local @ wf[1]], 1))
    counts = torch.stack([meshes.verts_per_shape, meshes.faces_per_shape], 1).to(torch.float64)
    return [tuple(row) for row in torch.cat([counts, vsum, fsum], 1).tolist()]


def simplify_meshes(meshes, budget: int, image_size: int | None = None, min_iou: float = 0.0):
    """Apply ``simplify`` shape by shape to packed Meshes; returns new Meshes (no vertex gradients).

    Shapes already simplified for these settings on this device come from a cache keyed by
    ``fingerprints`` (no host round trip); only new shapes are copied to the host and simplified."""
    from ..data.shapes import Meshes

    if meshes.verts.requires_grad:
        raise ValueError("renderer.lod=true cannot be combined with gradients to vertex positions: "
                         "simplification creates new vertices; set renderer.lod=false")
    if len(meshes) == 0 or int(meshes.faces_per_shape.max()) <= budget:
        return meshes
    dev = meshes.verts.device
    settings = (budget, image_size if min_iou > 0 else None, min_iou, str(dev), meshes.verts.dtype)
    vs, fs = [], []
    offsets = fstarts = None
    for b, fp in enumerate(fingerprints(meshes)):
        key = (fp, *settings)
        hit = _DEVICE_CACHE.get(key)
        if hit is None:
            if offsets is None:
                offsets = meshes.vert_offsets().tolist()
                fstarts = (torch.cumsum(meshes.faces_per_shape, 0) - meshes.faces_per_shape).tolist()
            nv, nf = int(fp[0]), int(fp[1])
            v = meshes.verts[offsets[b]:offsets[b] + nv].detach().cpu().numpy()
            f = (meshes.faces[fstarts[b]:fstarts[b] + nf] - offsets[b]).cpu().numpy()
            r = simplify(v, f, budget, image_size, min_iou)
            hit = (torch.as_tensor(r.verts, device=dev, dtype=meshes.verts.dtype), torch.as_tensor(r.faces, device=dev))
            if len(_DEVICE_CACHE) >= DEVICE_CACHE_SIZE:
                _DEVICE_CACHE.pop(next(iter(_DEVICE_CACHE)))
            _DEVICE_CACHE[key] = hit
        vs.append(hit[0])
        fs.append(hit[1])
    return Meshes.from_list(vs, fs, meshes.names)
