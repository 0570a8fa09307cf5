"""Learned view selection: the MVTN regressor (Hamdi et al., ICCV 2021, Sec. 3.2).

    u = u0 + u_bound * tanh(G(S, u0))       (circular, spherical, direct_offset)
    u = u_bound * tanh(G(S))                (direct: the paper's MVTN-direct)

``G`` is a point encoder (PointNet, b = 40 features) followed by an MLP over
``concat(features [B, b], u0 [B, 2M])`` (over the features alone for ``direct``):
``b (+ 2M) -> b -> b -> 5M -> 2M`` (BatchNorm + ReLU between hidden layers, last layer linear;
``regressor="compact"``, the default) or the official code's MLP (``regressor="official"``: every one
of those four layers Linear + BatchNorm + ReLU + Dropout(0.5), then a plain Linear(2M, 2M)).
Parameters at b = 40 (``regressor_parameters``): compact 10M^2 + 297M + 3440 with the u0 input,
10M^2 + 217M + 3440 without (direct); official 14M^2 + 303M + 3440 / 14M^2 + 223M + 3440. The
paper states 14M^2 + 211M + 3320 (7,868 at M = 12): no consistent arrangement of these layers
gives it (the M^2 term is the official tail's, the constant needs 120 fewer parameters than b ->
b -> b with biases and BatchNorm), so "official" is the closest faithful G. ``u0`` enters
normalised (azimuth / 180, elevation / 90). The MLP output is split into M azimuth offsets and M
elevation offsets (plus M distance offsets when ``learn_distance``).

What each variant learns (both angles are learned per view and per shape in every variant):

=============  ======================================  ==========================  ================
variant        u0 (initial views)                      azimuth offset bound        elevation bound
=============  ======================================  ==========================  ================
circular       ``layouts.circular`` (elevation 30)     +-180 / M                   +-90
spherical      ``layouts.spherical`` (``sphere``)      +-180 / M                   +-90
direct         none (0, 0): G sees the shape only      +-180 (any azimuth)         +-90
direct_offset  ``layouts.spherical`` (``sphere``)      +-180 (any azimuth)         +-90
=============  ======================================  ==========================  ================

"direct" is the paper's MVTN-direct: no u0, no u0 input. Its last layer keeps PyTorch's default
initialisation (as the official code), because with zero weights all M views would start at
(0, 0), render the same image and receive the same gradient: they would never separate.
"direct_offset" (this project's earlier "direct") regresses the views as freely but from the
spherical layout, with u0 as input, so its M views are distinct from the start. Angles are neither wrapped nor clamped (that would cut gradients): an elevation
beyond +-90 degrees is a valid camera (``mvtn_exp.render.cameras`` is smooth there), and it is
the camera over the pole at azimuth + 180.

Distance: constant ``distance`` unless ``learn_distance``, then
``distance + distance_bound * tanh(extra M outputs)``.

Initialisation (default ``init_std=0``): the last linear layer's weights and bias are zero, so at initialisation
``u == u0`` exactly. Gradients still flow because ``tanh'(0) = 1``: on the first step the loss
gradient reaches the last layer (its inputs are non-zero), and once that layer is non-zero it
reaches the hidden layers and the point encoder too (at the very first step their gradient is
exactly zero, since the zero weights block it).

``u_bound`` (buffer ``[3]``: azimuth, elevation in degrees, distance in world units; the
distance bound is 0 when the distance is not learned) is the one place the bounds are defined;
``azim_bound`` / ``elev_bound`` override the paper's values for ablations.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Optional, Union

import torch
from torch import Tensor, nn

from mvtn_exp.config.checks import at_least, one_of
from mvtn_exp.models.point_encoders import build_point_encoder
from mvtn_exp.render import layouts
from mvtn_exp.selectors.config import LearnedSelectorConfig, register
from mvtn_exp.selectors.fixed import ViewSelector, Views

if TYPE_CHECKING:  # pragma: no cover
    from mvtn_exp.config.schema import TrainConfig

VARIANTS = ("direct", "direct_offset", "circular", "spherical")
REGRESSORS = ("compact", "official")
OFFICIAL_DROPOUT = 0.5


def build_regressor(in_features: int, features: int, views: int, outputs: int, init_std: Optional[float] = 0.0,
              kind: str = "compact") -> nn.Sequential:
    """The MVTN MLP ``[B, in_features] -> [B, outputs]``: ``-> b -> b -> 5M -> outputs`` (compact),
    or ``-> b -> b -> 5M -> outputs -> outputs`` with BatchNorm, ReLU and dropout 0.5 after every
    layer but the last (official; see the module docstring).

    The last layer's bias is zero and its weights are ``N(0, init_std^2)`` (0: exactly u0 at
    start); ``init_std=None`` keeps PyTorch's default initialisation of that layer."""
    if kind not in REGRESSORS:
        raise ValueError(f"MVTNSelector: unknown regressor {kind!r}; allowed: {', '.join(REGRESSORS)}")
    official = kind == "official"
    widths = (in_features, features, features, 5 * views) + ((outputs,) if official else ())
    layers: list[nn.Module] = []
    for cin, cout in zip(widths[:-1], widths[1:]):
        layers += [nn.Linear(cin, cout), nn.BatchNorm1d(cout), nn.ReLU(inplace=True)]
        layers += [nn.Dropout(OFFICIAL_DROPOUT)] if official else []
    last = nn.Linear(widths[-1], outputs)
    if init_std is None:
        pass
    elif init_std > 0:
        nn.init.normal_(last.weight, std=float(init_std))
    else:
        nn.init.zeros_(last.weight)
    nn.init.zeros_(last.bias)
    return nn.Sequential(*layers, last)


