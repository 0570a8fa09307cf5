"""Dataset registry: ``build_dataset(cfg.dataset, split)`` for every ``dataset=`` option.

Every dataset yields ``collate_shapes`` items (``points``, ``label``, ``name``, and ``verts`` /
``faces`` for meshes) and has ``classes`` (sorted names; label = index). A dataset that is not
on disk fails with ``DatasetNotFound`` naming the path and the layout it expects.
"""
from __future__ import annotations

from pathlib import Path

from torch.utils.data import Dataset

from ..schema import DatasetConfig
from .mesh_io import DatasetNotFound
from .modelnet import LAYOUT as MODELNET_LAYOUT
from .modelnet import ModelNetMeshes
from .synthetic import SyntheticShapes

# What each real dataset's folder must contain.
LAYOUTS = {
    "modelnet40": MODELNET_LAYOUT,
    "scanobjectnn": "<root>/main_split/{training,test}_objectdataset[_augmentedrot_scale75].h5 "
                    "(variant obj_bg: main_split, obj_only: main_split_nobg, pb_t50_rs: *_augmentedrot_scale75.h5)",
    "shapenet": "<root>/<synset>/<model_id>/models/model_normalized.obj (ShapeNetCore.v2) and "
                "<root>/all.csv (the SHREC17 split: id,synsetId,subSynsetId,modelId,split)",
}


def _require_root(cfg: DatasetConfig) -> Path:
    root = Path(cfg.root)
    if not root.is_dir():
        raise DatasetNotFound(f"dataset {cfg.name} not found at {root.resolve()}; expected layout: "
                              f"{LAYOUTS[cfg.name]}. Set dataset.root=PATH (or paths.data_dir=DIR).")
    return root


def build_dataset(cfg: DatasetConfig, split: str, progress: bool = True) -> Dataset:
    """The ``split`` ("train" | "val" | "test") of the dataset ``cfg`` describes."""
    if cfg.name == "synthetic":
        return SyntheticShapes(cfg.root, split, num_per_class=cfg.num_per_class, seed=cfg.seed, rotate=cfg.rotate,
                               num_points=cfg.num_points, as_points=cfg.shape == "points",
                               max_faces=cfg.max_faces, progress=progress)
    if cfg.rotate != "none":
        raise ValueError(f"dataset.rotate={cfg.rotate!r}: only dataset=synthetic rotates its shapes; "
                         f"use dataset.rotate=none for {cfg.name}")
    if cfg.name == "modelnet40":
        _require_root(cfg)
        return ModelNetMeshes(cfg.root, split, cache_dir=Path(cfg.cache_dir) / "modelnet", num_points=cfg.num_points,
                              max_vertices=cfg.max_vertices, val_fraction=cfg.val_fraction, seed=cfg.seed,
                              strict=cfg.strict, as_points=cfg.shape == "points", progress=progress)
    if cfg.name in LAYOUTS:
        root = _require_root(cfg)
        raise NotImplementedError(f"dataset {cfg.name} at {root}: its reader is not built yet "
                                  "(tracked by the real-datasets issue); only dataset=synthetic trains today")
    raise ValueError(f"dataset={cfg.name!r}: expected one of synthetic, {', '.join(LAYOUTS)}")
