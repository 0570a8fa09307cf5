"""The 2D segmentation networks of part segmentation (``segnet=NAME``): images ``[N, 3, H, W]`` ->
per-pixel logits ``[N, num_classes, H, W]`` at the input's size.

* ``deeplabv3``: the paper's network (DeepLabV3: "Rethinking Atrous Convolution for Semantic
  Image Segmentation", Chen et al. 2017), as torchvision builds it: a ResNet of this project's
  ``backbone`` option with layer3 and layer4 dilated instead of strided (output stride 8), the ASPP
  head (rates 12, 24, 36 and image pooling, 256 channels), and optionally the auxiliary FCN head on
  layer3 (``aux``, what the paper's 61 M parameters with ResNet-101 count). Dilation keeps every
  key and shape of the ResNet, so ImageNet weights (``backbone.weights=imagenet``) load as they are.
* ``fcn_small``: a small fully convolutional encoder-decoder for CPU runs and tests.

A segnet is one registered config class (``SegNetConfig``): ``build(num_classes, backbone,
weights)`` gives the network; ``forward(x)`` returns the logits (``aux_logits`` holds the
auxiliary head's after a training forward, None otherwise).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Optional

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from ..config.checks import at_least
from ..config.options import OPTIONS, OptionConfig
from .backbones import IMAGENET_MEAN, IMAGENET_STD, Bottleneck, ResNet, _init_weights, build_backbone


def _conv_bn_relu(cin: int, cout: int, k: int = 3, dilation: int = 1) -> nn.Sequential:
    pad = dilation * (k // 2)
    return nn.Sequential(nn.Conv2d(cin, cout, k, padding=pad, dilation=dilation, bias=False), nn.BatchNorm2d(cout),
                         nn.ReLU(inplace=True))


def dilate(resnet: ResNet, layer: nn.Sequential, dilation: int, previous: int) -> None:
    """Make ``layer`` of ``resnet`` keep its input's resolution: its stride goes, its 3x3 convs
    dilate (torchvision's ``replace_stride_with_dilation``: the first block keeps ``previous``,
    the others take ``dilation``); keys and shapes are unchanged."""
    for i, block in enumerate(layer):
        d = previous if i == 0 else dilation
        convs = [block.conv2] if isinstance(block, Bottleneck) else [block.conv1, block.conv2]
        for conv in convs:
            if conv.kernel_size == (3, 3):
                conv.stride, conv.dilation, conv.padding = (1, 1), (d, d), (d, d)
            else:
                conv.stride = (1, 1)
        if block.downsample is not None:
            block.downsample[0].stride = (1, 1)


class ASPP(nn.Module):
    """Atrous spatial pyramid pooling: a 1x1 branch, one 3x3 branch per rate, and image pooling,
    each ``out`` channels, concatenated and projected to ``out`` (dropout 0.5, as torchvision)."""

    def __init__(self, cin: int, rates=(12, 24, 36), out: int = 256) -> None:
        super().__init__()
        self.branches = nn.ModuleList([_conv_bn_relu(cin, out, 1)] + [_conv_bn_relu(cin, out, 3, r) for r in rates])
        self.pool = nn.Sequential(nn.AdaptiveAvgPool2d(1), nn.Conv2d(cin, out, 1, bias=False), nn.BatchNorm2d(out),
                                  nn.ReLU(inplace=True))
        self.project = nn.Sequential(_conv_bn_relu(out * (len(rates) + 2), out, 1), nn.Dropout(0.5))

    def forward(self, x: Tensor) -> Tensor:
        pooled = F.interpolate(self.pool(x), size=x.shape[-2:], mode="bilinear", align_corners=False)
        return self.project(torch.cat([b(x) for b in self.branches] + [pooled], 1))


class DeepLabV3(nn.Module):
    """DeepLabV3 on a dilated ResNet (module docstring): ``[N, 3, H, W] -> [N, num_classes, H, W]``."""

    def __init__(self, resnet: ResNet, num_classes: int, aux: bool = False) -> None:
        super().__init__()
        if not isinstance(resnet, ResNet):
            raise ValueError(f"segnet=deeplabv3 needs a ResNet backbone, got {type(resnet).__name__}")
        dilate(resnet, resnet.layer3, 2, 1)
        dilate(resnet, resnet.layer4, 4, 2)
        resnet.fc = None  # (the classifier is not used: no parameter without a gradient)
        self.backbone = resnet
        c4 = resnet.feature_dim
        self.head = nn.Sequential(ASPP(c4), _conv_bn_relu(256, 256), nn.Conv2d(256, num_classes, 1))
        self.aux_head = nn.Sequential(_conv_bn_relu(c4 // 2, 256), nn.Dropout(0.1), nn.Conv2d(256, num_classes, 1)) \
            if aux else None
        self.aux_logits: Optional[Tensor] = None
        _init_weights(self.head)
        if self.aux_head is not None:
            _init_weights(self.aux_head)

    def forward(self, x: Tensor) -> Tensor:
        size = x.shape[-2:]
        r = self.backbone
        r._check_input(x)
        x = r.maxpool(r.relu(r.bn1(r.conv1(x))))
        mid = r.layer3(r.layer2(r.layer1(x)))
        out = F.interpolate(self.head(r.layer4(mid)), size=size, mode="bilinear", align_corners=False)
        self.aux_logits = None
        if self.aux_head is not None and self.training:
            self.aux_logits = F.interpolate(self.aux_head(mid), size=size, mode="bilinear", align_corners=False)
        return out


class Residual(nn.Module):
    """``x + f(x)``: an extra conv layer of a stage that keeps its input's channels and size."""

    def __init__(self, f: nn.Module) -> None:
        super().__init__()
        self.f = f

    def forward(self, x: Tensor) -> Tensor:
        return x + self.f(x)


