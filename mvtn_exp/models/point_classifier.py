"""A point-only C (``mvnet=point_classifier``): the run's point encoder classifies the points alone.

The paper's occlusion table compares MVTN with PointNet and DGCNN trained as point classifiers on
ModelNet40 point clouds (Table 5, L479-L498; L434, L989). This C reads the shape's points (the
first ``num_points``, null: all) through the run's ``point_encoder`` with ``out_features`` = the
class count and ignores the images; the model then renders nothing (``reads_images = False``:
``MVTN.render`` returns ``[B, M, 3, 0, 0]``), so a run costs what the point network costs. Views
are not learned (the config refuses a selector that learns or refines them, as for late fusion).
``features`` (retrieval) are the logits.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Optional, Union

from torch import Tensor, nn

from ..config.checks import at_least
from .multiview import MVNetConfig, register, views_move_with_c
from .point_encoders import build_point_encoder

if TYPE_CHECKING:  # pragma: no cover
    from ..config.schema import TrainConfig


class PointClassifier(nn.Module):
    """``forward(images, views, points [B, N, 3]) -> (logits [B, K], features = logits)``; images unused."""

    reads_points = True
    reads_images = False
    needs_views = False

    def __init__(self, backbone=None, num_classes: int = 40, weights=None,
                 point_encoder: Union[str, nn.Module] = "pointnet_paper", point_encoder_kwargs: Optional[dict] = None,
                 num_points: Optional[int] = None) -> None:
        super().__init__()
        if weights is not None:
            raise ValueError("mvnet=point_classifier has no 2D backbone: backbone.weights must be null")
        self.num_classes = self.feature_dim = int(num_classes)
        self.point_encoder = point_encoder if isinstance(point_encoder, nn.Module) else build_point_encoder(
            point_encoder, out_features=self.num_classes, **(point_encoder_kwargs or {}))
        self.num_points = num_points

    def normalize_input(self, mean, std) -> "PointClassifier":
        return self  # (no images are read)

    def forward(self, images: Optional[Tensor] = None, views=None, points: Optional[Tensor] = None) -> tuple[Tensor, Tensor]:
        if points is None or points.dim() != 3 or points.shape[-1] != 3:
            got = "none" if points is None else list(points.shape)
            raise ValueError(f"mvnet=point_classifier classifies the shape's points: forward needs points [B, N, 3], got {got}")
        if self.num_points is not None:
            points = points[:, :self.num_points]
        logits = self.point_encoder(points)
        return logits, logits

    def training_loss(self, logits: Tensor, labels: Tensor, loss_fn) -> Tensor:
        return loss_fn(logits, labels)


@register("point_classifier")
@dataclass
class PointClassifierConfig(MVNetConfig):
    """A point-only C: the run's ``point_encoder`` as the classifier (``num_points``: the first n of
    the shape's points, null: all). No images are rendered; ``backbone`` is not used."""

    name: str = "point_classifier"
    num_points: Optional[int] = None
    network = PointClassifier

    def validate(self) -> "PointClassifierConfig":
        super().validate()
        if self.num_points is not None:
            at_least("mvnet.num_points", self.num_points, 1)
        return self

    def check(self, cfg: "TrainConfig") -> None:
        moves = views_move_with_c(cfg)
        if moves:
            raise ValueError(f"mvnet=point_classifier classifies points without views; selector={cfg.selector.name} "
                             f"{moves} views against C: use a fixed layout (selector=circular)")
        if cfg.backbone.weights is not None:
            raise ValueError(f"backbone.weights={cfg.backbone.weights}: mvnet=point_classifier has no 2D backbone "
                             "(set backbone.weights=null)")
        if self.num_points is not None:
            cfg.point_encoder.check_points(self.num_points, f"mvnet.num_points={self.num_points}")

    def kwargs(self) -> dict:
        return {"num_points": self.num_points}
