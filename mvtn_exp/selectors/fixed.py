"""Fixed (non-learned) view selectors: circular, spherical and random camera layouts.

Every selector is an ``nn.Module`` with the same interface:

    forward(points [B, N, 3]) -> (azim [B, M], elev [B, M], dist [B, M])

angles in degrees, distance in world units (conventions in ``mvtn_exp.render.cameras``), on the
device and in the floating dtype of ``points``. Attributes: ``views`` (M) and ``learned`` (bool).
Fixed selectors only read the batch size, device and dtype of ``points``.
"""
from __future__ import annotations

import operator
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from mvtn_exp.config.checks import at_least, one_of
from mvtn_exp.render import layouts
from mvtn_exp.selectors.config import SelectorConfig, register

Views = tuple[Tensor, Tensor, Tensor]


def check_views(views) -> int:
    """``views`` must be an integer >= 1 (bool, float and str are rejected, even 4.0)."""
    m = None
    if not isinstance(views, bool):
        try:
            m = operator.index(views)
        except TypeError:
            m = None
    if m is None or m < 1:
        raise ValueError(f"views: expected an integer number of views M >= 1, got {views!r}")
    return int(m)


class ViewSelector(nn.Module):
    """Base class: ``forward(points [B, N, 3]) -> (azim, elev, dist)``, each ``[B, M]``."""

    learned: bool = False

    def __init__(self, views: int) -> None:
        super().__init__()
        self.views = check_views(views)

    def _check_points(self, points: Tensor) -> None:
        if not isinstance(points, Tensor) or points.dim() != 3 or points.shape[-1] != 3:
            shape = list(points.shape) if isinstance(points, Tensor) else type(points).__name__
            raise ValueError(f"{type(self).__name__} expects points [B, N, 3], got {shape}")

    def refine(self, model, batch: dict, views: Views) -> Views:
        """The views after any per-batch work against the model's R and C (none: ``views``)."""
        return views

    @staticmethod
    def _dtype(points: Tensor) -> torch.dtype:
        return points.dtype if points.is_floating_point() else torch.get_default_dtype()

    def extra_repr(self) -> str:
        return f"views={self.views}"


class CircularSelector(ViewSelector):
    """M views at one ``elevation``, azimuths ``azim_start + 360 k / M`` (the official code's fixed
    circular layout starts at 90); same for every shape."""

    def __init__(self, views: int, elevation: float = 30.0, distance: float = 2.2, azim_start: float = 90.0) -> None:
        super().__init__(views)
        self.elevation, self.distance, self.azim_start = float(elevation), float(distance), float(azim_start)

    def forward(self, points: Tensor) -> Views:
        """``[B, N, 3] -> (azim, elev, dist)``, each ``[B, M]``."""
        self._check_points(points)
        return layouts.circular(self.views, points.shape[0], self.elevation, self.distance,
                                device=points.device, dtype=self._dtype(points), azim_start=self.azim_start)


class SphericalSelector(ViewSelector):
    """Exactly M views spread over the sphere (``layouts.spherical``: the paper's equal-area rings
    or a Fibonacci lattice, ``sphere``); the same for every shape."""

    def __init__(self, views: int, distance: float = 2.2, sphere: str = "equal_area") -> None:
        super().__init__(views)
        if sphere not in layouts.SPHERES:
            raise ValueError(f"SphericalSelector: sphere={sphere!r}; expected one of {', '.join(layouts.SPHERES)}")
        self.distance, self.sphere = float(distance), sphere

    def forward(self, points: Tensor) -> Views:
        """``[B, N, 3] -> (azim, elev, dist)``, each ``[B, M]``."""
        self._check_points(points)
        return layouts.spherical(self.views, points.shape[0], self.distance,
                                 device=points.device, dtype=self._dtype(points), sphere=self.sphere)


def random_directions(shape: tuple[int, ...], generator: torch.Generator | None = None) -> tuple[Tensor, Tensor]:
    """Directions uniform on the sphere: azimuth ~ U[0, 360), elevation = asin(U[-1, 1]) (degrees).

    Drawn on the CPU in float64 (so a seed gives the same views on every device). Returns
    ``(azim, elev)``, each of ``shape``.
    """
    u = torch.rand(2, *shape, generator=generator, dtype=torch.float64)
    azim = u[0] * 360.0
    elev = torch.rad2deg(torch.asin((2.0 * u[1] - 1.0).clamp(-1.0, 1.0)))
    return azim, elev


