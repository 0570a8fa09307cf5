"""Selector options: one config dataclass per option, and the registry that maps a name to it.

Each option (``selector=NAME``) is a dataclass registered with ``@register("NAME")`` in the module
of its selector; ``conf/selector/NAME.yaml`` starts from it (``defaults: [/schema/selector/NAME@_here_]``),
so a key of another option is refused at compose time. A config knows:

- ``learned`` (class attribute): whether G has parameters to train;
- ``build(views, seed, point_encoder)``: the ``ViewSelector`` module, M = ``views``;
- ``modules(views)``: extra state the model keeps for G's training (``{}``; see ``training.py``);
- ``training()``: the class of G's training in the loop (``selectors/training.py``);
- ``validate()`` (own keys) and ``check(cfg)`` (against the whole ``TrainConfig``).

Angles are degrees, distances world units (Y-up; ``render/cameras.py``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar, Optional

from ..config.checks import at_least, fraction, one_of
from ..config.options import OPTIONS, OptionConfig, load
from ..render.layouts import SPHERES

if TYPE_CHECKING:  # pragma: no cover
    from ..config.schema import TrainConfig

# the key that asks for each per-shape module of G's training (``modules``)
MODULE_KEYS = {"hypotheses": "hypotheses", "polarity": "flip_explore"}

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
    training_keys: ClassVar[tuple] = ("bn_recalibrate", "bn_recalibrate_scope")

    @classmethod
    def free_keys(cls) -> list[str]:
        """The dotted ``training_keys`` (``selector.lr``, ...): they may differ on resume and view transfer."""
        return [f"selector.{k}" for k in cls.training_keys]

    def validate(self) -> "SelectorConfig":
        super().validate()
        at_least("selector.distance", self.distance, 0.0, strict=True)
        one_of("selector.canonical", self.canonical, ("none", "pca"))
        at_least("selector.bn_recalibrate", self.bn_recalibrate, 0)
        one_of("selector.bn_recalibrate_scope", self.bn_recalibrate_scope, BN_SCOPES)
        return self

    def build(self, views: int, seed: int, point_encoder=None):
        raise NotImplementedError(f"{type(self).__name__}.build")

    def modules(self, views: int) -> dict:
        """Extra modules the model keeps for G's training (their buffers travel in checkpoints)."""
        return {}

    def multi_process_problem(self, views: int, processes: int) -> Optional[str]:
        """One line when this selector cannot train in ``processes`` processes (per-shape statistics
        of its training that are not shared between them), else None."""
        extra = self.modules(views)
        if not extra:
            return None
        key = next(MODULE_KEYS[name] for name in extra if name in MODULE_KEYS)
        return (f"selector.{key}={getattr(self, key)} with {processes} processes: selector={self.name}'s per-shape "
                f"statistics ({', '.join(extra)}) are not shared between processes yet; run it in one process")

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


GRADIENTS = ("autograd", "smoothed", "search")  # how G gets its gradient (selectors/view_gradient.py)
LOSSES = ("task", "centered_logit")  # what G minimises (tasks/classification.py: selector_loss_fn)
WARMUP_VIEWS = ("u0", "random", "spherical", "canonical")


