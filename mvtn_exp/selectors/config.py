"""Selector options: one config dataclass per option, and the registry that maps a name to it.

Each option (``selector=NAME``) is a dataclass registered with ``@register("NAME")`` in the module
of its selector; ``conf/selector/NAME.yaml`` starts from it (``defaults: [/schema/selector/NAME@_here_]``),
so a key of another option is refused at compose time. A config knows:

- ``learned`` (class attribute): whether G has parameters to train;
- ``build(views, seed, point_encoder)``: the ``ViewSelector`` module, M = ``views``;
- ``strategies`` (class attribute): the training strategies it offers, in the order their hooks
  run (``selectors/strategies/``); their keys dataclasses are mixed into the config as flat keys;
- ``modules(views)``: extra state the model keeps for G's training (its enabled strategies');
- ``training()``: the class of G's training in the loop (``selectors/training.py``);
- ``validate()`` (own keys) and ``check(cfg)`` (against the whole ``TrainConfig``).

Angles are degrees, distances world units (Y-up; ``render/cameras.py``).
"""
from __future__ import annotations

from dataclasses import dataclass, field, make_dataclass
from typing import TYPE_CHECKING, ClassVar, Optional

from ..config.checks import at_least, fraction, one_of
from ..config.options import OPTIONS, OptionConfig, load, summary
from ..render.layouts import SPHERES
from .strategies import (FlipKeys, Flips, Search, SearchKeys, Smoothed, SmoothedKeys, StrategyKeys, declare_base_keys,
                         key_names)

if TYPE_CHECKING:  # pragma: no cover
    from ..config.schema import TrainConfig

REGISTRY = OPTIONS["selector"]  # every selector option, by name (filled by the selector modules)
register = REGISTRY.register
schema = REGISTRY.schema
BN_SCOPES = ("all", "eval")  # what re-estimated BatchNorm statistics serve (models/precise_bn.py)


@dataclass
class SelectorConfig(OptionConfig):
    """Keys every selector has: ``name`` (the option; set it with ``selector=NAME``),
    ``distance``, the camera distance in world units (the shapes lie in the unit sphere), and
    ``canonical``: ``none`` (shapes as posed) or ``pca`` (each shape turned into its principal
    frame before G and R see it, ``selectors/canonical.py``: the pose-canonicalised baseline).
    ``bn_recalibrate``: before each validation C's BatchNorm statistics are re-estimated over this
    many training batches on the selector's current views (0: the paper's running averages;
    ``models/precise_bn.py``), fixed views as learned ones; ``bn_recalibrate_scope``: ``eval``
    (they serve validation, checkpoints and test; training keeps its own) or ``all``."""

    distance: float = 2.2
    canonical: str = "none"
    bn_recalibrate: int = 0
    bn_recalibrate_scope: str = "eval"

    kind = "selector"

    learned: ClassVar[bool] = False
    # keys that set how the run trains, not what the model is: they may change when a run is resumed
    # (the strategies' own training keys are added by ``free_keys``)
    training_keys: ClassVar[tuple] = ("bn_recalibrate", "bn_recalibrate_scope")
    strategies: ClassVar[tuple] = ()  # the training strategies this option offers, in hook order

    def __init_subclass__(cls, **kw) -> None:
        """A config offers a strategy only with its keys class among its bases, and no other class
        of it (but the keys class's own subclasses, which may change defaults) declares those keys."""
        super().__init_subclass__(**kw)
        missing = [s.name for s in cls.strategies if not issubclass(cls, s.keys)]
        if missing:
            raise TypeError(f"{cls.__name__} offers strategies {missing} without their keys: derive it from "
                            f"{', '.join(s.keys.__name__ for s in cls.strategies if s.name in missing)}")
        for s in cls.strategies:
            mine = set(key_names(s.keys))
            for base in cls.__mro__:
                clash = mine & set(base.__dict__.get("__annotations__", {}))
                if clash and not issubclass(base, s.keys):
                    raise TypeError(f"{cls.__name__}: selector.{sorted(clash)[0]} is a key of strategy {s.name!r} "
                                    f"and of {base.__name__}")

    @classmethod
    def free_keys(cls) -> list[str]:
        """The dotted training keys, the option's and its strategies' (``selector.lr``, ...): they
        may differ on resume and view transfer."""
        keys = list(cls.training_keys) + [k for s in cls.strategies for k in s.training_keys]
        return [f"selector.{k}" for k in dict.fromkeys(keys)]

    def validate(self) -> "SelectorConfig":
        super().validate()
        at_least("selector.distance", self.distance, 0.0, strict=True)
        one_of("selector.canonical", self.canonical, ("none", "pca"))
        at_least("selector.bn_recalibrate", self.bn_recalibrate, 0)
        one_of("selector.bn_recalibrate_scope", self.bn_recalibrate_scope, BN_SCOPES)
        return self

    def build(self, views: int, seed: int, point_encoder=None):
        raise NotImplementedError(f"{type(self).__name__}.build")

    def enabled_strategies(self) -> list[type]:
        """The strategies this config turns on, in hook order."""
        return [s for s in type(self).strategies if s.enabled(self)]

    def modules(self, views: int) -> dict:
        """Extra modules the model keeps for G's training (their buffers travel in checkpoints)."""
        return {name: m for s in self.enabled_strategies() for name, m in s.modules(self, views).items()}

    def multi_process_problem(self, views: int, processes: int) -> Optional[str]:
        """One line when this selector cannot train in ``processes`` processes (the first enabled
        strategy that says so: per-shape statistics not shared between them), else None."""
        return next((p for s in self.enabled_strategies() if (p := s.multi_process_problem(self, views, processes))),
                    None)

    def segmentation_problem(self) -> Optional[str]:
        """One line when this selector cannot serve ``task=segmentation`` (its training strategies
        score views by a classification loss), else None."""
        names = [s.name for s in self.enabled_strategies()]
        if names:
            return (f"its training strategies ({', '.join(names)}) score views by a classification loss; turn them "
                    f"off (e.g. use the plain option's defaults)")
        if getattr(self, "loss", "task") != "task":
            return f"selector.loss={self.loss} is a classification loss; use selector.loss=task"
        return None

    def training(self):
        from .training import SelectorTraining

        return SelectorTraining

    def kept_points(self) -> Optional[int]:
        """How many of the shape's points G reads (None: all)."""
        return None

    def lr_scale(self, epoch: int) -> float:
        """G's learning-rate multiplier on top of the schedule during 0-based ``epoch``."""
        return 1.0

    def uses_camera_gradient(self) -> bool:
        """Whether training differentiates R with respect to the cameras (then R needs a useful gradient)."""
        return False


