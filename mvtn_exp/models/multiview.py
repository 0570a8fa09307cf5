"""Multi-view network C of MVTN: one shared 2D backbone per view, then view aggregation.

``images [B, M, 3, H, W] -> (logits [B, num_classes], features [B, feature_dim])``.
The M views are folded into the batch (one backbone call on ``[B*M, 3, H, W]``) and nothing
is detached, so gradients reach the images and, through the renderer, the cameras.

The backbone's own ``fc`` is never called (only ``backbone.features``); the classifier is
``self.head``. Its ``fc`` parameters therefore get no gradient (DDP: ``find_unused_parameters``).

A network is one registered config class (``mvnet=NAME``, ``MVNetConfig``) whose ``network`` is its
constructor; ``build_multiview(name, ...)`` builds it by name.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, ClassVar, Optional, Union

import torch
from torch import Tensor, nn

from ..config.checks import fraction, one_of
from ..config.options import OPTIONS, OptionConfig
from .backbones import IMAGENET_MEAN, IMAGENET_STD, PathLike, build_backbone, load_weights

if TYPE_CHECKING:  # pragma: no cover
    from ..config.schema import TrainConfig

POOLS = ("max", "mean")


class MVCNN(nn.Module):
    """MVCNN: shared backbone, view pooling over M, then ``Linear(feature_dim, num_classes)``.

    Args:
        backbone: a registered backbone name (``"resnet18"``, ``"small_cnn"``, ...) or a module
            with ``feature_dim`` and ``features(x [N, 3, H, W]) -> [N, feature_dim]``.
        num_classes: K, the number of logits.
        weights: optional local state_dict file loaded into the backbone (a classifier of another
            size in the file is ignored, see ``backbones.load_weights``).
        pool: ``"max"`` (MVCNN) or ``"mean"`` over views. With max pooling each feature channel
            takes its gradient from the single view that wins it, so a view that wins no channel
            gets exactly zero gradient (neither it nor its camera learns from that sample); with
            mean pooling every view gets ``1/M`` of the gradient.
        dropout: dropout probability on the pooled descriptor before the head.

    Pooling is symmetric in the views, so the output is invariant to their order.

    ``forward(images, views=None)``: every multi-view network takes the views ``(azim, elev, dist)``
    ``[B, M]`` the images were rendered from; those with ``needs_views`` (ViewGCN) use them, the
    others ignore them. ``training_loss`` is the loss the trainer minimises (a network with
    auxiliary outputs adds their losses).
    """

    needs_views = False

    def __init__(self, backbone: Union[nn.Module, str], num_classes: int,
                 weights: Optional[PathLike] = None, pool: str = "max", dropout: float = 0.0) -> None:
        super().__init__()
        if pool not in POOLS:
            raise ValueError(f"unknown view pooling {pool!r}; allowed: {', '.join(POOLS)}")
        if isinstance(backbone, str):
            backbone = build_backbone(backbone, num_classes=num_classes, weights=weights)
        elif weights is not None:
            load_weights(backbone, weights)
        if not hasattr(backbone, "features") or not hasattr(backbone, "feature_dim"):
            raise TypeError(f"backbone {type(backbone).__name__} needs `features(x)` and `feature_dim`")
        self.backbone = backbone
        self.feature_dim = int(backbone.feature_dim)
        self.num_classes = num_classes
        self.pool = pool
        self.dropout = nn.Dropout(dropout)
        self.head = nn.Linear(self.feature_dim, num_classes)
        self.register_buffer("input_mean", None, persistent=False)  # set by normalize_input
        self.register_buffer("input_std", None, persistent=False)

    def normalize_input(self, mean, std) -> "MVCNN":
        """Scale every view ``(x - mean) / std`` per channel before the backbone (ImageNet's for
        pretrained weights); kept out of the state_dict (a setting, not a learned value)."""
        self.register_buffer("input_mean", torch.tensor(mean, dtype=torch.float32).view(1, 1, -1, 1, 1), persistent=False)
        self.register_buffer("input_std", torch.tensor(std, dtype=torch.float32).view(1, 1, -1, 1, 1), persistent=False)
        return self

    def view_features(self, images: Tensor) -> Tensor:
        """``[B, M, C, H, W] -> [B, M, feature_dim]``: the backbone on every view, one call."""
        if images.dim() != 5 or images.shape[1] < 1:
            raise ValueError(f"{type(self).__name__} expects images [B, M, C, H, W] with M >= 1, "
                             f"got {list(images.shape)}")
        if self.input_mean is not None:
            images = (images - self.input_mean.to(images.dtype)) / self.input_std.to(images.dtype)
        b, m = images.shape[:2]
        feats = self.backbone.features(images.reshape(b * m, *images.shape[2:]))  # [B*M, D]
        return feats.reshape(b, m, -1)

    def aggregate(self, feats: Tensor) -> Tensor:
        """``[B, M, D] -> [B, D]`` view pooling (max or mean over M)."""
        return feats.amax(dim=1) if self.pool == "max" else feats.mean(dim=1)

    def forward(self, images: Tensor, views=None) -> tuple[Tensor, Tensor]:
        """``[B, M, 3, H, W] -> (logits [B, num_classes], features [B, feature_dim])``.

        ``features`` is the pooled shape descriptor before dropout and the head (for retrieval).
        ``views`` is not used (see the class docstring).
        """
        features = self.aggregate(self.view_features(images))
        return self.head(self.dropout(features)), features

    def training_loss(self, logits: Tensor, labels: Tensor, loss_fn) -> Tensor:
        """The training objective of the last forward: ``loss_fn(logits [B, K], labels [B])``."""
        return loss_fn(logits, labels)


class LogitMean(MVCNN):
    """Score averaging: classify every view with the shared head, then average the M logits
    (``mvnet=logit_mean``; not the paper's late fusion, which is ``mvnet=late_fusion``,
    ``models/late_fusion.py``).

    Same interface as MVCNN; ``features [B, feature_dim]`` is the mean of the view features.
    Note: the head is linear, so without dropout (or in eval mode) the logits equal
    ``head(mean_m f_m)``, i.e. MVCNN with ``pool="mean"``; the variants differ only in where
    dropout acts (per view here, on the pooled vector there). ``pool`` is fixed to ``"mean"``.
    """

    def __init__(self, backbone: Union[nn.Module, str], num_classes: int,
                 weights: Optional[PathLike] = None, pool: str = "mean", dropout: float = 0.0) -> None:
        if pool != "mean":
            raise ValueError(f"LogitMean averages views; pool must be 'mean', got {pool!r}")
        super().__init__(backbone, num_classes, weights=weights, pool="mean", dropout=dropout)

    def forward(self, images: Tensor, views=None) -> tuple[Tensor, Tensor]:
        """``[B, M, 3, H, W] -> (logits [B, num_classes], features [B, feature_dim])``."""
        feats = self.view_features(images)                          # [B, M, D]
        logits = self.head(self.dropout(feats)).mean(dim=1)         # [B, M, K] -> [B, K]
        return logits, feats.mean(dim=1)


def build_multiview(name: str, backbone: Union[nn.Module, str], num_classes: int, **kw) -> nn.Module:
    """Build a registered multi-view network: ``[B, M, 3, H, W] -> (logits [B, K], features [B, D])``.

    ``kw`` goes to the constructor (the option's ``network``: ``weights``, ``pool``, ``dropout``;
    ``view_transformer`` also takes ``blocks``, ``heads``, ``width``, ``mlp_ratio``; ``viewgcn`` takes
    ``k``; ``late_fusion`` and ``point_classifier`` take ``point_encoder``, ``point_encoder_kwargs``,
    ``num_points``).
    """
    return OPTIONS["mvnet"].lookup(name, "multi-view network").network(backbone, num_classes, **kw)


# ----------------------------------------------------------------------------- config options (mvnet=NAME)
register = OPTIONS["mvnet"].register


@dataclass
class MVNetConfig(OptionConfig):
    """The multi-view network C (``mvnet=NAME``): ``dropout`` on the pooled descriptor. A net with a
    training schedule of its own (ViewGCN's stages) overrides ``stage_span`` / ``holds_views`` /
    ``start_epoch``; the trainer calls them for every net."""

    dropout: float = 0.0

    kind = "mvnet"
    any_view_set = True  # C takes any set of views as one shape (raced hypotheses can be pooled)
    # the constructor: (backbone name or module, num_classes, weights=, **kwargs(), **point_kwargs()) -> C
    network: ClassVar[Callable[..., nn.Module]]

    def validate(self) -> "MVNetConfig":
        super().validate()
        fraction("mvnet.dropout", self.dropout)
        return self

    def kwargs(self) -> dict:
        """Constructor arguments beyond the backbone, the class count and the weights."""
        return {"dropout": self.dropout}

    def point_kwargs(self, point_encoder) -> dict:
        """Constructor arguments from the run's point encoder option, for a C that reads the shape's
        points (its network's ``reads_points``); none for the others or without an option."""
        if point_encoder is None or not getattr(type(self).network, "reads_points", False):
            return {}
        return {"point_encoder": point_encoder.name, "point_encoder_kwargs": point_encoder.kwargs()}

    def build(self, backbone: str, num_classes: int, weights: Optional[str] = None,
              input_norm: str = "none", point_encoder=None) -> nn.Module:
        """The net (``network``); ``input_norm="imagenet"`` scales its input by ImageNet's mean and std;
        ``point_encoder`` (the run's ``point_encoder`` option) serves a net that reads points."""
        net = type(self).network(backbone, num_classes, weights=weights, **self.kwargs(),
                                 **self.point_kwargs(point_encoder))
        return net.normalize_input(IMAGENET_MEAN, IMAGENET_STD) if input_norm == "imagenet" else net

    def stage_span(self, epoch: int, epochs: int) -> tuple[int, int]:
        """``(first epoch, epochs)`` of the training stage holding 0-based ``epoch``: the whole run."""
        return 0, epochs

    def holds_views(self, epoch: int) -> bool:
        """Whether 0-based ``epoch`` trains C on G's initial views with G frozen; never by default."""
        return False

    def start_epoch(self, mvnet: nn.Module, epoch: int) -> Optional[str]:
        """Prepare the net for ``epoch``; a line to log when model selection restarts (None: it does not)."""
        return None


def views_move_with_c(cfg: "TrainConfig") -> Optional[str]:
    """``"learns"`` / ``"refines"`` when the run's selector moves its views against C (a learned G,
    or one optimised per batch), else None: a C that reads the shape's points (late fusion, the
    point classifier) is called without them there, so it needs fixed views."""
    if cfg.selector.learned:
        return "learns"
    return "refines" if cfg.selector.uses_camera_gradient() else None


@register("mvcnn")
@dataclass
class MVCNNConfig(MVNetConfig):
    """MVCNN: the shared backbone's view features pooled (``pool``: max | mean), a linear classifier."""

    name: str = "mvcnn"
    pool: str = "max"
    network = MVCNN

    def validate(self) -> "MVCNNConfig":
        super().validate()
        one_of("mvnet.pool", self.pool, POOLS)
        return self

    def kwargs(self) -> dict:
        return {"pool": self.pool, "dropout": self.dropout}


@register("logit_mean")
@dataclass
class LogitMeanConfig(MVCNNConfig):
    """Score averaging: each view classified on its own, the M logits averaged (``pool``: mean)."""

    name: str = "logit_mean"
    pool: str = "mean"
    network = LogitMean

    def validate(self) -> "LogitMeanConfig":
        super().validate()
        if self.pool != "mean":
            raise ValueError(f"mvnet.pool={self.pool}: mvnet=logit_mean averages the views' logits (pool=mean only; "
                             "max pooling of features: mvnet=mvcnn)")
        return self
