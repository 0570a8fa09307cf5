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
"""
from __future__ import annotations

import json
import math
import operator
import re
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import yaml
from scipy import stats

from .folders import METRICS_FILE, Run, find_runs, flatten  # noqa: F401 (find_runs re-exported: runs/folders.py reads runs)
from .settings import RUN_LOCAL, is_local  # noqa: F401 (RUN_LOCAL re-exported)

PROTECTED = ("dataset", "epochs", "patience")  # data, its splits and the training length


class CompareError(ValueError):
    """A comparison that cannot be made as asked (mismatched sides, too few seeds, nothing to read)."""


_DEFAULTS: dict = {}


def current_defaults(settings: dict) -> dict:
    """The current code's default of every dotted key of a run with ``settings``'s options (the
    top-level ``TrainConfig`` fields, and each option kind's schema for the option it names: only
    that schema's keys, not those of the kind's default option, which a fixed selector lacks)."""
    from omegaconf import OmegaConf

    from ..config.options import OPTIONS
    from ..config.schema import OPTION_KINDS, TrainConfig

    names = tuple(settings.get(f"{kind}.name") for kind in OPTION_KINDS)
    if names not in _DEFAULTS:
        out = flatten(OmegaConf.to_container(OmegaConf.structured(TrainConfig)))
        for kind, name in zip(OPTION_KINDS, names):
            try:
                schema = OPTIONS[kind].schema(str(name))
            except ValueError:  # an option this code no longer has: nothing to fill from
                continue
            out = {k: v for k, v in out.items() if not k.startswith(f"{kind}.")}
            out.update(flatten(OmegaConf.to_container(OmegaConf.structured(schema)), kind))
        _DEFAULTS[names] = out
    return _DEFAULTS[names]


def fill_added_keys(runs: list[Run]) -> None:
    """A key some run's record has and another's lacks, and that the current code defaults: the
    lacking run gets the default (recorded in ``Run.filled``); a key without a current default
    stays absent (and still makes a difference)."""
    readable = [r for r in runs if r.settings is not None]
    every = set().union(*(r.settings for r in readable)) if readable else set()
    for r in readable:
        missing = every - set(r.settings)
        if not missing:
            continue
        defaults = current_defaults(r.settings)
        for key in sorted(missing):
            if key in defaults and not is_local(key):
                r.settings[key] = defaults[key]
                r.filled.append(key)


def parse_condition(text: str) -> dict:
    """``"selector.name=poi views=1"`` -> ``{"selector.name": "poi", "views": 1}`` (values read as YAML)."""
    out = {}
    for part in text.split():
        key, eq, value = part.partition("=")
        if not eq or not key:
            raise CompareError(f"--where {text!r}: expected KEY=VALUE pairs separated by spaces, got {part!r}")
        if key.lstrip("+") == "seed":
            raise CompareError(f"--where {text!r}: seed is what runs are paired on, not a side's condition")
        out[key.lstrip("+")] = yaml.safe_load(value)
    return out


def _matches(settings: dict, condition: dict) -> bool:
    """``selector=poi`` reads as ``selector.name=poi`` (a group's option)."""
    return all(settings.get(k if k in settings else f"{k}.name", "<absent>") == v for k, v in condition.items())


def _show(v) -> str:
    return json.dumps(v, separators=(",", ":")) if isinstance(v, (list, dict)) else str(v)


def differing(a: dict, b: dict) -> list[str]:
    """Keys whose values differ between two flattened settings (a key missing on one side differs)."""
    return sorted(k for k in set(a) | set(b) if a.get(k, "<absent>") != b.get(k, "<absent>"))


def _protected(key: str, allowed) -> bool:
    under = any(key == p or key.startswith(p + ".") for p in PROTECTED)
    return under and not any(key == k or key.startswith(k + ".") for k in allowed)


@dataclass
class Side:
    label: str
    settings: dict
    runs: dict = field(default_factory=dict)  # seed -> finished Run
    unfinished: list = field(default_factory=list)


def _label(settings: dict, keys: list[str]) -> str:
    """The side's values of the keys that differ between sides: an option's name stands for its
    own keys (``selector.name=poi``, not every ``selector.*``)."""
    names = [k for k in keys if k.endswith(".name")]
    owners = tuple(k[: -len("name")] for k in names)
    shown = names + [k for k in keys if k not in names and not k.startswith(owners)]
    text = " ".join(f"{k}={_show(settings.get(k, '-'))}" for k in shown[:3])
    return text + (" ..." if len(shown) > 3 else "") if text else "(defaults)"


def _by_option(keys: list[str]) -> list[str]:
    """Differing keys, an option whose name differs shown once as ``selector.*``."""
    owners = tuple(k[: -len("name")] for k in keys if k.endswith(".name"))
    return [f"{o}*" for o in owners] + [k for k in keys if not k.startswith(owners)]


def _add(side: Side, run: Run) -> None:
    if run.status != "ok":
        side.unfinished.append(run)
    elif run.seed in side.runs:
        raise CompareError(f"seed={run.seed}: two finished runs of side '{side.label}' ({side.runs[run.seed].path}, "
                           f"{run.path}); pass the folders of one of them")
    else:
        side.runs[run.seed] = run


def make_sides(runs: list[Run], where: list[str] | None = None, group: str | None = None,
               reference: str | None = None) -> dict:
    """``{group value: [Side, ...]}``: runs sorted into sides, by ``where`` conditions (one side
    each, in their order) or, without them, one side per distinct configuration (first seen first;
    the one matching the ``reference`` condition first of all)."""
    readable = [r for r in runs if r.settings is not None]
    if not any(r.status == "ok" for r in readable):
        raise CompareError(f"no finished run (a run dir with metrics.json) among the {len(runs)} found")
    groups: dict = {}
    for r in readable:
        groups.setdefault(r.settings.get(group) if group else None, []).append(r)

    def key_of(settings: dict) -> tuple:
        return tuple(sorted((k, _show(v)) for k, v in settings.items() if k != group))

    ref = parse_condition(reference) if reference else None
    rank = {}
    for r in sorted(readable, key=lambda r: not (ref and _matches(r.settings, ref))):
        rank.setdefault(key_of(r.settings), len(rank))
    out = {}
    for g, members in groups.items():
        sides: dict = {}
        if where:
            conditions = [parse_condition(w) for w in where]
            for r in members:
                hit = [i for i, c in enumerate(conditions) if _matches(r.settings, c)]
                if len(hit) > 1:
                    raise CompareError(f"{r.path}: matches --where {where[hit[0]]!r} and {where[hit[1]]!r}; "
                                       "make the conditions exclusive")
                if hit:
                    sides.setdefault(hit[0], []).append(r)
            order = [i for i in range(len(where)) if i in sides]
            if ref:  # the side matching the reference condition first (the others keep their order)
                order.sort(key=lambda i: not _matches(sides[i][0].settings, ref))
        else:
            for r in members:
                sides.setdefault(key_of(r.settings), []).append(r)
            order = sorted(sides, key=rank.get)
        built = []
        finished = {i: [r for r in sides[i] if r.status == "ok"] for i in order}
        order = [i for i in order if finished[i]]  # a side none of whose runs finished: listed under not finished
        reference_settings = {i: finished[i][0].settings for i in order}
        keys = sorted({k for i in order for j in order for k in differing(reference_settings[i], reference_settings[j])
                       if k != group})
        for i in order:
            ok = finished[i]
            if where and ok:
                for r in ok[1:]:
                    diff = [k for k in differing(ok[0].settings, r.settings) if k != group]
                    if diff:
                        raise CompareError(f"--where {where[i]!r}: its runs differ in {diff[0]} ({_show(ok[0].settings.get(diff[0]))} "
                                           f"in {ok[0].path}, {_show(r.settings.get(diff[0]))} in {r.path}); add {diff[0]}=... "
                                           f"to the condition{' or --group ' + diff[0] if not group else ''}")
            side = Side(where[i] if where else _label(reference_settings[i], keys), reference_settings[i])
            for r in sides[i]:
                _add(side, r)
            built.append(side)
        out[g] = built
    return out


def paired(ref: list[float], other: list[float]) -> dict:
    """Paired statistics of ``other - ref`` (same seeds, same order): mean, sample std, the 95%
    paired-t interval and the counts of seeds ahead / tied / behind."""
    d = [b - a for a, b in zip(ref, other)]
    n, mean = len(d), sum(d) / len(d)
    sd = math.sqrt(sum((x - mean) ** 2 for x in d) / (n - 1))
    half = float(stats.t.ppf(0.975, n - 1)) * sd / math.sqrt(n)
    return {"diff": mean, "diff_sd": sd, "low": mean - half, "high": mean + half,
            "ahead": sum(x > 0 for x in d), "tied": sum(x == 0 for x in d), "behind": sum(x < 0 for x in d)}


COMPARISONS = {">=": operator.ge, "<=": operator.le, ">": operator.gt, "<": operator.lt}


def parse_count(text: str) -> tuple[str, str, float]:
    """``'METRIC>=VALUE'`` (or ``<=``, ``>``, ``<``) -> ``(metric, operator, value)``."""
    m = re.fullmatch(r"\s*([A-Za-z_][\w.]*)\s*(>=|<=|>|<)\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*", text)
    if not m:
        raise CompareError(f"--count {text!r}: expected METRIC>=VALUE (or <=, >, <), e.g. test_detail_seen>=0.5")
    return m.group(1), m.group(2), float(m.group(3))


def wilson(k: int, n: int) -> tuple[float, float]:
    """The Wilson score 95% interval of a share ``k / n``."""
    z = float(stats.norm.ppf(0.975))
    p, d = k / n, 1 + z * z / n
    centre, half = (p + z * z / (2 * n)) / d, z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    return max(0.0, centre - half), min(1.0, centre + half)


def count(values: list[float], op: str, bound: float) -> dict:
    """How many ``values`` meet ``value op bound`` (``parse_count``), of how many, with the Wilson interval."""
    k = sum(COMPARISONS[op](v, bound) for v in values)
    low, high = wilson(k, len(values))
    return {"k": k, "n": len(values), "low": low, "high": high}


def mean_sd(x: list[float]) -> tuple[float, float]:
    m = sum(x) / len(x)
    return m, (math.sqrt(sum((v - m) ** 2 for v in x) / (len(x) - 1)) if len(x) > 1 else 0.0)


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


def _check_pair(ref: Side, side: Side, allowed, group_text: str) -> list[str]:
    diff = differing(ref.settings, side.settings)
    bad = [k for k in diff if _protected(k, allowed)]
    if bad:
        k = bad[0]
        raise CompareError(f"{k}: '{ref.label}' has {_show(ref.settings.get(k, '(absent)'))}, '{side.label}' has "
                           f"{_show(side.settings.get(k, '(absent)'))}{group_text}: the sides differ in data, split or "
                           f"epochs; pass --key {k} if that is the key under comparison")
    return diff


def _common_seeds(ref: Side, side: Side, group_text: str) -> tuple[list, list]:
    a, b = set(ref.runs), set(side.runs)
    unfinished = {r.seed for r in ref.unfinished + side.unfinished}
    if a != b and not (a ^ b) <= unfinished:
        raise CompareError(f"seed: '{ref.label}' has seeds {_seeds(a)}, '{side.label}' has {_seeds(b)}{group_text}; "
                           "run the same seeds on both sides")
    common = sorted(a & b)
    if len(common) < 2:
        raise CompareError(f"seed: '{ref.label}' and '{side.label}'{group_text} share {len(common)} finished seed(s) "
                           f"({_seeds(set(common)) or 'none'}); a paired comparison needs at least 2")
    return common, sorted(a ^ b)


def _seeds(s: set) -> str:
    return ", ".join(map(str, sorted(s, key=lambda x: (str(type(x)), x))))


def ratio(ref: list[float], side: list[float]) -> dict:
    """``side / ref`` over paired seeds: the geometric mean of the per-seed ratios and its 95% paired-t
    interval (on the logarithms); every value must be > 0."""
    if min(ref + side) <= 0:
        raise CompareError("--ratio: the metric must be > 0 on every run to form ratios")
    logs = [math.log(b / a) for a, b in zip(ref, side)]
    m, sd = mean_sd(logs)
    half = stats.t.ppf(0.975, len(logs) - 1) * sd / math.sqrt(len(logs))
    return {"ratio": math.exp(m), "ratio_low": math.exp(m - half), "ratio_high": math.exp(m + half)}


def _only_one(side: Side, runs: list[Run], group, g, group_text: str) -> str:
    """The refusal when one configuration has finished runs; it names the runs of other
    configurations that have not finished (a side still running or failed), if any."""
    other = [r for r in runs if r.status != "ok" and r.settings is not None
             and (not group or r.settings.get(group) == g)
             and [k for k in differing(side.settings, r.settings) if k != group]]
    waiting = (f"; {len(other)} run(s) of another configuration not finished ({other[0].path}: {other[0].status}"
               + (", ..." if len(other) > 1 else "") + ")") if other else ""
    return (f"only one configuration{group_text} with finished runs ('{side.label}' ...): nothing to compare{waiting} "
            "(give the folders of both sides, or --where one condition per side)")


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
        ref, rows = sides[0], []
        for side in sides:
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
            rows.append(entry)
            machines.update(r.machine or "not recorded" for r in side.runs.values())
        result["groups"].append({"group": g, "sides": rows})
    result["machines"] = dict(sorted(machines.items()))
    return result


def _cell(mean: float, sd: float) -> str:
    return f"{mean:.3f} ± {sd:.3f}"


def _ratio_cell(r) -> str:
    return "1 (reference)" if r is None else f"{r['ratio']:.2f} x [{r['ratio_low']:.2f}, {r['ratio_high']:.2f}]"


def _count_cell(c: dict) -> str:
    return f"{c['k']} of {c['n']} [{c['low']:.2f}, {c['high']:.2f}]"


def _letter(i: int) -> str:
    """The per-seed table's short name of side ``i`` (0-based): A, B, ..., Z, AA, AB, ..."""
    return ("" if i < 26 else _letter(i // 26 - 1)) + chr(ord("A") + i % 26)


def _seed_cell(side: dict, also: str | None, seed: int) -> str:
    """One seed's value of ``side``'s metric (``also``: None) or of an ``--also`` column; '-' if missing."""
    if seed not in side["seeds"]:
        return "-"
    return f"{(side['also_values'][also] if also else side['values'])[side['seeds'].index(seed)]:.4f}"


def to_markdown(result: dict) -> str:
    """``compare.md``: per group, the per-seed table and the summary table."""
    metric = result["metric"]
    lines = ["# Comparison", "", f"Metric: `{metric}`. Differences are in points (x 100) against the reference "
             f"(the first side), with the {result['interval']}.", ""]
    for grp in result["groups"]:
        sides = grp["sides"]
        if result["group"]:
            lines += [f"## {result['group']} = {_show(grp['group'])}", ""]
        seeds = sorted({s for side in sides for s in side["seeds"]}, key=lambda x: (str(type(x)), x))
        also, ratios = list(sides[0]["also"]), list(sides[0].get("ratios", {}))
        counts = list(sides[0].get("counts", {}))
        lines += ["| side | seeds | " + metric + " (mean ± std) | " + "".join(f"{k} | " for k in also)
                  + "".join(f"{k} / reference [95%] | " for k in ratios)
                  + "".join(f"seeds with {c} [Wilson 95%] | " for c in counts)
                  + "vs reference (points) | 95% interval | ahead / tied / behind | commit |",
                  "|---|---|---|" + "---|" * (len(also) + len(ratios) + len(counts)) + "---|---|---|---|"]
        for i, s in enumerate(sides):
            vs = ("reference" if i == 0 else f"{100 * s['diff']:+.1f} ± {100 * s['diff_sd']:.1f}")
            ci = "" if i == 0 else f"[{100 * s['low']:+.1f}, {100 * s['high']:+.1f}]"
            wins = "" if i == 0 else f"{s['ahead']} / {s['tied']} / {s['behind']}"
            lines.append(f"| {s['label']} | {len(s['seeds'])} | {_cell(s['mean'], s['sd'])} | "
                         + "".join(f"{_cell(*s['also'][k])} | " for k in also)
                         + "".join(f"{_ratio_cell(s['ratios'][k])} | " for k in ratios)
                         + "".join(f"{_count_cell(s['counts'][c])} | " for c in counts)
                         + f"{vs} | {ci} | {wins} | {', '.join(s['commits']) or '-'} |")
        columns = [(i, None) for i in range(len(sides))] + [(i, k) for k in also for i in range(len(sides))]
        lines += ["", f"Per seed ({metric}{', then ' + ', '.join(also) if also else ''}; "
                  + "; ".join(f"{_letter(i)}: {s['label']}" for i, s in enumerate(sides)) + "):", "",
                  "| seed | " + " | ".join(_letter(i) + (f" {k}" if k else "") for i, k in columns) + " |",
                  "|---|" + "---|" * len(columns)]
        for seed in seeds:
            cells = [_seed_cell(sides[i], k, seed) for i, k in columns]
            lines.append(f"| {seed} | " + " | ".join(cells) + " |")
        for s in sides[1:]:
            keys = _by_option(s["differs_in"])
            note = f"'{s['label']}' differs from the reference in: {', '.join(keys[:8])}" + (" ..." if len(keys) > 8 else "")
            if s["dropped_seeds"]:
                note += f"; seeds left out (unfinished on one side): {_seeds(set(s['dropped_seeds']))}"
            lines += ["", note]
        lines.append("")
    if result.get("filled"):
        lines += ["Keys some runs' records lack (made before the key existed), read as the current default: "
                  + ", ".join(f"{k} ({n} run{'s' if n > 1 else ''})" for k, n in result["filled"].items()), ""]
    if len(result.get("machines", {})) > 1:
        lines += ["Runs made on more than one machine (float rounding differs between them, so a seed's run "
                  "repeats to the digit only on its own): " + ", ".join(f"{m} ({n} run{'s' if n > 1 else ''})"
                                                                       for m, n in result["machines"].items()), ""]
    if result["not_finished"]:
        lines += ["Runs not finished (left out):", ""]
        lines += [f"- {r['path']}: {r['status']}" + (f": {r['error']}" if r["error"] else "") for r in result["not_finished"]]
        lines.append("")
    return "\n".join(lines)


def write(result: dict, out_dir) -> tuple[Path, Path]:
    """``compare.md`` and ``compare.json`` into ``out_dir`` (made if needed); their paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    md, js = out / "compare.md", out / "compare.json"
    md.write_text(to_markdown(result))
    js.write_text(json.dumps(result, indent=1, default=str))
    return md, js
