"""Vision Transformers as view backbones: ``vit_tiny``, ``vit_small`` and ``vit_base`` (patch 16).

``[N, 3, H, W] -> [N, num_classes]``; ``features(x) -> [N, feature_dim]`` is the class token
after the last block and LayerNorm (192-d tiny, 384-d small, 768-d base). H and W may be any multiple of 16:
the position embedding is stored for a 14 x 14 grid (224 px, as in the released weights) and
resampled bicubically to the input's grid, so one set of weights serves every image size.

``state_dict`` keys and shapes are timm's ``vit_{tiny,small,base}_patch16_224``
(``patch_embed.proj``, ``cls_token``, ``pos_embed``, ``blocks.i.{norm1,attn.qkv,attn.proj,norm2,
mlp.fc1,mlp.fc2}``, ``norm``, ``head``), so such a file loads with ``backbone.weights=PATH``
through ``backbones.load_weights`` (a head of another class count is left fresh; MAE's and DINO's
ViT-B/16 files hold the same names without a head). ``backbone.weights=imagenet`` fetches DeiT's
(``models/pretrained.py``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .backbones import BackboneConfig, register

if TYPE_CHECKING:  # pragma: no cover
    from ..config.schema import TrainConfig

PATCH = 16
REF_GRID = 14  # 224 / 16: the grid the position embedding is stored for


class Attention(nn.Module):
    def __init__(self, dim: int, heads: int) -> None:
        super().__init__()
        self.heads = heads
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: Tensor) -> Tensor:
        B, T, D = x.shape
        q, k, v = self.qkv(x).view(B, T, 3, self.heads, D // self.heads).permute(2, 0, 3, 1, 4)
        return self.proj(F.scaled_dot_product_attention(q, k, v).transpose(1, 2).reshape(B, T, D))


class Mlp(nn.Module):
    def __init__(self, dim: int, hidden: int) -> None:
        super().__init__()
        self.fc1, self.act, self.fc2 = nn.Linear(dim, hidden), nn.GELU(), nn.Linear(hidden, dim)

    def forward(self, x: Tensor) -> Tensor:
        return self.fc2(self.act(self.fc1(x)))


class Block(nn.Module):
    """Pre-norm transformer block ``[B, T, D] -> [B, T, D]`` (timm's names)."""

    def __init__(self, dim: int, heads: int, mlp_ratio: float = 4.0) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=1e-6)
        self.attn = Attention(dim, heads)
        self.norm2 = nn.LayerNorm(dim, eps=1e-6)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))

    def forward(self, x: Tensor) -> Tensor:
        x = x + self.attn(self.norm1(x))
        return x + self.mlp(self.norm2(x))


class PatchEmbed(nn.Module):
    def __init__(self, in_channels: int, dim: int) -> None:
        super().__init__()
        self.proj = nn.Conv2d(in_channels, dim, PATCH, stride=PATCH)

    def forward(self, x: Tensor) -> Tensor:
        return self.proj(x).flatten(2).transpose(1, 2)  # [N, grid_h * grid_w, D]


def check_image_size(name: str, size: int) -> None:
    """One line for an image size a ViT cannot split into patches."""
    if size % PATCH or size < PATCH:
        raise ValueError(f"image_size={size}: backbone={name} cuts images into {PATCH}x{PATCH} patches; "
                         f"allowed: multiples of {PATCH} (e.g. 32, 64, 224)")


