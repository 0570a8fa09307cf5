"""Part segmentation metrics of the ShapeNet Parts benchmark: instance and class mean IoU.

Numpy / torch only. Part ids are GLOBAL (0..49 on ShapeNet Parts); ``parts_of`` maps a category
index to the sorted global part ids of that category (the dataset's ``parts_of``). The rules are
those of the benchmark's evaluation code (PointNet, PointNet++, DGCNN):

* a shape is scored over its own category's parts only: ``shape_iou`` is the mean, over those
  parts, of the part's IoU (intersection over union of the points predicted as the part and the
  points labelled with it); a part absent from both prediction and truth counts as 1;
* predictions are made among the category's parts only (``restrict``: the argmax over the
  category's logits, the category being known at test time);
* instance mIoU is the mean of ``shape_iou`` over all shapes; class mIoU is the mean over the
  categories present of each category's mean ``shape_iou`` (every category weighs the same,
  whatever its number of shapes).

Scores are fractions in [0, 1] (the paper's tables print them in percent).
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import torch


def _numpy(x) -> np.ndarray:
    """``x`` (a tensor on any device, an array, a list) as a numpy array."""
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy()
    return np.asarray(x)


def _parts(parts_of: Mapping, category) -> list[int]:
    """The part ids of ``category``; one line naming the categories ``parts_of`` knows otherwise."""
    c = int(category)
    if c not in parts_of or not len(parts_of[c]):
        raise ValueError(f"category {c} has no parts in parts_of (categories: {sorted(parts_of)})")
    return [int(p) for p in parts_of[c]]


def _restrict_one(logits, parts: list[int]):
    """``logits [P, K]`` -> ``[P]`` global part ids, the argmax among ``parts``' columns."""
    if max(parts) >= logits.shape[-1]:
        raise ValueError(f"logits have {logits.shape[-1]} part columns; part {max(parts)} needs more")
    if isinstance(logits, torch.Tensor):
        ids = torch.as_tensor(parts, dtype=torch.long, device=logits.device)
        return ids[logits[..., ids].argmax(-1)]
    ids = np.asarray(parts, np.int64)
    return ids[np.asarray(logits)[..., ids].argmax(-1)]


def restrict(logits, category, parts_of: Mapping):
    """Predicted global part ids among the category's parts only.

    ``logits``: ``[P, K]`` (one shape; ``category`` an int) or ``[B, P, K]`` (``category`` an int
    for every shape, or B of them), K >= the largest part id + 1 (50 on ShapeNet Parts); a tensor
    or an array. Returns ``[P]`` / ``[B, P]`` global part ids (long tensor / int64 array, as the
    input): per point the part of ``parts_of[category]`` with the largest logit (ties: the lowest
    part id). A part of another category is never predicted, however large its logit."""
    if logits.ndim == 2:
        return _restrict_one(logits, _parts(parts_of, category))
    if logits.ndim != 3:
        raise ValueError(f"restrict: logits of shape {tuple(logits.shape)}; expected [P, K] or [B, P, K]")
    cats = _numpy(category).reshape(-1)
    if len(cats) == 1:
        cats = np.repeat(cats, logits.shape[0])
    if len(cats) != logits.shape[0]:
        raise ValueError(f"restrict: {len(cats)} categories for a batch of {logits.shape[0]} shapes")
    out = [_restrict_one(lg, _parts(parts_of, c)) for lg, c in zip(logits, cats)]
    return torch.stack(out) if isinstance(logits, torch.Tensor) else np.stack(out)


def shape_iou(pred, true, parts: Sequence[int]) -> float:
    """The IoU of one shape: the mean over ``parts`` (its category's global part ids) of
    ``|pred == p and true == p| / |pred == p or true == p|``, where a part absent from both
    ``pred`` and ``true`` counts as 1 (the benchmark's rule).

    ``pred``, ``true``: ``[P]`` global part ids of the same points. A predicted id outside
    ``parts`` matches no part: it only lowers the IoU of the point's true part."""
    pred, true = _numpy(pred).reshape(-1), _numpy(true).reshape(-1)
    if len(pred) != len(true):
        raise ValueError(f"shape_iou: {len(pred)} predicted labels for {len(true)} true labels")
    if not len(parts):
        raise ValueError("shape_iou: no parts to score")
    ious = []
    for p in parts:
        inter = np.count_nonzero((pred == p) & (true == p))
        union = np.count_nonzero((pred == p) | (true == p))
        ious.append(1.0 if union == 0 else inter / union)
    return float(np.mean(ious))


def part_miou(preds, trues, categories, parts_of: Mapping, classes: Sequence[str]) -> dict:
    """Instance and class mIoU of N shapes.

    ``preds``, ``trues``: N per-shape ``[P_i]`` global part ids (a list, or ``[N, P]``);
    ``categories``: N category indices (keys of ``parts_of``, indices into ``classes``).
    Returns ``instance_miou`` (mean ``shape_iou`` over the N shapes), ``class_miou`` (mean over
    the categories present of their mean ``shape_iou``) and ``per_category``
    ``{class name: {"miou": mean shape_iou, "shapes": count}}`` for the categories present only."""
    cats = [int(c) for c in _numpy(categories).reshape(-1)]
    if not cats:
        raise ValueError("part_miou: no shapes")
    if len(preds) != len(cats) or len(trues) != len(cats):
        raise ValueError(f"part_miou: {len(preds)} predictions and {len(trues)} truths for {len(cats)} categories")
    ious = [shape_iou(p, t, _parts(parts_of, c)) for p, t, c in zip(preds, trues, cats)]
    per_category = {}
    for c in sorted(set(cats)):
        mine = [iou for iou, k in zip(ious, cats) if k == c]
        per_category[str(classes[c])] = {"miou": float(np.mean(mine)), "shapes": len(mine)}
    return {"instance_miou": float(np.mean(ious)),
            "class_miou": float(np.mean([v["miou"] for v in per_category.values()])),
            "per_category": per_category}
