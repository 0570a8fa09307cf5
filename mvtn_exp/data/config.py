"""The dataset schema (``dataset=NAME``): which shapes, where they are, and how they are read."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

from ..config.checks import at_least, fraction, one_of
from .synthetic import ROTATIONS

DATASETS = ("synthetic", "synthetic_views", "modelnet40", "scanobjectnn", "shapenet")
SHAPES = ("mesh", "points")
VIEW_FAMILIES = ("cup", "decoys", "slab")  # dataset=synthetic_views families (data/synthetic_views.py FAMILIES)

SCANOBJECTNN_FORMATS = ("h5", "object_dataset")  # the h5 release; the per-object files


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
    (meshes), ``normal_resampled`` or ``ply_hdf5_2048`` (the PointNet authors' point releases);
    ScanObjectNN ``format``: ``h5`` (the h5 release, 2,048 points per cloud) or ``object_dataset``
    (the per-object files, any ``num_points``: the paper's 5,000, L251; obj_bg and obj_only only).
    ``variant``: ScanObjectNN variant (obj_bg, obj_only, pb_t50_rs); ``family``: the synthetic_views
    family (cup, decoys, slab; empty for every other dataset); ``val_fraction``: share of
    the official train split held out for model selection when a dataset has no val split.
    ``num_workers``: DataLoader worker processes; null: automatic (none on CPU, where the loader's
    work is small next to the step's; on CUDA up to 4, within the process's share of the cores:
    ``engine/loaders.workers``).
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
    family: str = ""
    format: str = "off"
    split_csv: Optional[str] = None
    synset_dict: Optional[str] = None
    val_fraction: float = 0.1
    num_workers: Optional[int] = None

    def validate(self) -> "DatasetConfig":
        one_of("dataset.name", self.name, DATASETS)
        one_of("dataset.shape", self.shape, SHAPES)
        one_of("dataset.rotate", self.rotate, ROTATIONS)
        if self.name == "scanobjectnn":
            if self.format == "off":  # (configs stored before ScanObjectNN had formats: the h5 release)
                self.format = "h5"
            one_of("dataset.format", self.format, SCANOBJECTNN_FORMATS)
            if self.format == "object_dataset" and self.variant == "pb_t50_rs":
                raise ValueError("dataset.format=object_dataset: the per-object files hold obj_bg and obj_only; "
                                 "pb_t50_rs exists only in the h5 release (dataset.format=h5)")
        else:
            one_of("dataset.format", self.format, ("off", "normal_resampled", "ply_hdf5_2048"))
        if self.name == "synthetic_views":
            one_of("dataset.family", self.family or "cup", VIEW_FAMILIES)
        elif self.family:
            raise ValueError(f"dataset.family={self.family}: only dataset=synthetic_views has families; drop it for "
                             f"dataset={self.name}")
        at_least("dataset.num_points", self.num_points, 1)
        at_least("dataset.seed", self.seed, 0)
        at_least("dataset.max_faces", self.max_faces, 1)
        at_least("dataset.max_vertices", self.max_vertices, 0)
        if self.num_workers is not None:
            at_least("dataset.num_workers", self.num_workers, 0)
        if len(self.num_per_class) != 3 or min(self.num_per_class) < 1:
            raise ValueError(f"dataset.num_per_class={list(self.num_per_class)}: expected 3 counts >= 1 "
                             "(train, val, test)")
        fraction("dataset.val_fraction", self.val_fraction)
        return self
