"""Where a learned run's wall time goes, epoch by epoch, against a fixed run's: the budget a cost
target leaves.

Reads finished runs' ``metrics.json`` (``epoch_seconds``; ``history[i].hypothesis_losses`` marks
the epochs in which hypotheses raced) and prints, per side, the mean whole run and the mean epoch
of each phase (fixed: every epoch; learned: racing epochs and the epochs after the race). Then,
for ``--target`` T (the learned run at most T x the fixed run, same epochs): the budget T x the
fixed run's mean; the learned run's epochs without the race alone against it; and the most
racing epochs the budget affords at the measured phase costs (negative: none, even with no race).

Run: ``python scripts/studies/epoch_budget.py --fixed RUN_OR_SIDE_DIR... --learned RUN_OR_SIDE_DIR...
[--target 1.5]`` (a side dir is searched for ``*/metrics.json``).
"""
from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
from pathlib import Path


def run_files(paths: list[str]) -> list[Path]:
    """Run dirs (holding ``metrics.json``) or folders above them -> their ``metrics.json`` files."""
    files = []
    for p in map(Path, paths):
        if (p / "metrics.json").is_file():
            files.append(p / "metrics.json")
        else:
            found = sorted(p.glob("*/metrics.json"))
            if not found:
                raise ValueError(f"{p}: no metrics.json in it or in its sub-folders (expected finished runs)")
            files += found
    return files


def phases(metrics: dict) -> tuple[list[float], list[float]]:
    """``(racing epochs' seconds, other epochs' seconds)`` of one run's ``metrics.json``."""
    seconds = metrics.get("epoch_seconds")
    history = metrics.get("history") or []
    if not seconds or len(history) != len(seconds):
        raise ValueError("metrics.json: expected epoch_seconds and one history entry per epoch")
    racing = [bool(h.get("hypothesis_losses")) for h in history]
    return ([s for s, r in zip(seconds, racing) if r], [s for s, r in zip(seconds, racing) if not r])


def side_summary(files: list[Path]) -> dict:
    """Means over the runs: whole run, epochs, racing epochs (count and seconds each), other epochs."""
    runs = [json.loads(f.read_text()) for f in files]
    split = [phases(m) for m in runs]
    race = [s for r, _ in split for s in r]
    other = [s for _, o in split for s in o]
    return dict(runs=len(runs), whole=statistics.mean(sum(m["epoch_seconds"]) for m in runs),
                epochs=statistics.mean(len(m["epoch_seconds"]) for m in runs),
                race_epochs=statistics.mean(len(r) for r, _ in split),
                race=statistics.mean(race) if race else math.nan, other=statistics.mean(other) if other else math.nan)


def budget(fixed: dict, learned: dict, target: float) -> dict:
    """The budget ``target x`` the fixed run, the learned run's non-racing epochs alone against it,
    and the most racing epochs affordable: ``(budget - E x other) / (race - other)``."""
    E = learned["epochs"]
    total = target * fixed["whole"]
    no_race = E * learned["other"]
    extra = learned["race"] - learned["other"]
    affordable = (total - no_race) / extra if extra > 0 else math.inf
    return dict(budget=total, no_race=no_race, no_race_ratio=no_race / fixed["whole"], affordable=affordable)


def table(fixed: dict, learned: dict, target: float) -> str:
    b = budget(fixed, learned, target)
    fmt = lambda x: "-" if math.isnan(x) else f"{x:.1f}"  # noqa: E731
    rows = ["| side | runs | epochs | whole run (s) | racing epochs | s per racing epoch | s per other epoch |",
            "|---|---|---|---|---|---|---|"]
    for name, s in (("fixed", fixed), ("learned", learned)):
        rows.append(f"| {name} | {s['runs']} | {s['epochs']:g} | {s['whole']:.1f} | {s['race_epochs']:g} | "
                    f"{fmt(s['race'])} | {fmt(s['other'])} |")
    rows += ["", f"budget at {target:g} x the fixed run: {b['budget']:.1f} s; the learned run's epochs without "
             f"its race alone: {b['no_race']:.1f} s ({b['no_race_ratio']:.2f} x the fixed run); racing epochs the "
             f"budget affords: {b['affordable']:.2f}"]
    return "\n".join(rows)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--fixed", nargs="+", required=True)
    ap.add_argument("--learned", nargs="+", required=True)
    ap.add_argument("--target", type=float, default=1.5)
    args = ap.parse_args(argv)
    try:
        if not args.target > 0:
            raise ValueError(f"--target {args.target}: expected a ratio above 0")
        fixed, learned = (side_summary(run_files(p)) for p in (args.fixed, args.learned))
        if fixed["epochs"] != learned["epochs"]:
            raise ValueError(f"the fixed runs have {fixed['epochs']:g} epochs, the learned {learned['epochs']:g}: "
                             "expected the same epochs on both sides")
    except (ValueError, OSError, KeyError, json.JSONDecodeError) as e:
        print(f"epoch_budget: {e}", file=sys.stderr)
        return 2
    print(table(fixed, learned, args.target))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
