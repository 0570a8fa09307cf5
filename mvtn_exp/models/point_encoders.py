"""Point-cloud encoders (the MVTN selector's shape encoder) and dense point sampling.

* ``PointNet`` (``point_encoder=pointnet``, this project's compact encoder, ~0.18 M parameters):
  shared MLP 3 -> 64 -> 128 -> 1024 (Conv1d k=1 + BatchNorm + ReLU), global max-pool, projection
  to ``out_features`` (MVTN's b = 40); the input 3x3 T-net is optional (``use_tnet``).
* ``PaperPointNet`` (``point_encoder=pointnet_paper``): the PointNet classifier the paper's G uses,
  with the input and feature T-nets and the 1024-512-256 head (3.47 M parameters at b = 40).
* ``sample_points(shapes, n)``: a ``PointClouds`` / ``Meshes`` batch -> dense ``[B, n, 3]``.
* ``build_point_encoder(name, ...)``: an encoder by name; each is one registered config class
  (``point_encoder=NAME``, ``PointEncoderConfig``) whose ``network`` is its constructor (``dgcnn``:
  ``dgcnn.py``).

Every encoder maps points ``[B, N, 3] -> [B, out_features]`` and exposes ``out_features``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, ClassVar, Optional, Sequence, Union

import torch
from torch import Tensor, nn

from mvtn_exp.data.shapes import Meshes, PointClouds

from ..config.checks import at_least
from ..config.options import OPTIONS, OptionConfig

from .pooled_layer import pooled_layer


def _check_points(name: str, points: Tensor) -> None:
    if points.dim() != 3 or points.shape[-1] != 3:
        raise ValueError(f"{name} expects points [B, N, 3], got {list(points.shape)}")
    if points.shape[1] == 0:
        raise ValueError(f"{name} got point clouds with N = 0 points; nothing to max-pool")


def _shared_mlp(widths: Sequence[int]) -> nn.Sequential:
    """Per-point MLP ``[B, widths[0], N] -> [B, widths[-1], N]`` (Conv1d k=1 + BN + ReLU each)."""
    layers: list[nn.Module] = []
    for cin, cout in zip(widths[:-1], widths[1:]):
        layers += [nn.Conv1d(cin, cout, 1, bias=False), nn.BatchNorm1d(cout), nn.ReLU(inplace=True)]
    return nn.Sequential(*layers)


def _max_pooled(mlp: nn.Sequential, points: Tensor) -> Tensor:
    """``_shared_mlp`` then a max over the points: ``[B, N, 3] -> [B, widths[-1]]``. The last
    layer, its BatchNorm and the max run as one (``pooled_layer``: same values, no ``[B, C, N]``
    activations)."""
    return pooled_layer(mlp[:-3](points.transpose(1, 2)), mlp[-3], mlp[-2])


def _fc_stack(widths: Sequence[int]) -> nn.Sequential:
    """Per-shape MLP ``[B, widths[0]] -> [B, widths[-1]]`` (Linear + BN + ReLU each)."""
    layers: list[nn.Module] = []
    for cin, cout in zip(widths[:-1], widths[1:]):
        layers += [nn.Linear(cin, cout, bias=False), nn.BatchNorm1d(cout), nn.ReLU(inplace=True)]
    return nn.Sequential(*layers)


class InputTNet(nn.Module):
    """PointNet's input transform network: points ``[B, N, 3]`` -> 3x3 matrices ``[B, 3, 3]``.

    Shared MLP 3 -> 64 -> 128 -> 1024, max-pool, FC 1024 -> 512 -> 256 -> 9. The last layer is
    initialised to zero weights and an identity bias, so the transform starts as the identity.
    Its FC layers use BatchNorm, so training mode needs B >= 2.
    """

    def __init__(self) -> None:
        super().__init__()
        self.mlp = _shared_mlp((3, 64, 128, 1024))
        self.fc = _fc_stack((1024, 512, 256))
        self.out = nn.Linear(256, 9)
        nn.init.zeros_(self.out.weight)
        with torch.no_grad():
            self.out.bias.copy_(torch.eye(3).flatten())

    def forward(self, points: Tensor) -> Tensor:
        x = _max_pooled(self.mlp, points)  # [B, 1024]
        return self.out(self.fc(x)).view(-1, 3, 3)


class PointNet(nn.Module):
    """PointNet encoder: points ``[B, N, 3]`` -> features ``[B, out_features]``.

    ``use_tnet``: apply the learned input 3x3 transform first (``points @ T``); off by default.
    ``head_widths``: hidden widths between the 1024-d global feature and the output
    (Linear + BN + ReLU each). Default ``()`` = a single linear projection 1024 -> out_features;
    ``(512, 256)`` gives PointNet's classification head (without dropout).
    The global max-pool makes the output invariant to the order of the points.
    """

    feature_dim = 1024

    def __init__(self, out_features: int = 40, use_tnet: bool = False, head_widths: Sequence[int] = ()) -> None:
        super().__init__()
        if int(out_features) != out_features or out_features < 1:
            raise ValueError(f"PointNet: out_features must be an integer >= 1, got {out_features!r}")
        self.out_features = int(out_features)
        self.use_tnet = bool(use_tnet)
        self.tnet = InputTNet() if self.use_tnet else None
        self.mlp = _shared_mlp((3, 64, 128, self.feature_dim))
        widths = (self.feature_dim, *[int(w) for w in head_widths])
        self.head = nn.Sequential(_fc_stack(widths), nn.Linear(widths[-1], self.out_features))

    def global_features(self, points: Tensor) -> Tensor:
        """``[B, N, 3] -> [B, 1024]`` max-pooled per-point features."""
        _check_points(type(self).__name__, points)
        if self.tnet is not None:
            points = torch.bmm(points, self.tnet(points))
        return _max_pooled(self.mlp, points)

    def forward(self, points: Tensor) -> Tensor:
        """``[B, N, 3] -> [B, out_features]``."""
        return self.head(self.global_features(points))


class TNet(nn.Module):
    """PointNet's k x k transform network: ``[B, k, N]`` -> ``[B, k, k]``, as the reference
    PyTorch PointNet has it: conv k -> 64 -> 128 -> 1024 (bias, BatchNorm, ReLU), max over the
    points, FC 1024 -> 512 -> 256 (BatchNorm, ReLU) -> k*k, plus the identity. The last layer
    starts at zero, so the transform starts as the identity."""

    def __init__(self, k: int) -> None:
        super().__init__()
        self.k = k
        self.convs = nn.Sequential(*_conv_bn_relu((k, 64, 128, 1024)))
        self.fcs = nn.Sequential(*_linear_bn_relu((1024, 512, 256)))
        self.out = nn.Linear(256, k * k)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    def forward(self, x: Tensor) -> Tensor:
        g = self.convs(x).amax(2)
        eye = torch.eye(self.k, dtype=x.dtype, device=x.device)
        return self.out(self.fcs(g)).view(-1, self.k, self.k) + eye


def _conv_bn_relu(widths: Sequence[int], last_relu: bool = True) -> list[nn.Module]:
    layers: list[nn.Module] = []
    for i, (cin, cout) in enumerate(zip(widths[:-1], widths[1:])):
        layers += [nn.Conv1d(cin, cout, 1), nn.BatchNorm1d(cout)]
        if last_relu or i < len(widths) - 2:
            layers.append(nn.ReLU(inplace=True))
    return layers


def _linear_bn_relu(widths: Sequence[int]) -> list[nn.Module]:
    layers: list[nn.Module] = []
    for cin, cout in zip(widths[:-1], widths[1:]):
        layers += [nn.Linear(cin, cout), nn.BatchNorm1d(cout), nn.ReLU(inplace=True)]
    return layers


class PaperPointNet(nn.Module):
    """The PointNet classifier that MVTN's G uses as its point encoder: points ``[B, N, 3]`` ->
    ``[B, out_features]`` (the paper's b = 40: its "PointNet" rows, 3.47-3.49 M parameters, L736,
    L777-L781; 3,471,473 here at b = 40).

    The reference PyTorch PointNet classifier: input T-net (3 x 3), conv 3 -> 64, feature T-net
    (64 x 64), conv 64 -> 128 -> 1024 (the last with BatchNorm, no ReLU), max over the points,
    FC 1024 -> 512 -> 256 (BatchNorm, ReLU; dropout ``dropout`` before the second BatchNorm) ->
    out_features. The feature transform's orthogonality loss is not added (G trains on the task
    loss only). Training mode needs B >= 2 (BatchNorm over the batch).
    """

    feature_dim = 1024

    def __init__(self, out_features: int = 40, dropout: float = 0.3) -> None:
        super().__init__()
        self.out_features = int(out_features)
        self.input_tnet, self.feature_tnet = TNet(3), TNet(64)
        self.conv1 = nn.Sequential(*_conv_bn_relu((3, 64)))
        self.conv23 = nn.Sequential(*_conv_bn_relu((64, 128, 1024), last_relu=False))
        self.fc1 = nn.Sequential(*_linear_bn_relu((1024, 512)))
        self.fc2 = nn.Linear(512, 256)
        self.drop = nn.Dropout(dropout)
        self.bn2 = nn.BatchNorm1d(256)
        self.fc3 = nn.Linear(256, self.out_features)

    def global_features(self, points: Tensor) -> Tensor:
        """``[B, N, 3] -> [B, 1024]`` max-pooled per-point features."""
        _check_points(type(self).__name__, points)
        x = torch.bmm(points, self.input_tnet(points.transpose(1, 2))).transpose(1, 2)  # [B, 3, N]
        x = self.conv1(x)
        x = torch.bmm(self.feature_tnet(x).transpose(1, 2), x)  # (x^T A)^T: the features transformed
        return self.conv23(x).amax(2)

    def forward(self, points: Tensor) -> Tensor:
        x = self.fc1(self.global_features(points))
        return self.fc3(torch.relu(self.bn2(self.drop(self.fc2(x)))))


def build_point_encoder(name: str, out_features: int = 40, **kw) -> nn.Module:
    """Build a registered point encoder: ``[B, N, 3] -> [B, out_features]``; ``kw``: its constructor's
    own arguments (the option's ``network``; the config's ``kwargs()``)."""
    return OPTIONS["point_encoder"].lookup(name, "point encoder").network(out_features=out_features, **kw)


# ----------------------------------------------------------------------------- config options (point_encoder=NAME)
register = OPTIONS["point_encoder"].register


@dataclass
class PointEncoderConfig(OptionConfig):
    """G's point encoder: ``[B, N, 3] -> [B, features]`` (b = 40 in the paper)."""

    features: int = 40

    kind = "point_encoder"
    network: ClassVar[Callable[..., nn.Module]]  # the constructor: (out_features, **kwargs()) -> encoder

    def validate(self) -> "PointEncoderConfig":
        super().validate()
        at_least("point_encoder.features", self.features, 1)
        return self

    def kwargs(self) -> dict:
        """The encoder's own constructor arguments (beyond ``out_features``)."""
        return {}

    def build(self, out_features: Optional[int] = None) -> nn.Module:
        """The encoder ``[B, N, 3] -> [B, out_features]`` (None: ``features``) with this config's keys."""
        size = self.features if out_features is None else out_features
        return type(self).network(out_features=size, **self.kwargs())

    def check_points(self, n: int, where: str) -> None:
        """One line if the encoder cannot read ``n`` points per shape (``where``: the keys that set n)."""


