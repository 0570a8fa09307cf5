"""The strategy interface: a keys dataclass, a ``Strategy`` with its hooks, the step's shared context, the registry.

The package docstring (``selectors/strategies/__init__.py``) states the contract in full; this
module holds the classes and the registry that checks every strategy's declaration.
"""
from __future__ import annotations

from dataclasses import dataclass, fields, is_dataclass
from typing import TYPE_CHECKING, Any, ClassVar, Optional

from torch import Tensor

if TYPE_CHECKING:  # pragma: no cover
    from ...config.schema import TrainConfig


@dataclass
class StrategyKeys:
    """The root of every strategy's keys dataclass (and of the learned selectors' base keys): flat
    ``selector.*`` fields with defaults, mixed into a selector config. ``validate()`` and
    ``check(cfg)`` are cooperative: a subclass calls ``super()`` first, then checks its own keys
    (it may read the keys of the config it is mixed into, e.g. ``grad``), and ``validate`` returns
    ``self``."""

    def validate(self):
        up = getattr(super(), "validate", None)
        return up() if up is not None else self

    def check(self, cfg: "TrainConfig") -> None:
        up = getattr(super(), "check", None)
        if up is not None:
            up(cfg)


@dataclass
class StepContext:
    """One training step as the strategies see it; the training fills it in this order.

    Given: ``model``, ``batch``, ``step`` (global, 0-based), ``loss_fn`` (C's), ``timer``, and
    the epoch's phase (``warm``: C trains on warm-up views with G frozen; ``frozen``: G's views
    without G's gradient; ``learning``: G trains). ``begin_step`` hooks may set ``hypotheses`` H
    (G gives H sets of M views: ``views [B, H * M]``), ``sets`` S (C classifies each shape as S
    rows: S = H, or 1 for all H x M views pooled) and ``hold_g`` (strategies add no G term this
    step). Then ``views`` (G's, after the ``transform_views`` hooks), ``seen`` (what R renders for
    C, after the ``training_views`` hooks), and after C's forward ``images [B * S, M', 3, h, w]``,
    ``logits [B * S, K]``, ``labels [B * S]`` and C's ``loss``."""

    model: Any
    batch: dict
    step: int
    loss_fn: Any
    timer: Any
    warm: bool = False
    frozen: bool = False
    learning: bool = False
    hypotheses: int = 1
    sets: int = 1
    hold_g: bool = False
    views: Optional[tuple] = None
    seen: Optional[tuple] = None
    images: Optional[Tensor] = None
    logits: Optional[Tensor] = None
    labels: Optional[Tensor] = None
    loss: Optional[Tensor] = None


class Strategy:
    """One mechanism of G's training (the package docstring states the contract).

    Class attributes: ``name`` (its registry name), ``keys`` (its keys dataclass), ``training_keys``
    (those of its keys that may change on resume), ``multi_process`` (whether it trains in several
    processes), ``switch`` (the key that turns it on, for messages: one of its keys, or ``grad``
    for a gradient), ``grad`` (the ``selector.grad``
    value it answers to, when it is G's gradient; None otherwise). Built once per run with the
    whole ``TrainConfig`` when ``enabled``; every hook is a no-op by default."""

    name: ClassVar[str] = ""
    keys: ClassVar[type] = StrategyKeys
    training_keys: ClassVar[tuple] = ()
    multi_process: ClassVar[bool] = True
    switch: ClassVar[str] = ""
    grad: ClassVar[Optional[str]] = None

    def __init__(self, cfg) -> None:
        self.cfg, self.s = cfg, cfg.selector

    @classmethod
    def enabled(cls, s) -> bool:
        """Whether the selector config ``s`` turns this strategy on (default: its ``grad`` is chosen,
        or always for a strategy that is no gradient)."""
        return cls.grad is None or s.grad == cls.grad

    @classmethod
    def modules(cls, s, views: int) -> dict:
        """Per-shape modules the model keeps for this strategy (buffers in checkpoints), by attribute
        name (``MVTN`` registers each under that name; one with ``transforms_views`` maps G's views)."""
        return {}

    @classmethod
    def multi_process_problem(cls, s, views: int, processes: int) -> Optional[str]:
        """One line when this strategy cannot train in ``processes`` processes, else None."""
        if cls.multi_process or processes <= 1:
            return None
        held = ", ".join(cls.modules(s, views)) or "its training state"
        return (f"selector.{cls.switch}={getattr(s, cls.switch)} with {processes} processes: selector={s.name}'s "
                f"per-shape statistics ({held}) are not shared between processes yet; run it in one process")

    def start_epoch(self, model, epoch: int, ctx: StepContext) -> None:
        """Before 0-based ``epoch``'s first step; ``ctx`` carries the epoch's phase only."""

    def begin_step(self, ctx: StepContext) -> None:
        """Before G: may set ``ctx.hypotheses``, ``ctx.sets``, ``ctx.hold_g``."""

    def transform_views(self, ctx: StepContext) -> tuple:
        """G's views ``ctx.views`` -> the views of this step (inside G's stage and grad mode)."""
        return ctx.views

    def training_views(self, ctx: StepContext) -> tuple:
        """What R renders for C: ``ctx.seen`` (G's views so far) -> the views C trains on."""
        return ctx.seen

    def differentiates_render(self, ctx: StepContext) -> bool:
        """False when this step must not differentiate R (G's gradient comes from elsewhere)."""
        return True

    def after_forward(self, ctx: StepContext) -> None:
        """After C's forward and loss (``ctx.images``, ``logits``, ``labels``, ``loss``): record."""

    def g_term(self, ctx: StepContext) -> Optional[Tensor]:
        """A scalar added to the objective (G's gradient), or None."""
        return None

    def end_epoch(self, model, epoch: int) -> list[str]:
        """Decisions after 0-based ``epoch``'s steps, as log lines."""
        return []

    def history(self, model) -> dict:
        """What the epoch's record keeps of this strategy's state."""
        return {}


