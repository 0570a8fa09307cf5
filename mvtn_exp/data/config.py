"""The dataset options (``dataset=NAME``): one config class per dataset, registered in
``OPTIONS["dataset"]`` (``config/options.py``) as every other option kind's.

``DatasetConfig`` holds the keys every dataset has; each option's subclass adds its own keys, checks
them (``validate``, at compose time: a key of another dataset is refused there in one line naming
the dataset that has it) and reads the data (``build(split, progress) -> Dataset``). Its
``conf/dataset/NAME.yaml`` starts from the stored schema (``defaults: [/schema/dataset/NAME@_here_,
_self_]``). ``data/datasets.build_dataset`` is the lookup every caller uses.

Every dataset yields ``collate_shapes`` items (``points``, ``label``, ``name``, and ``verts`` /
``faces`` for meshes) and has ``classes`` (sorted names; label = index). A real dataset that is not
on disk fails in ``build`` with ``DatasetNotFound`` naming the path and the layout it expects.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar, Optional

from torch.utils.data import Dataset

from ..config.checks import at_least, fraction, one_of
from ..config.options import OPTIONS, OptionConfig
from . import modelnet, modelnet_points, scanobjectnn, scanobjectnn_objects, shapenet, synthetic, synthetic_views
from .mesh_io import DatasetNotFound
from .synthetic import ROTATIONS

REGISTRY = OPTIONS["dataset"]  # every dataset option, by name
register = REGISTRY.register

SHAPES = ("mesh", "points")
VIEW_FAMILIES = synthetic_views.FAMILIES  # dataset=synthetic_views families
MODELNET_FORMATS = ("off", *modelnet_points.FORMATS)  # the meshes; the PointNet authors' point releases
SCANOBJECTNN_FORMATS = ("h5", "object_dataset")  # the h5 release; the per-object files


@dataclass
class DatasetConfig(OptionConfig):
    """Keys every dataset has: ``name`` (the option; set it with ``dataset=NAME``), ``root`` (the
    dataset folder; synthetic ones: their cache folder), ``shape`` (render meshes or point clouds),
    ``num_points`` (points per shape fed to G, and rendered when ``shape=points``), ``seed`` (the
    data seed: synthetic geometry, a held-out val split, point subsets; separate from the training
    seed) and ``num_workers`` (DataLoader worker processes; null: automatic, none on CPU, where the
    loader's work is small next to the step's; on CUDA up to 4 within the process's share of the
    cores: ``engine/loaders.workers``)."""

    root: str = ""
    shape: str = "mesh"
    num_points: int = 1024
    seed: int = 0
    num_workers: Optional[int] = None

    kind = "dataset"
    has_parts: ClassVar[bool] = False  # items carry part_labels (task=segmentation)

    def validate(self) -> "DatasetConfig":
        super().validate()
        one_of("dataset.shape", self.shape, SHAPES)
        at_least("dataset.num_points", self.num_points, 1)
        at_least("dataset.seed", self.seed, 0)
        if self.num_workers is not None:
            at_least("dataset.num_workers", self.num_workers, 0)
        return self

    def build(self, split: str, progress: bool = True) -> Dataset:
        """The ``split`` ("train" | "val" | "test") of this dataset (its preprocessing on first use)."""
        raise NotImplementedError(f"{type(self).__name__}.build")


def require_root(cfg: DatasetConfig, layout: str) -> Path:
    """``cfg.root`` as a folder; missing: ``DatasetNotFound`` naming the path and ``layout``."""
    root = Path(cfg.root)
    if not root.is_dir():
        raise DatasetNotFound(f"dataset {cfg.name} not found at {root.resolve()}; expected layout: "
                              f"{layout}. Set dataset.root=PATH (or paths.data_dir=DIR).")
    return root


def _check_counts(num_per_class) -> None:
    """Three counts (train, val, test), each at least 1; else one line naming ``dataset.num_per_class``."""
    if len(num_per_class) != 3 or min(num_per_class) < 1:
        raise ValueError(f"dataset.num_per_class={list(num_per_class)}: expected 3 counts >= 1 (train, val, test)")


@register("synthetic")
@dataclass
class SyntheticConfig(DatasetConfig):
    """The embedded procedural meshes: 12 classes, generated once and cached under root.

    ``rotate``: a fixed random pose per shape (none | y: about the vertical axis | so3);
    ``num_per_class``: shapes per class for (train, val, test); ``max_faces``: the face budget."""

    name: str = "synthetic"
    root: str = "${paths.cache_dir}/synthetic"
    rotate: str = "none"
    num_per_class: list[int] = field(default_factory=lambda: [24, 12, 24])
    max_faces: int = 2000

    def validate(self) -> "SyntheticConfig":
        super().validate()
        one_of("dataset.rotate", self.rotate, ROTATIONS)
        at_least("dataset.max_faces", self.max_faces, 1)
        _check_counts(self.num_per_class)
        return self

    def _shapes(self) -> dict:
        """The reader's keyword arguments both synthetic datasets share."""
        return dict(num_per_class=self.num_per_class, seed=self.seed, rotate=self.rotate, num_points=self.num_points,
                    as_points=self.shape == "points", max_faces=self.max_faces)

    def build(self, split: str, progress: bool = True) -> Dataset:
        return synthetic.SyntheticShapes(self.root, split, progress=progress, **self._shapes())


