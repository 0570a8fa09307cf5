"""The project's own 2D image backbones (no torchvision dependency).

* ``resnet18`` / ``resnet34`` / ``resnet50`` / ``resnet101``: ResNets written from scratch whose
  ``state_dict`` keys and shapes are identical to torchvision's, so a torchvision
  ``.pth`` file loads with ``load_state_dict(strict=True)``.
* ``SmallCNN`` / ``small_cnn``: a fast CPU backbone for tests and quick experiments.
* ``vit_tiny`` / ``vit_small`` / ``vit_base``: Vision Transformers with timm's key names (``vit.py``).

Every model maps images ``[N, C, H, W] -> [N, num_classes]`` and exposes
``feature_dim`` plus ``features(x) -> [N, feature_dim]`` (the pooled vector before ``fc``).
Weights are only ever read from local files here (``pretrained.py`` fetches published ones).

A backbone is one registered config class (``backbone=NAME``, ``BackboneConfig``): its ``network``
(the constructor) and ``feature_dim``; ``build_backbone(name, ...)`` builds it by name.
"""
from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Callable, ClassVar, Optional, Union

import torch
from torch import Tensor, nn

from ..config.checks import one_of
from ..config.options import OPTIONS, OptionConfig
from . import pretrained

PathLike = Union[str, "os.PathLike[str]"]
IMAGENET_MEAN, IMAGENET_STD = (0.485, 0.456, 0.406), (0.229, 0.224, 0.225)
INPUT_NORMS = ("auto", "imagenet", "none")

class _Backbone(nn.Module):
    """Shared interface: ``features(x) -> [N, feature_dim]``, ``forward(x) = fc(features(x))``."""

    feature_dim: int
    in_channels: int
    fc: nn.Linear

    def _check_input(self, x: Tensor, min_size: int = 1) -> None:
        if x.dim() != 4 or x.shape[1] != self.in_channels:
            raise ValueError(f"{type(self).__name__} expects input [N, {self.in_channels}, H, W], "
                             f"got {list(x.shape)}")
        if min(x.shape[-2:]) < min_size:
            raise ValueError(f"{type(self).__name__} needs H, W >= {min_size}, got {list(x.shape)}")

    def forward(self, x: Tensor) -> Tensor:
        """``[N, C, H, W] -> [N, num_classes]`` logits."""
        return self.fc(self.features(x))


def _init_weights(model: nn.Module) -> None:
    """torchvision's ResNet init: kaiming-normal (fan_out, relu) convs, norm weight 1 / bias 0."""
    for m in model.modules():
        if isinstance(m, nn.Conv2d):
            nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
        elif isinstance(m, (nn.BatchNorm2d, nn.GroupNorm)):
            nn.init.constant_(m.weight, 1)
            nn.init.constant_(m.bias, 0)


def _conv(cin: int, cout: int, k: int, stride: int = 1) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, kernel_size=k, stride=stride, padding=k // 2, bias=False)


class BasicBlock(nn.Module):
    """Two 3x3 convs + identity: ``[N, inplanes, H, W] -> [N, planes, H/stride, W/stride]``."""

    expansion = 1

    def __init__(self, inplanes: int, planes: int, stride: int = 1,
                 downsample: Optional[nn.Module] = None) -> None:
        super().__init__()
        self.conv1 = _conv(inplanes, planes, 3, stride)
        self.bn1 = nn.BatchNorm2d(planes)
        self.relu = nn.ReLU(inplace=True)
        self.conv2 = _conv(planes, planes, 3)
        self.bn2 = nn.BatchNorm2d(planes)
        self.downsample = downsample

    def forward(self, x: Tensor) -> Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return self.relu(out + identity)


class Bottleneck(nn.Module):
    """1x1 -> 3x3 (strided, as torchvision "v1.5") -> 1x1:
    ``[N, inplanes, H, W] -> [N, 4 * planes, H/stride, W/stride]``."""

    expansion = 4

    def __init__(self, inplanes: int, planes: int, stride: int = 1,
                 downsample: Optional[nn.Module] = None) -> None:
        super().__init__()
        self.conv1 = _conv(inplanes, planes, 1)
        self.bn1 = nn.BatchNorm2d(planes)
        self.conv2 = _conv(planes, planes, 3, stride)
        self.bn2 = nn.BatchNorm2d(planes)
        self.conv3 = _conv(planes, planes * self.expansion, 1)
        self.bn3 = nn.BatchNorm2d(planes * self.expansion)
        self.relu = nn.ReLU(inplace=True)
        self.downsample = downsample

    def forward(self, x: Tensor) -> Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.relu(self.bn2(self.conv2(out)))
        out = self.bn3(self.conv3(out))
        return self.relu(out + identity)