STRATEGIES: dict[str, type] = {}  # every registered strategy, by name
_BASE_KEYS: list[type] = []  # the base configs' key classes no strategy may redeclare


def key_names(cls: type) -> list[str]:
    """The field names of a keys dataclass."""
    return [f.name for f in fields(cls)] if is_dataclass(cls) else []


def collisions(strategy: type) -> list[str]:
    """Lines naming each key of ``strategy`` that a base config or another registered strategy declares."""
    mine = set(key_names(strategy.keys))
    out = []
    for base in _BASE_KEYS:
        out += [f"selector.{k}: a key of {base.__name__}" for k in sorted(mine & set(key_names(base)))]
    for other in STRATEGIES.values():
        if other is not strategy:
            out += [f"selector.{k}: a key of strategy {other.name!r}" for k in sorted(mine & set(key_names(other.keys)))]
    return out


def declaration_problems(strategy: type) -> list[str]:
    """What is missing or wrong in a strategy's declaration (empty: complete)."""
    problems = []
    if not strategy.name:
        problems.append("no name")
    if not (isinstance(strategy.keys, type) and issubclass(strategy.keys, StrategyKeys) and is_dataclass(strategy.keys)):
        problems.append("keys is not a StrategyKeys dataclass")
    names = set(key_names(strategy.keys))
    problems += [f"training key {k!r} is not one of its keys" for k in strategy.training_keys if k not in names]
    if not isinstance(strategy.multi_process, bool):
        problems.append("multi_process is not a bool")
    if strategy.switch and strategy.switch not in names and not (strategy.grad and strategy.switch == "grad"):
        problems.append(f"switch {strategy.switch!r} is not one of its keys (nor grad, for a gradient)")
    if not strategy.multi_process and not strategy.switch:
        problems.append("a single-process strategy names its switch key")
    return problems + collisions(strategy)


def register_strategy(strategy: type) -> type:
    """Class decorator: add ``strategy`` to ``STRATEGIES`` after checking its declaration (its keys
    collide with no base config's and no other strategy's); one line naming each problem."""
    if STRATEGIES.get(strategy.name) not in (None, strategy):
        raise ValueError(f"strategy {strategy.name!r} is registered twice ({STRATEGIES[strategy.name].__name__}, "
                         f"{strategy.__name__})")
    problems = declaration_problems(strategy)
    if problems:
        raise ValueError(f"strategy {strategy.__name__}: {'; '.join(problems)}")
    STRATEGIES[strategy.name] = strategy
    return strategy


def declare_base_keys(*classes: type) -> None:
    """The base configs' key classes (``SelectorConfig``, the learned base keys): no strategy may
    declare their keys; the strategies registered so far are checked now."""
    _BASE_KEYS.extend(c for c in classes if c not in _BASE_KEYS)
    for strategy in STRATEGIES.values():
        problems = collisions(strategy)
        if problems:
            raise ValueError(f"strategy {strategy.__name__}: {'; '.join(problems)}")
