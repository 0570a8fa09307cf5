"""What part segmentation costs per shape at inference, stage by stage, against classification.

For each M the same renderer (the training default: soft, smooth shading), fixed spherical views,
the embedded part meshes and the default networks (``segnet=fcn_small``; ``mvnet=mvcnn`` on
``small_cnn``), both freshly initialised (time does not depend on the weights). One batch of
``--batch`` test shapes, forward in eval mode under ``no_grad``; each stage timed alone, median of
``--repeats`` runs, divided by the batch:

- segmentation: R (the images), the index (what each pixel shows, ``primitive_index``), C (the
  2D network over every view), lift (fuse the views' logits on the points, fill the unseen ones,
  predict among the category's parts);
- classification: R and C (MVCNN) on the same images.

Run: ``python scripts/studies/segmentation_time.py [--views 1 4 8 12] [--batch 8]`` (Markdown on stdout).
"""
from __future__ import annotations

import argparse

import torch

from mvtn_exp.bench.timing import med_ms, time_runs
from mvtn_exp.config.compose import compose_train_config
from mvtn_exp.data.collate import collate_shapes
from mvtn_exp.data.datasets import build_dataset
from mvtn_exp.model import build_mvtn
from mvtn_exp.tasks.heads import build_head


def _models(M: int, image_size: int, cache: str | None):
    common = ["dataset=synthetic_parts", "selector=spherical", f"views={M}", f"image_size={image_size}"]
    common += [f"dataset.root={cache}"] if cache else []
    seg_cfg = compose_train_config(common + ["task=segmentation"])
    cls_cfg = compose_train_config(common)
    ds = build_dataset(seg_cfg.dataset, "test", progress=False)
    head = build_head(seg_cfg.task, ds)
    torch.manual_seed(0)
    seg = build_mvtn(seg_cfg, head.num_outputs).eval()
    cls = build_mvtn(cls_cfg, len(ds.classes)).eval()
    return ds, head, seg, cls


def row(M: int, batch: int, image_size: int, repeats: int, cache: str | None = None) -> dict:
    """ms per shape of each stage at M views (module docstring)."""
    ds, head, seg, cls = _models(M, image_size, cache)
    b = collate_shapes([ds[i] for i in range(batch)])
    dev = torch.device("cpu")
    with torch.no_grad():
        views = seg.select(b)
        images = seg.render(b, *views)
        logits, _ = seg.classify(images, views, b)
        targets = head.targets(seg, b, views)
        stages = {"render": lambda: seg.render(b, *views), "index": lambda: seg.primitive_index(b, *views),
                  "C seg": lambda: seg.classify(images, views, b), "lift": lambda: head.predict(logits, targets, b),
                  "C cls": lambda: cls.classify(images, views, b)}
        ms = {k: med_ms(time_runs(fn, dev, repeats, 60.0)) / batch for k, fn in stages.items()}
    seg_total = ms["render"] + ms["index"] + ms["C seg"] + ms["lift"]
    return {"M": M, **ms, "segmentation": seg_total, "classification": ms["render"] + ms["C cls"],
            "ratio": seg_total / (ms["render"] + ms["C cls"])}


def markdown(rows: list[dict]) -> str:
    head = ("| M | R | index | C (fcn_small) | lift | segmentation | C (MVCNN small_cnn) | classification | "
            "segmentation / classification |\n|---|---|---|---|---|---|---|---|---|\n")
    return head + "".join(f"| {r['M']} | {r['render']:.2f} | {r['index']:.2f} | {r['C seg']:.2f} | {r['lift']:.2f} | "
                          f"{r['segmentation']:.2f} | {r['C cls']:.2f} | {r['classification']:.2f} | "
                          f"{r['ratio']:.2f} |\n" for r in rows)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--views", type=int, nargs="+", default=[1, 4, 8, 12])
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--image-size", type=int, default=64)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--cache", default=None, help="dataset.root of synthetic_parts (default: the config's)")
    a = p.parse_args()
    torch.set_num_threads(torch.get_num_threads())
    print("ms per shape, inference (eval, no_grad), CPU, "
          f"{a.image_size} px, batch {a.batch}, {torch.get_num_threads()} threads\n")
    print(markdown([row(M, a.batch, a.image_size, a.repeats, a.cache) for M in a.views]))


if __name__ == "__main__":
    main()