def regressor_parameters(views: int, features: int = 40, u0_input: bool = True, kind: str = "compact") -> int:
    """``build_regressor``'s parameter count for 2M outputs (M = ``views``, b = ``features``), layer by
    layer: each hidden layer ``in * out`` weights, ``out`` biases and ``2 out`` BatchNorm
    parameters, then the last Linear's ``in * 2M + 2M``."""
    M, b = int(views), int(features)
    cin = b + 2 * M * bool(u0_input)
    hidden = [(cin, b), (b, b), (b, 5 * M)] + ([(5 * M, 2 * M)] if kind == "official" else [])
    n = sum(i * o + o + 2 * o for i, o in hidden)  # Linear weights + bias, BatchNorm weight + bias
    last_in = 2 * M if kind == "official" else 5 * M
    return n + last_in * 2 * M + 2 * M


class MVTNSelector(ViewSelector):
    """Learned per-shape views: ``forward(points [B, N, 3]) -> (azim, elev, dist)``, each ``[B, M]``.

    views: M. variant: "direct" | "circular" | "spherical" (see the module docstring).
    point_encoder: a registered name (``mvtn_exp.models.point_encoders``) or an ``nn.Module``
    mapping ``[B, N, 3] -> [B, features]``. features: b (40 in the paper).
    distance: camera distance (the centre of the learned range when ``learn_distance``).
    elevation, azim_start: elevation and first azimuth of the circular u0 (circular variant only;
    180: the official code's learned circular layout). init_std: std of the last
    layer's weights at initialisation (None: 0 for the offset variants, so they start exactly at
    u0, and PyTorch's default for ``direct``). sphere: the spherical u0's construction
    (``layouts.SPHERES``: equal_area, the paper's, or fibonacci). regressor: ``REGRESSORS``
    (compact, or official: the official code's MLP; see the module docstring).
    BatchNorm in the encoder and the regressor: training mode needs B >= 2; in eval mode the
    views of a shape do not depend on the other shapes in the batch.
    """

    learned = True

    def __init__(self, views: int, variant: str, point_encoder: Union[str, nn.Module] = "pointnet",
                 features: int = 40, distance: float = 2.2, learn_distance: bool = False,
                 distance_bound: float = 1.0, elevation: float = 30.0,
                 point_encoder_kwargs: Optional[dict] = None, azim_bound: Optional[float] = None,
                 elev_bound: Optional[float] = None, init_std: Optional[float] = None,
                 sphere: str = "equal_area", regressor: str = "compact", azim_start: float = 180.0,
                 categories: int = 0) -> None:
        super().__init__(views)
        if variant not in VARIANTS:
            raise ValueError(f"MVTNSelector: unknown variant {variant!r}; allowed: {', '.join(VARIANTS)}")
        if isinstance(features, bool) or int(features) != features or features < 1:
            raise ValueError(f"MVTNSelector: features must be an integer >= 1, got {features!r}")
        if learn_distance and not distance_bound > 0:
            raise ValueError(f"MVTNSelector: distance_bound must be > 0, got {distance_bound!r}")
        M, b = self.views, int(features)
        self.variant, self.features = variant, b
        self.distance, self.learn_distance = float(distance), bool(learn_distance)

        self.uses_u0 = variant != "direct"
        if variant == "circular":
            azim0, elev0, _ = layouts.circular(M, 1, elevation=elevation, distance=distance, azim_start=azim_start)
        elif variant == "direct":  # u = u_bound * tanh(G(S)): no initial views
            azim0, elev0 = torch.zeros(1, M), torch.zeros(1, M)
        else:  # "spherical" and "direct_offset" start from the spherical layout
            azim0, elev0, _ = layouts.spherical(M, 1, distance=distance, sphere=sphere)
        self.register_buffer("azim0", azim0[0], persistent=False)  # [M] degrees
        self.register_buffer("elev0", elev0[0], persistent=False)  # [M] degrees
        if azim_bound is None:
            azim_bound = 180.0 if variant.startswith("direct") else 180.0 / M
        elev_bound = 90.0 if elev_bound is None else elev_bound
        if init_std is None and variant != "direct":
            init_std = 0.0
        if not (azim_bound >= 0 and elev_bound >= 0 and (init_std is None or init_std >= 0)):
            raise ValueError(f"MVTNSelector: need azim_bound, elev_bound, init_std >= 0 "
                             f"(got {azim_bound}, {elev_bound}, {init_std})")
        dist_bound = float(distance_bound) if self.learn_distance else 0.0
        self.register_buffer("u_bound", torch.tensor([float(azim_bound), float(elev_bound), dist_bound]),
                             persistent=False)

        if isinstance(point_encoder, nn.Module):
            self.encoder = point_encoder
        else:
            self.encoder = build_point_encoder(point_encoder, out_features=b, **(point_encoder_kwargs or {}))
        self.regressor_kind = regressor
        self.categories = int(categories)  # > 0: the shape's category one-hot joins the point features
        self.regressor = build_regressor(b + 2 * M * self.uses_u0 + self.categories, b, M,
                                         (3 if self.learn_distance else 2) * M, init_std, regressor)

    def initial_views(self, batch: int = 1) -> Views:
        """u0: ``(azim, elev, dist)``, each ``[batch, M]``."""
        azim = self.azim0.expand(batch, -1).clone()
        return azim, self.elev0.expand(batch, -1).clone(), torch.full_like(azim, self.distance)

    def forward(self, points: Tensor, category: Optional[Tensor] = None) -> Views:
        """``[B, N, 3] -> (azim, elev, dist)``, each ``[B, M]`` (degrees, degrees, world units);
        ``category [B]``: the shapes' category indices, read when ``categories`` > 0."""
        self._check_points(points)
        B, M = points.shape[0], self.views
        dtype = self.azim0.dtype
        feats = self.encoder(points.to(dtype))  # [B, b]
        if self.uses_u0:
            u0 = torch.cat([self.azim0 / 180.0, self.elev0 / 90.0]).expand(B, -1)  # [B, 2M]
            feats = torch.cat([feats, u0], dim=1)
        if self.categories:
            if category is None:
                raise ValueError(f"MVTNSelector(categories={self.categories}): call it with the shapes' categories")
            feats = torch.cat([feats, nn.functional.one_hot(category.long(), self.categories).to(feats.dtype)], dim=1)
        t = torch.tanh(self.regressor(feats))  # [B, 2M or 3M]
        azim = self.azim0 + self.u_bound[0] * t[:, :M]
        elev = self.elev0 + self.u_bound[1] * t[:, M:2 * M]
        if self.learn_distance:
            dist = self.distance + self.u_bound[2] * t[:, 2 * M:]
        else:
            dist = torch.full_like(azim, self.distance)
        return azim, elev, dist

    def extra_repr(self) -> str:
        return (f"views={self.views}, variant={self.variant!r}, features={self.features}, "
                f"distance={self.distance}, learn_distance={self.learn_distance}, regressor={self.regressor_kind!r}")


