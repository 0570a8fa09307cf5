"""The accuracy level of detail costs: a trained checkpoint evaluated with LOD at several budgets.

The model is rebuilt from ``ckpt`` (its stored config) and evaluated on a split without LOD, with
the renderer's default rule (32 faces per pixel row, silhouette-checked), and with the former area
rule at 1/8 and 1/16 face per pixel, each with and without the silhouette check
(``renderer.lod_min_iou=0``). Only the evaluation renders change; the weights are the same.

Run: ``python scripts/studies/lod_accuracy.py --ckpt RUN/best.pt [--split test]`` (Markdown on stdout).
"""
from __future__ import annotations

import argparse
from dataclasses import replace

import torch

from mvtn_exp.data.datasets import build_dataset
from mvtn_exp.runtime import checkpoint
from mvtn_exp.evaluation.evaluate import config_from_checkpoint, load_model
from mvtn_exp.engine.trainer import eval_loader
from mvtn_exp.render import lod
from mvtn_exp.tasks import classification

SETTINGS = (None, {}, {"lod_faces_per_pixel": 0.125}, {"lod_faces_per_pixel": 0.125, "lod_min_iou": 0.0},
            {"lod_faces_per_pixel": 0.0625}, {"lod_faces_per_pixel": 0.0625, "lod_min_iou": 0.0})


def rows(ckpt, split: str = "test", settings=SETTINGS) -> list[dict]:
    state = checkpoint.load(ckpt)
    cfg = config_from_checkpoint(state, ckpt)
    cfg.logger.progress = False
    ds = build_dataset(cfg.dataset, split, progress=False)
    out = []
    for kw in settings:
        rc = cfg.renderer if kw is None else replace(cfg.renderer, lod=True, **kw)
        c = replace(cfg, renderer=rc)
        model = load_model(c, state, len(ds.classes), ckpt, "cpu")
        res = classification.evaluate(model, eval_loader(c, ds), len(ds.classes), desc=split, progress=False)
        rule = "-" if kw is None else (
            ("32 per row" if "lod_faces_per_pixel" not in kw else f"{kw['lod_faces_per_pixel']:g} per pixel")
            + (", unchecked" if kw.get("lod_min_iou") == 0.0 else ", checked"))
        budget = "-" if kw is None else lod.face_budget(c.image_size, rc.lod_faces_per_row, rc.lod_faces_per_pixel)
        out.append(dict(lod="false" if kw is None else "true", rule=rule, budget=budget, size=c.image_size,
                        acc=res["acc"], loss=res["loss"], n=res["n"]))
    return out


def to_markdown(table: list[dict]) -> str:
    size = table[0]["size"]
    lines = [f"| renderer.lod | budget rule | faces at {size} px | test acc | test loss |", "|---|---|---|---|---|"]
    lines += [f"| {r['lod']} | {r['rule']} | {r['budget']} | {r['acc']:.4f} | {r['loss']:.4f} |" for r in table]
    return "\n".join(lines)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--ckpt", required=True)
    p.add_argument("--split", default="test")
    args = p.parse_args(argv)
    torch.manual_seed(0)
    print(to_markdown(rows(args.ckpt, args.split)))


if __name__ == "__main__":
    main()
