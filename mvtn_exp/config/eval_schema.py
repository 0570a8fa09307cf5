"""The schema of ``mvtn-eval`` (``EvalConfig``): which checkpoint, split and task, and the settings
of its rotation, occlusion and retrieval modes."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

from .checks import at_least, fraction, one_of
from .schema import PathsConfig, check_device


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
    (the k-th neighbour among all samples, the former default); ``list_length`` for SHREC-style
    metrics."""

    dim: int = 128
    k: int = 7
    scaling: str = "class"
    list_length: int = 1000


EVAL_TASKS = ("classification", "retrieval", "segmentation")
ROBUSTNESS = ("none", "rotation", "occlusion")


@dataclass
class EvalConfig:
    """``mvtn-eval ckpt=PATH``: rebuild the model from the checkpoint's config, evaluate ``split``.

    ``task``: classification | retrieval | segmentation (null: the checkpoint's own, classification
    or segmentation; a checkpoint of the other task is refused); ``robustness``: none | rotation | occlusion (with
    classification); ``views``: also analyse the predicted views (per-class histograms, cameras
    around a shape, accuracy with per-class-averaged views). ``device``: auto (CUDA when available, else CPU), cpu, cuda[:N], or null for the checkpoint's; ``batch_size``: null keeps the checkpoint's. ``root``:
    override the dataset root stored in the checkpoint (data moved); ``paths.output_dir``: where
    the run dir goes (``<output_dir>/eval/runs/<time>-<pid>``)."""

    ckpt: Optional[str] = None
    split: str = "test"
    task: Optional[str] = None
    robustness: str = "none"
    views: bool = False
    device: Optional[str] = "auto"
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
        if self.task is not None:
            one_of("task", self.task, EVAL_TASKS)
        one_of("robustness", self.robustness, ROBUSTNESS)
        if self.device is not None:
            check_device("device", self.device)
        if self.task == "retrieval" and self.split == "train":
            raise ValueError("split=train: retrieval queries the train split as its database; use split=test or val")
        if self.task in ("retrieval", "segmentation") and self.robustness != "none":
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