EVAL_DRAWS = ("fresh", "frozen")


class RandomSelector(ViewSelector):
    """Random directions, uniform on the sphere, at a fixed ``distance``.

    Training mode: new views for every shape at every call, drawn from torch's *global* generator
    (so ``torch.manual_seed`` makes a run reproducible). Eval mode, ``eval_draw``:
    ``fresh`` (the official code): new views for every shape at every call too, drawn from a
    private generator that restarts from ``seed`` each time the selector enters eval mode, so
    every evaluation pass over the same loader sees the same draws; ``frozen``: one set of M views
    drawn once from ``seed``, identical for every call and every shape.
    """

    def __init__(self, views: int, distance: float = 2.2, seed: int = 0, eval_draw: str = "fresh") -> None:
        super().__init__(views)
        if eval_draw not in EVAL_DRAWS:
            raise ValueError(f"selector.eval_draw={eval_draw!r}: expected one of {', '.join(EVAL_DRAWS)}")
        self.distance, self.seed, self.eval_draw = float(distance), int(seed), eval_draw
        self._eval_gen = torch.Generator().manual_seed(self.seed)
        azim, elev = random_directions((self.views,), torch.Generator().manual_seed(self.seed))
        # Non-persistent: a pure function of (views, seed), so checkpoints need not carry it.
        self.register_buffer("eval_azim", azim, persistent=False)
        self.register_buffer("eval_elev", elev, persistent=False)

    def train(self, mode: bool = True) -> "RandomSelector":
        if not mode and self.training:  # entering eval mode: the fresh draws start over
            self._eval_gen.manual_seed(self.seed)
        return super().train(mode)

    def forward(self, points: Tensor) -> Views:
        """``[B, N, 3] -> (azim, elev, dist)``, each ``[B, M]``."""
        self._check_points(points)
        B, dtype, device = points.shape[0], self._dtype(points), points.device
        if self.training:
            azim, elev = random_directions((B, self.views))
        elif self.eval_draw == "fresh":
            azim, elev = random_directions((B, self.views), self._eval_gen)
        else:
            azim, elev = self.eval_azim.expand(B, -1), self.eval_elev.expand(B, -1)
        azim = azim.to(device=device, dtype=dtype).clone()
        elev = elev.to(device=device, dtype=dtype).clone()
        return azim, elev, torch.full_like(azim, self.distance)

    def extra_repr(self) -> str:
        return f"views={self.views}, distance={self.distance}, seed={self.seed}, eval_draw={self.eval_draw}"


BASE_LAYOUTS = ("circular", "spherical")


def base_layout(who: str, views: int, layout: str, elevation: float, distance: float, sphere: str) -> ViewSelector:
    """The fixed layout another selector starts from: circular (at ``elevation``) or spherical
    (``sphere``); an unknown ``layout`` is a one-line error naming ``who``."""
    if layout not in BASE_LAYOUTS:
        raise ValueError(f"{who}: layout={layout!r}; expected one of {', '.join(BASE_LAYOUTS)}")
    return CircularSelector(views, elevation, distance) if layout == "circular" else SphericalSelector(views, distance, sphere)


class NoisySelector(ViewSelector):
    """A fixed layout with Gaussian noise on every view, redrawn at every training call: the paper's
    alternative to learned views (std 18 degrees in azimuth and 9 in elevation: the official code's
    ``input_view_noise = 0.1`` times 180 and 90).

    ``layout``: ``circular`` (at ``elevation``) or ``spherical`` (``sphere``). Training mode adds
    ``azim_std`` / ``elev_std`` (degrees) of noise per shape and view, drawn from torch's global
    generator (so ``torch.manual_seed`` makes a run reproducible); evaluation mode gives the layout
    itself. Elevations are not clipped: a view pushed past a pole looks from the other side
    (the renderer takes any elevation).
    """

    LAYOUTS = BASE_LAYOUTS

    def __init__(self, views: int, layout: str = "circular", azim_std: float = 18.0, elev_std: float = 9.0,
                 elevation: float = 30.0, distance: float = 2.2, sphere: str = "equal_area") -> None:
        super().__init__(views)
        self.base = base_layout("NoisySelector", views, layout, elevation, distance, sphere)
        if not (azim_std >= 0 and elev_std >= 0):
            raise ValueError(f"NoisySelector: noise std must be >= 0, got azim {azim_std}, elev {elev_std}")
        self.layout, self.azim_std, self.elev_std = layout, float(azim_std), float(elev_std)

    def forward(self, points: Tensor) -> Views:
        """``[B, N, 3] -> (azim, elev, dist)``, each ``[B, M]``."""
        azim, elev, dist = self.base(points)
        if self.training:
            noise = torch.randn(2, *azim.shape, dtype=torch.float64)  # CPU, float64: the same draw on any device
            azim = azim + (noise[0] * self.azim_std).to(azim)
            elev = elev + (noise[1] * self.elev_std).to(elev)
        return azim, elev, dist

    def extra_repr(self) -> str:
        return f"views={self.views}, layout={self.layout}, azim_std={self.azim_std}, elev_std={self.elev_std}"


