"""Do ``mvtn_poi``'s descriptors tell where the detail is? A supervised per-point oracle (``synthetic_views``).

``python scripts/studies/poi_oracle.py --family decoys --points 256`` reads the train and validation
splits of a ``synthetic_views`` family (never test), computes ``mvtn_poi``'s rotation-invariant
descriptors of each shape's first ``--points`` points (what G reads with ``selector.num_points``),
and fits a per-point classifier (gradient-boosted trees) on the train shapes to tell the points
inside the cup that holds the detail (privileged: the dataset's detail frame). On the validation
shapes it then does what G does with its per-point scores: the softmax of the log-scores (at
temperature ``--temperature``) weights the centred points into a point of interest, and the view
looks from its direction. Printed per descriptor set (all, each left out, concavity alone): the
share of validation shapes whose view sees the detail, and the share whose highest-scored point lies
in the detail's cup. Classes without a detail (``empty``) are left out.

What it bounds: a G of this form (a per-point score of these descriptors) can aim no better than
this oracle, which is *told* the answer; a share near 1 means the descriptors carry where the
detail is and what G lacks end to end is the signal. Not a method (it reads the detail frame).
"""
from __future__ import annotations

import argparse
from typing import Sequence

import numpy as np
import torch


def load(root: str, family: str, split: str, seed: int, num_per_class: Sequence[int], points: int,
         max_shapes: int | None = None):
    """Shapes of ``split`` with a detail -> (centred points ``[B, N, 3]``, descriptors ``[B, N, D]``,
    in-cup labels ``[B, N]`` bool, detail frame ``(anchor, axis, size)`` each ``[B, 3]``)."""
    from mvtn_exp.data.synthetic_views import SyntheticViews
    from mvtn_exp.selectors.poi import invariant_descriptors

    ds = SyntheticViews(root, split, tuple(num_per_class), seed=seed, family=family, progress=False)
    idx = [i for i in range(len(ds)) if ds.classes[int(ds[i]["label"])] != "empty"][:max_shapes]
    raw = torch.stack([ds[i]["points"][:points] for i in idx]).float()
    P = raw - raw.mean(1, keepdim=True)
    frame = tuple(ds._a[k][idx] for k in ("detail_anchor", "detail_axis", "detail_size"))
    return P, invariant_descriptors(P), in_detail_cup(raw, *frame), frame


def in_detail_cup(points: torch.Tensor, anchor, axis, size) -> torch.Tensor:
    """``[B, N]``: the point (dataset frame) lies in the cylinder of the detail's cup: above its
    floor, below its rim, within its inner radius (``size``: r_in, h, rd)."""
    anchor, axis, size = (torch.as_tensor(np.asarray(x), dtype=points.dtype) for x in (anchor, axis, size))
    rel = points - anchor[:, None]
    up = (rel * axis[:, None]).sum(-1)
    lateral = (rel - up[..., None] * axis[:, None]).norm(dim=-1)
    return (up > -1e-3) & (up < size[:, 1:2]) & (lateral < size[:, 0:1])


def view_share(scores: torch.Tensor, points: torch.Tensor, frame, temperature: float) -> float:
    """Share of shapes whose view, from the direction of the softmax(log score / T)-weighted point
    of interest (``scores [B, N]`` in (0, 1], centred ``points [B, N, 3]``), sees the detail."""
    from mvtn_exp.data.view_detail import sees_detail

    w = torch.softmax(torch.log(scores.clamp_min(1e-6)) / temperature, 1)
    d = torch.nn.functional.normalize((w[..., None] * points).sum(1), dim=-1, eps=1e-12).numpy()
    return float(sees_detail(*frame, 2.2 * d[:, None])[:, 0].mean())


def oracle_scores(d_train: torch.Tensor, y_train: torch.Tensor, d_val: torch.Tensor, seed: int = 0) -> torch.Tensor:
    """Per-point probability of lying in the detail's cup, ``[B, N]``, from a classifier fitted on the train points."""
    from sklearn.ensemble import HistGradientBoostingClassifier

    D = d_train.shape[-1]
    clf = HistGradientBoostingClassifier(max_iter=200, random_state=seed)
    clf.fit(d_train.reshape(-1, D).numpy(), y_train.reshape(-1).numpy())
    return torch.from_numpy(clf.predict_proba(d_val.reshape(-1, D).numpy())[:, 1].reshape(d_val.shape[:2]).copy()).float()


def run(root: str, family: str, points: int, seed: int = 0, num_per_class=(48, 12, 24), temperature: float = 0.05,
        max_shapes: int | None = None) -> list[dict]:
    from mvtn_exp.selectors.poi import DESCRIPTORS, descriptor_columns

    Ptr, Dtr, ytr, _ = load(root, family, "train", seed, num_per_class, points, max_shapes)
    Pva, Dva, yva, frame = load(root, family, "val", seed, num_per_class, points, max_shapes)
    sets = ([("all", DESCRIPTORS)] + [(f"all but {d}", tuple(x for x in DESCRIPTORS if x != d)) for d in DESCRIPTORS]
            + [("concavity alone", ("concavity",))])
    rows = []
    for name, keep in sets:
        cols = descriptor_columns(keep, (16, 48))
        s = oracle_scores(Dtr[..., cols], ytr, Dva[..., cols])
        top = s.argmax(1)
        rows.append(dict(family=family, points=points, descriptors=name, seen=view_share(s, Pva, frame, temperature),
                         top_in_cup=float(yva[torch.arange(len(top)), top].float().mean()), shapes=len(Pva)))
    return rows


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--family", default="decoys")
    ap.add_argument("--points", type=int, default=256, help="the first n of each shape's points (selector.num_points)")
    ap.add_argument("--seed", type=int, default=0, help="dataset.seed (0: the tuning data)")
    ap.add_argument("--temperature", type=float, default=0.05)
    ap.add_argument("--root", default="outputs/cache/synthetic_views", help="the dataset's cache folder")
    a = ap.parse_args(argv)
    torch.manual_seed(0)
    print("| family | points | descriptors | validation shapes | view sees the detail | top point in the detail's cup |")
    print("|---|---|---|---|---|---|")
    for r in run(a.root, a.family, a.points, a.seed, temperature=a.temperature):
        print(f"| {r['family']} | {r['points']} | {r['descriptors']} | {r['shapes']} | {r['seen']:.3f} | {r['top_in_cup']:.3f} |", flush=True)


if __name__ == "__main__":
    main()
