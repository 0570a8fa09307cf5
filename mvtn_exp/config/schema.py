"""Config schemas: one dataclass per config group and the top-level ``TrainConfig`` (``mvtn-eval``'s: ``eval_schema``).

Hydra composes ``mvtn_exp/conf/train.yaml`` (group files under ``conf/<group>/``) on top of these
schemas, registered in the ConfigStore by ``config/store.register_configs``: an unknown key or a wrong type
fails at compose time. ``validate`` methods check values (names, ranges) and raise ``ValueError``
naming the key and the allowed values. Angles are degrees; the world is Y-up.

Group -> schema: dataset -> DatasetConfig (``data/config.py``), renderer -> RendererConfig, selector
-> SelectorConfig, point_encoder -> PointEncoderConfig, backbone -> BackboneConfig, mvnet -> MVNetConfig
(C of classification), segnet -> SegNetConfig (C of segmentation) (``OPTION_KINDS``: a subclass per
option), task -> TaskConfig, optim -> OptimConfig, logger -> LoggerConfig,
paths -> PathsConfig; ``augment`` (AugmentConfig) has no group files: set ``augment.rotate=so3``.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Optional

from .checks import at_least, one_of
from ..data.config import DatasetConfig, SyntheticConfig
from ..data.synthetic import ROTATIONS
from ..models.backbones import BackboneConfig, SmallCNNConfig
from ..models import pretrained
from ..models.multiview import MVCNNConfig, MVNetConfig
from ..models.precision import check_precision
from ..models.point_encoders import PointEncoderConfig, PointNetConfig
from ..models.segnets import SegNetConfig, SmallFCNConfig
from .options import OPTIONS
from ..render.config import RendererConfig
from ..selectors.config import SelectorConfig
from ..selectors.mvtn import MVTNSphericalConfig
from ..tasks.config import TaskConfig

OPTIMIZERS = ("adamw",)
SCHEDULES = ("cosine", "step")


def check_device(key: str, device: str) -> None:
    """``auto``, ``cpu``, ``cuda`` or ``cuda:N``, and a CUDA device must exist on this machine
    (``auto`` never fails: ``resolve_device``)."""
    import re

    import torch

    if not (device in ("auto", "cpu") or re.fullmatch(r"cuda(:\d+)?", str(device))):
        raise ValueError(f"{key}={device!r}: expected auto, cpu, cuda or cuda:N")
    if device.startswith("cuda"):
        if not torch.cuda.is_available():
            raise ValueError(f"{key}={device!r}: CUDA is not available on this machine (torch {torch.__version__}, "
                             "built with CUDA " + str(torch.version.cuda) + "); use device=cpu or device=auto")
        index = int(device.split(":")[1]) if ":" in device else 0
        if index >= torch.cuda.device_count():
            raise ValueError(f"{key}={device!r}: this machine has {torch.cuda.device_count()} CUDA device(s)")


def resolve_device(device: str | None) -> str:
    """``auto`` (or None) -> ``cuda`` when torch sees a CUDA device, else ``cpu``; any other name unchanged."""
    if device in (None, "auto"):
        import torch

        return "cuda" if torch.cuda.is_available() else "cpu"
    return device


@dataclass
class OptimConfig:
    """C's optimiser: AdamW at ``lr`` with ``weight_decay``; a learned G has its own group, set in
    the selector (``selector.lr``, ``selector.beta1``, ``selector.clip``). Schedule per epoch, both
    groups unless ``decay_selector=false`` (the official code's: the step decay applies to C only, G
    keeps ``selector.lr``): cosine to 0 or step (x ``step_gamma`` every ``step_size`` epochs). ``ema_decay``: keep
    an exponential moving average of G's and C's weights with this decay (e.g. 0.999; null: none),
    evaluated on validation beside the raw weights every epoch; the better of the two is kept as
    best.pt (``engine/ema.py``)."""

    name: str = "adamw"
    lr: float = 1e-3
    weight_decay: float = 0.01
    schedule: str = "cosine"
    step_size: int = 30
    step_gamma: float = 0.1
    decay_selector: bool = True
    ema_decay: Optional[float] = None

    def validate(self) -> "OptimConfig":
        one_of("optim", self.name, OPTIMIZERS)
        one_of("optim.schedule", self.schedule, SCHEDULES)
        at_least("optim.lr", self.lr, 0.0, strict=True)
        at_least("optim.weight_decay", self.weight_decay, 0.0)
        if self.ema_decay is not None and not 0.0 < self.ema_decay < 1.0:
            raise ValueError(f"optim.ema_decay={self.ema_decay}: expected a number in (0, 1), e.g. 0.999, or null")
        at_least("optim.step_size", self.step_size, 1)
        return self


@dataclass
class AugmentConfig:
    """Training-time augmentation, drawn from the training seed's RNG (so resume stays exact).

    ``rotate``: every training shape is turned by a new random rotation at every step, points and
    mesh together (none | y: uniform about the vertical axis | so3: uniform over SO(3)). Validation
    and test shapes are never turned."""

    rotate: str = "none"

    def validate(self) -> "AugmentConfig":
        one_of("augment.rotate", self.rotate, ROTATIONS)
        return self


@dataclass
class LoggerConfig:
    """Progress bars and TensorBoard (``<run>/tb``): scalars every ``log_every`` steps, a view grid
    and view histograms every epoch."""

    tensorboard: bool = True
    progress: bool = True
    log_every: int = 10
    images: bool = True

    def validate(self) -> "LoggerConfig":
        at_least("logger.log_every", self.log_every, 1)
        return self


@dataclass
class PathsConfig:
    """Where data is read from and where outputs and caches go (relative to the working dir)."""

    data_dir: str = "data"
    output_dir: str = "outputs"
    cache_dir: str = "${paths.output_dir}/cache"


# What a training run can return to an optimising sweeper (``TrainConfig.objectives``): validation
# accuracy and the measured cost of ``engine/cost.py``; never a test metric.
OBJECTIVES = ("best_val_acc", "best_val_instance_miou", "cost.infer_ms_per_shape", "cost.train_seconds_per_shape", "cost.train_peak_mib",
              "cost.infer_peak_mib", "cost.render_ms_per_shape", "cost.params_selector", "cost.params_mvnet",
              "cost.flops_selector_per_shape", "cost.flops_mvnet_per_shape")


@dataclass
class TrainConfig:
    """``mvtn-train``. Top-level keys everyone reaches for; the rest in the groups.

    ``views``: M; ``image_size``: rendered H = W (sets ``renderer.image_size``); ``patience``: stop
    once this many epochs in a row have not raised the best validation accuracy (null: train all
    ``epochs``; the learning-rate schedule still spans ``epochs``, and ``best.pt`` is tested as
    always); ``seed``: the training seed (init, order, augmentation); ``ckpt_path``: resume from
    this checkpoint;
    ``threads``: torch's CPU threads for this process (null: torch's default, or under the joblib
    launcher the cores divided by the jobs that run at once); ``precision``: fp32, or autocast of
    the multi-view network C in bf16 or fp16 (CUDA only; G and the renderer stay float32:
    ``models/precision.py``); ``deterministic``: torch's deterministic algorithms for the whole run
    and ``renderer.deterministic`` (repeatable CUDA runs, at a cost: ``engine/seeding.deterministic``);
    ``overwrite``: a new run may replace the run in its ``hydra.run.dir``
    (one holding a ``last.pt``; else refused: ``engine/run_dir.py``); ``sync_bn``: with several
    processes (torchrun), BatchNorm statistics over the whole global batch (``models/sync_bn.py``;
    false: each process over its own share, as plain DDP); no effect in one process.
    ``objectives``: what the run returns to a sweeper that optimises (``hydra/sweeper=optuna``, e.g.
    ``+experiment=tradeoff_search``), in order: ``best_val_acc`` or ``cost.<field>`` of its
    metrics.json (``engine/cost.py``); test metrics are refused (a search chooses on validation).
    """

    views: int = 4
    image_size: int = 64
    epochs: int = 8
    patience: Optional[int] = None
    batch_size: int = 16
    seed: int = 0
    device: str = "auto"
    ckpt_path: Optional[str] = None
    threads: Optional[int] = None
    precision: str = "fp32"
    deterministic: bool = False
    overwrite: bool = False
    sync_bn: bool = True
    objectives: list[str] = field(default_factory=list)
    dataset: DatasetConfig = field(default_factory=SyntheticConfig)
    # renderer.image_size follows the top-level image_size (an interpolation, resolved at compose time);
    # training defaults to soft smooth rendering (conf/renderer/soft.yaml: camera gradients for G)
    renderer: RendererConfig = field(default_factory=lambda: RendererConfig(
        image_size="${image_size}", mode="soft", shading="smooth"))  # type: ignore[arg-type]
    selector: SelectorConfig = field(default_factory=MVTNSphericalConfig)
    point_encoder: PointEncoderConfig = field(default_factory=PointNetConfig)
    backbone: BackboneConfig = field(default_factory=SmallCNNConfig)
    mvnet: MVNetConfig = field(default_factory=MVCNNConfig)
    segnet: SegNetConfig = field(default_factory=SmallFCNConfig)
    task: TaskConfig = field(default_factory=TaskConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    augment: AugmentConfig = field(default_factory=AugmentConfig)
    logger: LoggerConfig = field(default_factory=LoggerConfig)
    paths: PathsConfig = field(default_factory=PathsConfig)

    def _check_budget(self) -> None:
        """``renderer.memory_budget_mb`` below what one shape's views need whatever its size: refused now."""
        r = self.renderer
        if r.memory_budget_mb is None or not isinstance(self.image_size, int):
            return
        from ..render import budget

        kind = "points" if self.dataset.shape == "points" else ("soft" if r.mode == "soft" else "hard")
        least = budget.smallest_mb(kind, self.views, self.image_size, self.batch_size)
        if r.memory_budget_mb < least:
            raise ValueError(f"renderer.memory_budget_mb={r.memory_budget_mb:g}: {self.batch_size} shapes of {self.views} "
                             f"views of {self.image_size} px ({kind}) need {least} MiB at least; set "
                             f"renderer.memory_budget_mb >= {least} (or null: automatic)")

    @property
    def c(self):
        """The option of C: ``segnet`` under ``task=segmentation``, else ``mvnet``."""
        return self.segnet if self.task.name == "segmentation" else self.mvnet

    def _check_task(self) -> None:
        """``task=segmentation`` needs part labels, C of ``segnet`` and a G that trains on C's loss
        alone: anything else is one line."""
        if self.task.name != "segmentation":
            return
        if not self.dataset.has_parts:
            having = sorted(n for n, c in OPTIONS["dataset"].items() if c.has_parts)
            raise ValueError(f"task=segmentation: dataset={self.dataset.name} has no part labels; the datasets "
                             f"that have them: {', '.join(having)}")
        if self.mvnet.name != MVCNNConfig.name:
            raise ValueError(f"mvnet={self.mvnet.name} with task=segmentation: C is segnet={self.segnet.name} there "
                             f"(mvnet is the multi-view network of classification; leave it unset)")
        problem = self.selector.segmentation_problem()
        if problem:
            raise ValueError(f"selector={self.selector.name} with task=segmentation: {problem}")

    def validate(self) -> "TrainConfig":
        for key in ("views", "image_size", "epochs", "batch_size"):
            at_least(key, getattr(self, key), 1)
        at_least("seed", self.seed, 0)
        if self.patience is not None:
            at_least("patience", self.patience, 1)
        check_device("device", self.device)
        if self.threads is not None:
            at_least("threads", self.threads, 1)
        check_precision(self.precision, resolve_device(self.device))
        for name in self.objectives:
            if str(name).startswith("test_"):
                raise ValueError(f"objectives: {name!r} reads the test split; a search chooses on validation "
                                 f"(one of {', '.join(OBJECTIVES)})")
            one_of("objectives", name, OBJECTIVES)
        for part in (self.dataset, self.selector, self.point_encoder, self.backbone, self.mvnet, self.segnet, self.task,
                     self.optim, self.augment, self.logger):
            part.validate()
        self._check_task()
        for part in (self.selector, self.point_encoder, self.backbone, self.c):
            part.check(self)  # each option against the rest of the config (e.g. ViewGCN needs M >= 2)
        if self.renderer.image_size != self.image_size:
            raise ValueError(f"renderer.image_size={self.renderer.image_size} differs from image_size={self.image_size}: "
                             "set the top-level image_size")
        self.renderer.validate()
        self._check_budget()
        return self


