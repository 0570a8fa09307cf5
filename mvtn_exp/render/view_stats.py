"""How the predicted views spread: across shapes (do all shapes get one view?) and within a shape
(do a shape's M views collapse onto each other?), for learned selectors.

``view_spread``: for each view slot m, the mean angle (degrees) between shape n's camera direction
and the slot's mean direction over the shapes, averaged over the slots: 0 for a fixed selector,
small where a learned G gives every shape nearly the same view.
``view_separation``: the mean over shapes of the smallest angle (degrees) between two of the
shape's M camera directions (None at M = 1): 0 where two views coincide.
"""
from __future__ import annotations

import torch
from torch import Tensor

from ..data.view_detail import camera_positions


def _angle(u: Tensor, v: Tensor) -> Tensor:
    """Degrees between unit vectors (last dim 3), by atan2 (exact near 0 and 180)."""
    return torch.rad2deg(torch.atan2(torch.linalg.cross(u, v, dim=-1).norm(dim=-1), (u * v).sum(-1)))


def view_stats(azim: Tensor, elev: Tensor) -> dict:
    """``{"view_spread", "view_separation"}`` (degrees; module docstring) of views ``[N, M]``."""
    if azim.numel() == 0:
        return {"view_spread": 0.0, "view_separation": None}
    d = torch.from_numpy(camera_positions(azim.double().cpu().numpy(), elev.double().cpu().numpy(), 1.0))  # [N, M, 3]
    mean = d.mean(0, keepdim=True)
    norm = mean.norm(dim=-1, keepdim=True)
    # a slot whose directions cancel out (mean ~ 0) has no mean direction: 90 deg is its spread
    spread = torch.where(norm[..., 0] > 1e-9, _angle(d, mean / norm.clamp_min(1e-12)), torch.full_like(d[..., 0], 90.0))
    out = {"view_spread": float(spread.mean()), "view_separation": None}
    M = d.shape[1]
    if M > 1:
        i, j = torch.triu_indices(M, M, 1)
        out["view_separation"] = float(_angle(d[:, i], d[:, j]).min(1).values.mean())
    return out
