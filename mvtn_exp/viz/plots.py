"""Figures written as PNG with matplotlib (Agg backend: no display needed)."""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np


def pyplot():
    """matplotlib.pyplot with the Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path) -> Path:
    """Write ``fig`` as a PNG at ``path`` (folders created) and close it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    pyplot().close(fig)
    return path


def occlusion_png(results: dict, directions: Sequence[str], path) -> Path:
    """Accuracy vs occlusion ratio, one line per direction and the mean. ``results``:
    ``{ratio_str: {"per_direction": {d: acc}, "mean_acc": acc}}``."""
    plt = pyplot()
    ratios = [float(r) for r in results]
    fig, ax = plt.subplots(figsize=(5, 3.5), dpi=100)
    for d in directions:
        ax.plot(ratios, [results[r]["per_direction"][d] for r in results], marker=".", lw=1, label=d)
    ax.plot(ratios, [results[r]["mean_acc"] for r in results], color="black", lw=2, marker="o", label="mean")
    ax.set_xlabel("occlusion ratio")
    ax.set_ylabel("accuracy")
    ax.set_ylim(0, 1)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    return save_figure(fig, path)


def confusion_png(confusion: Sequence[Sequence[int]], classes: Sequence[str], path, title: str = "") -> Path:
    """Row-normalised confusion matrix (rows: true class, columns: predicted) with the counts
    written in the cells -> ``path`` (PNG)."""
    plt = pyplot()
    conf = np.asarray(confusion, dtype=np.int64)
    k = conf.shape[0]
    if conf.shape != (k, k) or len(classes) != k:
        raise ValueError(f"confusion_png: confusion {conf.shape} does not match {len(classes)} classes")
    rates = conf / np.maximum(conf.sum(1, keepdims=True), 1)
    size = max(4.0, 0.45 * k + 2.0)
    fig, ax = plt.subplots(figsize=(size, size), dpi=100)
    ax.imshow(rates, cmap="Blues", vmin=0.0, vmax=1.0)
    ax.set_xticks(range(k), labels=list(classes), rotation=90, fontsize=8)
    ax.set_yticks(range(k), labels=list(classes), fontsize=8)
    ax.set_xlabel("predicted")
    ax.set_ylabel("true")
    if k <= 40:
        for i in range(k):
            for j in range(k):
                if conf[i, j]:
                    ax.text(j, i, str(conf[i, j]), ha="center", va="center", fontsize=6,
                            color="white" if rates[i, j] > 0.5 else "black")
    if title:
        ax.set_title(title, fontsize=10)
    fig.tight_layout()
    return save_figure(fig, path)