@register("pointnet")
@dataclass
class PointNetConfig(PointEncoderConfig):
    """PointNet, this project's compact encoder (a linear projection of the pooled 1024-d feature,
    ~0.18 M parameters); ``use_tnet``: the input transform."""

    name: str = "pointnet"
    use_tnet: bool = False
    network = PointNet

    def kwargs(self) -> dict:
        return {"use_tnet": self.use_tnet}


@register("pointnet_paper")
@dataclass
class PaperPointNetConfig(PointEncoderConfig):
    """The paper's PointNet (``PaperPointNet``: both T-nets, the 1024-512-256 head, 3.47 M
    parameters at b = 40); ``dropout`` before the head's last BatchNorm (the reference's 0.3)."""

    name: str = "pointnet_paper"
    dropout: float = 0.3
    network = PaperPointNet

    def validate(self) -> "PaperPointNetConfig":
        super().validate()
        if not 0 <= self.dropout < 1:
            raise ValueError(f"point_encoder.dropout={self.dropout!r}: expected 0 <= dropout < 1")
        return self

    def kwargs(self) -> dict:
        return {"dropout": self.dropout}


# ---------------------------------------------------------------------------------------------
# Sampling a batch of shapes into a dense [B, n, 3] tensor
# ---------------------------------------------------------------------------------------------

