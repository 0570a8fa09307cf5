"""A multi-view network that treats the M views as a set: self-attention over per-view features.

``images [B, M, 3, H, W] -> (logits [B, num_classes], features [B, width])``:

    f = backbone.features(view)       [B, M, D]     shared over the views, as in MVCNN
    x = proj(f)                       [B, M, width] (identity when width = D)
    x = x + MHA(LN(x)); x = x + MLP(LN(x))   repeated ``blocks`` times (pre-norm)
    features = pool_M(LN(x))          [B, width]    max or mean over the views
    logits = head(dropout(features))

There is no positional encoding and no view index anywhere, so the output does not depend on
the order of the views, and any M >= 1 works (M = 1: attention over one view). Since the paper,
aggregators of this kind (views as an unordered set with attention) have reported the strongest
ModelNet40 numbers; this is the plain version: a few blocks over the per-view features.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Optional, Union

from torch import Tensor, nn

from ..config.checks import at_least
from .backbones import PathLike
from .multiview import MVCNN, MVCNNConfig, register

if TYPE_CHECKING:  # pragma: no cover
    from ..config.schema import TrainConfig


class ViewBlock(nn.Module):
    """Pre-norm transformer block over a set of view tokens ``[B, M, width] -> [B, M, width]``."""

    def __init__(self, width: int, heads: int, mlp_ratio: float = 2.0, dropout: float = 0.0) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(width)
        self.attn = nn.MultiheadAttention(width, heads, dropout=dropout, batch_first=True)
        self.norm2 = nn.LayerNorm(width)
        hidden = int(round(width * mlp_ratio))
        self.mlp = nn.Sequential(nn.Linear(width, hidden), nn.GELU(), nn.Dropout(dropout), nn.Linear(hidden, width))

    def forward(self, x: Tensor) -> Tensor:
        h = self.norm1(x)
        x = x + self.attn(h, h, h, need_weights=False)[0]
        return x + self.mlp(self.norm2(x))


class ViewTransformer(MVCNN):
    """MVCNN's shared backbone, then ``blocks`` self-attention blocks over the M view features.

    Args (besides MVCNN's ``backbone``, ``num_classes``, ``weights``, ``pool``, ``dropout``):
        blocks: transformer blocks (>= 1).
        heads: attention heads; must divide ``width``.
        width: token width (None: the backbone's ``feature_dim``; otherwise a linear projection
            from it).
        mlp_ratio: hidden width of each block's MLP over ``width``.
    """

    def __init__(self, backbone: Union[nn.Module, str], num_classes: int, weights: Optional[PathLike] = None,
                 pool: str = "max", dropout: float = 0.0, blocks: int = 2, heads: int = 4,
                 width: Optional[int] = None, mlp_ratio: float = 2.0) -> None:
        super().__init__(backbone, num_classes, weights=weights, pool=pool, dropout=dropout)
        d = self.feature_dim
        width = d if width is None else int(width)
        check_view_transformer(blocks, heads, width)
        self.proj = nn.Identity() if width == d else nn.Linear(d, width)
        self.blocks = nn.ModuleList(ViewBlock(width, heads, mlp_ratio, dropout) for _ in range(blocks))
        self.norm = nn.LayerNorm(width)
        self.feature_dim = width
        self.head = nn.Linear(width, num_classes)

    def aggregate(self, feats: Tensor) -> Tensor:
        """``[B, M, D] -> [B, width]``: attention over the views, then max or mean over them."""
        x = self.proj(feats)
        for block in self.blocks:
            x = block(x)
        return super().aggregate(self.norm(x))


def check_view_transformer(blocks: int, heads: int, width: int) -> None:
    """One-line errors naming the ``mvnet`` keys for settings the view transformer cannot take."""
    if blocks < 1:
        raise ValueError(f"mvnet.blocks={blocks}: the view transformer needs at least 1 block")
    if heads < 1 or width % heads:
        raise ValueError(f"mvnet.heads={heads} must be >= 1 and divide the token width {width} "
                         "(mvnet.width, or the backbone's feature size when mvnet.width is null)")


@register("view_transformer")
@dataclass
class ViewTransformerConfig(MVCNNConfig):
    """View transformer: self-attention over the view features as a set, then ``pool``. ``blocks``
    blocks with ``heads`` heads, tokens ``width`` wide (null: the backbone's feature size), MLP
    ``mlp_ratio`` x wide."""

    name: str = "view_transformer"
    blocks: int = 2
    heads: int = 4
    width: Optional[int] = None
    mlp_ratio: float = 2.0
    network = ViewTransformer

    def validate(self) -> "ViewTransformerConfig":
        super().validate()
        at_least("mvnet.blocks", self.blocks, 1)
        at_least("mvnet.heads", self.heads, 1)
        if self.width is not None:
            at_least("mvnet.width", self.width, 1)
        at_least("mvnet.mlp_ratio", self.mlp_ratio, 0.0, strict=True)
        return self

    def check(self, cfg: "TrainConfig") -> None:
        feature_dim = cfg.backbone.feature_dim
        width = self.width if self.width is not None else feature_dim
        if width % self.heads:
            raise ValueError(f"mvnet.heads={self.heads} must divide the view transformer's token width {width} "
                             f"(mvnet.width={self.width}; null takes backbone={cfg.backbone.name}'s feature size "
                             f"{feature_dim})")

    def kwargs(self) -> dict:
        return {**super().kwargs(), "blocks": self.blocks, "heads": self.heads, "width": self.width,
                "mlp_ratio": self.mlp_ratio}