GROUPS = {"dataset": DatasetConfig, "renderer": RendererConfig, "selector": SelectorConfig,
          "point_encoder": PointEncoderConfig, "backbone": BackboneConfig, "mvnet": MVNetConfig,
          "segnet": SegNetConfig, "task": TaskConfig, "optim": OptimConfig, "logger": LoggerConfig, "paths": PathsConfig}


OPTION_KINDS = ("selector", "point_encoder", "backbone", "mvnet", "segnet", "dataset")  # one schema per option: options.py


def _option_schemas(data: dict, cfg) -> dict:
    """``kind -> config class`` of the option each kind of ``data`` names (the default's if unnamed)."""
    from omegaconf import DictConfig, OmegaConf

    out = {}
    for kind in OPTION_KINDS:
        node = data.get(kind) or {}
        name = node.get("name") or TrainConfig.__dataclass_fields__[kind].default_factory().name
        option = OPTIONS[kind].schema(name)
        if isinstance(cfg, DictConfig) and kind in cfg:
            composed = OmegaConf.get_type(cfg[kind])
            if composed not in (None, dict, option) and getattr(composed, "name", name) != name:
                raise ValueError(f"{kind}.name={name}: the option is chosen with {kind}={name} (this config was "
                                 f"composed as {kind}={composed.name})")
        out[kind] = option
    return out


