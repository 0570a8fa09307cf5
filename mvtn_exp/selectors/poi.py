"""Learned views that look at a learned point of interest (``mvtn_poi``): a pose-equivariant G.

For each of the M views a per-point MLP scores every point from *rotation-invariant* local
descriptors; the softmax of the scores over the points weights the (centred) points into a point
of interest ``q_m [B, 3]``, and the camera looks from the direction ``d_m = normalize(d0_m + gain *
q_m)`` (``d0``: the spherical layout, the same u0 as ``mvtn_spherical``):

    s = MLP(desc(P))        [B, N, M]     desc: rotation invariant, no gradient needed
    w = softmax_N(s)        [B, N, M]
    q = w^T (P - mean P)    [B, M, 3]
    d = normalize(d0 + gain * q) -> (azim, elev)

Why (measured on ``synthetic_views``, where the class detail is visible only from a cone around
a cup axis in a random SO(3) pose): the paper's regressor must learn a map from xyz to angles
that works for every pose, through tanh, from the classification gradient alone; in short runs it
moves its views by a few degrees, the same for every shape. Here the score function is shared by
all points of all shapes in every pose, so every shape's gradient (move the camera towards the
points whose side shows the detail) trains the same small function, and the views turn with the
shape by construction (rotating the points rotates ``q`` and so the camera, exactly for
``d0 = 0``). There is no tanh and no angle wrap: the direction is a smooth function of ``q``.

At initialisation the last layer is zero: the weights are uniform, ``q = 0`` and ``u = u0``
exactly, as in the paper's MVTN.

``learn_gain``: the gain is learned (as ``log gain``, starting at ``gain``). The u0 term is the
same world direction for every pose, so under a random pose it tilts each camera away from the
direction of ``q`` by up to ``atan(1 / (gain |q|))`` in a direction that changes with the pose
(about 20 degrees for ``|q| = 0.3`` at gain 8). A learned gain lets G shrink that tilt where a
view along ``q`` is better; the start, ``u = u0``, is unchanged.

Descriptors per point ``p`` (centred at the cloud's mean), for each ``k`` in ``ks`` with the
``k`` nearest neighbours and their centroid ``c``: the mean neighbour distance, ``(c - p) . p / |p|``
(positive in concavities that open away from the centre, such as the floor of a cup),
``|c - p|``, and the two smallest PCA eigenvalue ratios of the neighbourhood (flatness); plus
``|p|``. All are divided by the cloud's RMS radius. Being rotation invariant, they are computed
once per shape and looked up at later steps (``cache`` shapes kept; ``invariant_cache.py``).
``descriptors`` keeps a subset by name (``DESCRIPTORS``: ``radius`` = ``|p|``, ``spacing``,
``concavity`` = ``(c - p) . p / |p|``, ``offset`` = ``|c - p|``, ``flatness``; all by default),
to measure what each brings.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import partial
from typing import ClassVar, Sequence

import torch
from torch import Tensor, nn

from mvtn_exp.config.checks import at_least
from mvtn_exp.render import layouts
from mvtn_exp.render.cameras import view_directions
from mvtn_exp.selectors.config import LearnedSelectorConfig, register
from mvtn_exp.selectors.fixed import ViewSelector, Views
from mvtn_exp.selectors.invariant_cache import InvariantCache
from mvtn_exp.selectors.polarity import antipode
from mvtn_exp.selectors.strategies import Flips, Race, RaceKeys, Search, Smoothed
from mvtn_exp.selectors.strategies.race import ONE_SET


def invariant_descriptors(points: Tensor, ks: Sequence[int] = (16, 48)) -> Tensor:
    """``[B, N, 3]`` (centred) -> rotation-invariant per-point descriptors ``[B, N, 1 + 5 * len(ks)]``."""
    B, N, _ = points.shape
    scale = points.pow(2).sum(-1).mean(1).sqrt().clamp_min(1e-6)[:, None, None]  # [B, 1, 1]
    p = points / scale
    r = p.norm(dim=-1, keepdim=True)  # [B, N, 1]
    radial = p / r.clamp_min(1e-6)
    d2 = torch.cdist(p, p)  # [B, N, N]
    feats = [r]
    kmax = min(max(ks), N)
    dist, idx = d2.topk(kmax, dim=-1, largest=False)  # [B, N, kmax] (self first)
    for k in ks:
        k = max(min(k, N), 2)
        nb = torch.gather(p.unsqueeze(1).expand(B, N, N, 3), 2, idx[:, :, :k, None].expand(B, N, k, 3))  # [B,N,k,3]
        c = nb.mean(2)
        off = c - p
        x = nb - c.unsqueeze(2)
        cov = x.transpose(-1, -2) @ x / k  # [B, N, 3, 3]
        ev = torch.linalg.eigvalsh(cov).clamp_min(0)  # ascending
        tot = ev.sum(-1, keepdim=True).clamp_min(1e-12)
        feats += [dist[:, :, 1:k].mean(-1, keepdim=True), (off * radial).sum(-1, keepdim=True),
                  off.norm(dim=-1, keepdim=True), ev[..., :2] / tot]
    return torch.cat(feats, -1)


DESCRIPTORS = ("radius", "spacing", "concavity", "offset", "flatness")


def descriptor_columns(names: Sequence[str], ks: Sequence[int]) -> list[int]:
    """Columns of ``invariant_descriptors(.., ks)`` holding the named descriptors (``DESCRIPTORS``)."""
    unknown = [n for n in names if n not in DESCRIPTORS]
    if unknown or not names:
        raise ValueError(f"selector.descriptors={list(names)}: expected a non-empty subset of {', '.join(DESCRIPTORS)}")
    per_k = {"spacing": [0], "concavity": [1], "offset": [2], "flatness": [3, 4]}
    cols = [0] if "radius" in names else []
    for j in range(len(ks)):
        cols += [1 + 5 * j + c for n in DESCRIPTORS[1:] if n in names for c in per_k[n]]
    return cols


def direction_to_angles(d: Tensor) -> tuple[Tensor, Tensor]:
    """Directions ``[..., 3]`` (any length) -> azimuth, elevation in degrees (finite gradients at the poles)."""
    x, y, z = d.unbind(-1)
    azim = torch.rad2deg(torch.atan2(x, z))
    elev = torch.rad2deg(torch.atan2(y, torch.sqrt(x * x + z * z + 1e-12)))
    return azim, elev


class PointOfInterestSelector(ViewSelector):
    """``forward(points [B, N, 3]) -> (azim, elev, dist)``, each ``[B, M]`` (see the module docstring).

    views: M; hidden: MLP width; ks: neighbourhood sizes of the descriptors; gain: how far the
    point of interest pulls the camera from u0 (the shapes lie in the unit sphere: with gain 8 a
    point 0.25 from the centre outweighs u0 twice); distance: camera distance; cache: how many
    shapes' descriptors are kept for later steps (0: computed at every call); learn_gain: the gain
    is a parameter (``log_gain``), trained with G; hypotheses: sets of M views held side by side
    (the module docstring).
    """

    learned = True

    def __init__(self, views: int, hidden: int = 64, ks: Sequence[int] = (16, 48), gain: float = 8.0,
                 distance: float = 2.2, sphere: str = "equal_area", cache: int = 0, learn_gain: bool = False,
                 hypotheses: int = 1, descriptors: Sequence[str] = DESCRIPTORS, antipodes: bool = False,
                 **_ignored) -> None:
        super().__init__(views)
        if not gain > 0:
            raise ValueError(f"PointOfInterestSelector: gain must be > 0, got {gain!r}")
        if int(hypotheses) < 1:
            raise ValueError(f"PointOfInterestSelector: hypotheses must be >= 1, got {hypotheses!r}")
        if antipodes and int(hypotheses) % 2:
            raise ValueError(f"PointOfInterestSelector: antipodes needs an even number of hypotheses, got {hypotheses!r}")
        M, self.hypotheses, self.antipodes = self.views, int(hypotheses), bool(antipodes)
        H = self.hypotheses
        free = H // 2 if antipodes else H  # hypotheses with their own scores (the rest: their antipodes)
        if H > 1:
            self.register_buffer("active", torch.zeros((), dtype=torch.long))
        self.ks, self.distance = tuple(int(k) for k in ks), float(distance)
        log_gain = torch.tensor(float(gain)).log()
        if learn_gain:
            self.log_gain = nn.Parameter(log_gain)
        else:
            self.register_buffer("log_gain", log_gain, persistent=False)
        self.descriptors = InvariantCache(partial(invariant_descriptors, ks=self.ks), cache)
        azim0, elev0, _ = layouts.spherical(M * free, 1, distance=distance, sphere=sphere)
        order = torch.arange(M * free).reshape(M, free).T.reshape(-1)  # hypothesis h, view m <- layout m * free + h
        azim0, elev0 = azim0[0, order], elev0[0, order]
        if antipodes:  # hypothesis free + h: hypothesis h's views from the opposite side
            far = antipode(azim0, elev0)
            azim0, elev0 = torch.cat([azim0, far[0]]), torch.cat([elev0, far[1]])
        self.register_buffer("azim0", azim0, persistent=False)  # [H * M], hypothesis-major
        self.register_buffer("elev0", elev0, persistent=False)
        self.register_buffer("d0", view_directions(azim0, elev0), persistent=False)  # [H * M, 3]
        self.register_buffer("columns", torch.tensor(descriptor_columns(descriptors, self.ks)), persistent=False)
        f = len(self.columns)
        self.scorer = nn.Sequential(nn.BatchNorm1d(f), nn.Linear(f, hidden), nn.BatchNorm1d(hidden), nn.ReLU(inplace=True),
                                    nn.Linear(hidden, hidden), nn.BatchNorm1d(hidden), nn.ReLU(inplace=True),
                                    nn.Linear(hidden, M * free))
        nn.init.zeros_(self.scorer[-1].weight)
        nn.init.zeros_(self.scorer[-1].bias)

    def _columns(self, t: Tensor, all_hypotheses: bool) -> Tensor:
        """``[..., H * M]`` -> the active hypothesis's ``[..., M]`` (all of them if asked, or if H = 1)."""
        if self.hypotheses == 1 or all_hypotheses:
            return t
        a = int(self.active)
        return t[..., a * self.views:(a + 1) * self.views]

    def initial_views(self, batch: int = 1, all_hypotheses: bool = False) -> Views:
        azim = self._columns(self.azim0, all_hypotheses).expand(batch, -1).clone()
        elev = self._columns(self.elev0, all_hypotheses).expand(batch, -1).clone()
        return azim, elev, torch.full_like(azim, self.distance)

    def point_weights(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """``[B, N, 3]`` -> (centred points ``[B, N, 3]``, softmax weights over the points ``[B, N, H' * M]``;
        H' = H, or H / 2 with ``antipodes``)."""
        p = points - points.mean(1, keepdim=True)
        with torch.no_grad():
            desc = self.descriptors(p.detach())[..., self.columns]  # [B, N, F]
        B, N, F = desc.shape
        s = self.scorer(desc.reshape(B * N, F)).reshape(B, N, self.scorer[-1].out_features)
        return p, torch.softmax(s, dim=1)

    def forward(self, points: Tensor, all_hypotheses: bool = False) -> Views:
        """``[B, N, 3]`` -> views ``[B, M]`` (``[B, H * M]`` with ``all_hypotheses``)."""
        self._check_points(points)
        p, w = self.point_weights(points.to(self.d0.dtype))
        q = torch.einsum("bnm,bnc->bmc", w, p)  # [B, H' * M, 3]
        if self.antipodes:  # the second half of the hypotheses: d -> -d (d0 is negated there already)
            q = torch.cat([q, -q], 1)
        azim, elev = direction_to_angles(self.d0 + self.log_gain.exp() * q)
        azim, elev = self._columns(azim, all_hypotheses), self._columns(elev, all_hypotheses)
        return azim, elev, torch.full_like(azim, self.distance)

    @property
    def gain(self) -> float:
        """The current gain (learned with ``learn_gain``)."""
        return float(self.log_gain.detach().exp())

    def extra_repr(self) -> str:
        learned = ", learned" if isinstance(self.log_gain, nn.Parameter) else ""
        anti = ", antipodes" if self.antipodes else ""
        hyp = f", hypotheses={self.hypotheses}{anti} (active {int(self.active)})" if self.hypotheses > 1 else ""
        return f"views={self.views}, ks={self.ks}, gain={self.gain:g}{learned}, distance={self.distance}{hyp}"


# ----------------------------------------------------------------------------- config options
@register("mvtn_poi")
@dataclass
class PoiConfig(RaceKeys, LearnedSelectorConfig):
    """The point-of-interest G alone (defaults: the paper's training, autograd on C's loss).

    ``gain``: how far the point of interest pulls the cameras from u0 (``learn_gain``: a parameter
    of G starting there); ``cache``: shapes whose rotation-invariant descriptors are kept (0: none;
    4096 shapes x 256 points: about 46 MB). ``hypotheses``: H sets of M views raced side by side
    for at most ``race_epochs`` epochs, the one of lowest G loss kept (earlier once it leads every
    other by ``race_z`` paired standard errors; null: never earlier); ``race_batches``: a racing
    epoch renders all hypotheses for at most this many batches, then the race is decided for good on
    them (null: whole epochs); ``race_mode``: C classifies each hypothesis's views as a shape of its
    own (separate) or all H x M views pooled (pooled); ``antipodes``: the second half of the H
    hypotheses are the first half's views from the opposite side (G scores H / 2);
    ``race_probes``: false holds G's hypotheses where they start while they race (no probes, no
    G step: a racing step then costs C's passes alone) and lets the kept one move after the race
    (the race: ``selectors/strategies/race.py``).
    ``descriptors``: the subset G scores from (``DESCRIPTORS``); ``ks``: the neighbourhood sizes
    (points) they are computed over."""

    name: str = "mvtn_poi"
    gain: float = 8.0
    cache: int = 4096
    learn_gain: bool = False
    antipodes: bool = False
    descriptors: list[str] = field(default_factory=lambda: list(DESCRIPTORS))
    ks: list[int] = field(default_factory=lambda: [16, 48])

    training_keys: ClassVar[tuple] = LearnedSelectorConfig.training_keys + ("cache",)
    strategies: ClassVar[tuple] = (Smoothed, Flips, Race, Search)

    def validate(self) -> "PoiConfig":
        super().validate()
        if not self.ks or any(int(k) != k or k < 2 for k in self.ks):
            raise ValueError(f"selector.ks={list(self.ks)}: expected a non-empty list of neighbourhood sizes, "
                             "each an integer >= 2")
        descriptor_columns(self.descriptors, tuple(self.ks))
        at_least("selector.gain", self.gain, 0.0, strict=True)
        at_least("selector.cache", self.cache, 0)
        if self.antipodes and (self.hypotheses < 2 or self.hypotheses % 2):
            raise ValueError(f"selector.antipodes=true with selector.hypotheses={self.hypotheses}: expected an even "
                             "number of hypotheses (each free one raced against its views from the opposite side); "
                             f"one set of views: {ONE_SET}")
        return self

    def build(self, views: int, seed: int, point_encoder=None) -> PointOfInterestSelector:
        return PointOfInterestSelector(views, distance=self.distance, gain=self.gain, sphere=self.sphere,
                                       cache=self.cache, learn_gain=self.learn_gain, hypotheses=self.hypotheses,
                                       descriptors=tuple(self.descriptors), ks=tuple(int(k) for k in self.ks),
                                       antipodes=self.antipodes)


@register("poi")
@dataclass
class PoiRecipeConfig(PoiConfig):
    """This project's learned views, the recipe that wins on view-dependent data, as defaults: G
    trained on the smoothed gradient (2 antithetic probe pairs, 10 degrees) of the centered
    true-class logit at learning rate 1e-2, gain 32, C's BatchNorm statistics re-estimated over 24
    training batches before each validation; ``conf/selector/poi.yaml`` also picks the hard
    renderer with a camera light on white shapes (``renderer=hard_camera``; a ``renderer=`` on the
    command line wins). Eight hypotheses race for 8 epochs, pooled, four of them the others' views
    from the opposite side (``antipodes``); how often G finds the detail with eight, four or one
    set of views, and at what cost: docs/results/finding-the-detail.md. Four:
    ``selector.hypotheses=4``; one set of views, the cheapest: ``selector.hypotheses=1
    selector.race_epochs=0 selector.antipodes=false``."""

    name: str = "poi"
    gain: float = 32.0
    hypotheses: int = 8
    race_epochs: int = 8
    antipodes: bool = True
    race_mode: str = "pooled"
    lr: float = 1e-2
    grad: str = "smoothed"
    loss: str = "centered_logit"
    bn_recalibrate: int = 24
