"""View selectors: ``forward(points [B, N, 3]) -> (azim, elev, dist)``, each ``[B, M]``.

Fixed layouts live in ``fixed.py``, the learned MVTN regressor in ``mvtn.py``; ``SELECTORS`` /
``build_selector`` is the registry the configs use.
"""
from __future__ import annotations

from typing import Callable

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


SELECTORS: dict[str, Callable[..., ViewSelector]] = {
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
}


def build_selector(name: str, views: int, **kw) -> ViewSelector:
    """Build a registered selector with M = ``views``."""
    if name not in SELECTORS:
        raise ValueError(f"unknown selector {name!r}; allowed: {', '.join(sorted(SELECTORS))}")
    check_views(views)
    return SELECTORS[name](views, **kw)


__all__ = [
    "SELECTORS", "VARIANTS", "CircularSelector", "MVTNSelector", "NoisySelector", "OptimizedSelector", "RandomSelector", "SphericalSelector",
    "PointOfInterestSelector", "ViewSelector", "build_selector", "check_views", "mvtn_circular", "mvtn_direct", "mvtn_direct_offset",
    "mvtn_spherical",
]