def _stage(cin: int, cout: int, depth: int, dilation: int = 1) -> nn.Sequential:
    """One conv to ``cout`` channels, then ``depth - 1`` residual convs at ``cout``."""
    first = _conv_bn_relu(cin, cout, 3, dilation)
    if depth == 1:
        return first  # the original layer, its parameter names unchanged
    return nn.Sequential(first, *[Residual(_conv_bn_relu(cout, cout, 3, dilation)) for _ in range(depth - 1)])


class SmallFCN(nn.Module):
    """A small fully convolutional net: a stem and ``stages`` strided stages (``width`` channels,
    doubled at each stage), a dilated context conv, and a decoder that adds each stage back as it
    upsamples: ``[N, in_channels, H, W] -> [N, num_classes, H, W]`` (any H, W). Every stage, the
    context and each decoder step hold ``depth`` conv layers (the ones past the first residual);
    ``stages=2, depth=1`` is the original network (its parameter names unchanged)."""

    def __init__(self, num_classes: int, in_channels: int = 3, width: int = 16, stages: int = 2,
                 depth: int = 1) -> None:
        super().__init__()
        w = [width * 2 ** i for i in range(stages + 1)]
        self.stem = _stage(in_channels, w[0], depth)
        self.down = nn.ModuleList([nn.Sequential(nn.MaxPool2d(2, ceil_mode=True), _stage(a, b, depth))
                                   for a, b in zip(w, w[1:])])
        self.context = _stage(w[-1], w[-1], depth, dilation=2)
        self.up = nn.ModuleList([_stage(b, a, depth) for a, b in zip(w, w[1:])][::-1])
        self.classifier = nn.Conv2d(w[0], num_classes, 1)
        self.aux_logits: Optional[Tensor] = None
        _init_weights(self)

    def forward(self, x: Tensor) -> Tensor:
        skips = [self.stem(x)]
        for down in self.down:
            skips.append(down(skips[-1]))
        y = self.context(skips.pop())
        for up in self.up:
            skip = skips.pop()
            y = skip + up(F.interpolate(y, size=skip.shape[-2:], mode="bilinear", align_corners=False))
        return self.classifier(y)