def typed_train_config(cfg):
    """``cfg`` (a TrainConfig, or a DictConfig / dict as composed or stored) as an OmegaConf node
    typed by ``TrainConfig``, each of its ``OPTION_KINDS`` typed by the chosen option's own schema:
    a key of another option or a moved key is one ``ValueError`` line."""
    from omegaconf import DictConfig, OmegaConf
    from omegaconf.errors import ConfigAttributeError, ConfigKeyError

    if isinstance(cfg, TrainConfig):
        return OmegaConf.structured(cfg)
    data = OmegaConf.to_container(cfg, resolve=False) if isinstance(cfg, DictConfig) else dict(cfg)
    options = _option_schemas(data, cfg)
    base = OmegaConf.structured(TrainConfig)
    for kind, option in options.items():
        base[kind] = OmegaConf.structured(option)
    try:
        return OmegaConf.merge(base, data)
    except (ConfigKeyError, ConfigAttributeError) as exc:
        key = getattr(exc, "full_key", "") or ""
        kind, _, sub = key.partition(".")
        if kind in options and sub:
            raise ValueError(OPTIONS[kind].foreign_key_message(options[kind].name, sub)) from None
        raise ValueError(str(exc).splitlines()[0]) from None


def as_config(cfg) -> TrainConfig:
    """TrainConfig | DictConfig | dict -> a validated TrainConfig (type-checked against the schema,
    interpolations resolved)."""
    from omegaconf import OmegaConf

    obj: TrainConfig = OmegaConf.to_object(typed_train_config(cfg))
    return obj.validate()


PATH_KEYS = (("dataset", "root"), ("dataset", "cache_dir"), ("dataset", "split_csv"), ("dataset", "synset_dict"),
             ("backbone", "weights"), ("paths", "data_dir"), ("paths", "output_dir"), ("paths", "cache_dir"))


def config_dict(cfg: TrainConfig) -> dict:
    """``cfg`` as plain data, with its file and folder paths made absolute (``PATH_KEYS``): what a
    checkpoint and metrics.json record works from any working directory (``backbone.weights=imagenet``
    names published weights, not a file: kept as it is)."""
    out = asdict(cfg)
    for group, key in PATH_KEYS:
        value = out.get(group, {}).get(key)
        if isinstance(value, str) and value and not pretrained.is_source(value):
            out[group][key] = str(Path(value).expanduser().resolve())
    return out