@dataclass
class LearnedSelectorConfig(SelectorConfig):
    """A G with parameters, and how it trains (``selectors/training.py``, ``selectors/probes.py``).

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

    ``grad``: ``autograd`` (the paper's: through the differentiable renderer) or ``smoothed`` (the
    task loss smoothed over the views by a Gaussian of ``probe_sigma`` degrees, estimated from
    ``probe_pairs`` antithetic pairs of renders every ``probe_every`` steps, their renders in one
    renderer call with ``probe_batched``; any renderer); ``train_jitter``: C trains on G's views
    moved by Gaussian noise of this many degrees in azimuth and elevation, so that it does not
    adapt to G's exact view (0: G's views; needs ``grad=smoothed``, whose probes stay at G's views).
    ``search``: C's loss read at ``search_views`` candidate directions over the sphere every
    ``search_every`` steps, each view pulled towards the best candidate near it with weight
    ``search_weight`` (``selectors/search.py``; any renderer).
    ``loss``: what G minimises: ``task`` (the paper's: C's loss) or ``centered_logit``
    (``mean_c z_c - z_y``; needs ``grad=smoothed`` or ``search``). ``flip_explore``: for the first
    ``flip_epochs`` epochs each view is rendered from its antipode with this probability, and a
    view whose antipode had the lower loss turns round (0: off; ``selectors/polarity.py``).
    ``bn_recalibrate`` / ``bn_recalibrate_scope`` (every selector's keys, ``SelectorConfig``) re-estimate
    C's BatchNorm statistics on G's current views before each validation.
    """

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
    probe_pairs: int = 2
    probe_sigma: float = 10.0
    train_jitter: float = 0.0
    probe_every: int = 1
    probe_batched: bool = False
    search_views: int = 12
    search_every: int = 1
    search_weight: float = 1.0
    flip_explore: float = 0.0
    flip_epochs: int = 10

    learned: ClassVar[bool] = True
    # keys that set how G trains, not what the model is: they may change when a run is resumed
    training_keys: ClassVar[tuple] = SelectorConfig.training_keys + (
                                      "lr", "beta1", "clip", "stop_epoch", "move_every", "warmup_epochs", "warmup_views",
                                      "warmup_num_views", "warmup_elevation", "grad", "loss", "probe_pairs", "probe_sigma", "probe_every", "train_jitter",
                                      "probe_batched", "search_views", "search_every", "search_weight",
                                      "flip_epochs", "race_epochs",
                                      "race_z", "race_batches", "race_mode", "race_probes", "cache")

    def validate(self) -> "LearnedSelectorConfig":
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
        one_of("selector.grad", self.grad, GRADIENTS)
        one_of("selector.loss", self.loss, LOSSES)
        if self.loss != "task" and self.grad == "autograd":
            raise ValueError(f"selector.loss={self.loss}: G's own loss is read from extra renders; it needs "
                             "selector.grad=smoothed or search (autograd trains G on C's loss)")
        at_least("selector.search_views", self.search_views, 1)
        at_least("selector.search_every", self.search_every, 1)
        at_least("selector.search_weight", self.search_weight, 0.0, strict=True)
        if self.grad == "search" and self.flip_explore > 0:
            raise ValueError("selector.grad=search with selector.flip_explore: the search already looks all round; "
                             "set selector.flip_explore=0")
        at_least("selector.probe_pairs", self.probe_pairs, 1)
        at_least("selector.probe_sigma", self.probe_sigma, 0.0, strict=True)
        at_least("selector.train_jitter", self.train_jitter, 0.0)
        if self.train_jitter > 0 and self.grad != "smoothed":
            raise ValueError(f"selector.train_jitter={self.train_jitter}: C's views are moved off G's only with "
                             "selector.grad=smoothed (G's gradient from probes at its own views)")
        at_least("selector.probe_every", self.probe_every, 1)
        if not 0.0 <= self.flip_explore < 1.0:
            raise ValueError(f"selector.flip_explore={self.flip_explore!r}: expected a probability in [0, 1)")
        at_least("selector.flip_epochs", self.flip_epochs, 1)
        if self.from_ckpt and self.flip_explore > 0:
            raise ValueError("selector.from_ckpt with selector.flip_explore: a transferred G is frozen, its views are "
                             "not turned round")
        return self

    def check(self, cfg: "TrainConfig") -> None:
        if cfg.batch_size < 2:
            raise ValueError(f"batch_size={cfg.batch_size}: a learned selector (BatchNorm in G) trains on batches "
                             "of at least 2 shapes")
        n_warm = self.warmup_num_views
        if n_warm is not None and n_warm != cfg.views and self.warmup_views == "u0":
            raise ValueError(f"selector.warmup_num_views={n_warm} with selector.warmup_views=u0: G's initial views "
                             f"are views={cfg.views}; use warmup_views=spherical or random for another count")

    def modules(self, views: int) -> dict:
        from .polarity import ViewPolarity

        return {"polarity": ViewPolarity(views)} if self.flip_explore > 0 else {}

    def training(self):
        from .probes import ProbeTraining
        from .search import SearchTraining
        from .training import LearnedTraining

        if self.grad == "search":
            return SearchTraining
        return ProbeTraining if (self.grad == "smoothed" or self.flip_explore > 0) else LearnedTraining

    def kept_points(self) -> Optional[int]:
        return self.num_points

    def uses_camera_gradient(self) -> bool:
        return not self.from_ckpt and self.grad == "autograd"

    def lr_scale(self, epoch: int) -> float:
        """G's learning-rate multiplier on top of the schedule during 0-based ``epoch``."""
        return 0.0 if self.stop_epoch is not None and epoch >= self.stop_epoch else 1.0
