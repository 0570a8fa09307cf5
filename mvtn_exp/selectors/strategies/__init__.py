"""G's training as composable strategies: each mechanism beyond the paper's autograd training is one strategy.

A strategy (``base.Strategy``, registered with ``@register_strategy``) is one mechanism of how a
learned G trains, with its own keys and its own state:

- ``keys``: a dataclass deriving from ``StrategyKeys`` whose fields are flat ``selector.*`` keys
  with defaults; its ``validate()`` / ``check(cfg)`` call ``super()`` first, then check its own
  keys. A selector config offers the strategy by mixing the keys class in (``class
  MyConfig(MyKeys, MVTNSphericalConfig)``) and listing the strategy in its ``strategies`` class
  attribute (order matters: the hooks run in that order), or in one call:
  ``selectors.config.compose_selector("NAME", MVTNSphericalConfig, MyStrategy)`` registers the selector
  option ``NAME``. No key of a strategy may be a key of a base config or of another strategy
  (checked at registration).
- ``training_keys``: its keys that say how G trains, not what the model is (they may change when
  a run is resumed or G transferred); ``multi_process`` and ``switch``: whether it trains in
  several processes, and the key that turns it on (named in the one-line refusal); ``grad``: the
  ``selector.grad`` value it answers to when it is G's gradient (the value is then allowed).
- ``enabled(s)``: whether selector config ``s`` turns it on; ``modules(s, views)``: per-shape
  modules the model keeps for it (buffers in checkpoints; the model takes ``polarity`` and
  ``hypotheses``).
- hooks, called by the one ``train_step`` of ``selectors/training.py`` for every enabled strategy,
  in the config's order, around a ``StepContext``: ``start_epoch(model, epoch, ctx)`` (the
  epoch's phase: ``ctx.warm`` / ``frozen`` / ``learning``); per step ``begin_step(ctx)`` (may set
  the hypotheses H, the rows per shape S, ``hold_g``), ``transform_views(ctx) -> views`` (G's
  views, inside G's stage), ``training_views(ctx) -> views`` (what R renders for C),
  ``differentiates_render(ctx)`` (False: R runs without gradient), ``after_forward(ctx)``
  (record from C's logits and loss), ``g_term(ctx) -> scalar | None`` (added to C's loss: the
  objective whose backward trains G and C); after the steps ``end_epoch(model, epoch) -> lines``
  (decisions, for the log) and ``history(model) -> dict`` (the epoch's record).

A strategy keeps its random draws in streams of its own (``view_gradient.noise_generator`` of the
run seed plus a constant, and the global step), so that a resumed run draws what the whole run
drew. The built-in strategies: ``smoothed`` (``grad=smoothed``: probe renders, C's jitter),
``flips`` (``flip_explore``), ``race`` (``hypotheses``; ``PoiConfig`` only) and ``search``
(``grad=search``).
"""
from __future__ import annotations

from .base import (STRATEGIES, StepContext, Strategy, StrategyKeys, declare_base_keys, declaration_problems,
                   key_names, register_strategy)
from .flips import FlipKeys, Flips
from .race import Race, RaceKeys
from .search import Search, SearchKeys
from .smoothed import Smoothed, SmoothedKeys

__all__ = [
    "STRATEGIES", "FlipKeys", "Flips", "Race", "RaceKeys", "Search", "SearchKeys", "Smoothed", "SmoothedKeys",
    "StepContext", "Strategy", "StrategyKeys", "declaration_problems", "declare_base_keys", "key_names",
    "register_strategy",
]