class ResNet(_Backbone):
    """torchvision-compatible ResNet: ``[N, in_channels, H, W] -> [N, num_classes]``."""

    def __init__(self, block: type, layers: list[int], num_classes: int = 1000,
                 in_channels: int = 3) -> None:
        super().__init__()
        self.in_channels = in_channels
        self.inplanes = 64
        self.conv1 = nn.Conv2d(in_channels, 64, kernel_size=7, stride=2, padding=3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(kernel_size=3, stride=2, padding=1)
        self.layer1 = self._make_layer(block, 64, layers[0])
        self.layer2 = self._make_layer(block, 128, layers[1], stride=2)
        self.layer3 = self._make_layer(block, 256, layers[2], stride=2)
        self.layer4 = self._make_layer(block, 512, layers[3], stride=2)
        self.avgpool = nn.AdaptiveAvgPool2d((1, 1))
        self.feature_dim = 512 * block.expansion
        self.fc = nn.Linear(self.feature_dim, num_classes)
        _init_weights(self)

    def _make_layer(self, block: type, planes: int, blocks: int, stride: int = 1) -> nn.Sequential:
        downsample = None
        if stride != 1 or self.inplanes != planes * block.expansion:
            downsample = nn.Sequential(_conv(self.inplanes, planes * block.expansion, 1, stride),
                                       nn.BatchNorm2d(planes * block.expansion))
        layers = [block(self.inplanes, planes, stride, downsample)]
        self.inplanes = planes * block.expansion
        layers += [block(self.inplanes, planes) for _ in range(1, blocks)]
        return nn.Sequential(*layers)

    def features(self, x: Tensor) -> Tensor:
        """``[N, in_channels, H, W] -> [N, feature_dim]`` (global-average-pooled layer4)."""
        self._check_input(x)
        x = self.maxpool(self.relu(self.bn1(self.conv1(x))))
        x = self.layer4(self.layer3(self.layer2(self.layer1(x))))
        return torch.flatten(self.avgpool(x), 1)


class SmallCNN(_Backbone):
    """Fast CPU backbone: 4 x (conv3x3-BN-ReLU-maxpool2) with widths w, 2w, 4w, 8w, then GAP.

    ``[N, in_channels, H, W] -> [N, num_classes]`` for any H, W >= 16; ``feature_dim = 8 * width``.
    """

    def __init__(self, num_classes: int, in_channels: int = 3, width: int = 32) -> None:
        super().__init__()
        self.in_channels = in_channels
        chans = [in_channels, width, 2 * width, 4 * width, 8 * width]
        stages: list[nn.Module] = []
        for cin, cout in zip(chans[:-1], chans[1:]):
            stages += [_conv(cin, cout, 3), nn.BatchNorm2d(cout), nn.ReLU(inplace=True), nn.MaxPool2d(2)]
        self.body = nn.Sequential(*stages)
        self.avgpool = nn.AdaptiveAvgPool2d((1, 1))
        self.feature_dim = chans[-1]
        self.fc = nn.Linear(self.feature_dim, num_classes)
        _init_weights(self)

    def features(self, x: Tensor) -> Tensor:
        """``[N, in_channels, H, W] -> [N, feature_dim]``."""
        self._check_input(x, min_size=16)
        return torch.flatten(self.avgpool(self.body(x)), 1)


def _fmt(items: list[str], limit: int = 5) -> str:
    more = f", ... (+{len(items) - limit} more)" if len(items) > limit else ""
    return ", ".join(items[:limit]) + more


def load_weights(model: nn.Module, path: PathLike) -> nn.Module:
    """Load a local state_dict file (plain, or under a 'state_dict'/'model' key) into ``model``.

    If only the classifier's output size differs (``fc.weight`` is ``[K', feature_dim]``; ``head``
    for models whose ``classifier`` says so, the ViTs), or the file has no classifier at all (a
    self-supervised backbone such as DINO's), every other tensor is loaded and the classifier keeps
    its fresh initialisation. Keys under a ``module.`` (DataParallel) or ``backbone.`` prefix (DINO's
    training checkpoints, ``teacher``) are read without it when the bare keys do not match. Missing
    ``*.num_batches_tracked`` buffers (old torchvision files) are tolerated.
    Raises FileNotFoundError / ValueError naming the file and the offending keys.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"backbone weights file not found: '{path}'")
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # corrupt file, pickle with non-tensor objects, ...
        raise ValueError(f"could not read backbone weights from '{path}': {e}") from e
    if isinstance(obj, Mapping):
        for key in ("state_dict", "model", "teacher"):
            if isinstance(obj.get(key), Mapping):
                obj = obj[key]
                break
    if not isinstance(obj, Mapping) or not all(isinstance(v, Tensor) for v in obj.values()):
        raise ValueError(f"'{path}' does not hold a state_dict (a mapping of names to tensors)")
    own = model.state_dict()
    sd = _strip_wrapper(dict(obj), own)
    head = getattr(model, "classifier", "fc")
    fw, own_fw = sd.get(f"{head}.weight"), own.get(f"{head}.weight")
    if (fw is not None and own_fw is not None and fw.dim() == 2
            and fw.shape[1] == own_fw.shape[1] and fw.shape[0] != own_fw.shape[0]):
        sd[f"{head}.weight"], sd[f"{head}.bias"] = own[f"{head}.weight"], own[f"{head}.bias"]  # keep the fresh head
    if fw is None and f"{head}.bias" not in sd and own_fw is not None:  # a backbone without classifier (DINO)
        sd[f"{head}.weight"], sd[f"{head}.bias"] = own[f"{head}.weight"], own[f"{head}.bias"]
    for k, v in own.items():
        if k.endswith("num_batches_tracked") and k not in sd:
            sd[k] = v
    missing = [k for k in own if k not in sd]
    unexpected = [k for k in sd if k not in own]
    mismatched = [f"{k}: file {list(sd[k].shape)} vs model {list(v.shape)}"
                  for k, v in own.items() if k in sd and sd[k].shape != v.shape]
    if missing or unexpected or mismatched:
        parts = [f"{name} ({len(keys)}): {_fmt(keys)}" for name, keys in
                 (("missing keys", missing), ("unexpected keys", unexpected),
                  ("shape mismatches", mismatched)) if keys]
        raise ValueError(f"cannot load '{path}' into {type(model).__name__}: " + "; ".join(parts))
    model.load_state_dict(sd, strict=True)
    return model


def _strip_wrapper(sd: dict, own: Mapping) -> dict:
    """``sd`` with a ``module.``, then an ``mvnet.backbone.`` (C's backbone in an ``mvtn-train``
    checkpoint: a finished run's backbone as the start of another, the paper's FSL pretraining)
    and then a ``backbone.`` prefix removed (keys without it dropped), each only when no key of
    ``sd`` matches ``own`` as it is."""
    for prefix in ("module.", "mvnet.backbone.", "backbone."):
        if not any(k in own for k in sd) and any(k.startswith(prefix) for k in sd):
            sd = {k[len(prefix):]: v for k, v in sd.items() if k.startswith(prefix)}
    return sd


def _resnet(block: type, layers: list[int], num_classes: int, weights: Optional[PathLike],
            in_channels: int) -> ResNet:
    model = ResNet(block, layers, num_classes=num_classes, in_channels=in_channels)
    return load_weights(model, weights) if weights is not None else model


def resnet18(num_classes: int = 1000, weights: Optional[PathLike] = None, in_channels: int = 3) -> ResNet:
    """ResNet-18, ``[N, 3, H, W] -> [N, num_classes]``, feature_dim 512."""
    return _resnet(BasicBlock, [2, 2, 2, 2], num_classes, weights, in_channels)


def resnet34(num_classes: int = 1000, weights: Optional[PathLike] = None, in_channels: int = 3) -> ResNet:
    """ResNet-34, ``[N, 3, H, W] -> [N, num_classes]``, feature_dim 512."""
    return _resnet(BasicBlock, [3, 4, 6, 3], num_classes, weights, in_channels)


def resnet50(num_classes: int = 1000, weights: Optional[PathLike] = None, in_channels: int = 3) -> ResNet:
    """ResNet-50, ``[N, 3, H, W] -> [N, num_classes]``, feature_dim 2048."""
    return _resnet(Bottleneck, [3, 4, 6, 3], num_classes, weights, in_channels)


def resnet101(num_classes: int = 1000, weights: Optional[PathLike] = None, in_channels: int = 3) -> ResNet:
    """ResNet-101, ``[N, 3, H, W] -> [N, num_classes]``, feature_dim 2048 (DeepLabV3's in the paper)."""
    return _resnet(Bottleneck, [3, 4, 23, 3], num_classes, weights, in_channels)


def small_cnn(num_classes: int = 1000, weights: Optional[PathLike] = None, in_channels: int = 3,
              width: int = 32) -> SmallCNN:
    """SmallCNN, ``[N, 3, H, W] -> [N, num_classes]`` (H, W >= 16), feature_dim ``8 * width``."""
    model = SmallCNN(num_classes, in_channels=in_channels, width=width)
    return load_weights(model, weights) if weights is not None else model


def build_backbone(name: str, num_classes: int, weights: Optional[PathLike] = None,
                   in_channels: int = 3) -> _Backbone:
    """Build a registered backbone by name: ``[N, in_channels, H, W] -> [N, num_classes]``."""
    cfg = OPTIONS["backbone"].lookup(name, "backbone")()
    return cfg.build(num_classes, weights=weights, in_channels=in_channels)


# ----------------------------------------------------------------------------- config options (backbone=NAME)
register = OPTIONS["backbone"].register


@dataclass
class BackboneConfig(OptionConfig):
    """The 2D backbone shared over views. ``weights``: published weights by name (``imagenet``:
    ``models/pretrained.py``, downloaded once into torch's hub cache and hash-checked) or a local
    torchvision/timm-style state_dict file, or a finished run's ``best.pt`` / ``last.pt`` (its C's
    backbone: the paper's FSL pretraining, phase 2). ``normalize``: the input scaling the renders get before the backbone:
    ``imagenet`` ((x - mean) / std with ImageNet's mean and std, what pretrained weights were
    trained on), ``none`` (the renders' [0, 1]), ``auto`` (imagenet when ``weights`` is given)."""

    weights: Optional[str] = None
    normalize: str = "auto"

    kind = "backbone"
    # the constructor, (num_classes, in_channels=3) -> the backbone freshly initialised (a subclass
    # sets it with staticmethod), and the width of its features(x) [N, feature_dim] (checked by a test)
    network: ClassVar[Callable[..., nn.Module]]
    feature_dim: ClassVar[int]

    def validate(self) -> "BackboneConfig":
        super().validate()
        one_of("backbone.normalize", self.normalize, INPUT_NORMS)
        pretrained.check(self.name, self.weights)
        return self

    @property
    def input_norm(self) -> str:
        """``imagenet`` or ``none``: ``normalize`` with ``auto`` resolved."""
        if self.normalize == "auto":
            return "imagenet" if self.weights is not None else "none"
        return self.normalize

    def build(self, num_classes: int, weights: Optional[PathLike] = None, in_channels: int = 3) -> nn.Module:
        """The backbone ``[N, in_channels, H, W] -> [N, num_classes]`` with ``features(x) -> [N,
        feature_dim]``; ``weights``: a local state_dict file loaded into it (``load_weights``; the
        file ``pretrained.resolve`` gives for ``self.weights``), None: fresh initialisation."""
        model = type(self).network(num_classes, in_channels=in_channels)
        return load_weights(model, weights) if weights is not None else model


@register("resnet18")
@dataclass
class ResNet18Config(BackboneConfig):
    """ResNet-18 (torchvision's keys and init): 512-d features."""

    name: str = "resnet18"
    network = staticmethod(resnet18)
    feature_dim = 512


@register("resnet34")
@dataclass
class ResNet34Config(BackboneConfig):
    """ResNet-34 (torchvision's keys and init): 512-d features."""

    name: str = "resnet34"
    network = staticmethod(resnet34)
    feature_dim = 512


@register("resnet50")
@dataclass
class ResNet50Config(BackboneConfig):
    """ResNet-50 (torchvision's keys and init, bottleneck blocks): 2048-d features."""

    name: str = "resnet50"
    network = staticmethod(resnet50)
    feature_dim = 2048


@register("resnet101")
@dataclass
class ResNet101Config(BackboneConfig):
    """ResNet-101 (torchvision's keys and init, bottleneck blocks): 2048-d features; the paper's
    DeepLabV3 backbone for part segmentation."""

    name: str = "resnet101"
    network = staticmethod(resnet101)
    feature_dim = 2048


@register("small_cnn")
@dataclass
class SmallCNNConfig(BackboneConfig):
    """SmallCNN, the fast CPU backbone for tests and quick runs (four conv stages, width 32): 256-d features."""

    name: str = "small_cnn"
    network = staticmethod(small_cnn)
    feature_dim = 256
