"""Pose canonicalisation (``selector.canonical=pca``): each shape turned into its own principal frame
before G and R see it, so that a fixed layout looks at every shape from the same side of its shape.

The baseline a reviewer asks of learned views first: if the shapes' poses are random, align them,
then use fixed views. The frame of a shape, from its points ``[N, 3]`` (centred on their mean):

- the eigenvectors of the covariance, by decreasing variance, ``e1, e2, e3``;
- each turned so that the third moment of the points along it is >= 0 (the heavier tail
  positive: the usual sign rule of PCA alignment);
- the canonical axes ``x = e1`` (most spread), ``y = e3`` (least spread: a flat shape lies in the
  XZ plane and the fixed layout's elevation looks down on it), ``z = x cross y`` (a rotation, no
  mirror).

``R [B, 3, 3]`` has those axes as rows, so ``R @ p`` are a point's canonical coordinates and
turning a canonical shape again gives the identity (idempotent). Shapes with two equal variances
have no unique frame (a sphere, a cylinder's cross-section): any frame PCA returns is used, as in
every PCA alignment. Computed in float64; finite for any finite input, including a single point.
"""
from __future__ import annotations

import torch
from torch import Tensor, nn

from ..render.cameras import direction_angles, view_directions

def pca_frames(points: Tensor) -> Tensor:
    """``points [B, N, 3]`` -> ``R [B, 3, 3]`` (rows: canonical x, y, z in world coordinates; det +1)."""
    p = points.detach().double()
    c = p - p.mean(1, keepdim=True)
    cov = c.transpose(1, 2) @ c / max(p.shape[1], 1)
    _, vecs = torch.linalg.eigh(cov)  # ascending variance; columns are the eigenvectors
    e = vecs.flip(-1).transpose(1, 2)  # rows e1, e2, e3 by decreasing variance
    skew = torch.einsum("bkj,bnj->bkn", e, c).pow(3).mean(-1)
    e = e * torch.where(skew < 0, -1.0, 1.0).unsqueeze(-1)
    x, y = e[:, 0], e[:, 2]
    return torch.stack([x, y, torch.linalg.cross(x, y)], 1).to(points.dtype)


def world_views(views, R: Tensor):
    """Views ``(azim, elev, dist)`` ``[B, M]`` (degrees) chosen in the canonical frame ``R [B, 3, 3]``
    -> the same camera directions in the world frame (``R^T d``); the distance is unchanged."""
    azim, elev, dist = views
    d = view_directions(azim, elev)  # [B, M, 3]
    return (*direction_angles(torch.einsum("bji,bmj->bmi", R.to(d), d)), dist)


class CanonicalPose(nn.Module):
    """``forward(batch) -> (batch turned into each shape's principal frame, R [B, 3, 3])``: points,
    mesh vertices and any pose records of the batch turn together (``tasks.robustness.turn_batch``)."""

    def forward(self, batch: dict) -> tuple[dict, Tensor]:
        from ..tasks.robustness import turn_batch

        R = pca_frames(batch["points"])
        return turn_batch(batch, R), R
