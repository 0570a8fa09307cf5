"""DGCNN (Wang et al. 2019), the paper's alternative point encoder for G.

``points [B, N, 3] -> features [B, out_features]``:

    x0 = points                                          [B, 3, N]
    x_l = max_j LeakyReLU(BN(W_l [x_i, x_j - x_i]))       EdgeConv over the k nearest neighbours
                                                         of x_{l-1} in feature space ("dynamic
                                                         graph"), widths 64, 64, 128, 256
    g = LeakyReLU(BN(W [x_1, x_2, x_3, x_4]))             [B, emb_dims, N]
    features = head([max_N g, mean_N g])                 [B, out_features]
    head = Linear(2 emb_dims, 512)-BN-LeakyReLU-Dropout, Linear(512, 256)-BN-LeakyReLU-Dropout,
           Linear(256, out_features)                     the original classifier (dropout 0.5)

The neighbours of the first layer are found in xyz, those of the later layers in the previous
layer's features; each point counts as its own nearest neighbour, as in the reference code. Needs
N >= k points (checked at compose time against the points G reads).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import torch
from torch import Tensor, nn

from ..config.checks import at_least, fraction
from .point_encoders import PointEncoderConfig, register

EDGE_WIDTHS = (64, 64, 128, 256)


def knn(x: Tensor, k: int) -> Tensor:
    """``x [B, C, N]`` -> indices of each point's ``k`` nearest points (itself included) ``[B, N, k]``."""
    sq = x.pow(2).sum(1)  # [B, N]
    neg = 2 * torch.bmm(x.transpose(1, 2), x) - sq[:, :, None] - sq[:, None, :]  # -|xi - xj|^2
    return neg.topk(k, dim=-1).indices


def edge_features(x: Tensor, k: int) -> Tensor:
    """``x [B, C, N]`` -> ``[B, 2C, N, k]``: ``(x_j - x_i, x_i)`` for the k nearest ``j`` of each ``i``."""
    B, C, N = x.shape
    idx = knn(x.detach(), k)  # the graph is rebuilt from values; no gradient through the choice
    pts = x.transpose(1, 2)  # [B, N, C]
    nb = pts.reshape(B * N, C).index_select(0, (idx + torch.arange(B, device=x.device)[:, None, None] * N).reshape(-1))
    nb = nb.view(B, N, k, C)
    centre = pts[:, :, None, :].expand(B, N, k, C)
    return torch.cat([nb - centre, centre], dim=3).permute(0, 3, 1, 2)


class EdgeConv(nn.Module):
    """``[B, cin, N] -> [B, cout, N]``: shared MLP on edge features, max over the k neighbours."""

    def __init__(self, cin: int, cout: int, k: int) -> None:
        super().__init__()
        self.k = k
        self.mlp = nn.Sequential(nn.Conv2d(2 * cin, cout, 1, bias=False), nn.BatchNorm2d(cout), nn.LeakyReLU(0.2))

    def forward(self, x: Tensor) -> Tensor:
        return self.mlp(edge_features(x, self.k)).amax(dim=3)


class DGCNN(nn.Module):
    """DGCNN encoder: points ``[B, N, 3]`` -> ``[B, out_features]`` (see the module docstring).

    ``k``: neighbours per point (20 in the paper); ``emb_dims``: width of the global feature
    before pooling (1024); ``head_widths``: hidden widths of the head (Linear + BN + LeakyReLU +
    Dropout(``dropout``); the original ``(512, 256)``; ``()``: one linear layer from the pooled
    ``2 * emb_dims``, this project's former head).
    """

    def __init__(self, out_features: int = 40, k: int = 20, emb_dims: int = 1024,
                 head_widths: Sequence[int] = (512, 256), dropout: float = 0.5) -> None:
        super().__init__()
        if int(out_features) != out_features or out_features < 1:
            raise ValueError(f"DGCNN: out_features must be an integer >= 1, got {out_features!r}")
        if k < 1 or emb_dims < 1:
            raise ValueError(f"DGCNN: point_encoder.k={k} and point_encoder.emb_dims={emb_dims} must be >= 1")
        self.out_features, self.k = int(out_features), int(k)
        widths = (3, *EDGE_WIDTHS)
        self.edges = nn.ModuleList(EdgeConv(a, b, self.k) for a, b in zip(widths[:-1], widths[1:]))
        self.embed = nn.Sequential(nn.Conv1d(sum(EDGE_WIDTHS), emb_dims, 1, bias=False), nn.BatchNorm1d(emb_dims),
                                   nn.LeakyReLU(0.2))
        layers: list[nn.Module] = []
        dims = (2 * emb_dims, *[int(w) for w in head_widths])
        for a, b in zip(dims[:-1], dims[1:]):
            layers += [nn.Linear(a, b, bias=False), nn.BatchNorm1d(b), nn.LeakyReLU(0.2), nn.Dropout(dropout)]
        self.head = nn.Sequential(*layers, nn.Linear(dims[-1], self.out_features))

    def forward(self, points: Tensor) -> Tensor:
        """``[B, N, 3] -> [B, out_features]``."""
        if points.dim() != 3 or points.shape[-1] != 3:
            raise ValueError(f"DGCNN expects points [B, N, 3], got {list(points.shape)}")
        if points.shape[1] < self.k:
            raise ValueError(f"DGCNN: {points.shape[1]} points per shape, fewer than point_encoder.k={self.k} "
                             "neighbours")
        x = points.transpose(1, 2)
        feats = []
        for edge in self.edges:
            x = edge(x)
            feats.append(x)
        g = self.embed(torch.cat(feats, dim=1))  # [B, emb_dims, N]
        return self.head(torch.cat([g.amax(dim=2), g.mean(dim=2)], dim=1))


@register("dgcnn")
@dataclass
class DGCNNConfig(PointEncoderConfig):
    """DGCNN: ``k`` neighbours per point in feature space, ``emb_dims`` wide before pooling;
    ``head_widths`` (the original ``[512, 256]``; ``[]``: one linear layer) with ``dropout``."""

    name: str = "dgcnn"
    network = DGCNN
    k: int = 20
    emb_dims: int = 1024
    head_widths: list[int] = field(default_factory=lambda: [512, 256])
    dropout: float = 0.5

    def validate(self) -> "DGCNNConfig":
        super().validate()
        at_least("point_encoder.k", self.k, 1)
        at_least("point_encoder.emb_dims", self.emb_dims, 1)
        for w in self.head_widths:
            at_least("point_encoder.head_widths", w, 1)
        fraction("point_encoder.dropout", self.dropout)
        return self

    def kwargs(self) -> dict:
        return {"k": self.k, "emb_dims": self.emb_dims, "head_widths": tuple(int(w) for w in self.head_widths),
                "dropout": float(self.dropout)}

    def check_points(self, n: int, where: str) -> None:
        if n < self.k:
            raise ValueError(f"point_encoder.k={self.k}: DGCNN needs at least k points, G reads {n} ({where})")