LOSSES = ("task", "centered_logit")  # what G minimises (tasks/classification.py: selector_loss_fn)
WARMUP_VIEWS = ("u0", "random", "spherical", "canonical")


@dataclass
class LearnedKeys(StrategyKeys):
    """The base keys of every learned selector (``LearnedSelectorConfig`` documents them)."""

    sphere: str = "equal_area"
    num_points: Optional[int] = 256
    from_ckpt: Optional[str] = None
    lr: float = 1e-3
    beta1: float = 0.9
    clip: float = 30.0
    stop_epoch: Optional[int] = None
    move_every: int = 1
    warmup_epochs: int = 0
    warmup_views: str = "u0"
    warmup_num_views: Optional[int] = None
    warmup_elevation: float = 30.0
    grad: str = "autograd"
    loss: str = "task"

    def gradients(self) -> tuple:
        """The ``grad`` values allowed: ``autograd`` and the gradient strategies the config offers."""
        return ("autograd",) + tuple(s.grad for s in type(self).strategies if s.grad)

    def validate(self):
        super().validate()
        one_of("selector.sphere", self.sphere, SPHERES)
        if self.num_points is not None:
            at_least("selector.num_points", self.num_points, 1)
        at_least("selector.lr", self.lr, 0.0)
        fraction("selector.beta1", self.beta1)
        at_least("selector.clip", self.clip, 0.0, strict=True)
        if self.stop_epoch is not None:
            at_least("selector.stop_epoch", self.stop_epoch, 0)
        at_least("selector.move_every", self.move_every, 1)
        at_least("selector.warmup_epochs", self.warmup_epochs, 0)
        one_of("selector.warmup_views", self.warmup_views, WARMUP_VIEWS)
        if not -90.0 <= self.warmup_elevation <= 90.0:
            raise ValueError(f"selector.warmup_elevation={self.warmup_elevation!r}: expected degrees in [-90, 90]")
        if self.warmup_num_views is not None:
            at_least("selector.warmup_num_views", self.warmup_num_views, 1)
            if self.warmup_epochs == 0:
                raise ValueError(f"selector.warmup_num_views={self.warmup_num_views}: there is no warm-up; set "
                                 "selector.warmup_epochs >= 1")
        one_of("selector.grad", self.grad, self.gradients())
        one_of("selector.loss", self.loss, LOSSES)
        if self.loss != "task" and self.grad == "autograd":
            raise ValueError(f"selector.loss={self.loss}: G's own loss is read from extra renders; it needs "
                             f"selector.grad={' or '.join(self.gradients()[1:])} (autograd trains G on C's loss)")
        return self

    def check(self, cfg: "TrainConfig") -> None:
        super().check(cfg)
        if cfg.batch_size < 2:
            raise ValueError(f"batch_size={cfg.batch_size}: a learned selector (BatchNorm in G) trains on batches "
                             "of at least 2 shapes")
        n_warm = self.warmup_num_views
        if n_warm is not None and n_warm != cfg.views and self.warmup_views == "u0":
            raise ValueError(f"selector.warmup_num_views={n_warm} with selector.warmup_views=u0: G's initial views "
                             f"are views={cfg.views}; use warmup_views=spherical or random for another count")


