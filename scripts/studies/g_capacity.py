"""Can a selector's G *express* where to look on ``synthetic_views``? G trained alone, supervised.

``python scripts/studies/g_capacity.py [--epochs N] [--lr LR] [mvtn-train overrides ...]`` builds
the selector of the composed config (e.g. ``selector=mvtn_spherical views=1``) and trains only its
parameters, without R or C, to point a view down each training shape's cup axis (privileged: the
dataset's detail frame), under the config's augmentation (a fresh SO(3) pose every step with
``augment.rotate=so3``). The loss per shape is ``1 - max_m cos(view m, cup axis)``, views taken
as directions from the origin (the cup's floor centre lies on its axis through the origin). It
prints, per epoch, the loss and the share of validation shapes of which some view sees the detail
(``sees_detail``), and at the end the test share: the best a G of this form can do when it is
*told* the answer. A G that cannot reach a high share here cannot find the detail from C's loss
either; one that can, but does not when trained end to end, lacks the signal, not the capacity.
Not a method (it reads the detail frame).
"""
from __future__ import annotations

import argparse
import sys

import numpy as np
import torch
from tqdm.auto import tqdm

from mvtn_exp.render.cameras import view_directions as directions


def capacity_loss(views, axis: torch.Tensor) -> torch.Tensor:
    """Mean over shapes of ``1 - max_m cos(direction of view m, axis)``; ``axis [B, 3]`` unit."""
    cos = (directions(views[0], views[1]) * axis[:, None].to(views[0])).sum(-1)
    return (1.0 - cos.max(1).values).mean()


def seen_share(selector, ds, batch_size: int, points: int | None) -> float:
    """Share of ``ds``'s shapes (as posed) of which some view of ``selector`` sees the detail."""
    from mvtn_exp.data.collate import collate_shapes

    views = []
    selector.eval()
    with torch.no_grad():
        for lo in range(0, len(ds), batch_size):
            batch = collate_shapes([ds[i] for i in range(lo, min(lo + batch_size, len(ds)))])
            p = batch["points"] if points is None else batch["points"][:, :points]
            views.append([v.double() for v in selector(p)])
    azim, elev, dist = (torch.cat([v[k] for v in views]).numpy() for k in range(3))
    selector.train()
    return float(ds.detail_seen(azim, elev, dist).any(1).mean())


def run(overrides: list[str], epochs: int, lr: float, progress: bool = True) -> dict:
    """Train the config's G alone, supervised (module docstring) -> ``{"val": [...], "test": share}``."""
    from mvtn_exp.config.compose import compose_train_config
    from mvtn_exp.data.collate import collate_shapes
    from mvtn_exp.engine.trainer import make_datasets
    from mvtn_exp.tasks.robustness import random_rotations, turn_batch

    cfg = compose_train_config(overrides, prog="g_capacity")
    if cfg.dataset.name != "synthetic_views":
        raise SystemExit("g_capacity: needs dataset=synthetic_views (it reads the detail frame)")
    torch.manual_seed(cfg.seed)
    datasets = make_datasets(cfg)
    selector = cfg.selector.build(cfg.views, seed=cfg.seed, point_encoder=cfg.point_encoder)
    params = [p for p in selector.parameters() if p.requires_grad]
    if not params:
        raise SystemExit(f"g_capacity: selector={cfg.selector.name} has no parameters to train")
    opt = torch.optim.Adam(params, lr=lr)
    points = cfg.selector.kept_points()
    train, history = datasets["train"], []
    gen = torch.Generator().manual_seed(cfg.seed)
    for epoch in tqdm(range(epochs), desc="g_capacity", disable=None if progress else True):
        order, total = torch.randperm(len(train), generator=gen).tolist(), 0.0
        for lo in range(0, len(order), cfg.batch_size):
            batch = collate_shapes([train[i] for i in order[lo:lo + cfg.batch_size]])
            batch = turn_batch(batch, random_rotations(len(batch["points"]), cfg.augment.rotate, gen))
            p = batch["points"] if points is None else batch["points"][:, :points]
            loss = capacity_loss(selector(p), batch["detail_axis"])
            opt.zero_grad()
            loss.backward()
            opt.step()
            total += float(loss.detach()) * len(p)
        history.append({"epoch": epoch + 1, "loss": total / len(train),
                        "val_seen": seen_share(selector, datasets["val"], cfg.batch_size, points)})
    return {"selector": cfg.selector.name, "history": history,
            "test_seen": seen_share(selector, datasets["test"], cfg.batch_size, points)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python scripts/studies/g_capacity.py", description=__doc__.splitlines()[0])
    p.add_argument("--epochs", type=int, default=20)
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("overrides", nargs="*", help="mvtn-train overrides (dataset=synthetic_views, selector=..., views=...)")
    args = p.parse_args(argv)
    res = run(args.overrides, args.epochs, args.lr)
    print(f"selector={res['selector']}: G trained alone to look down the cup axis ({args.epochs} epochs, lr {args.lr})\n")
    print("| epoch | loss (1 - cos) | val shapes seen |\n|---|---|---|")
    for h in res["history"]:
        print(f"| {h['epoch']} | {h['loss']:.3f} | {h['val_seen']:.3f} |")
    print(f"\ntest shapes of which some view sees the detail: {res['test_seen']:.3f}")
    return 0


if __name__ == "__main__":
    np.set_printoptions(precision=3)
    sys.exit(main())
