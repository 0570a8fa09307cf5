"""Each part's IoU over all test points, from finished segmentation runs' part confusion.

For every run folder under the given folders (a ``metrics.json`` with ``part_names``), the IoU of
each part over the points of the whole test split (``|true and predicted| / |true or predicted|``
from ``confusion_matrix``), averaged over the runs of each side (``--side KEY``: a config key
whose value names the side, e.g. ``selector.name``). Unlike the benchmark's instance mIoU (per
shape, then averaged), it shows which parts the network gets and which it misses.

``--curve``: instead, each side's instance mIoU and coverage at each M (mean ± sample std over
its runs, and their count), for a sweep whose M differ (too few seeds to pair: ``mvtn-compare``
pairs when every M has two seeds or more).

Run: ``python scripts/studies/part_iou.py outputs/parts/m4 [--side selector.name] [--curve]`` (Markdown on stdout).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def part_iou(confusion) -> np.ndarray:
    """``confusion [P, P]`` (rows: true, columns: predicted) -> ``[P]`` IoU (0 for a part neither
    true nor predicted anywhere)."""
    c = np.asarray(confusion, dtype=np.float64)
    inter = np.diag(c)
    union = c.sum(0) + c.sum(1) - inter
    return np.where(union > 0, inter / np.maximum(union, 1), 0.0)


def _value(config: dict, dotted: str):
    node = config
    for part in dotted.split("."):
        node = node[part]
    return node


def sides(folders, side: str) -> tuple[list[str], dict]:
    """``(part names, {side value: [P] mean IoU over its runs, and their count}``."""
    per, names = {}, None
    for folder in folders:
        for path in sorted(Path(folder).rglob("metrics.json")):
            m = json.loads(path.read_text())
            if "part_names" not in m:
                continue
            names = m["part_names"]
            per.setdefault(str(_value(m["config"], side)), []).append(part_iou(m["confusion_matrix"]))
    if names is None:
        raise SystemExit(f"part_iou: no segmentation run (metrics.json with part_names) under {list(map(str, folders))}")
    return names, {k: (np.mean(v, 0), len(v)) for k, v in per.items()}


def markdown(names: list[str], by_side: dict) -> str:
    keys = list(by_side)
    head = "| part | " + " | ".join(f"{k} ({by_side[k][1]} runs)" for k in keys) + " |\n"
    head += "|---|" + "---|" * len(keys) + "\n"
    return head + "".join(f"| {n} | " + " | ".join(f"{by_side[k][0][i]:.3f}" for k in keys) + " |\n"
                          for i, n in enumerate(names))


def curve(folders, side: str) -> str:
    """``| side | M | runs | instance mIoU | coverage |`` per side and M, from ``metrics.json``."""
    cells: dict = {}
    for folder in folders:
        for path in sorted(Path(folder).rglob("metrics.json")):
            m = json.loads(path.read_text())
            if "test_instance_miou" in m:
                key = (str(_value(m["config"], side)), int(m["config"]["views"]))
                cells.setdefault(key, []).append((m["test_instance_miou"], m["test_coverage"]))
    out = "| side | M | runs | test_instance_miou | test_coverage |\n|---|---|---|---|---|\n"
    for (name, M), vals in sorted(cells.items()):
        v = np.asarray(vals)
        sd = v.std(0, ddof=1) if len(v) > 1 else np.zeros(2)
        out += f"| {name} | {M} | {len(v)} | {v[:, 0].mean():.3f} ± {sd[0]:.3f} | {v[:, 1].mean():.3f} ± {sd[1]:.3f} |\n"
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("folders", nargs="+")
    p.add_argument("--side", default="selector.name")
    p.add_argument("--curve", action="store_true", help="each side's instance mIoU and coverage at each M")
    a = p.parse_args()
    print(curve(a.folders, a.side) if a.curve else markdown(*sides(a.folders, a.side)))


if __name__ == "__main__":
    main()
