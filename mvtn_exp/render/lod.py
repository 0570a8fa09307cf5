"""Level of detail: simplify meshes to a face budget the image resolution can show (cached).

The budget is a request: fast-simplification does not always reach it on open or non-manifold
meshes (real ModelNet samples: 18% reduction asked 90%). What it achieved is recorded and the
original mesh is kept whenever simplification fails or would corrupt it.
"""
from __future__ import annotations

import hashlib
import logging
from dataclasses import dataclass

import numpy as np
import torch

log = logging.getLogger(__name__)


@dataclass
class LodResult:
    verts: np.ndarray
    faces: np.ndarray
    faces_in: int
    budget: int

    @property
    def faces_out(self) -> int:
        return len(self.faces)


_CACHE: dict[tuple[str, int], LodResult] = {}


def face_budget(image_size: int, faces_per_pixel: float) -> int:
    return max(16, int(faces_per_pixel * image_size * image_size))


def simplify(verts: np.ndarray, faces: np.ndarray, budget: int) -> LodResult:
    """Simplify ``[V, 3]`` / ``[F, 3]`` to about ``budget`` faces; returns the input if it fits or fails."""
    if len(faces) <= budget:
        return LodResult(verts, faces, len(faces), budget)
    key = (hashlib.sha1(np.ascontiguousarray(verts, dtype=np.float32).tobytes()
                        + np.ascontiguousarray(faces, dtype=np.int64).tobytes()).hexdigest(), budget)
    hit = _CACHE.get(key)
    if hit is not None:
        return hit
    import fast_simplification

    try:
        v, f = fast_simplification.simplify(
            np.ascontiguousarray(verts, dtype=np.float32), np.ascontiguousarray(faces, dtype=np.int32),
            target_reduction=1.0 - budget / len(faces),
        )
        ok = len(f) > 0 and np.isfinite(v).all() and f.min() >= 0 and f.max() < len(v)
    except Exception as exc:  # keep the original mesh: LOD must never lose a shape
        log.warning("lod: simplification failed (%s); keeping %d faces", exc, len(faces))
        ok = False
    res = LodResult(v.astype(verts.dtype), f.astype(np.int64), len(faces), budget) if ok else LodResult(verts, faces, len(faces), budget)
    _CACHE[key] = res
    return res


def simplify_meshes(meshes, budget: int):
    """Apply ``simplify`` shape by shape to packed Meshes; returns new Meshes (no vertex gradients)."""
    from ..data.shapes import Meshes

    if meshes.verts.requires_grad:
        raise ValueError("renderer.lod=true cannot be combined with gradients to vertex positions: "
                         "simplification creates new vertices; set renderer.lod=false")
    if len(meshes) == 0 or int(meshes.faces_per_shape.max()) <= budget:
        return meshes
    vs, fs = [], []
    offsets = meshes.vert_offsets().tolist()
    fstart = 0
    for b, (nv, nf) in enumerate(zip(meshes.verts_per_shape.tolist(), meshes.faces_per_shape.tolist())):
        v = meshes.verts[offsets[b]:offsets[b] + nv].detach().cpu().numpy()
        f = (meshes.faces[fstart:fstart + nf] - offsets[b]).cpu().numpy()
        fstart += nf
        r = simplify(v, f, budget)
        vs.append(torch.as_tensor(r.verts, device=meshes.verts.device, dtype=meshes.verts.dtype))
        fs.append(torch.as_tensor(r.faces, device=meshes.verts.device))
    return Meshes.from_list(vs, fs, meshes.names)