class ViewSegmenter(nn.Module):
    """C of part segmentation: one 2D segmentation network shared over the views.

    ``forward(images [B, M, 3, H, W], views=None) -> (logits [B, M, K, H, W], features [B, 0])``
    (no shape descriptor); ``training_loss(logits, targets, loss_fn)``: ``loss_fn`` on the logits,
    plus ``aux_weight`` times it on the auxiliary head's (DeepLabV3 with ``aux``)."""

    needs_views = False

    def __init__(self, net: nn.Module, aux_weight: float = 0.0) -> None:
        super().__init__()
        self.net, self.aux_weight = net, aux_weight
        self.register_buffer("input_mean", None, persistent=False)
        self.register_buffer("input_std", None, persistent=False)

    def normalize_input(self, mean, std) -> "ViewSegmenter":
        """Scale every view ``(x - mean) / std`` per channel first (ImageNet's for pretrained weights)."""
        self.register_buffer("input_mean", torch.tensor(mean, dtype=torch.float32).view(1, -1, 1, 1), persistent=False)
        self.register_buffer("input_std", torch.tensor(std, dtype=torch.float32).view(1, -1, 1, 1), persistent=False)
        return self

    def forward(self, images: Tensor, views=None) -> tuple[Tensor, Tensor]:
        if images.dim() != 5 or images.shape[1] < 1:
            raise ValueError(f"ViewSegmenter expects images [B, M, 3, H, W] with M >= 1, got {list(images.shape)}")
        B, M = images.shape[:2]
        x = images.reshape(B * M, *images.shape[2:])
        if self.input_mean is not None:
            x = (x - self.input_mean.to(x.dtype)) / self.input_std.to(x.dtype)
        logits = self.net(x)
        return logits.reshape(B, M, *logits.shape[1:]), logits.new_zeros(B, 0)

    def training_loss(self, logits: Tensor, targets, loss_fn) -> Tensor:
        loss = loss_fn(logits, targets)
        aux = getattr(self.net, "aux_logits", None)
        if aux is not None and self.aux_weight:
            loss = loss + self.aux_weight * loss_fn(aux.reshape(logits.shape), targets)
        return loss


# ----------------------------------------------------------------------------- config options (segnet=NAME)
register = OPTIONS["segnet"].register


@dataclass
class SegNetConfig(OptionConfig):
    """The 2D segmentation network C of part segmentation, shared over views."""

    kind = "segnet"
    uses_backbone: ClassVar[bool] = False  # whether it is built on the ``backbone`` option

    def build(self, num_classes: int, backbone: str = "resnet50", weights: Optional[str] = None) -> nn.Module:
        raise NotImplementedError(f"{type(self).__name__}.build")

    def aux_loss_weight(self) -> float:
        """The weight of an auxiliary head's loss (0: none)."""
        return 0.0

    def build_c(self, num_classes: int, backbone: str = "resnet50", weights: Optional[str] = None,
                input_norm: str = "none") -> ViewSegmenter:
        """C: the network over every view (``input_norm="imagenet"``: ImageNet's mean and std first)."""
        c = ViewSegmenter(self.build(num_classes, backbone, weights), self.aux_loss_weight())
        return c.normalize_input(IMAGENET_MEAN, IMAGENET_STD) if input_norm == "imagenet" else c


@register("deeplabv3")
@dataclass
class DeepLabV3Config(SegNetConfig):
    """DeepLabV3 (ASPP on a dilated ResNet of the ``backbone`` option), the paper's 2D network.

    ``aux``: the auxiliary FCN head on layer3 (its loss weighs ``aux_weight``)."""

    name: str = "deeplabv3"
    aux: bool = False
    aux_weight: float = 0.4

    uses_backbone: ClassVar[bool] = True

    def aux_loss_weight(self) -> float:
        return self.aux_weight if self.aux else 0.0

    def build(self, num_classes: int, backbone: str = "resnet50", weights: Optional[str] = None) -> nn.Module:
        return DeepLabV3(build_backbone(backbone, 1000, weights=weights), num_classes, aux=self.aux)


@register("fcn_small")
@dataclass
class SmallFCNConfig(SegNetConfig):
    """A small fully convolutional net for CPU runs: ``width`` channels in its first stage,
    ``stages`` downsamplings by 2 (each doubling the channels), ``depth`` conv layers per stage."""

    name: str = "fcn_small"
    width: int = 16
    stages: int = 2
    depth: int = 1

    def validate(self) -> "SmallFCNConfig":
        super().validate()
        at_least("segnet.width", self.width, 1)
        at_least("segnet.stages", self.stages, 1)
        at_least("segnet.depth", self.depth, 1)
        return self

    def build(self, num_classes: int, backbone: str = "resnet50", weights: Optional[str] = None) -> nn.Module:
        return SmallFCN(num_classes, width=self.width, stages=self.stages, depth=self.depth)
