"""The paper's late fusion (``mvnet=late_fusion``): a point encoder and MVCNN fused at the last layer.

The paper's alternative to MVTN (main text L555-L556, supplement Table S4, L1207-L1259): "PointNet
and MVCNN can be max pooled together at the last layers and trained jointly", on fixed circular
or spherical views. Here the run's point encoder (``point_encoder=pointnet_paper | dgcnn | ...``)
reads the shape's points and ends in ``feature_dim`` outputs (the backbone's feature size: 512
for ResNet-18, 2048 for ResNet-50), so that its vector joins the M view features as one more
member of the pool; the pooled vector goes through dropout and the linear head, as in MVCNN. The
paper does not say how the two widths are matched; sizing the encoder's last layer to the view
features is this project's reading (the paper's G sizes the same layer to b = 40).

C then reads the points as well as the images: ``forward(images, views, points)``; the model
hands it the (posed) points of the batch (``MVTN.mvnet_forward``). The views stay fixed (the
paper's setup), which the config checks: a selector that learns or refines views against C
calls C without the points.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Optional, Union

import torch
from torch import Tensor, nn

from ..config.checks import at_least
from .backbones import PathLike
from .multiview import MVCNN, MVCNNConfig, register, views_move_with_c
from .point_encoders import build_point_encoder

if TYPE_CHECKING:  # pragma: no cover
    from ..config.schema import TrainConfig


class PointLateFusion(MVCNN):
    """``forward(images [B, M, 3, H, W], views, points [B, N, 3]) -> (logits [B, K], features [B, D])``.

    ``features``: the pool (``pool``: max, the paper's, or mean) of the M view features and the
    point encoder's ``[B, D]`` vector; ``num_points``: the encoder reads the first n points (the
    batch's points are uniform surface samples in random order; None: all of them).
    """

    reads_points = True

    def __init__(self, backbone: Union[nn.Module, str], num_classes: int, weights: Optional[PathLike] = None,
                 pool: str = "max", dropout: float = 0.0, point_encoder: Union[str, nn.Module] = "pointnet_paper",
                 point_encoder_kwargs: Optional[dict] = None, num_points: Optional[int] = None) -> None:
        super().__init__(backbone, num_classes, weights=weights, pool=pool, dropout=dropout)
        if isinstance(point_encoder, nn.Module):
            self.point_encoder = point_encoder
        else:
            self.point_encoder = build_point_encoder(point_encoder, out_features=self.feature_dim,
                                                     **(point_encoder_kwargs or {}))
        self.num_points = num_points

    def forward(self, images: Tensor, views=None, points: Optional[Tensor] = None) -> tuple[Tensor, Tensor]:
        if points is None or points.dim() != 3 or points.shape[-1] != 3:
            got = "none" if points is None else list(points.shape)
            raise ValueError(f"mvnet=late_fusion fuses the shape's points with its views: forward needs points "
                             f"[B, N, 3], got {got}")
        if len(points) != len(images):
            raise ValueError(f"mvnet=late_fusion: {len(images)} shapes of images but {len(points)} of points")
        if self.num_points is not None:
            points = points[:, :self.num_points]
        view_feats = self.view_features(images)  # [B, M, D]
        point_feat = self.point_encoder(points.to(view_feats.dtype))  # [B, D]
        features = self.aggregate(torch.cat([view_feats, point_feat.unsqueeze(1).to(view_feats.dtype)], 1))
        return self.head(self.dropout(features)), features


@register("late_fusion")
@dataclass
class LateFusionConfig(MVCNNConfig):
    """The paper's late fusion: the run's ``point_encoder`` beside MVCNN, pooled together
    (``pool``: max, the paper's; or mean); ``num_points``: the encoder reads the first n of the
    shape's points (null: all)."""

    name: str = "late_fusion"
    pool: str = "max"
    num_points: Optional[int] = None
    network = PointLateFusion

    def validate(self) -> "LateFusionConfig":
        super().validate()
        if self.num_points is not None:
            at_least("mvnet.num_points", self.num_points, 1)
        return self

    def check(self, cfg: "TrainConfig") -> None:
        """The paper fuses on fixed views; a selector that learns or refines its views against C
        calls C without the shape's points."""
        moves = views_move_with_c(cfg)
        if moves:
            raise ValueError(f"mvnet=late_fusion fuses a point encoder with fixed views (the paper's setup, L556); "
                             f"selector={cfg.selector.name} {moves} its views against C: "
                             "use a fixed layout (selector=circular, spherical, ...) or mvnet=mvcnn")
        n = self.num_points
        if n is not None:
            cfg.point_encoder.check_points(n, f"mvnet.num_points={n}")

    def kwargs(self) -> dict:
        return {**super().kwargs(), "num_points": self.num_points}