class VisionTransformer(nn.Module):
    """ViT with a class token: ``[N, C, H, W] -> [N, num_classes]`` (H, W multiples of 16)."""

    classifier = "head"  # the classifier's state_dict prefix (``backbones.load_weights``)

    def __init__(self, num_classes: int, dim: int, depth: int, heads: int, in_channels: int = 3) -> None:
        super().__init__()
        self.feature_dim, self.in_channels = dim, in_channels
        self.patch_embed = PatchEmbed(in_channels, dim)
        self.cls_token = nn.Parameter(torch.zeros(1, 1, dim))
        self.pos_embed = nn.Parameter(torch.zeros(1, 1 + REF_GRID * REF_GRID, dim))
        self.blocks = nn.ModuleList(Block(dim, heads) for _ in range(depth))
        self.norm = nn.LayerNorm(dim, eps=1e-6)
        self.head = nn.Linear(dim, num_classes)
        nn.init.trunc_normal_(self.pos_embed, std=0.02)
        nn.init.normal_(self.cls_token, std=1e-6)
        for m in self.modules():
            if isinstance(m, nn.Linear):
                nn.init.trunc_normal_(m.weight, std=0.02)
                nn.init.zeros_(m.bias)

    def position(self, gh: int, gw: int) -> Tensor:
        """Position embedding ``[1, 1 + gh * gw, D]`` for a ``gh x gw`` patch grid."""
        if (gh, gw) == (REF_GRID, REF_GRID):
            return self.pos_embed
        grid = self.pos_embed[:, 1:].reshape(1, REF_GRID, REF_GRID, -1).permute(0, 3, 1, 2)
        grid = F.interpolate(grid, size=(gh, gw), mode="bicubic", align_corners=False)
        return torch.cat([self.pos_embed[:, :1], grid.flatten(2).transpose(1, 2)], dim=1)

    def features(self, x: Tensor) -> Tensor:
        """``[N, C, H, W] -> [N, feature_dim]``: the class token after the last block and norm."""
        if x.dim() != 4 or x.shape[1] != self.in_channels or x.shape[-1] % PATCH or x.shape[-2] % PATCH:
            raise ValueError(f"{type(self).__name__} expects input [N, {self.in_channels}, H, W] with H, W multiples "
                             f"of {PATCH}, got {list(x.shape)}")
        gh, gw = x.shape[-2] // PATCH, x.shape[-1] // PATCH
        tokens = torch.cat([self.cls_token.expand(len(x), -1, -1), self.patch_embed(x)], dim=1)
        tokens = tokens + self.position(gh, gw)
        for block in self.blocks:
            tokens = block(tokens)
        return self.norm(tokens)[:, 0]

    def forward(self, x: Tensor) -> Tensor:
        """``[N, C, H, W] -> [N, num_classes]`` logits."""
        return self.head(self.features(x))


def vit_tiny(num_classes: int = 1000, in_channels: int = 3) -> VisionTransformer:
    """ViT-Tiny/16: 192-d, 12 blocks, 3 heads (5,717,416 parameters with 1000 classes)."""
    return VisionTransformer(num_classes, 192, 12, 3, in_channels)


def vit_small(num_classes: int = 1000, in_channels: int = 3) -> VisionTransformer:
    """ViT-Small/16: 384-d, 12 blocks, 6 heads (22,050,664 parameters with 1000 classes)."""
    return VisionTransformer(num_classes, 384, 12, 6, in_channels)


def vit_base(num_classes: int = 1000, in_channels: int = 3) -> VisionTransformer:
    """ViT-Base/16: 768-d, 12 blocks, 12 heads (86,567,656 parameters with 1000 classes); the size
    of MAE's smallest public weights (the paper's "MAE ViT", L644)."""
    return VisionTransformer(num_classes, 768, 12, 12, in_channels)


@dataclass
class ViTConfig(BackboneConfig):
    """A ViT backbone: the image size must be a multiple of the patch size."""

    def check(self, cfg: "TrainConfig") -> None:
        check_image_size(self.name, cfg.image_size)


@register("vit_tiny")
@dataclass
class ViTTinyConfig(ViTConfig):
    """ViT-Tiny/16 (timm's keys): 192-d features."""

    name: str = "vit_tiny"
    network = staticmethod(vit_tiny)
    feature_dim = 192


@register("vit_small")
@dataclass
class ViTSmallConfig(ViTConfig):
    """ViT-Small/16 (timm's keys): 384-d features."""

    name: str = "vit_small"
    network = staticmethod(vit_small)
    feature_dim = 384


@register("vit_base")
@dataclass
class ViTBaseConfig(ViTConfig):
    """ViT-Base/16 (timm's keys; MAE's and DINO's ViT-B/16 files load into it): 768-d features."""

    name: str = "vit_base"
    network = staticmethod(vit_base)
    feature_dim = 768
