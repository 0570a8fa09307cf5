"""Slow, obviously correct dense references: every pixel against every face / point (numpy, float64).

They return what the tile search returns (per pixel, the K nearest primitives), so the tests can
swap them in for the tile kernels and compare ids and final images.
"""
from __future__ import annotations

import numpy as np
import torch

from mvtn_exp.render import nearest


def _pixel_grid(H, W):
    j, i = np.meshgrid(np.arange(W), np.arange(H))
    x = (2 * j + 1) / W - 1
    y = 1 - (2 * i + 1) / H
    return x.reshape(-1), y.reshape(-1)


def _seg_sqdist(p, a, b):
    e = b - a
    ll = max(float(e @ e), 1e-30)
    t = np.clip(((p - a) @ e) / ll, 0, 1)
    d = p - a - t[:, None] * e
    return (d * d).sum(1)


def dense_face_search(xy, z, image, *, H, W, K, blur, znear, cull_backfaces, area_eps, num_images, ranking=None):
    """xy ``[N, 3, 2]`` NDC, z ``[N, 3]``, image ``[N]`` -> Selection (same contract as search_faces).

    Hard (blur 0): per pixel the covering faces by (depth, index). Soft: every face within
    ``blur``, by (minus the blend logit, index), the logit ``zinv / gamma + log p`` with log p = 0
    for covering faces and ``log sigmoid(-d^2 / sigma)`` otherwise (``ranking``, a SoftRanking).
    K=None keeps every candidate in the slots (the unlimited-K reference)."""
    xy = xy.detach().double().cpu().numpy()
    z = z.detach().double().cpu().numpy()
    image = image.cpu().numpy()
    px, py = _pixel_grid(H, W)
    P = np.stack([px, py], 1)
    cands = [[] for _ in range(num_images * H * W)]
    for f in range(len(xy)):
        v0, v1, v2 = xy[f]
        area2 = (v1[0] - v0[0]) * (v2[1] - v0[1]) - (v1[1] - v0[1]) * (v2[0] - v0[0])
        if (z[f] < znear).any() or abs(area2) <= area_eps or (cull_backfaces and area2 <= 0):
            continue
        # barycentrics by solving [v0 - v2, v1 - v2] [l0, l1]^T = p - v2
        T = np.array([[v0[0] - v2[0], v1[0] - v2[0]], [v0[1] - v2[1], v1[1] - v2[1]]])
        l01 = np.linalg.solve(T, (P - v2).T).T
        lam = np.concatenate([l01, 1 - l01.sum(1, keepdims=True)], 1)
        inside = (lam >= 0).all(1)
        d2 = np.minimum(np.minimum(_seg_sqdist(P, v1, v2), _seg_sqdist(P, v2, v0)), _seg_sqdist(P, v0, v1))
        ok = inside | (d2 <= blur * blur) if blur > 0 else inside
        lam = np.where(inside[:, None], lam, np.clip(lam, 0, None))
        lam = lam / lam.sum(1, keepdims=True)
        depth = 1.0 / (lam / z[f]).sum(1)
        if blur > 0 and ranking.by_depth:
            key = depth
        elif blur > 0:
            zf, zn = float(ranking.zfar[image[f]]), float(ranking.znear[image[f]])
            log_p = np.where(inside, 0.0, -np.logaddexp(0.0, d2 / ranking.sigma))
            key = -((zf - depth) / (zf - zn) / ranking.gamma + log_p)
        else:
            key = depth
        base = image[f] * H * W
        for p in np.nonzero(ok)[0]:
            cands[base + p].append((key[p], f))
    return _to_selection(cands, K)


def dense_point_search(xy, z, image, *, H, W, K, radius, znear, num_images):
    xy = xy.detach().double().cpu().numpy()
    z = z.detach().double().cpu().numpy()
    image = image.cpu().numpy()
    px, py = _pixel_grid(H, W)
    cands = [[] for _ in range(num_images * H * W)]
    for n in range(len(xy)):
        if z[n] < znear or (np.abs(xy[n]) > 1 + radius).any():
            continue
        d2 = (px - xy[n, 0]) ** 2 + (py - xy[n, 1]) ** 2
        for p in np.nonzero(d2 < radius * radius)[0]:
            cands[image[n] * H * W + p].append((z[n], n))
    return _to_selection(cands, K)


def _to_selection(cands, K) -> nearest.Selection:
    """Per pixel, sorted candidates -> the first K as slots and the others as the rest."""
    if K is None:
        K = max(1, max(len(c) for c in cands))
    pix, prim, rest_pix, rest_prim = [], [], [], []
    for p, c in enumerate(cands):
        if c:
            c.sort()
            ids = [f for *_, f in c]
            pix.append(p)
            prim.append(ids[:K] + [-1] * (K - len(ids[:K])))
            rest_pix += [p] * len(ids[K:])
            rest_prim += ids[K:]
    long = dict(dtype=torch.long)
    return nearest.Selection(torch.tensor(pix, **long), torch.tensor(prim, **long).reshape(-1, K),
                           torch.tensor(rest_pix, **long), torch.tensor(rest_prim, **long),
                           max((len(c) for c in cands), default=0))