@register("synthetic_views")
@dataclass
class SyntheticViewsConfig(SyntheticConfig):
    """The view-dependent benchmark: 8 classes told apart only by a small detail inside a cup.

    ``family``: the body the detail hides in (cup, decoys, slab: ``data/synthetic_views.py``); its
    YAML sets ``rotate: so3``, the schema keeps ``none`` as every synthetic dataset's."""

    name: str = "synthetic_views"
    root: str = "${paths.cache_dir}/synthetic_views"
    family: str = "cup"

    def validate(self) -> "SyntheticViewsConfig":
        super().validate()
        one_of("dataset.family", self.family, VIEW_FAMILIES)
        return self

    def build(self, split: str, progress: bool = True) -> Dataset:
        return synthetic_views.SyntheticViews(self.root, split, progress=progress, family=self.family,
                                              **self._shapes())


@register("synthetic_parts")
@dataclass
class SyntheticPartsConfig(SyntheticConfig):
    """The embedded part-segmentation meshes: 5 categories, 18 labelled parts (some seen only from
    some sides), generated once and cached under root (``data/synthetic_parts.py``). Items add
    ``part_labels`` (and ``face_parts`` for meshes); the dataset has ``part_names`` and ``parts_of``."""

    name: str = "synthetic_parts"
    has_parts: ClassVar[bool] = True
    root: str = "${paths.cache_dir}/synthetic_parts"
    num_per_class: list[int] = field(default_factory=lambda: [16, 8, 16])

    def build(self, split: str, progress: bool = True) -> Dataset:
        from . import synthetic_parts

        return synthetic_parts.SyntheticParts(self.root, split, progress=progress, **self._shapes())


@register("modelnet40")
@dataclass
class ModelNet40Config(DatasetConfig):
    """ModelNet40: the .off meshes, or the PointNet authors' point-cloud releases (format).

    ``format``: ``off`` (meshes, preprocessed once into ``cache_dir``/modelnet and simplified to
    about ``max_vertices`` vertices, 0: never; the paper used 20,000), ``normal_resampled`` or
    ``ply_hdf5_2048`` (point clouds, ``shape=points`` only). ``val_fraction``: share of each class's
    train shapes held out for model selection (ModelNet has no val split); ``strict``: a broken
    shape file stops the run instead of being skipped and counted."""

    name: str = "modelnet40"
    root: str = "${paths.data_dir}/ModelNet40"
    format: str = "off"
    max_vertices: int = 20000
    val_fraction: float = 0.1
    strict: bool = False
    cache_dir: str = "${paths.cache_dir}"

    def validate(self) -> "ModelNet40Config":
        super().validate()
        one_of("dataset.format", self.format, MODELNET_FORMATS)
        if self.format != "off" and self.shape != "points":
            raise ValueError(f"dataset.format={self.format}: point clouds only; use dataset.shape=points")
        at_least("dataset.max_vertices", self.max_vertices, 0)
        fraction("dataset.val_fraction", self.val_fraction)
        return self

    def build(self, split: str, progress: bool = True) -> Dataset:
        if self.format != "off":
            if not Path(self.root).is_dir():
                raise DatasetNotFound(f"dataset modelnet40 ({self.format}) not found at {Path(self.root).resolve()}; "
                                      f"expected layout: {modelnet_points.LAYOUTS[self.format]}")
            return modelnet_points.ModelNetPoints(self.root, split, format=self.format, num_points=self.num_points,
                                                  val_fraction=self.val_fraction, seed=self.seed, strict=self.strict)
        require_root(self, modelnet.LAYOUT)
        return modelnet.ModelNetMeshes(self.root, split, cache_dir=Path(self.cache_dir) / "modelnet",
                                       num_points=self.num_points, max_vertices=self.max_vertices,
                                       val_fraction=self.val_fraction, seed=self.seed, strict=self.strict,
                                       as_points=self.shape == "points", progress=progress)