# ----------------------------------------------------------------------------- config options
@dataclass
class MVTNConfig(LearnedSelectorConfig):
    """The paper's learned G (a point encoder from the ``point_encoder`` group, then the regressor):
    ``azim_bound`` / ``elev_bound`` (degrees; null: the variant's, see the module docstring),
    ``learn_distance`` within ``distance_bound``, ``init_std`` (null: 0 for the offset variants,
    PyTorch's default for direct), ``regressor`` (compact | official), ``category_input`` (the
    shape's category one-hot beside G's point features, as point segmentation models condition on
    it; ``task=segmentation`` only, where the category is given). Trained as the paper does:
    autograd through the differentiable renderer on C's loss."""

    azim_bound: Optional[float] = None
    elev_bound: Optional[float] = None
    learn_distance: bool = False
    distance_bound: float = 1.0
    init_std: Optional[float] = None
    regressor: str = "compact"
    category_input: bool = False

    variant = ""  # class attribute: the MVTNSelector variant

    def validate(self) -> "MVTNConfig":
        super().validate()
        one_of("selector.regressor", self.regressor, REGRESSORS)
        for key in ("azim_bound", "elev_bound", "init_std"):
            if getattr(self, key) is not None:
                at_least(f"selector.{key}", getattr(self, key), 0.0)
        if self.learn_distance:
            at_least("selector.distance_bound", self.distance_bound, 0.0, strict=True)
            if self.grad == "smoothed":
                raise ValueError("selector.grad=smoothed estimates G's azimuth and elevation gradients only; "
                                 "selector.learn_distance=true needs selector.grad=autograd")
        return self

    def check(self, cfg: "TrainConfig") -> None:
        super().check(cfg)
        if self.category_input and cfg.task.name != "segmentation":
            raise ValueError(f"selector.category_input=true with task={cfg.task.name}: G would read the label it is to "
                             "predict; the category is an input of task=segmentation only")
        n = min(cfg.dataset.num_points, self.num_points or cfg.dataset.num_points)
        cfg.point_encoder.check_points(n, f"selector.num_points={self.num_points}, "
                                          f"dataset.num_points={cfg.dataset.num_points}")

    def layout_kwargs(self) -> dict:
        return {"sphere": self.sphere}

    def build(self, views: int, seed: int, point_encoder=None, categories: int = 0) -> "MVTNSelector":
        """G; ``categories``: the dataset's category count (read with ``category_input``)."""
        pe = point_encoder
        if self.category_input and categories < 1:
            raise ValueError("selector.category_input=true: G needs the dataset's category count to build")
        return MVTNSelector(views, self.variant, point_encoder=pe.name, features=pe.features, distance=self.distance,
                            learn_distance=self.learn_distance, distance_bound=self.distance_bound,
                            azim_bound=self.azim_bound, elev_bound=self.elev_bound, init_std=self.init_std,
                            point_encoder_kwargs=pe.kwargs(), regressor=self.regressor,
                            categories=categories if self.category_input else 0, **self.layout_kwargs())