# ----------------------------------------------------------------------------- config options


@register("circular")
@dataclass
class CircularConfig(SelectorConfig):
    """Fixed: M views at ``elevation`` degrees, azimuths ``azim_start + 360 k / M`` (90: the official
    code's fixed layout); the same for every shape. When: the paper's fixed baseline for upright
    shapes (ModelNet's MVCNN setting)."""

    name: str = "circular"
    elevation: float = 30.0
    azim_start: float = 90.0

    def build(self, views: int, seed: int, point_encoder=None) -> ViewSelector:
        return CircularSelector(views, elevation=self.elevation, distance=self.distance, azim_start=self.azim_start)


@register("spherical")
@dataclass
class SphericalConfig(SelectorConfig):
    """Fixed: exactly M views over the sphere (``sphere``: equal_area, the paper's rings, or
    fibonacci). When: shapes in any pose; the strongest fixed baseline where no side is special."""

    name: str = "spherical"
    sphere: str = "equal_area"

    def validate(self) -> "SphericalConfig":
        super().validate()
        one_of("selector.sphere", self.sphere, layouts.SPHERES)
        return self

    def build(self, views: int, seed: int, point_encoder=None) -> ViewSelector:
        return SphericalSelector(views, distance=self.distance, sphere=self.sphere)


@register("random")
@dataclass
class RandomConfig(SelectorConfig):
    """Random directions, new every training step; at evaluation ``eval_draw``: ``fresh`` (the
    official code: new directions for every shape, reproducible from the run's seed) or ``frozen``
    (one draw from the run's seed for every shape)."""

    name: str = "random"
    eval_draw: str = "fresh"

    def validate(self) -> "RandomConfig":
        super().validate()
        one_of("selector.eval_draw", self.eval_draw, EVAL_DRAWS)
        return self

    def build(self, views: int, seed: int, point_encoder=None) -> ViewSelector:
        return RandomSelector(views, distance=self.distance, seed=seed, eval_draw=self.eval_draw)


@dataclass
class LayoutConfig(SelectorConfig):
    """A fixed starting layout: ``base_layout`` circular (at ``elevation``) or spherical (``sphere``)."""

    base_layout: str = "circular"
    elevation: float = 30.0
    sphere: str = "equal_area"

    def validate(self) -> "LayoutConfig":
        super().validate()
        one_of("selector.base_layout", self.base_layout, BASE_LAYOUTS)
        one_of("selector.sphere", self.sphere, layouts.SPHERES)
        return self


@register("noisy")
@dataclass
class NoisyConfig(LayoutConfig):
    """The paper's alternative to learned views: the base layout plus Gaussian noise of
    ``noise_azim`` / ``noise_elev`` degrees std, redrawn at every training step; none at evaluation."""

    name: str = "noisy"
    noise_azim: float = 18.0
    noise_elev: float = 9.0

    def validate(self) -> "NoisyConfig":
        super().validate()
        at_least("selector.noise_azim", self.noise_azim, 0.0)
        at_least("selector.noise_elev", self.noise_elev, 0.0)
        return self

    def build(self, views: int, seed: int, point_encoder=None) -> ViewSelector:
        return NoisySelector(views, layout=self.base_layout, azim_std=self.noise_azim, elev_std=self.noise_elev,
                             elevation=self.elevation, distance=self.distance, sphere=self.sphere)
