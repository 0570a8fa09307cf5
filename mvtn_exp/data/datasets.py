"""Dataset registry: ``build_dataset(cfg.dataset, split)`` for every ``dataset=`` option.

Every dataset yields ``collate_shapes`` items (``points``, ``label``, ``name``, and ``verts`` /
``faces`` for meshes) and has ``classes`` (sorted names; label = index). A dataset that is not
on disk fails with ``DatasetNotFound`` naming the path and the layout it expects.
"""
from __future__ import annotations

from pathlib import Path

from torch.utils.data import Dataset

from .config import DatasetConfig
from .mesh_io import DatasetNotFound
from .modelnet import LAYOUT as MODELNET_LAYOUT
from .modelnet import ModelNetMeshes
from .modelnet_points import LAYOUTS as MODELNET_POINT_LAYOUTS
from .modelnet_points import ModelNetPoints
from .scanobjectnn import LAYOUT as SCANOBJECTNN_LAYOUT
from .scanobjectnn import VARIANTS as SCANOBJECTNN_VARIANTS
from .scanobjectnn import ScanObjectNN
from .scanobjectnn_objects import ScanObjectNNObjects
from .shapenet import LAYOUT as SHAPENET_LAYOUT
from .shapenet import ShapeNetCore
from .synthetic import SyntheticShapes
from .synthetic_views import SyntheticViews

# What each real dataset's folder must contain.
LAYOUTS = {
    "modelnet40": MODELNET_LAYOUT,
    "scanobjectnn": SCANOBJECTNN_LAYOUT,
    "shapenet": SHAPENET_LAYOUT,
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
    if cfg.name == "synthetic_views":
        return SyntheticViews(cfg.root, split, num_per_class=cfg.num_per_class, seed=cfg.seed, rotate=cfg.rotate,
                              num_points=cfg.num_points, as_points=cfg.shape == "points",
                              max_faces=cfg.max_faces, progress=progress, family=cfg.family or "cup")
    if cfg.family:
        raise ValueError(f"dataset.family={cfg.family!r}: only dataset=synthetic_views has families; "
                         f"drop it for {cfg.name}")
    if cfg.rotate != "none":
        raise ValueError(f"dataset.rotate={cfg.rotate!r}: only dataset=synthetic and synthetic_views rotate their "
                         f"shapes; use dataset.rotate=none for {cfg.name}")
    if cfg.name == "modelnet40" and cfg.format != "off":
        if cfg.shape != "points":
            raise ValueError(f"dataset.format={cfg.format}: point clouds only; use dataset.shape=points")
        if not Path(cfg.root).is_dir():
            raise DatasetNotFound(f"dataset modelnet40 ({cfg.format}) not found at {Path(cfg.root).resolve()}; "
                                  f"expected layout: {MODELNET_POINT_LAYOUTS[cfg.format]}")
        return ModelNetPoints(cfg.root, split, format=cfg.format, num_points=cfg.num_points,
                              val_fraction=cfg.val_fraction, seed=cfg.seed, strict=cfg.strict)
    if cfg.name == "modelnet40":
        _require_root(cfg)
        return ModelNetMeshes(cfg.root, split, cache_dir=Path(cfg.cache_dir) / "modelnet", num_points=cfg.num_points,
                              max_vertices=cfg.max_vertices, val_fraction=cfg.val_fraction, seed=cfg.seed,
                              strict=cfg.strict, as_points=cfg.shape == "points", progress=progress)
    if cfg.name == "scanobjectnn":
        if cfg.variant not in SCANOBJECTNN_VARIANTS:
            raise ValueError(f"dataset.variant={cfg.variant!r}: expected one of {', '.join(SCANOBJECTNN_VARIANTS)}")
        if cfg.shape != "points":
            raise ValueError("dataset.shape=mesh: ScanObjectNN holds point clouds only; use dataset.shape=points")
        _require_root(cfg)
        if cfg.format == "object_dataset":  # the per-object files: OBJ_BG / OBJ_ONLY at any point count
            return ScanObjectNNObjects(cfg.root, split, variant=cfg.variant, num_points=cfg.num_points,
                                       val_fraction=cfg.val_fraction, seed=cfg.seed, strict=cfg.strict)
        return ScanObjectNN(cfg.root, split, variant=cfg.variant, num_points=cfg.num_points,
                            val_fraction=cfg.val_fraction, seed=cfg.seed, strict=cfg.strict)
    if cfg.name == "shapenet":
        _require_root(cfg)
        return ShapeNetCore(cfg.root, split, split_csv=cfg.split_csv, synset_dict=cfg.synset_dict,
                            cache_dir=Path(cfg.cache_dir) / "shapenet", num_points=cfg.num_points,
                            max_vertices=cfg.max_vertices, seed=cfg.seed, strict=cfg.strict,
                            as_points=cfg.shape == "points", progress=progress)
    raise ValueError(f"dataset={cfg.name!r}: expected one of synthetic, synthetic_views, {', '.join(LAYOUTS)}")


def view_report(dataset, res: dict) -> dict:
    """What a dataset can say about the predicted views of ``res`` (a ``classification.evaluate``
    result on it, same order): ``dataset.view_report(res)`` where the dataset defines one
    (``synthetic_views``: where its class detail shows), else ``{}``."""
    report = getattr(dataset, "view_report", None)
    return report(res) if report is not None else {}


def view_headline(dataset, report: dict) -> dict:
    """The entries of ``report`` (``view_report``'s) the dataset names in ``VIEW_HEADLINE``, the
    ones a training log shows every epoch (``{}`` for a dataset that names none)."""
    return {k: report[k] for k in getattr(dataset, "VIEW_HEADLINE", ()) if report.get(k) is not None}


def view_figures(dataset, res: dict, run_dir) -> None:
    """The dataset's own figures of the predicted views (``dataset.view_figures``), if it has any."""
    figures = getattr(dataset, "view_figures", None)
    if figures is not None:
        figures(res, run_dir)


def retrieval_report(dataset, q_z, q_y, list_length: int) -> dict:
    """A dataset's own retrieval metrics of query features ``q_z`` (``dataset.retrieval_report``:
    ShapeNet's SHREC'17 grading), else ``{}``."""
    report = getattr(dataset, "retrieval_report", None)
    return report(q_z, q_y, list_length) if report is not None else {}