@register("scanobjectnn")
@dataclass
class ScanObjectNNConfig(DatasetConfig):
    """ScanObjectNN: 15 classes of scanned objects, point clouds only.

    ``variant``: obj_bg, obj_only or pb_t50_rs; ``format``: ``h5`` (the h5 release, 2,048 points
    per cloud) or ``object_dataset`` (the per-object files at any ``num_points``: the paper's 5,000,
    L251; obj_bg and obj_only only). ``val_fraction``: share of the train split held out for model
    selection; ``strict``: a broken cloud stops the run instead of being skipped and counted."""

    name: str = "scanobjectnn"
    root: str = "${paths.data_dir}/ScanObjectNN"
    shape: str = "points"
    variant: str = "pb_t50_rs"
    format: str = "h5"
    val_fraction: float = 0.1
    strict: bool = False

    def validate(self) -> "ScanObjectNNConfig":
        super().validate()
        if self.shape != "points":
            raise ValueError(f"dataset.shape={self.shape}: ScanObjectNN holds point clouds only; "
                             "use dataset.shape=points")
        one_of("dataset.variant", self.variant, scanobjectnn.VARIANTS)
        one_of("dataset.format", self.format, SCANOBJECTNN_FORMATS)
        if self.format == "object_dataset" and self.variant not in scanobjectnn_objects.VARIANTS:
            raise ValueError(f"dataset.format=object_dataset: the per-object files hold "
                             f"{' and '.join(scanobjectnn_objects.VARIANTS)}; {self.variant} exists only in the h5 "
                             "release (dataset.format=h5)")
        fraction("dataset.val_fraction", self.val_fraction)
        return self

    def build(self, split: str, progress: bool = True) -> Dataset:
        require_root(self, scanobjectnn.LAYOUT)
        objects = self.format == "object_dataset"  # the per-object files: obj_bg / obj_only at any point count
        reader = scanobjectnn_objects.ScanObjectNNObjects if objects else scanobjectnn.ScanObjectNN
        return reader(self.root, split, variant=self.variant, num_points=self.num_points,
                      val_fraction=self.val_fraction, seed=self.seed, strict=self.strict)


@register("shapenet")
@dataclass
class ShapeNetConfig(DatasetConfig):
    """ShapeNetCore55 (ShapeNetCore.v2, 55 synsets) with the SHREC'17 split.

    ``split_csv``: the split (null: ``<root>/all.csv``); ``synset_dict``: synset id -> name (null:
    ``<root>/shapenet_synset_dict_v2.json``). Meshes are preprocessed once into ``cache_dir``/shapenet,
    simplified to about ``max_vertices`` vertices (0: never); ``strict``: a broken mesh stops the
    run instead of being skipped and counted."""

    name: str = "shapenet"
    root: str = "${paths.data_dir}/ShapeNetCore.v2"
    split_csv: Optional[str] = None
    synset_dict: Optional[str] = None
    max_vertices: int = 20000
    strict: bool = False
    cache_dir: str = "${paths.cache_dir}"

    def validate(self) -> "ShapeNetConfig":
        super().validate()
        at_least("dataset.max_vertices", self.max_vertices, 0)
        return self

    def build(self, split: str, progress: bool = True) -> Dataset:
        require_root(self, shapenet.LAYOUT)
        return shapenet.ShapeNetCore(self.root, split, split_csv=self.split_csv, synset_dict=self.synset_dict,
                                     cache_dir=Path(self.cache_dir) / "shapenet", num_points=self.num_points,
                                     max_vertices=self.max_vertices, seed=self.seed, strict=self.strict,
                                     as_points=self.shape == "points", progress=progress)


@register("shapenet_parts")
@dataclass
class ShapeNetPartsConfig(DatasetConfig):
    """ShapeNet Parts: 16 categories of point clouds with a part label per point (50 parts).

    The PointNet++ release (``data/shapenet_parts.py``), read once into ``cache_dir``/shapenet_parts
    with ``num_points`` points per shape; items carry ``part_labels`` (global part ids) beside the
    category ``label``. Point clouds only (``shape=points``); ``strict``: a broken point file stops
    the run instead of being skipped and counted (a part outside its category always stops it)."""

    name: str = "shapenet_parts"
    has_parts: ClassVar[bool] = True
    root: str = "${paths.data_dir}/shapenetcore_partanno_segmentation_benchmark_v0_normal"
    shape: str = "points"
    num_points: int = 2048
    strict: bool = False
    cache_dir: str = "${paths.cache_dir}"

    def validate(self) -> "ShapeNetPartsConfig":
        super().validate()
        if self.shape != "points":
            raise ValueError(f"dataset.shape={self.shape}: ShapeNet Parts holds point clouds only (no meshes); "
                             "use dataset.shape=points")
        return self

    def build(self, split: str, progress: bool = True) -> Dataset:
        from . import shapenet_parts

        require_root(self, shapenet_parts.LAYOUT)
        return shapenet_parts.ShapeNetParts(self.root, split, cache_dir=Path(self.cache_dir) / "shapenet_parts",
                                            num_points=self.num_points, seed=self.seed, strict=self.strict,
                                            progress=progress)