def _rng_device(generator: Optional[torch.Generator], fallback: torch.device) -> torch.device:
    return generator.device if generator is not None else fallback


def _report_empty(names: Sequence[str], empty: Sequence[int], what: str, allow_empty: bool) -> None:
    if empty and not allow_empty:
        listed = ", ".join(f"'{names[i]}' (batch index {i})" for i in empty)
        raise ValueError(f"sample_points: shape {listed} {what}; drop it or pass allow_empty=True "
                         "to get zeros")


def _sample_clouds(clouds: PointClouds, n: int, generator, allow_empty: bool) -> Tensor:
    pts = clouds.points
    counts = clouds.points_per_shape.tolist()
    rng_dev = _rng_device(generator, pts.device)
    empty = [i for i, c in enumerate(counts) if c == 0]
    _report_empty(clouds.names, empty, "has no points", allow_empty)
    out = []
    for part, c in zip(torch.split(pts, counts), counts):
        if c == 0:
            out.append(pts.new_zeros(n, 3))
            continue
        if c == n:
            idx = torch.arange(n, device=rng_dev)
        elif c > n:  # uniform random subset, without replacement
            idx = torch.randperm(c, generator=generator, device=rng_dev)[:n]
        else:  # every point once, plus n - c extra points drawn uniformly with replacement
            extra = torch.randint(0, c, (n - c,), generator=generator, device=rng_dev)
            idx = torch.cat([torch.arange(c, device=rng_dev), extra])
        out.append(part[idx.to(pts.device)])
    if not out:
        return pts.new_zeros(0, n, 3)
    return torch.stack(out)


