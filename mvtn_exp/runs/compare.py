"""Paired comparisons over seeds: the numbers behind every "A beats B" of the project (``mvtn-compare``).

Reads every run below the given folders (``runs/folders.py``: a finished run's recorded config,
an unfinished one's outcome and Hydra's config), sorts the finished runs into
*sides* (one configuration each, runs differing only in ``seed``) and compares every side with the
reference side (the first) on the seeds both have:

- per seed: each side's value of the metric (``test_acc`` by default; ``best_val_acc`` to choose
  a recipe on validation);
- per side: mean +- sample std (n - 1) over the seeds;
- per side against the reference: the mean paired difference in points with its 95% paired-t
  interval (Student's t with n - 1 degrees of freedom on the per-seed differences) and on how many
  seeds the side is ahead, tied and behind;
- for costs (``ratios``, e.g. ``train_wall_seconds``): each side's paired ratio to the reference,
  the geometric mean of the per-seed ratios with the paired-t interval of their logarithms;
- for outcomes (``counts``, e.g. ``test_detail_seen>=0.5``: the run found the detail): on how many
  of its seeds each side meets the condition, with the Wilson 95% interval of that share.

A comparison is refused (``CompareError``, one line naming the key) when the two sides differ in
data, split or epochs (``PROTECTED``) unless that key is named as the one under comparison, when
their seeds differ (and no unfinished run explains it), or when fewer than 2 seeds are common.
Keys that say where or how a run ran (``RUN_LOCAL``: device, threads, paths, ...) never make a
difference. A key that another run's record has and an older run's lacks (the key was added after
the older run) is read as the key's default in the current code (``fill_added_keys``: adding a key
keeps the old behaviour as its default), and ``compare.md`` lists every key so filled.
Float rounding differs between machines (CPU model and torch's CPU capability, or GPU), so one
seed's run repeats to the digit only on the machine that made it: ``compare.md`` names the
machines when the compared runs come from more than one.

The sides and their refusals are ``sides.py``'s, the statistics ``paired_stats.py``'s, and
``compare.md`` / ``compare.json`` ``compare_md.py``'s.
"""
from __future__ import annotations

from collections import Counter

from .folders import METRICS_FILE, Run
from .paired_stats import count, mean_sd, paired, parse_count, ratio
from .sides import CompareError, Side, _check_pair, _common_seeds, _only_one, _show, differing, fill_added_keys, make_sides


# numbers derived from what older runs' metrics.json hold
def _at_best_epoch(key: str):
    """A validation number of the run's best epoch (``history[best_epoch - 1][key]``), e.g.
    ``val_detail_seen``: whether the views of the selected model found the detail, on validation."""
    def read(m: dict):
        history, best = m.get("history"), m.get("best_epoch")
        if not isinstance(history, list) or not isinstance(best, int) or not 1 <= best <= len(history):
            return None
        return history[best - 1].get(key)
    return read


def _race_led(m: dict):
    """1 where the raced hypotheses' race ended by a clear lead, 0 where it ran to its cap (or its
    batch budget) and the kept hypothesis led by less; None for runs without a race, or made
    before the history recorded how it ended (``race_end``)."""
    ends = [h.get("race_end") for h in m.get("history") or [] if isinstance(h, dict) and h.get("race_end")]
    return None if not ends else float(ends[-1] == "lead")


DERIVED = {"train_wall_seconds": lambda m: sum(m["epoch_seconds"]) if isinstance(m.get("epoch_seconds"), list) else None,
           "best_val_detail_seen": _at_best_epoch("val_detail_seen"),
           "race_led": _race_led}


def _value(run: Run, metric: str) -> float:
    v = run.metrics.get(metric)
    if v is None and metric in DERIVED:
        v = DERIVED[metric](run.metrics)
    if not isinstance(v, (int, float)) or isinstance(v, bool):
        raise CompareError(f"{run.path / METRICS_FILE}: no number under {metric!r} "
                           f"(numbers there: {', '.join(k for k, x in run.metrics.items() if isinstance(x, (int, float)))})")
    return float(v)


def compare(runs: list[Run], metric: str = "test_acc", where=None, group=None, keys=(), also=(),
            reference: str | None = None, ratios=(), counts=()) -> dict:
    """The comparison as a dict (what ``compare.json`` holds); see the module docstring. ``ratios``:
    metrics (times, costs) also given as each side's paired ratio to the reference (``ratio``);
    ``counts``: conditions (``'METRIC>=VALUE'``) counted over each side's seeds (``count``)."""
    conditions = {c: parse_count(c) for c in counts}  # text -> (metric, operator, bound)
    result = {"metric": metric, "interval": "95% paired t (Student's t, n - 1 df, on per-seed differences)",
              "group": group, "groups": [], "ratios": list(ratios), "counts": list(counts),
              "not_finished": [{"path": str(r.path), "status": r.status, "seed": r.seed, "error": r.error}
                               for r in runs if r.status != "ok"]}
    fill_added_keys(runs)
    filled = sorted({k for r in runs for k in r.filled})
    result["filled"] = {k: sum(k in r.filled for r in runs) for k in filled}
    machines: Counter = Counter()
    for g, sides in make_sides(runs, where, group, reference).items():
        group_text = f" at {group}={_show(g)}" if group else ""
        if len(sides) < 2:
            raise CompareError(_only_one(sides[0], runs, group, g, group_text))
        rows = []
        for side in sides:
            rows.append(_side_entry(sides[0], side, metric, keys, also, ratios, conditions, group_text))
            machines.update(r.machine or "not recorded" for r in side.runs.values())
        result["groups"].append({"group": g, "sides": rows})
    result["machines"] = dict(sorted(machines.items()))
    return result


def _side_entry(ref: Side, side: Side, metric: str, keys, also, ratios, conditions: dict, group_text: str) -> dict:
    """One side's row of the result: its values on its seeds (those it shares with the reference
    side ``ref``), their mean and std, and against ``ref`` the paired difference, ratios and counts."""
    entry = {"label": side.label, "settings": {k: side.settings.get(k) for k in differing(ref.settings, side.settings)},
             "commits": sorted({r.commit for r in side.runs.values() if r.commit}),
             "not_finished": [str(r.path) for r in side.unfinished]}
    seeds = sorted(side.runs)
    if side is not ref:
        entry["differs_in"] = _check_pair(ref, side, keys, group_text)
        seeds, dropped = _common_seeds(ref, side, group_text)
        entry["dropped_seeds"] = dropped
        entry.update(paired([_value(ref.runs[s], metric) for s in seeds],
                            [_value(side.runs[s], metric) for s in seeds]))
    values = [_value(side.runs[s], metric) for s in seeds]
    entry.update(seeds=seeds, values=values, mean=mean_sd(values)[0], sd=mean_sd(values)[1],
                 paths=[str(side.runs[s].path) for s in seeds],
                 also={k: mean_sd([_value(side.runs[s], k) for s in seeds]) for k in also},
                 also_values={k: [_value(side.runs[s], k) for s in seeds] for k in also},
                 ratios={k: None if side is ref else ratio([_value(ref.runs[s], k) for s in seeds],
                                                           [_value(side.runs[s], k) for s in seeds])
                         for k in ratios},
                 counts={c: count([_value(side.runs[s], m) for s in seeds], op, bound)
                         for c, (m, op, bound) in conditions.items()})
    return entry
