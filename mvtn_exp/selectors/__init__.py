"""View selectors: ``forward(points [B, N, 3]) -> (azim, elev, dist)``, each ``[B, M]``.

Fixed layouts live in ``fixed.py``, the paper's learned regressor in ``mvtn.py``, the
point-of-interest G and this project's recipe in ``poi.py``, scene-parameter optimisation in
``optimized.py``. Each option's config dataclass is registered in ``config.REGISTRY`` (``selector=NAME``)
and builds its module; how G trains in the loop is ``training.py`` / ``probes.py``.
"""
from __future__ import annotations

from mvtn_exp.selectors.config import REGISTRY, LearnedSelectorConfig, SelectorConfig, register, schema
from mvtn_exp.selectors.fixed import (CircularSelector, NoisySelector, RandomSelector, SphericalSelector,
                                      ViewSelector, check_views)
from mvtn_exp.selectors.mvtn import VARIANTS, MVTNSelector
from mvtn_exp.selectors.optimized import OptimizedSelector
from mvtn_exp.selectors.poi import PointOfInterestSelector


def mvtn_direct(views: int, **kw) -> MVTNSelector:
    """The paper's MVTN-direct: u = u_bound * tanh(G(S)), azimuth +-180, elevation +-90, no u0."""
    return MVTNSelector(views, "direct", **kw)


def mvtn_direct_offset(views: int, **kw) -> MVTNSelector:
    """Views regressed as freely as ``mvtn_direct`` but as offsets from the spherical layout, u0 an input of G."""
    return MVTNSelector(views, "direct_offset", **kw)


def mvtn_circular(views: int, **kw) -> MVTNSelector:
    """MVTN offsets (+-180/M azimuth, +-90 elevation) around the circular layout."""
    return MVTNSelector(views, "circular", **kw)


def mvtn_spherical(views: int, **kw) -> MVTNSelector:
    """MVTN offsets (+-180/M azimuth, +-90 elevation) around the spherical layout."""
    return MVTNSelector(views, "spherical", **kw)


# The selector modules by name, for building one directly with its constructor's arguments
# (configs build through their schema: ``REGISTRY[name]().build(views, seed, point_encoder)``).
MODULES = {
    "circular": CircularSelector,
    "spherical": SphericalSelector,
    "random": RandomSelector,
    "noisy": NoisySelector,
    "optimized": OptimizedSelector,
    "mvtn_direct": mvtn_direct,
    "mvtn_direct_offset": mvtn_direct_offset,
    "mvtn_circular": mvtn_circular,
    "mvtn_spherical": mvtn_spherical,
    "mvtn_poi": PointOfInterestSelector,
    "poi": PointOfInterestSelector,
}
SELECTORS = REGISTRY  # every selector option, by name


def build_selector(name: str, views: int, **kw) -> ViewSelector:
    """Build a selector module with M = ``views`` from its constructor's arguments ``kw``."""
    if name not in MODULES:
        raise ValueError(f"unknown selector {name!r}; allowed: {', '.join(sorted(MODULES))}")
    check_views(views)
    return MODULES[name](views, **kw)


__all__ = [
    "MODULES", "REGISTRY", "SELECTORS", "VARIANTS", "CircularSelector", "LearnedSelectorConfig", "MVTNSelector",
    "NoisySelector", "OptimizedSelector", "PointOfInterestSelector", "RandomSelector", "SelectorConfig",
    "SphericalSelector", "ViewSelector", "build_selector", "check_views", "mvtn_circular", "mvtn_direct",
    "mvtn_direct_offset", "mvtn_spherical", "register", "schema",
]
