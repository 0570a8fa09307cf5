"""The ceiling of part segmentation with fixed views: a perfect 2D network, lifted.

C's output is replaced by the true label images of the views (the part each pixel shows, or the
background), then lifted to the points as evaluation does (``task.fuse``, unseen points from their
nearest seen point, the argmax among the category's parts). What is left of a perfect score is what
the views miss: points no view sees, filled from the wrong part, and pixels too few to carry a small
part. No training: the selector's views are its layout (a learned G would start from these).

Run: ``python scripts/studies/parts_oracle.py [--selectors spherical circular] [--views 1 4 8 12]
[--split test] [--parts] [overrides ...]`` (Markdown on stdout; overrides as ``mvtn-train``'s, e.g.
``dataset.seed=1 image_size=128``). ``--parts`` adds each part's IoU over all the split's points
(as ``part_iou.py`` counts a trained C's), one column per selector and M.
"""
from __future__ import annotations

import argparse

import torch

from mvtn_exp.config.compose import compose_train_config
from mvtn_exp.data.collate import collate_shapes
from mvtn_exp.data.datasets import build_dataset
from mvtn_exp.model import build_mvtn
from mvtn_exp.tasks import part_metrics
from mvtn_exp.tasks.heads import build_head


def oracle(selector: str, M: int, split: str, overrides=(), batch: int = 8) -> dict:
    """Instance mIoU and coverage of the true label images lifted, over ``split``."""
    cfg = compose_train_config(["task=segmentation", "dataset=synthetic_parts", f"selector={selector}", f"views={M}",
                                *overrides])
    ds = build_dataset(cfg.dataset, split, progress=False)
    head = build_head(cfg.task, ds)
    model = build_mvtn(cfg, head.num_outputs).eval()
    ious, seen_share = [], []
    K = len(head.names)
    confusion = torch.zeros(K * K, dtype=torch.long)  # (true, predicted) over all points
    with torch.no_grad():
        for start in range(0, len(ds), batch):
            b = collate_shapes([ds[i] for i in range(start, min(start + batch, len(ds)))])
            t = head.targets(model, b, model.select(b))
            perfect = torch.nn.functional.one_hot(t.pixels, head.num_outputs).permute(0, 1, 4, 2, 3).float()
            pred, seen = head.predict(perfect, t, b)
            ious += [part_metrics.shape_iou(p, q, head.parts_of[int(c)]) for p, q, c in zip(pred, t.points, b["labels"])]
            seen_share.append(seen.float().mean(1))
            confusion += torch.bincount((t.points * K + pred).reshape(-1), minlength=K * K)
    c = confusion.view(K, K).double()
    inter, union = c.diag(), c.sum(0) + c.sum(1) - c.diag()
    parts = {name: float(inter[k] / union[k]) for k, name in enumerate(head.names) if union[k] > 0}
    return {"selector": selector, "M": M, "instance_miou": sum(ious) / len(ious), "parts": parts,
            "coverage": float(torch.cat(seen_share).mean()), "shapes": len(ious), "image_size": cfg.image_size}


def markdown(rows: list[dict]) -> str:
    return ("| views | M | image px | instance mIoU (perfect C) | coverage | shapes |\n|---|---|---|---|---|---|\n"
            + "".join(f"| {r['selector']} | {r['M']} | {r['image_size']} | {r['instance_miou']:.3f} | "
                      f"{r['coverage']:.3f} | {r['shapes']} |\n" for r in rows))


def parts_markdown(rows: list[dict]) -> str:
    """Each part's IoU (rows) for each selector and M (columns)."""
    names = sorted({name for r in rows for name in r["parts"]})
    head = "| part | " + " | ".join(f"{r['selector']} M = {r['M']}" for r in rows) + " |\n"
    lines = [f"| {n} | " + " | ".join(f"{r['parts'][n]:.3f}" if n in r["parts"] else "-" for r in rows) + " |\n"
             for n in names]
    return head + "|---" * (len(rows) + 1) + "|\n" + "".join(lines)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--selectors", nargs="+", default=["spherical", "circular"])
    p.add_argument("--views", type=int, nargs="+", default=[1, 4, 8, 12])
    p.add_argument("--split", default="test")
    p.add_argument("--parts", action="store_true", help="add each part's IoU")
    p.add_argument("overrides", nargs="*")
    a = p.parse_args()
    rows = [oracle(s, M, a.split, a.overrides) for s in a.selectors for M in a.views]
    print(markdown(rows))
    if a.parts:
        print(parts_markdown(rows))


if __name__ == "__main__":
    main()