@register("mvtn_direct")
@dataclass
class MVTNDirectConfig(MVTNConfig):
    """The paper's MVTN-direct: u = u_bound * tanh(G(S)), no initial views."""

    name: str = "mvtn_direct"
    variant = "direct"


@register("mvtn_direct_offset")
@dataclass
class MVTNDirectOffsetConfig(MVTNConfig):
    """Views as free as mvtn_direct's, regressed as offsets from the spherical layout (an input of G)."""

    name: str = "mvtn_direct_offset"
    variant = "direct_offset"


@register("mvtn_spherical")
@dataclass
class MVTNSphericalConfig(MVTNConfig):
    """The paper's MVTN-spherical: offsets (+-180/M azimuth, +-90 elevation) around the spherical layout."""

    name: str = "mvtn_spherical"
    variant = "spherical"


@register("mvtn_circular")
@dataclass
class MVTNCircularConfig(MVTNConfig):
    """The paper's MVTN-circular: offsets around the circular layout at ``elevation`` degrees whose
    azimuths start at ``azim_start`` (180: the official code's learned circular layout)."""

    name: str = "mvtn_circular"
    elevation: float = 30.0
    azim_start: float = 180.0
    variant = "circular"

    def layout_kwargs(self) -> dict:
        return {"elevation": self.elevation, "azim_start": self.azim_start}
