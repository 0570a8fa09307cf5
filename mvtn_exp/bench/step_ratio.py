"""What learned views cost per training step, against fixed views at the same M, in one process.

A learned-views step against a fixed-views step at the same M, and rendering's share of a step,
are ratios; timed as two separate training runs on a shared machine they move with its load
(docs/results/training-cost.md). This benchmark times both sides in one process, on the same
batches, alternating which goes
first, with the trainer's own step (``train_one_epoch``: augmentation, G's gradient, clipping,
AdamW) and its stage split (``StepTimer``: G, R and C, forward and backward each), and reports
medians over rounds.

Per M (``--views``): fixed views (``selector=spherical``) against the configured learned
selector (default ``mvtn_spherical``), the rest of the config as given (default: ``mvtn-train``'s
defaults: 16 shapes x M views x 64 px, soft smooth). Epoch time is steps times step time plus a
validation pass that is about the same for both sides, so the step ratio bounds the epoch ratio
from above.

Run: ``python -m mvtn_exp.bench.step_ratio [--views 1 4] [--rounds 5] [--batches 6] [--learned 'OVERRIDES']
[overrides...]`` (Markdown table on stdout); ``--learned`` overrides apply to the learned side only
(e.g. ``--learned 'selector.hypotheses=1 selector.race_epochs=0'``: a step after the race).
"""
from __future__ import annotations

import argparse
import statistics

import torch

from ..config.compose import compose_train_config
from ..data.collate import collate_shapes
from ..runtime.seeding import seed_everything
from ..engine.step_timer import STAGES, StepTimer
from ..engine.trainer import make_datasets, make_optimizer, train_one_epoch
from ..model import build_mvtn
from ..tasks import classification

SIDES = ("fixed", "learned")


class _NoLog:
    def scalars(self, *args, **kwargs) -> None:
        pass


def _side(overrides: list[str], views: int, fixed: bool, batches_n: int, seed: int, learned: list[str] = ()) -> dict:
    cfg = compose_train_config(overrides + [f"views={views}"] + (["selector=spherical"] if fixed else list(learned)))
    cfg.logger.progress = False
    seed_everything(seed)
    ds = make_datasets(cfg)["train"]
    g = torch.Generator().manual_seed(seed)
    order = torch.randperm(len(ds), generator=g).tolist()
    B = cfg.batch_size
    batches = [collate_shapes([ds[i] for i in order[k * B:(k + 1) * B]]) for k in range(min(batches_n, len(ds) // B))]
    if not batches:
        raise ValueError(f"step_ratio: the train split has {len(ds)} shapes, fewer than batch_size={B}")
    model = build_mvtn(cfg, len(ds.classes))
    g_training = cfg.selector.training()(cfg)
    opt, _ = make_optimizer(cfg, model, g_training)
    # the first epoch in which G learns (after selector.warmup_epochs)
    epoch = getattr(cfg.selector, "warmup_epochs", 0)
    return dict(cfg=cfg, model=model, opt=opt, g_training=g_training, batches=batches, epoch=epoch, loss_fn=classification.loss_fn(cfg.task),
                rounds=[])


def _run(side: dict) -> dict:
    timer = StepTimer(torch.device("cpu"))
    train_one_epoch(side["model"], side["batches"], side["opt"], side["cfg"], side["epoch"], side["loss_fn"], timer,
                    _NoLog(), 0, side["g_training"])
    return timer.means()


def measure(overrides: list[str], views=(1, 4), rounds: int = 5, batches: int = 6, seed: int = 0,
            learned: list[str] = ()) -> list[dict]:
    """One row per M: median seconds per step of each side (total and stages) over ``rounds``;
    ``learned``: overrides of the learned side alone."""
    rows = []
    for M in views:
        sides = {name: _side(overrides, M, name == "fixed", batches, seed, learned) for name in SIDES}
        for s in sides.values():
            _run(s)  # warm-up round, not counted
        for r in range(rounds):
            for name in (SIDES if r % 2 == 0 else SIDES[::-1]):
                sides[name]["rounds"].append(_run(sides[name]))
        row = {"views": M, "selector": sides["learned"]["cfg"].selector.name,
               "steps_per_round": len(sides["fixed"]["batches"]), "rounds": rounds}
        for name, s in sides.items():
            for key in (*STAGES, "total"):
                row[f"{name}_{key}"] = statistics.median(m[key] for m in s["rounds"])
        row["ratio"] = statistics.median(b["total"] / a["total"] for a, b in zip(sides["fixed"]["rounds"],
                                                                                 sides["learned"]["rounds"]))
        row["render_share"] = statistics.median(m["render"] / m["total"] for m in sides["learned"]["rounds"])
        rows.append(row)
    return rows


def to_markdown(rows: list[dict], title: str) -> str:
    ms = lambda v: f"{1e3 * v:.0f}"  # noqa: E731
    out = [f"{title}", "",
           "| M | fixed ms/step (G / R / C) | learned ms/step (G / R / C) | learned / fixed (target <= 1.5) "
           "| render share of the learned step (target <= 25%) |",
           "|---|---|---|---|---|"]
    for r in rows:
        parts = {n: f"{ms(r[f'{n}_total'])} ({ms(r[f'{n}_selector'])} / {ms(r[f'{n}_render'])} / "
                    f"{ms(r[f'{n}_backbone'])})" for n in SIDES}
        out.append(f"| {r['views']} | {parts['fixed']} | {parts['learned']} | {r['ratio']:.2f} x "
                   f"| {100 * r['render_share']:.0f}% |")
    return "\n".join(out)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--views", type=int, nargs="+", default=[1, 4])
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--batches", type=int, default=6, help="training steps per side per round")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--learned", default="", metavar="'OVERRIDES'", help="overrides of the learned side alone")
    p.add_argument("overrides", nargs="*", help="mvtn-train overrides (key=value), applied to both sides")
    args = p.parse_args(argv)
    learned = args.learned.split()
    rows = measure(args.overrides + ["logger=none"], args.views, args.rounds, args.batches, args.seed, learned)
    title = (f"learned ({rows[0]['selector']}) against fixed (spherical) views, {args.rounds} rounds x "
             f"{rows[0]['steps_per_round']} steps each, medians, {torch.get_num_threads()} threads; "
             f"overrides: {' '.join(args.overrides) or '(defaults)'}"
             + (f"; learned side: {' '.join(learned)}" if learned else ""))
    print(to_markdown(rows, title), flush=True)


if __name__ == "__main__":
    main()