@dataclass
class LearnedSelectorConfig(FlipKeys, SearchKeys, SmoothedKeys, LearnedKeys, SelectorConfig):
    """A G with parameters, and how it trains (``selectors/training.py``, ``selectors/strategies/``).

    ``sphere``: how spherical layouts spread M views (``equal_area``: the paper's rings, or
    ``fibonacci``). ``num_points``: G reads the first n of the shape's points (null: all).
    ``from_ckpt``: view transfer: G's weights from another run's checkpoint, frozen.

    G's optimiser (an AdamW group beside C's): ``lr``, ``beta1`` (first-moment decay), ``clip``
    (G's gradient L2 norm clipped before the step), ``stop_epoch`` (G's learning rate is 0 from
    this 0-based epoch on; null: never), ``move_every`` (after the warm-up G moves in one epoch of
    every k and holds its views for the k - 1 after it, while C learns from them; 1: every epoch).
    ``warmup_epochs``: G frozen for the first epochs while C
    trains on ``warmup_views`` (u0: G's initial views; random; spherical; canonical: a circular
    ring at ``warmup_elevation`` degrees in each shape's principal frame, ``selectors/canonical.py``,
    so that C learns from one consistent view of every shape before G moves), ``warmup_num_views``
    of them (null: ``views``).

    ``grad``: ``autograd`` (the paper's: through the differentiable renderer) or a gradient
    strategy: ``smoothed`` (the task loss smoothed over the views by a Gaussian of ``probe_sigma``
    degrees, estimated from ``probe_pairs`` antithetic pairs of renders every ``probe_every``
    steps, their renders in one renderer call with ``probe_batched``; any renderer;
    ``train_jitter``: C trains on G's views moved by Gaussian noise of this many degrees in azimuth
    and elevation, so that it does not adapt to G's exact view; ``strategies/smoothed.py``) or
    ``search`` (C's loss read at ``search_views`` candidate directions over the sphere every
    ``search_every`` steps, each view pulled towards the best candidate near it with weight
    ``search_weight``; ``strategies/search.py``; any renderer).
    ``loss``: what G minimises: ``task`` (the paper's: C's loss) or ``centered_logit``
    (``mean_c z_c - z_y``; needs ``grad=smoothed`` or ``search``). ``flip_explore``: for the first
    ``flip_epochs`` epochs each view is rendered from its antipode with this probability, and a
    view whose antipode had the lower loss turns round (0: off; ``strategies/flips.py``).
    ``bn_recalibrate`` / ``bn_recalibrate_scope`` (every selector's keys, ``SelectorConfig``) re-estimate
    C's BatchNorm statistics on G's current views before each validation.
    """

    learned: ClassVar[bool] = True
    # keys that set how G trains, not what the model is: they may change when a run is resumed
    training_keys: ClassVar[tuple] = SelectorConfig.training_keys + (
        "lr", "beta1", "clip", "stop_epoch", "move_every", "warmup_epochs", "warmup_views", "warmup_num_views",
        "warmup_elevation", "grad", "loss")
    strategies: ClassVar[tuple] = (Smoothed, Flips, Search)

    def training(self):
        from .training import LearnedTraining

        return LearnedTraining

    def kept_points(self) -> Optional[int]:
        return self.num_points

    def uses_camera_gradient(self) -> bool:
        return not self.from_ckpt and self.grad == "autograd"

    def lr_scale(self, epoch: int) -> float:
        """G's learning-rate multiplier on top of the schedule during 0-based ``epoch``."""
        return 0.0 if self.stop_epoch is not None and epoch >= self.stop_epoch else 1.0


declare_base_keys(SelectorConfig, LearnedKeys)


def compose_selector(name: str, base: type, *strategies: type, doc: Optional[str] = None) -> type:
    """Register selector option ``name``: ``base``'s config (a registered option's class) with
    ``strategies`` added after its own (their keys mixed in as flat keys, their hooks run last);
    ``doc``: the option's description (default: ``base``'s, naming the strategies). Returns the class."""
    names = ", ".join(s.name for s in strategies)
    cls = make_dataclass(
        "".join(p.title() for p in name.split("_")) + "Config", [("name", str, field(default=name))],
        bases=tuple(s.keys for s in reversed(strategies)) + (base,),
        namespace={"strategies": tuple(base.strategies) + tuple(strategies),
                   "__doc__": doc or f"{summary(base).rstrip('.')}, with {names}."})
    cls.__module__ = strategies[0].__module__ if strategies else base.__module__
    return register(name)(cls)
