"""``build_dataset(cfg.dataset, split)`` for every ``dataset=`` option, and what a dataset can
report of a run (its own view and retrieval metrics, where it defines them).

The options and their keys live in ``data/config.py`` (``OPTIONS["dataset"]``): each config class
checks its keys (``validate``) and reads its data (``build``); this module only dispatches to them.
"""
from __future__ import annotations

from torch.utils.data import Dataset

from .config import DatasetConfig


def build_dataset(cfg: DatasetConfig, split: str, progress: bool = True) -> Dataset:
    """The ``split`` ("train" | "val" | "test") of the dataset ``cfg`` (a registered dataset config)
    describes: ``cfg.validate()`` (one line naming a bad key), then its ``build``."""
    return cfg.validate().build(split, progress=progress)


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
