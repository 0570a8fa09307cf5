"""Config schemas: one dataclass per config group, the top-level ``TrainConfig`` / ``EvalConfig``.

Hydra composes ``mvtn_exp/conf/train.yaml`` (group files under ``conf/<group>/``) on top of these
schemas, registered in the ConfigStore by ``register_configs``: an unknown key or a wrong type
fails at compose time. ``validate`` methods check values (names, ranges) and raise ``ValueError``
naming the key and the allowed values. Angles are degrees; the world is Y-up.

Group -> schema: dataset -> DatasetConfig, renderer -> RendererConfig (``render/config.py``),
selector -> SelectorConfig, point_encoder -> PointEncoderConfig, backbone -> BackboneConfig,
mvnet -> MVNetConfig, task -> TaskConfig, optim -> OptimConfig, logger -> LoggerConfig,
paths -> PathsConfig; ``augment`` (AugmentConfig) has no group files: set ``augment.rotate=so3``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Optional

from .data.synthetic import ROTATIONS
from .models.backbones import BACKBONES, FEATURE_DIMS
from .models.multiview import MULTIVIEW, POOLS
from .models.vit import check_image_size
from .models.point_encoders import POINT_ENCODERS
from .render.config import RendererConfig
from .selectors import SELECTORS
from .selectors.mvtn import REGRESSORS
from .selectors.optimized import OBJECTIVES

DATASETS = ("synthetic", "synthetic_views", "modelnet40", "scanobjectnn", "shapenet")
SHAPES = ("mesh", "points")
SELECTOR_NAMES = tuple(SELECTORS)
POINT_ENCODER_NAMES = tuple(POINT_ENCODERS)
BACKBONE_NAMES = tuple(BACKBONES)
MVNET_NAMES = tuple(MULTIVIEW)
TASKS = ("classification",)
WARMUP_VIEWS = ("u0", "random", "spherical")
SELECTOR_GRADIENTS = ("autograd", "smoothed")  # how G gets its gradient (engine/view_gradient.py)
BN_RECALIBRATE_SCOPES = ("all", "eval")  # what the re-estimated BatchNorm statistics serve (engine/precise_bn.py)
SELECTOR_LOSSES = ("task", "centered_logit")  # what G minimises (tasks/classification.py: selector_loss_fn)
HYPOTHESIS_MODES = ("separate", "pooled")  # how C sees G's hypotheses while they race (selectors/hypotheses.py)
OPTIMIZERS = ("adamw",)
SCHEDULES = ("cosine", "step")


def check_device(key: str, device: str) -> None:
    """``cpu``, ``cuda`` or ``cuda:N``, and a CUDA device must exist on this machine."""
    import re

    import torch

    if not (device == "cpu" or re.fullmatch(r"cuda(:\d+)?", device)):
        raise ValueError(f"{key}={device!r}: expected cpu, cuda or cuda:N")
    if device.startswith("cuda"):
        if not torch.cuda.is_available():
            raise ValueError(f"{key}={device!r}: CUDA is not available on this machine (torch {torch.__version__}, "
                             "built with CUDA " + str(torch.version.cuda) + "); use device=cpu")
        index = int(device.split(":")[1]) if ":" in device else 0
        if index >= torch.cuda.device_count():
            raise ValueError(f"{key}={device!r}: this machine has {torch.cuda.device_count()} CUDA device(s)")


def one_of(key: str, value: Any, allowed) -> None:
    if value not in allowed:
        raise ValueError(f"{key}={value!r}: expected one of {', '.join(map(str, allowed))}")


def fraction(key: str, value: float) -> None:
    """``value`` in [0, 1)."""
    if not 0.0 <= value < 1.0:
        raise ValueError(f"{key}={value!r}: must be in [0, 1)")


def at_least(key: str, value, low, strict: bool = False) -> None:
    bad = value <= low if strict else value < low
    if value is None or bad:
        raise ValueError(f"{key}={value!r}: must be {'>' if strict else '>='} {low}")


@dataclass
class DatasetConfig:
    """Which shapes. ``root``: the dataset folder (synthetic: its cache folder).

    ``shape``: render meshes or point clouds; ``num_points``: points per shape fed to G (and
    rendered when ``shape=points``). ``rotate``: none | y (about the vertical axis) | so3 (synthetic
    datasets only; ``dataset=synthetic_views`` sets so3). ``seed``: the data seed (synthetic
    geometry), separate from the training seed.
    ``num_per_class`` / ``max_faces``: synthetic shapes per class for (train, val, test) and their
    face budget. ``max_vertices``: real meshes are simplified to about this many vertices (0: never;
    the paper used 20,000). ``strict``: a broken shape file stops the run instead of being skipped
    and counted. ``cache_dir``: where preprocessed real datasets are cached. ShapeNet:
    ``split_csv`` (default ``<root>/all.csv``, the SHREC17 split) and ``synset_dict`` (default
    ``<root>/shapenet_synset_dict_v2.json``, synset id -> name). ModelNet40 ``format``: ``off``
    (meshes), ``normal_resampled`` or ``ply_hdf5_2048`` (the PointNet authors' point releases).
    ``variant``: ScanObjectNN variant (obj_bg, obj_only, pb_t50_rs); ``val_fraction``: share of
    the official train split held out for model selection when a dataset has no val split.
    """

    name: str = "synthetic"
    root: str = "${paths.cache_dir}/synthetic"
    shape: str = "mesh"
    num_points: int = 1024
    rotate: str = "none"
    seed: int = 0
    num_per_class: list[int] = field(default_factory=lambda: [24, 12, 24])
    max_faces: int = 2000
    max_vertices: int = 20000
    strict: bool = False
    cache_dir: str = "${paths.cache_dir}"
    variant: str = ""
    format: str = "off"
    split_csv: Optional[str] = None
    synset_dict: Optional[str] = None
    val_fraction: float = 0.1
    num_workers: int = 0

    def validate(self) -> "DatasetConfig":
        one_of("dataset.name", self.name, DATASETS)
        one_of("dataset.shape", self.shape, SHAPES)
        one_of("dataset.rotate", self.rotate, ROTATIONS)
        one_of("dataset.format", self.format, ("off", "normal_resampled", "ply_hdf5_2048"))
        at_least("dataset.num_points", self.num_points, 1)
        at_least("dataset.seed", self.seed, 0)
        at_least("dataset.max_faces", self.max_faces, 1)
        at_least("dataset.max_vertices", self.max_vertices, 0)
        at_least("dataset.num_workers", self.num_workers, 0)
        if len(self.num_per_class) != 3 or min(self.num_per_class) < 1:
            raise ValueError(f"dataset.num_per_class={list(self.num_per_class)}: expected 3 counts >= 1 "
                             "(train, val, test)")
        fraction("dataset.val_fraction", self.val_fraction)
        return self


@dataclass
class SelectorConfig:
    """The view selector G (``selectors/``). Fixed: circular | spherical | random | noisy (the
    paper's alternative: ``base_layout`` circular or spherical plus Gaussian noise of
    ``noise_azim`` / ``noise_elev`` degrees std, redrawn at every training step; none at
    evaluation) | optimized (the paper's scene-parameter optimisation: the ``base_layout``
    layout, then ``opt_steps`` gradient steps of size ``opt_lr`` on each batch's views against
    ``opt_objective`` of the current C, labels included; ``selectors/optimized.py``); learned:
    mvtn_direct (the paper's: u = u_bound * tanh(G(S))) | mvtn_direct_offset | mvtn_circular |
    mvtn_spherical (u = u0 + u_bound * tanh(G(S, u0))) | mvtn_poi (experimental).

    ``distance``: camera distance; ``elevation``: elevation of the circular layout (degrees).
    ``sphere``: how the spherical layouts (spherical, and u0 of mvtn_spherical,
    mvtn_direct_offset, mvtn_poi) spread M views: ``equal_area`` (the paper's rings, e.g. M = 12:
    3 / 6 / 3 views at -60 / 0 / +60) or ``fibonacci`` (a Fibonacci lattice, this project's
    layout before 2026-12-01).
    ``azim_bound`` / ``elev_bound``: learned offsets' bounds in degrees (null: 180/M azimuth for
    the offset variants and 180 for direct; 90 elevation). ``learn_distance`` adds a distance
    offset bounded by ``distance_bound``. ``init_std``: std of G's last layer at initialisation
    (0: G starts exactly at u0; null: 0 for the offset variants, PyTorch's default for mvtn_direct). ``num_points``: a learned G reads the first n of the shape's points
    (null: all). Default 256, measured on the default experiment (8 epochs, 3 seeds): test accuracy
    0.866 +- 0.052 with 256 points vs 0.852 +- 0.050 with all 1024 (256 better by 0.014 +- 0.006 per
    seed), at 17.5 vs 26.0 s per epoch. The paper setups read all points.
    ``regressor`` (learned MVTN selectors): ``compact`` (b -> b -> b -> 5M -> 2M, the default) or
    ``official`` (the official code's MLP: one more 2M -> 2M layer, dropout 0.5; the paper setups).
    ``poi_gain``: how far mvtn_poi's point of interest pulls its cameras from u0 (``poi_learn_gain``:
    a parameter of G starting there, so G can shrink u0's pose-dependent tilt); ``poi_cache``: how
    many shapes' rotation-invariant point descriptors mvtn_poi keeps for later steps (0: computed
    at every step; 4096 shapes x 256 points: about 46 MB; ``selectors/invariant_cache.py``).
    ``from_ckpt``: view transfer: G's weights from this checkpoint of another run, frozen, and C
    trains on its views (``engine/view_transfer.py``; the checkpoint's views, selector and point
    encoder settings must match).
    ``hypotheses`` (mvtn_poi): sets of M views G holds and the trainer tries side by side for
    ``optim.hypothesis_epochs``, keeping the one with the lowest loss (``selectors/hypotheses.py``).
    """

    name: str = "mvtn_spherical"
    distance: float = 2.2
    elevation: float = 30.0
    sphere: str = "equal_area"
    azim_bound: Optional[float] = None
    elev_bound: Optional[float] = None
    learn_distance: bool = False
    distance_bound: float = 1.0
    init_std: Optional[float] = None
    num_points: Optional[int] = 256
    poi_gain: float = 8.0
    poi_cache: int = 4096
    poi_learn_gain: bool = False
    hypotheses: int = 1
    regressor: str = "compact"
    base_layout: str = "circular"
    noise_azim: float = 18.0
    noise_elev: float = 9.0
    from_ckpt: Optional[str] = None
    opt_steps: int = 10
    opt_lr: float = 50.0
    opt_objective: str = "min_ce"

    @property
    def learned(self) -> bool:
        return self.name.startswith("mvtn_")

    def validate(self) -> "SelectorConfig":
        one_of("selector", self.name, SELECTOR_NAMES)
        at_least("selector.distance", self.distance, 0.0, strict=True)
        one_of("selector.sphere", self.sphere, ("equal_area", "fibonacci"))
        one_of("selector.regressor", self.regressor, REGRESSORS)
        one_of("selector.base_layout", self.base_layout, ("circular", "spherical"))
        one_of("selector.opt_objective", self.opt_objective, OBJECTIVES)
        at_least("selector.opt_steps", self.opt_steps, 0)
        at_least("selector.opt_lr", self.opt_lr, 0.0, strict=True)
        if self.from_ckpt and not self.learned:
            raise ValueError(f"selector.from_ckpt={self.from_ckpt}: view transfer takes a learned G, got selector={self.name}")
        if self.from_ckpt and self.hypotheses > 1:
            raise ValueError("selector.from_ckpt with selector.hypotheses > 1: a transferred G is frozen, it races nothing")
        at_least("selector.noise_azim", self.noise_azim, 0.0)
        at_least("selector.noise_elev", self.noise_elev, 0.0)
        for key in ("azim_bound", "elev_bound"):
            if getattr(self, key) is not None:
                at_least(f"selector.{key}", getattr(self, key), 0.0)
        if self.init_std is not None:
            at_least("selector.init_std", self.init_std, 0.0)
        if self.num_points is not None:
            at_least("selector.num_points", self.num_points, 1)
        at_least("selector.poi_gain", self.poi_gain, 0.0, strict=True)
        at_least("selector.poi_cache", self.poi_cache, 0)
        at_least("selector.hypotheses", self.hypotheses, 1)
        if self.hypotheses > 1 and self.name != "mvtn_poi":
            raise ValueError(f"selector.hypotheses={self.hypotheses}: several sets of views are built for "
                             f"selector=mvtn_poi only, got selector={self.name}")
        if self.learn_distance:
            at_least("selector.distance_bound", self.distance_bound, 0.0, strict=True)
        return self


@dataclass
class PointEncoderConfig:
    """G's point encoder: ``[B, N, 3] -> [B, features]`` (b = 40 in the paper). ``pointnet``
    (``use_tnet``: the input transform) or ``dgcnn`` (``k`` neighbours per point, ``emb_dims``:
    the global feature's width before pooling)."""

    name: str = "pointnet"
    features: int = 40
    use_tnet: bool = False
    k: int = 20
    emb_dims: int = 1024

    def validate(self) -> "PointEncoderConfig":
        one_of("point_encoder", self.name, POINT_ENCODER_NAMES)
        at_least("point_encoder.features", self.features, 1)
        at_least("point_encoder.k", self.k, 1)
        at_least("point_encoder.emb_dims", self.emb_dims, 1)
        return self

    def kwargs(self) -> dict:
        """The chosen encoder's own constructor arguments."""
        return {"k": self.k, "emb_dims": self.emb_dims} if self.name == "dgcnn" else {"use_tnet": self.use_tnet}


@dataclass
class BackboneConfig:
    """The 2D backbone shared over views. ``weights``: a local torchvision-style state_dict file."""

    name: str = "small_cnn"
    weights: Optional[str] = None

    def validate(self) -> "BackboneConfig":
        one_of("backbone", self.name, BACKBONE_NAMES)
        return self


@dataclass
class MVNetConfig:
    """The multi-view network C: mvcnn (pool features over views) | late_fusion (pool logits) |
    view_transformer (``blocks`` self-attention blocks with ``heads`` heads over the view features
    as a set, tokens ``width`` wide (null: the backbone's feature size), then ``pool``;
    ``models/view_transformer.py``) | viewgcn (a graph over the view positions, ``k`` neighbours,
    M >= 2; ``models/viewgcn.py``). ``stages``: ``[S1, S2]`` (viewgcn only) trains S1 epochs on
    single views, then S2 epochs of the whole network; S1 + S2 must equal ``epochs``; the learning
    rate schedule runs over each stage on its own, and model selection counts stage 2 only."""

    name: str = "mvcnn"
    pool: str = "max"
    dropout: float = 0.0
    blocks: int = 2
    heads: int = 4
    width: Optional[int] = None
    mlp_ratio: float = 2.0
    k: int = 4
    stages: Optional[list[int]] = None

    def validate(self) -> "MVNetConfig":
        one_of("mvnet", self.name, MVNET_NAMES)
        one_of("mvnet.pool", self.pool, POOLS)
        fraction("mvnet.dropout", self.dropout)
        at_least("mvnet.blocks", self.blocks, 1)
        at_least("mvnet.heads", self.heads, 1)
        if self.width is not None:
            at_least("mvnet.width", self.width, 1)
        at_least("mvnet.mlp_ratio", self.mlp_ratio, 0.0, strict=True)
        at_least("mvnet.k", self.k, 1)
        if self.stages is not None:
            if self.name != "viewgcn":
                raise ValueError(f"mvnet.stages={list(self.stages)}: two-stage training is ViewGCN's (mvnet=viewgcn); "
                                 f"got mvnet={self.name}")
            if len(self.stages) != 2 or any(int(s) != s or s < 1 for s in self.stages):
                raise ValueError(f"mvnet.stages={list(self.stages)}: expected [S1, S2], two whole numbers of epochs >= 1 "
                                 "(single views, then the whole network)")
        if self.name == "viewgcn" and self.pool != "max":
            raise ValueError(f"mvnet.pool={self.pool}: ViewGCN max-pools each level; use mvnet.pool=max")
        return self

    def kwargs(self) -> dict:
        """Constructor arguments of ``build_multiview`` beyond the backbone and class count."""
        kw = dict(pool=self.pool, dropout=self.dropout)
        if self.name == "view_transformer":
            kw.update(blocks=self.blocks, heads=self.heads, width=self.width, mlp_ratio=self.mlp_ratio)
        if self.name == "viewgcn":
            kw.update(k=self.k)
        return kw


@dataclass
class TaskConfig:
    """The task head and its loss. ``classification``: cross-entropy over the dataset's classes."""

    name: str = "classification"
    label_smoothing: float = 0.0

    def validate(self) -> "TaskConfig":
        one_of("task", self.name, TASKS)
        fraction("task.label_smoothing", self.label_smoothing)
        return self


@dataclass
class OptimConfig:
    """AdamW with two parameter groups: C (``lr``) and G (``lr_selector``); G's gradient L2 norm
    is clipped to ``clip_selector`` before the step. Schedule per epoch: cosine to 0 or step
    (x ``step_gamma`` every ``step_size`` epochs). ``selector_warmup_epochs``: for the first
    epochs G is frozen and C trains on ``warmup_views`` (``u0``: G's initial views; ``random``:
    new uniform random views per shape and step; ``spherical``: the fixed layout of
    ``selector.sphere``), then G and C train together. ``warmup_num_views``: how many views C
    sees in those epochs (null: ``views``; any count with a view-pooling C, whose weights do not
    depend on M, so C can learn from a full ring of views before G picks a few).
    ``selector_epochs``: G's learning rate is 0 from this epoch on (null: G trains to the end).
    ``selector_beta1``: AdamW's first-moment decay for G's group (0.9, C's and AdamW's default):
    G steps along the running mean of about 1 / (1 - beta1) steps' gradients, so a larger value
    averages out more of the smoothed estimate's noise before G moves.
    ``selector_grad``: how G's gradient is got: ``autograd`` (the paper's: through the
    differentiable renderer) or ``smoothed`` (the gradient of the task loss smoothed over the views
    by a Gaussian of ``smoothed_sigma`` degrees, estimated from ``smoothed_pairs`` antithetic pairs
    of perturbed renders per step; the renderer is not differentiated: ``engine/view_gradient.py``);
    ``smoothed_every``: the estimate (and G's step) only every this many training steps; the steps
    between train C alone (a speed knob: G's probes cost 2-3 x C's step).
    ``flip_explore``: for the first ``flip_epochs`` epochs each training view of a learned G is
    rendered from its antipode with this probability, and a view whose flipped renders had the
    lower loss turns round (``selectors/polarity.py``); 0 (default): off. ``bn_recalibrate``: before
    each validation, C's BatchNorm statistics are re-estimated over this many training batches
    rendered as validation renders them (``engine/precise_bn.py``); 0 (default, the paper's): the
    running averages of training; ``bn_recalibrate_scope``: ``eval`` (default: they serve
    validation, the checkpoints and the test; training keeps its own, so it is bit-identical to a
    run without re-estimation) or ``all`` (training goes on from the re-estimated statistics).
    ``selector_loss``: what G's smoothed gradient minimises: ``task`` (the paper's: C's own loss)
    or ``centered_logit`` (``mean_c z_c - z_y``: the task loss without its label-free confidence
    term ``logsumexp z - mean z``, which pulls G to views where C's output is flat while C is still
    at chance; ``tasks/classification.py``); needs ``selector_grad=smoothed``.
    ``hypothesis_epochs``: with ``selector.hypotheses`` H > 1, at most this many first epochs render
    all H sets of views, train C on each, and keep the set with the lowest loss; earlier once it
    leads every other by ``hypothesis_z`` paired standard errors (null: never earlier;
    ``selectors/hypotheses.py``). ``hypothesis_mode``: while they race, C classifies each
    hypothesis's M views as a shape of its own (``separate``) or all H x M views of a shape pooled
    as one shape, like a run at H x M views, each hypothesis then scored by C alone on its own M
    views in eval mode (``pooled``). ``ema_decay``: keep an exponential moving average of G's and
    C's weights with this decay (e.g. 0.999; null: none), evaluated on validation beside the raw
    weights every epoch; the better of the two is kept as best.pt (``engine/ema.py``)."""

    name: str = "adamw"
    lr: float = 1e-3
    lr_selector: float = 1e-3
    weight_decay: float = 0.01
    clip_selector: float = 30.0
    schedule: str = "cosine"
    step_size: int = 30
    step_gamma: float = 0.1
    selector_warmup_epochs: int = 0
    warmup_views: str = "u0"
    warmup_num_views: Optional[int] = None
    selector_epochs: Optional[int] = None
    selector_beta1: float = 0.9
    selector_grad: str = "autograd"
    smoothed_pairs: int = 2
    smoothed_sigma: float = 10.0
    smoothed_every: int = 1
    selector_loss: str = "task"
    flip_explore: float = 0.0
    flip_epochs: int = 10
    hypothesis_epochs: int = 0
    hypothesis_z: Optional[float] = 3.0
    hypothesis_mode: str = "separate"
    bn_recalibrate: int = 0
    bn_recalibrate_scope: str = "eval"
    ema_decay: Optional[float] = None

    def validate(self) -> "OptimConfig":
        one_of("optim", self.name, OPTIMIZERS)
        one_of("optim.schedule", self.schedule, SCHEDULES)
        at_least("optim.lr", self.lr, 0.0, strict=True)
        at_least("optim.lr_selector", self.lr_selector, 0.0)
        at_least("optim.weight_decay", self.weight_decay, 0.0)
        at_least("optim.clip_selector", self.clip_selector, 0.0, strict=True)
        if self.ema_decay is not None and not 0.0 < self.ema_decay < 1.0:
            raise ValueError(f"optim.ema_decay={self.ema_decay}: expected a number in (0, 1), e.g. 0.999, or null")
        at_least("optim.step_size", self.step_size, 1)
        at_least("optim.selector_warmup_epochs", self.selector_warmup_epochs, 0)
        one_of("optim.warmup_views", self.warmup_views, WARMUP_VIEWS)
        if self.warmup_num_views is not None:
            at_least("optim.warmup_num_views", self.warmup_num_views, 1)
            if self.selector_warmup_epochs == 0:
                raise ValueError(f"optim.warmup_num_views={self.warmup_num_views}: there is no warm-up; set "
                                 "optim.selector_warmup_epochs >= 1")
        if self.selector_epochs is not None:
            at_least("optim.selector_epochs", self.selector_epochs, 0)
        if not 0.0 <= self.selector_beta1 < 1.0:
            raise ValueError(f"optim.selector_beta1={self.selector_beta1!r}: expected a value in [0, 1)")
        one_of("optim.selector_grad", self.selector_grad, SELECTOR_GRADIENTS)
        at_least("optim.smoothed_pairs", self.smoothed_pairs, 1)
        at_least("optim.smoothed_sigma", self.smoothed_sigma, 0.0, strict=True)
        at_least("optim.smoothed_every", self.smoothed_every, 1)
        one_of("optim.selector_loss", self.selector_loss, SELECTOR_LOSSES)
        if self.selector_loss != "task" and self.selector_grad != "smoothed":
            raise ValueError(f"optim.selector_loss={self.selector_loss}: G's own loss is estimated from perturbed "
                             "renders; it needs optim.selector_grad=smoothed (autograd trains G on C's loss)")
        if not 0.0 <= self.flip_explore < 1.0:
            raise ValueError(f"optim.flip_explore={self.flip_explore!r}: expected a probability in [0, 1)")
        at_least("optim.flip_epochs", self.flip_epochs, 1)
        at_least("optim.hypothesis_epochs", self.hypothesis_epochs, 0)
        one_of("optim.hypothesis_mode", self.hypothesis_mode, HYPOTHESIS_MODES)
        if self.hypothesis_z is not None:
            at_least("optim.hypothesis_z", self.hypothesis_z, 0.0)
        at_least("optim.bn_recalibrate", self.bn_recalibrate, 0)
        one_of("optim.bn_recalibrate_scope", self.bn_recalibrate_scope, BN_RECALIBRATE_SCOPES)
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


PRECISIONS = ("fp32", "bf16", "fp16")


def check_precision(precision: str, device: str) -> None:
    """One-line errors naming the keys, for a precision the device cannot run (``models/precision.py``)."""
    one_of("precision", precision, PRECISIONS)
    if precision == "fp16" and not str(device).startswith("cuda"):
        raise ValueError(f"precision=fp16 with device={device}: float16 autocast needs CUDA; on CPU use "
                         "precision=bf16 or fp32")


@dataclass
class TrainConfig:
    """``mvtn-train``. Top-level keys everyone reaches for; the rest in the groups.

    ``views``: M; ``image_size``: rendered H = W (sets ``renderer.image_size``); ``seed``: the
    training seed (init, order, augmentation); ``ckpt_path``: resume from this checkpoint;
    ``threads``: torch's CPU threads for this process (null: torch's default, or under the joblib
    launcher the cores divided by the jobs that run at once); ``precision``: fp32, or autocast of
    the multi-view network C in bf16 or fp16 (CUDA only; G and the renderer stay float32:
    ``models/precision.py``).
    """

    views: int = 4
    image_size: int = 64
    epochs: int = 8
    batch_size: int = 16
    seed: int = 0
    device: str = "cpu"
    ckpt_path: Optional[str] = None
    threads: Optional[int] = None
    precision: str = "fp32"
    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    # renderer.image_size follows the top-level image_size (an interpolation, resolved at compose time);
    # training defaults to soft smooth rendering (conf/renderer/soft.yaml: camera gradients for G)
    renderer: RendererConfig = field(default_factory=lambda: RendererConfig(
        image_size="${image_size}", mode="soft", shading="smooth"))  # type: ignore[arg-type]
    selector: SelectorConfig = field(default_factory=SelectorConfig)
    point_encoder: PointEncoderConfig = field(default_factory=PointEncoderConfig)
    backbone: BackboneConfig = field(default_factory=BackboneConfig)
    mvnet: MVNetConfig = field(default_factory=MVNetConfig)
    task: TaskConfig = field(default_factory=TaskConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    augment: AugmentConfig = field(default_factory=AugmentConfig)
    logger: LoggerConfig = field(default_factory=LoggerConfig)
    paths: PathsConfig = field(default_factory=PathsConfig)

    def validate(self) -> "TrainConfig":
        for key in ("views", "image_size", "epochs", "batch_size"):
            at_least(key, getattr(self, key), 1)
        at_least("seed", self.seed, 0)
        if self.selector.learned and self.batch_size < 2:
            raise ValueError(f"batch_size={self.batch_size}: a learned selector (BatchNorm in G) trains on batches "
                             "of at least 2 shapes")
        if self.optim.selector_grad == "smoothed" and self.selector.learn_distance:
            raise ValueError("optim.selector_grad=smoothed estimates G's azimuth and elevation gradients only; "
                             "selector.learn_distance=true needs optim.selector_grad=autograd")
        if self.selector.from_ckpt and self.optim.flip_explore > 0:
            raise ValueError("selector.from_ckpt with optim.flip_explore: a transferred G is frozen, its views are not "
                             "turned round")
        if self.optim.flip_explore > 0 and not self.selector.learned:
            raise ValueError(f"optim.flip_explore={self.optim.flip_explore}: turning views round needs a learned "
                             f"selector, got selector={self.selector.name}")
        if (self.selector.hypotheses > 1) != (self.optim.hypothesis_epochs > 0):
            raise ValueError(f"selector.hypotheses={self.selector.hypotheses} with optim.hypothesis_epochs="
                             f"{self.optim.hypothesis_epochs}: set both (hypotheses >= 2 and hypothesis_epochs >= 1) "
                             "or neither")
        if self.selector.hypotheses > 1 and self.optim.flip_explore > 0:
            raise ValueError("selector.hypotheses with optim.flip_explore: choose one way to explore")
        check_device("device", self.device)
        if self.threads is not None:
            at_least("threads", self.threads, 1)
        check_precision(self.precision, self.device)
        for part in (self.dataset, self.selector, self.point_encoder, self.backbone, self.mvnet, self.task,
                     self.optim, self.augment, self.logger):
            part.validate()
        if self.selector.learned and self.selector.name != "mvtn_poi" and self.point_encoder.name == "dgcnn":
            n = min(self.dataset.num_points, self.selector.num_points or self.dataset.num_points)
            if n < self.point_encoder.k:
                raise ValueError(f"point_encoder.k={self.point_encoder.k}: DGCNN needs at least k points, G reads {n} "
                                 f"(selector.num_points={self.selector.num_points}, dataset.num_points="
                                 f"{self.dataset.num_points})")
        if self.backbone.name.startswith("vit_"):
            check_image_size(self.backbone.name, self.image_size)
        if self.mvnet.name == "view_transformer":
            width = self.mvnet.width if self.mvnet.width is not None else FEATURE_DIMS[self.backbone.name]
            if width % self.mvnet.heads:
                raise ValueError(f"mvnet.heads={self.mvnet.heads} must divide the view transformer's token width "
                                 f"{width} (mvnet.width={self.mvnet.width}; null takes backbone={self.backbone.name}'s "
                                 f"feature size {FEATURE_DIMS[self.backbone.name]})")
        if self.mvnet.name == "viewgcn":
            check_viewgcn(self)
        n_warm = self.optim.warmup_num_views
        if n_warm is not None and n_warm != self.views and self.optim.warmup_views == "u0":
            raise ValueError(f"optim.warmup_num_views={n_warm} with optim.warmup_views=u0: G's initial views are "
                             f"views={self.views}; use warmup_views=spherical or random for another count")
        if self.renderer.image_size != self.image_size:
            raise ValueError(f"renderer.image_size={self.renderer.image_size} differs from image_size={self.image_size}: "
                             "set the top-level image_size")
        self.renderer.validate()
        return self


def check_viewgcn(cfg: "TrainConfig") -> None:
    """One-line errors naming the keys for settings ViewGCN cannot take (its graph needs M >= 2)."""
    if cfg.views < 2:
        raise ValueError(f"views={cfg.views}: mvnet=viewgcn builds a graph over the views and needs views >= 2")
    n_warm = cfg.optim.warmup_num_views
    if n_warm is not None and n_warm < 2:
        raise ValueError(f"optim.warmup_num_views={n_warm}: mvnet=viewgcn needs at least 2 views")
    if cfg.selector.hypotheses > 1:
        raise ValueError(f"selector.hypotheses={cfg.selector.hypotheses} with mvnet=viewgcn: racing hypotheses "
                         "is for MVCNN-style networks; use selector.hypotheses=1")
    stages = cfg.mvnet.stages
    if stages is not None and sum(stages) != cfg.epochs:
        raise ValueError(f"mvnet.stages={list(stages)} sums to {sum(stages)} epochs but epochs={cfg.epochs}: "
                         f"set epochs={sum(stages)} or change the stages")


@dataclass
class RotationEvalConfig:
    """Rotation robustness: each test shape turned about Y by an angle uniform in [-theta, theta]
    (degrees), ``repeats`` times with seeds ``seed, seed+1, ...``."""

    thetas: list[float] = field(default_factory=lambda: [90.0, 180.0])
    repeats: int = 10
    seed: int = 0


@dataclass
class OcclusionEvalConfig:
    """Occlusion robustness: cut each shape at ``ratio`` from each of +-X, +-Y, +-Z. ``frame``:
    ``unit_sphere`` (the paper's code: remove ``sign * x > 1 - 2 ratio`` of the unit sphere,
    the same plane for every shape) or ``extent`` (remove ``ratio`` of each shape's own extent)."""

    ratios: list[float] = field(default_factory=lambda: [0.0, 0.1, 0.2, 0.3, 0.5, 0.75])
    seed: int = 0
    frame: str = "unit_sphere"


@dataclass
class RetrievalEvalConfig:
    """Retrieval: features before the classifier, LFDA to ``dim`` (fitted on the database), every
    test shape queries the whole official train split (val included where it was carved out of
    train); ``k``: LFDA's local-scaling neighbour, ``scaling``: class (Sugiyama's, default) | all
    (the k-th neighbour among all samples, as before 2026-12-01); ``list_length`` for SHREC-style
    metrics."""

    dim: int = 128
    k: int = 7
    scaling: str = "class"
    list_length: int = 1000


EVAL_TASKS = ("classification", "retrieval")
ROBUSTNESS = ("none", "rotation", "occlusion")


@dataclass
class EvalConfig:
    """``mvtn-eval ckpt=PATH``: rebuild the model from the checkpoint's config, evaluate ``split``.

    ``task``: classification | retrieval; ``robustness``: none | rotation | occlusion (with
    classification); ``views``: also analyse the predicted views (per-class histograms, cameras
    around a shape, accuracy with per-class-averaged views). ``device`` / ``batch_size``: null keeps the checkpoint's values. ``root``:
    override the dataset root stored in the checkpoint (data moved); ``paths.output_dir``: where
    the run dir goes (``<output_dir>/eval/runs/<time>-<pid>``)."""

    ckpt: Optional[str] = None
    split: str = "test"
    task: str = "classification"
    robustness: str = "none"
    views: bool = False
    device: Optional[str] = None
    batch_size: Optional[int] = None
    root: Optional[str] = None
    progress: bool = True
    rotation: RotationEvalConfig = field(default_factory=RotationEvalConfig)
    occlusion: OcclusionEvalConfig = field(default_factory=OcclusionEvalConfig)
    retrieval: RetrievalEvalConfig = field(default_factory=RetrievalEvalConfig)
    paths: PathsConfig = field(default_factory=PathsConfig)  # run dirs go under paths.output_dir/eval

    def validate(self) -> "EvalConfig":
        if not self.ckpt:
            raise ValueError("ckpt: missing; pass ckpt=PATH to a best.pt / last.pt written by mvtn-train")
        one_of("split", self.split, ("train", "val", "test"))
        one_of("task", self.task, EVAL_TASKS)
        one_of("robustness", self.robustness, ROBUSTNESS)
        if self.device is not None:
            check_device("device", self.device)
        if self.task == "retrieval" and self.split == "train":
            raise ValueError("split=train: retrieval queries the train split as its database; use split=test or val")
        if self.task == "retrieval" and self.robustness != "none":
            raise ValueError(f"robustness={self.robustness}: robustness is evaluated with task=classification")
        if self.batch_size is not None:
            at_least("batch_size", self.batch_size, 1)
        at_least("rotation.repeats", self.rotation.repeats, 1)
        for t in self.rotation.thetas:
            if not 0 <= t <= 180:
                raise ValueError(f"rotation.thetas: {t} is outside [0, 180] degrees")
        for r in self.occlusion.ratios:
            fraction("occlusion.ratios", r)
        one_of("occlusion.frame", self.occlusion.frame, ("unit_sphere", "extent"))
        at_least("retrieval.dim", self.retrieval.dim, 1)
        at_least("retrieval.k", self.retrieval.k, 1)
        one_of("retrieval.scaling", self.retrieval.scaling, ("class", "all"))
        at_least("retrieval.list_length", self.retrieval.list_length, 1)
        return self


GROUPS = {"dataset": DatasetConfig, "renderer": RendererConfig, "selector": SelectorConfig,
          "point_encoder": PointEncoderConfig, "backbone": BackboneConfig, "mvnet": MVNetConfig,
          "task": TaskConfig, "optim": OptimConfig, "logger": LoggerConfig, "paths": PathsConfig}


def register_configs() -> None:
    """Store ``train_schema`` and ``eval_schema`` in Hydra's ConfigStore. The group files are
    merged into the typed fields of ``TrainConfig``, so each is checked against its group's schema."""
    from hydra.core.config_store import ConfigStore

    cs = ConfigStore.instance()
    cs.store(name="train_schema", node=TrainConfig)
    cs.store(name="eval_schema", node=EvalConfig)
