"""View selectors: ``forward(points [B, N, 3]) -> (azim, elev, dist)``, each ``[B, M]``.

Fixed layouts live in ``fixed.py``, the paper's learned regressor in ``mvtn.py``, the
point-of-interest G and this project's recipe in ``poi.py``, scene-parameter optimisation in
``optimized.py``. Each option's config dataclass is registered in ``config.REGISTRY`` (``selector=NAME``)
and builds its module; how G trains in the loop is ``training.py`` with the training strategies of
``strategies/`` (the smoothed gradient, view flips, raced hypotheses, the view search).
"""
from __future__ import annotations

from mvtn_exp.selectors.config import REGISTRY, LearnedSelectorConfig, SelectorConfig, register, schema
from mvtn_exp.selectors.fixed import (CircularSelector, NoisySelector, RandomSelector, SphericalSelector,
                                      ViewSelector, check_views)
from mvtn_exp.selectors.mvtn import VARIANTS, MVTNSelector
from mvtn_exp.selectors.optimized import OptimizedSelector
from mvtn_exp.selectors.poi import PointOfInterestSelector


SELECTORS = REGISTRY  # every selector option, by name


def build_selector(name: str, views: int, seed: int = 0, point_encoder=None, **keys) -> ViewSelector:
    """Selector ``name``'s module with M = ``views``, built through its config (``REGISTRY``) from
    the option's keys (``selector.<key>``, e.g. ``gain=8.0``); ``point_encoder``: a point encoder
    config for the MVTN selectors (default PointNet)."""
    from mvtn_exp.models.point_encoders import PointNetConfig

    check_views(views)
    cfg = schema(name)(**keys).validate()
    return cfg.build(views, seed=seed, point_encoder=point_encoder or PointNetConfig())


__all__ = [
    "REGISTRY", "SELECTORS", "VARIANTS", "CircularSelector", "LearnedSelectorConfig", "MVTNSelector",
    "NoisySelector", "OptimizedSelector", "PointOfInterestSelector", "RandomSelector", "SelectorConfig",
    "SphericalSelector", "ViewSelector", "build_selector", "check_views", "register", "schema",
]
