"""The task heads (``task=NAME``): what the one training loop asks of a task.

``build_head(cfg.task, dataset)`` gives an object with

- ``num_outputs``: C's outputs (classes; parts and the background); ``names``: the confusion
  matrix's rows (classes; parts); ``score``: the key of ``evaluate``'s result that model
  selection maximises on the validation split (``acc``; ``instance_miou``);
- ``targets(model, batch, views)``: what C's output is compared with, for views ``[B, M]`` as R
  renders them; ``head(logits, targets)``: C's loss (a scalar); ``hits(logits, targets)``: the
  share right, for the training accuracy;
- ``evaluate(model, loader, desc, progress, transform) -> dict``: ``acc``, ``mean_class_acc``,
  ``per_class_acc``, ``confusion``, ``loss``, ``n`` (shapes), the views ``azim`` / ``elev`` /
  ``dist [N, M]``, ``labels [N]``, ``images`` and the task's own keys; ``GATHERED`` / ``merge``:
  the result of several processes' shards;
- ``headline(res)``, ``metrics(res)``, ``summary_line(res)``: what the epoch line, ``metrics.json``
  and the run's last line add.
"""
from __future__ import annotations

from .classification import Classification
from .config import TaskConfig
from .segmentation import Segmentation

HEADS = {"classification": Classification, "segmentation": Segmentation}


def build_head(cfg: TaskConfig, dataset):
    """The head of ``task=cfg.name`` for ``dataset`` (its classes, and for segmentation its parts)."""
    return HEADS[cfg.name](cfg, dataset)