def _sample_meshes(meshes: Meshes, n: int, generator, allow_empty: bool) -> Tensor:
    verts, faces = meshes.verts, meshes.faces
    B = len(meshes)
    if B == 0:
        return verts.new_zeros(0, n, 3)
    tri = verts[faces]  # [F, 3, 3]
    areas = 0.5 * torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]).norm(dim=-1)
    F_per = meshes.faces_per_shape
    shape_of_face = meshes.shape_of_face()
    face_offsets = torch.cumsum(F_per, 0) - F_per
    local = torch.arange(len(faces), device=faces.device) - face_offsets[shape_of_face]
    Fmax = max(int(F_per.max()), 1)
    padded = areas.new_zeros(B, Fmax).detach()
    padded[shape_of_face, local] = areas.detach()
    total = padded.sum(1)
    empty = [i for i in range(B) if not float(total[i]) > 0.0]
    _report_empty(meshes.names, empty, "has no surface to sample (no faces, or zero total area)", allow_empty)
    if len(empty) == B:
        return verts.new_zeros(B, n, 3)
    rng_dev = _rng_device(generator, verts.device)
    weights = padded.to(rng_dev, torch.float64)
    if empty:
        weights[empty] = 1.0  # placeholder rows; their samples are replaced by zeros below
    choice = torch.multinomial(weights, n, replacement=True, generator=generator)  # [B, n] local
    r = torch.rand(B, n, 2, generator=generator, device=rng_dev, dtype=torch.float64)
    choice, r = choice.to(verts.device), r.to(device=verts.device, dtype=verts.dtype)
    global_face = (face_offsets[:, None] + choice).clamp(max=len(faces) - 1)  # clamp: placeholder rows only
    s = r[..., 0].sqrt()  # uniform barycentrics on a triangle: (1 - sqrt r1, sqrt r1 (1 - r2), sqrt r1 r2)
    bary = torch.stack([1.0 - s, s * (1.0 - r[..., 1]), s * r[..., 1]], -1)  # [B, n, 3]
    points = torch.einsum("bnk,bnkc->bnc", bary, tri[global_face])
    if empty:
        keep = torch.ones(B, 1, 1, dtype=points.dtype, device=points.device)
        keep[empty] = 0.0
        points = points * keep
    return points


def sample_points(shapes: Union[PointClouds, Meshes, Tensor], n: int, generator: Optional[torch.Generator] = None,
                  allow_empty: bool = False) -> Tensor:
    """A batch of B shapes -> dense points ``[B, n, 3]`` (dtype / device of the shapes).

    * ``PointClouds`` (or a dense ``[B, N, 3]`` tensor): a cloud of exactly n points is returned
      as is; more than n: a uniform random subset without replacement; fewer than n: every point
      once plus ``n - c`` points drawn uniformly with replacement (no bias towards the first
      points).
    * ``Meshes``: area-weighted uniform sampling of the surface (faces drawn with probability
      proportional to their area, then uniform barycentrics). Differentiable w.r.t. the vertices.

    ``generator``: a ``torch.Generator`` makes the result deterministic; without it torch's global
    generator is used. An empty shape (no points; a mesh with no faces or zero area) raises a
    ``ValueError`` naming it, unless ``allow_empty=True``, in which case its rows are zeros.
    """
    if isinstance(n, bool) or int(n) != n or n < 1:
        raise ValueError(f"sample_points: n must be an integer >= 1, got {n!r}")
    n = int(n)
    if isinstance(shapes, Tensor):
        if shapes.dim() != 3 or shapes.shape[-1] != 3:
            raise ValueError(f"sample_points: a tensor must be [B, N, 3], got {list(shapes.shape)}")
        shapes = PointClouds.from_padded(shapes)
    if isinstance(shapes, Meshes):
        return _sample_meshes(shapes, n, generator, allow_empty)
    if isinstance(shapes, PointClouds):
        return _sample_clouds(shapes, n, generator, allow_empty)
    raise TypeError(f"sample_points: expected PointClouds, Meshes or a [B, N, 3] tensor, got {type(shapes).__name__}")
