"""Does G's gradient point to where C reads the class? The loss landscape around the detail of ``synthetic_views``.

``python scripts/studies/view_landscape.py RUN_DIR`` loads a run trained on ``synthetic_views``
(``RUN_DIR/best.pt``), puts one camera per test shape at ``theta`` degrees from the shape's cup
axis (in a random direction around it), and reports per theta: C's loss and accuracy there, and
how well a descent step on G's views would turn the camera towards the axis, for

- ``autograd``: the renderer's camera gradient dL/du (what ``selector.grad=autograd`` uses),
- ``smoothed``: the antithetic estimate of the smoothed loss's gradient from loss values at
  perturbed views (``selector.grad=smoothed``, ``selectors/view_gradient.py``),

as the mean cosine between the camera's move and the direction to the axis, and the share of
shapes moved towards it (0.5: no information). The moves are what a step in (azimuth, elevation)
does to the camera position, the same map for both estimates. Each row also gives the mean of G's
other loss, the centered logit (``selector.loss=centered_logit``).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

from mvtn_exp.data.collate import collate_shapes
from mvtn_exp.data.view_detail import view_angles
from mvtn_exp.runtime import checkpoint
from mvtn_exp.selectors import view_gradient
from mvtn_exp.engine.trainer import as_config, make_datasets
from mvtn_exp.model import build_mvtn
from mvtn_exp.tasks import classification


def camera_move(azim: np.ndarray, elev: np.ndarray, g_azim: np.ndarray, g_elev: np.ndarray) -> np.ndarray:
    """``[N]`` degrees and gradients per degree -> ``[N, 3]`` move of the camera direction under a
    descent step ``-(g_azim, g_elev)`` (positions ``(cos e sin a, sin e, cos e cos a)``)."""
    a, e = np.radians(azim), np.radians(elev)
    d_a = np.stack([np.cos(e) * np.cos(a), 0 * a, -np.cos(e) * np.sin(a)], 1)
    d_e = np.stack([-np.sin(e) * np.sin(a), np.cos(e), -np.sin(e) * np.cos(a)], 1)
    return -(g_azim[:, None] * d_a + g_elev[:, None] * d_e)


def towards(move: np.ndarray, d: np.ndarray, axis: np.ndarray) -> tuple[float, float]:
    """Mean cosine of ``move`` with the tangent direction from ``d`` to ``axis``, and the share > 0."""
    tow = axis - (axis * d).sum(1, keepdims=True) * d
    cos = (move * tow).sum(1) / (np.linalg.norm(move, axis=1) * np.linalg.norm(tow, axis=1) + 1e-12)
    return float(cos.mean()), float((cos > 0).mean())


def landscape(run_dir, thetas=(0, 20, 40, 60), shapes: int = 96, pairs: int = 6, sigma: float = 12.0,
              seed: int = 0) -> list[dict]:
    """One row per theta (see the module docstring)."""
    state = checkpoint.load(Path(run_dir) / "best.pt")
    cfg = as_config(state["config"])
    cfg.logger.progress = False
    if cfg.dataset.name != "synthetic_views":
        raise ValueError(f"{run_dir}: trained on dataset {cfg.dataset.name!r}; the landscape needs synthetic_views "
                         "(the detail's frame)")
    ds = make_datasets(cfg)["test"]
    model = build_mvtn(cfg, len(ds.classes))
    model.load_state_dict(state["model"])
    model.eval()
    rng = np.random.default_rng(seed)
    idx = rng.choice(len(ds), min(shapes, len(ds)), replace=False)
    batch = collate_shapes([ds[int(i)] for i in idx])
    labels = batch["labels"]
    axis = ds._a["detail_axis"][idx].astype(np.float64)
    side = rng.normal(size=axis.shape)
    side -= (side * axis).sum(1, keepdims=True) * axis
    side /= np.linalg.norm(side, axis=1, keepdims=True)
    per_shape = classification.loss_fn(cfg.task, reduction="none")
    render_loss = view_gradient.model_render_loss(model, batch, labels, per_shape)
    rows = []
    for theta in thetas:
        t = np.radians(theta)
        d = np.cos(t) * axis + np.sin(t) * side
        a, e = view_angles(d)
        azim = torch.tensor(a, dtype=torch.float32)[:, None].requires_grad_(True)
        elev = torch.tensor(e, dtype=torch.float32)[:, None].requires_grad_(True)
        dist = torch.full_like(azim, cfg.selector.distance)
        logits, _ = model.mvnet(model.render(batch, azim, elev, dist), (azim, elev, dist))
        loss = per_shape(logits, labels)
        loss.sum().backward()
        auto = camera_move(a, e, azim.grad[:, 0].double().numpy(), elev.grad[:, 0].double().numpy())
        ga, ge = view_gradient.smoothed_view_gradient(render_loss, (azim.detach(), elev.detach(), dist), pairs, sigma,
                                                      view_gradient.noise_generator(seed, int(theta)))
        smooth = camera_move(a, e, ga[:, 0].double().numpy(), ge[:, 0].double().numpy())
        prob = torch.softmax(logits.detach().double(), 1)
        row = {"theta": theta, "loss": float(loss.detach().mean()),
               "centered": float(classification.centered_logit_loss(logits.detach(), labels).mean()),
               "acc": float((logits.argmax(1) == labels).float().mean()),
               "p_true": float(prob.gather(1, labels[:, None]).mean()),
               "entropy": float(-(prob * prob.clamp_min(1e-300).log()).sum(1).mean())}
        if 0 < theta < 180:  # on the axis (or opposite it) there is no direction towards it
            row.update(zip(("autograd_cos", "autograd_towards"), towards(auto, d, axis)))
            row.update(zip(("smoothed_cos", "smoothed_towards"), towards(smooth, d, axis)))
        rows.append(row)
    return rows


def main(argv=None) -> None:
    p = argparse.ArgumentParser(prog="python scripts/studies/view_landscape.py", description=__doc__.splitlines()[0])
    p.add_argument("run_dir", help="a run trained on synthetic_views (reads RUN_DIR/best.pt)")
    p.add_argument("--shapes", type=int, default=96)
    p.add_argument("--pairs", type=int, default=6, help="antithetic pairs of the smoothed estimate")
    p.add_argument("--sigma", type=float, default=12.0, help="smoothing std, degrees")
    p.add_argument("--thetas", default="0,20,40,60", help="comma-separated degrees from the cup axis")
    p.add_argument("--json", action="store_true", help="print JSON rows instead of a Markdown table")
    args = p.parse_args(argv)
    torch.manual_seed(0)
    try:
        thetas = [float(t) for t in args.thetas.split(",")]
        rows = landscape(args.run_dir, thetas=thetas, shapes=args.shapes, pairs=args.pairs, sigma=args.sigma)
    except (OSError, ValueError) as e:  # a missing or unfit run: one line, exit 2
        print(f"view_landscape: {e}", file=sys.stderr)
        raise SystemExit(2) from None

    if args.json:
        print(json.dumps(rows))
        return
    print(f"| theta (deg from the cup axis) | loss | centered logit | acc | p(true class) | entropy | autograd: cosine / towards | "
          f"smoothed ({args.pairs} pairs, sigma {args.sigma:g}): cosine / towards |\n|---|---|---|---|---|---|---|---|")
    for r in rows:
        cells = [f"{r['theta']:g}", f"{r['loss']:.3f}", f"{r['centered']:.3f}", f"{r['acc']:.2f}", f"{r['p_true']:.3f}",
                 f"{r['entropy']:.3f}"]
        for k in ("autograd", "smoothed"):
            cells.append(f"{r[k + '_cos']:.2f} / {r[k + '_towards']:.0%}" if f"{k}_cos" in r else "-")
        print("| " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
