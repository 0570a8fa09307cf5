"""Dense reference for the hard (K=1) face search: every pixel against every alive face-view.

For timing only (``mvtn-bench`` compares it with ``mesh_raster.search_faces``): no boxes, tiles or
row spans, just the barycentric inside test and perspective-correct depth of all pixel centres of an
image against all alive face-views of that image, chunked over faces so its working memory stays
bounded (about 60 bytes per (pixel, face) pair in a chunk; ``chunk_pairs = 2**22`` -> ~250 MiB).

The arithmetic is the same as ``search_faces`` (same planes, same evaluation order, same depth and
tie rule: smallest depth, then smallest face-view index), so on the same ``ProjectedFaces`` the two
return identical selections; ``tests/test_bench.py`` checks that.
"""
from __future__ import annotations

import torch

from ..render import mesh_raster, nearest, tiles
from ..render.edge_distance import covers

DEFAULT_CHUNK_PAIRS = 1 << 22


def estimate_pairs(num_faces: int, views: int, H: int, W: int, batch: int = 1) -> int:
    """Upper bound on the (pixel, face-view) pairs of a scene before culling: ``B * M * F * H * W``.

    ``num_faces`` is the number of faces of one shape (all B shapes the same size).
    """
    return int(batch) * int(views) * int(num_faces) * int(H) * int(W)


def dense_pairs(pf: mesh_raster.ProjectedFaces, H: int, W: int) -> int:
    """Exact number of (pixel, face-view) pairs ``dense_search`` tests: ``H * W * alive face-views``."""
    return int(H) * int(W) * int(pf.alive.sum())


def dense_search(pf: mesh_raster.ProjectedFaces, *, H: int, W: int, chunk_pairs: int = DEFAULT_CHUNK_PAIRS) -> nearest.Selection:
    """Nearest covering face per pixel (K=1, no blur) by brute force.

    Returns a ``nearest.Selection``: pix ``[P]`` ascending flat pixel index ``image*H*W + row*W + col``,
    prim ``[P, 1]`` face-view index; only pixels covered by at least one face appear.
    """
    dev = pf.cols.device
    with torch.no_grad():
        HW = H * W
        fv = torch.nonzero(pf.alive).squeeze(1)
        if len(fv) == 0:
            return nearest.Selection(torch.zeros(0, dtype=torch.long, device=dev), torch.zeros(0, 1, dtype=torch.long, device=dev))
        img = pf.image_of(fv)
        # group face-views by image; the stable sort keeps them in ascending fv inside each image
        order = torch.sort(img, stable=True).indices
        fv, img = fv.index_select(0, order), img.index_select(0, order)
        table = mesh_raster.face_table(pf.cols.index_select(1, fv))  # [18, F]
        px, py = tiles.pixel_centres(torch.arange(HW, device=dev), H, W, table.dtype)
        px, py = px[None, :], py[None, :]  # [1, HW]
        num_images = pf.num_images
        best_depth = torch.full((num_images, HW), float("inf"), dtype=table.dtype, device=dev)
        best_fv = torch.full((num_images, HW), -1, dtype=torch.long, device=dev)
        images, counts = torch.unique_consecutive(img, return_counts=True)
        step = max(1, int(chunk_pairs) // HW)
        start = 0
        for b, n in zip(images.tolist(), counts.tolist()):
            bd, bf = best_depth[b], best_fv[b]
            for s in range(start, start + n, step):
                e = min(s + step, start + n)
                t = table[:, s:e, None]  # [18, Fc, 1]
                # the search's arithmetic (mesh_raster.barycentrics / inverse_depth), broadcast to [Fc, HW]
                lam = [torch.addcmul(torch.addcmul(t[3 * k + 2], t[3 * k], px), t[3 * k + 1], py) for k in range(3)]
                inside = covers(lam)
                iz = t[mesh_raster.TABLE_INV_Z:mesh_raster.TABLE_INV_Z + 3]
                depth = 1.0 / torch.addcmul(torch.addcmul(lam[0] * iz[0], lam[1], iz[1]), lam[2], iz[2]).clamp(min=1e-12)
                del lam
                depth = torch.where(inside, depth, torch.full_like(depth, float("inf")))
                dmin, arg = depth.min(0)  # first (smallest fv) index among equal minima
                better = dmin < bd  # strict: earlier chunks (smaller fv) win ties
                bd.copy_(torch.where(better, dmin, bd))
                bf.copy_(torch.where(better, fv[s:e].index_select(0, arg), bf))
            start += n
        flat = best_fv.reshape(-1)
        pix = torch.nonzero(flat >= 0).squeeze(1)
        return nearest.Selection(pix, flat.index_select(0, pix).unsqueeze(1))
