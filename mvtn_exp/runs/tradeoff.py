"""The speed/accuracy trade of a sweep: one row per setting, its Pareto front, and which keys matter.

``mvtn-tradeoff DIR`` reads a sweep folder (``mvtn-train -m ...``: one job folder per run, read by
``runs/folders.py``: its overrides, its metrics and cost when it finished) and writes into it:

- ``tradeoff_jobs.csv``: one row per job (its swept keys, status, test accuracy and cost);
- ``tradeoff.csv``: one row per setting (the jobs that differ only in ``seed``): the swept keys,
  seeds, test accuracy mean and sample std over seeds, the mean of each cost field
  (``engine/cost.py``), and whether the setting is Pareto-optimal for inference and for training
  time (no other setting is at least as accurate and at least as fast, and better in one);
- ``tradeoff.md``: those tables, the failed jobs, and the effect of each key;
- ``pareto.png``: accuracy against inference ms per shape and against training s per shape (log
  scale), one point per setting with its std over seeds, the front joined and labelled.

The effect of a key: over every pair of settings that differ only in that key, at neighbouring
values (numeric order when the values are numbers, first-seen order otherwise), the mean change
of accuracy (points) and the mean factor of inference and training time per step.

``metric``: the accuracy the front is drawn on, ``test_acc`` (default) or ``best_val_acc`` (a
search or grid that chooses on validation; the table then shows each setting's test accuracy
beside it, read once per run). ``compare_fronts`` sets the inference front of two folders (a
search against a grid) side by side by their hypervolume (``hypervolume``).
"""
from __future__ import annotations

import csv
import json
import math
from pathlib import Path

from .paired_stats import mean_sd
from .folders import METRICS_FILE, Run, finished_at, started_at, sweep_jobs
from .sweep import _override_values, _setting, failed_jobs, job_row

COST_FIELDS = ("infer_ms_per_shape", "train_seconds_per_shape", "train_peak_mib", "infer_peak_mib",
               "params_selector", "params_mvnet", "flops_selector_per_shape", "flops_mvnet_per_shape",
               "render_ms_per_shape", "render_pixels_per_shape")
METRICS = ("test_acc", "best_val_acc")


class TradeoffError(ValueError):
    """A sweep folder the study cannot read (no finished job, mixed datasets, missing cost)."""


def job_rows(sweep_dir, retimed: bool = False, seed: int | None = None) -> list[dict]:
    """Every job of the sweep with its status; finished ones carry ``test_acc``, ``dataset`` and the cost.
    ``retimed``: ``infer_ms_per_shape`` from each finished job's ``retimed.json`` (``runs/retime.py``),
    the run's own timing kept as ``infer_ms_in_run``. ``seed``: only the jobs of that run seed
    (``job_seed``), e.g. a grid's seed-0 runs against a search's one run per setting."""
    sweep_dir = Path(sweep_dir)
    if not sweep_dir.is_dir():
        raise TradeoffError(f"{sweep_dir}: not a folder")
    jobs = sweep_jobs(sweep_dir)
    if seed is not None:
        jobs = [j for j in jobs if job_seed(j) == seed]
    rows = [_cost_row(j, retimed) for j in jobs]
    ok = [r for r in rows if r.get("status") == "ok"]
    if not ok:
        raise TradeoffError(f"{sweep_dir}: no finished job (a job folder with metrics.json) among {len(rows)}"
                            + ("" if seed is None else f" of seed {seed}"))
    datasets = sorted({str(r["dataset"]) for r in ok})
    if len(datasets) > 1:
        first = {d: next(r["job"] for r in ok if str(r["dataset"]) == d) for d in datasets}
        raise TradeoffError(f"{sweep_dir}: jobs from different datasets "
                            + ", ".join(f"{d} (e.g. {j})" for d, j in first.items()) + "; compare one dataset")
    return rows


def _cost_row(job: Run, retimed: bool) -> dict:
    """``sweep.job_row``, and for a finished job its dataset, test and validation accuracy and cost."""
    r, m = job_row(job), job.metrics
    if r["status"] != "ok":
        return r
    r["dataset"] = ((m.get("config") or {}).get("dataset") or {}).get("name")
    missing = [k for k in COST_FIELDS if k not in (m.get("cost") or {})]
    if missing:
        raise TradeoffError(f"{job.path / METRICS_FILE}: no cost fields {missing[:3]}"
                            f"{'...' if len(missing) > 3 else ''} (an older run wrote none; re-run the job)")
    r.update({k: m["cost"][k] for k in COST_FIELDS}, test_acc=m["test_acc"], best_val_acc=m.get("best_val_acc"),
             train_wall_seconds=m.get("train_wall_seconds"))
    if retimed:
        r["infer_ms_in_run"] = r["infer_ms_per_shape"]
        r["infer_ms_per_shape"] = _retimed_ms(job.path)
    return r


def job_seed(job: Run):
    """The run seed of a job: its ``seed=N`` override, else its config's ``seed``."""
    given = _override_values(job.overrides).get("seed")
    return int(given) if given is not None else job.seed


def output_name(name: str, seed: int | None) -> str:
    """``tradeoff.md`` -> ``tradeoff-seed0.md`` for the tables of one seed (the all-seed files stay)."""
    stem, dot, ext = name.partition(".")
    return name if seed is None else f"{stem}-seed{seed}{dot}{ext}"


def _retimed_ms(job_dir: Path) -> float:
    from .retime import RETIMED

    path = job_dir / RETIMED
    if not path.is_file():
        raise TradeoffError(f"{path}: not found (mvtn-tradeoff --retime times every finished job again)")
    return float(json.loads(path.read_text())["infer_ms_per_shape"])


def _number(v: str):
    try:
        return float(v)
    except ValueError:
        return None


def settings(rows: list[dict], metric: str = "test_acc") -> tuple[list[dict], list[str]]:
    """Rows per setting (finished jobs only) and the swept keys (overridden keys whose value varies).
    ``acc`` / ``acc_std``: ``metric``'s mean and sample std over the setting's runs (the front's axis);
    ``test_acc`` / ``test_acc_std`` always."""
    groups: dict[str, list[dict]] = {}
    for r in rows:
        if r.get("status") == "ok":
            groups.setdefault(_setting(r["overrides"]), []).append(r)
    values = {s: _override_values(m[0]["overrides"]) for s, m in groups.items()}
    keys = list(dict.fromkeys(k for v in values.values() for k in v if _setting([f"{k}=x"]) != "(defaults)"))
    swept = [k for k in keys if len({v.get(k, "") for v in values.values()}) > 1] or keys
    out = []
    for s, members in groups.items():
        mean, std = mean_sd([float(r["test_acc"]) for r in members])
        acc, acc_std = mean_sd([float(r[metric]) for r in members])
        row = {"setting": s, **{k: values[s].get(k, "") for k in swept}, "seeds": len(members),
               "test_acc": mean, "test_acc_std": std, "acc": acc, "acc_std": acc_std}
        row.update({k: sum(float(r[k]) for r in members) / len(members) for k in COST_FIELDS})
        out.append(row)
    for time_key, flag in (("infer_ms_per_shape", "pareto_infer"), ("train_seconds_per_shape", "pareto_train")):
        for r in out:
            r[flag] = not any(o is not r and o["acc"] >= r["acc"] and o[time_key] <= r[time_key]
                              and (o["acc"] > r["acc"] or o[time_key] < r[time_key]) for o in out)
    return out, swept


def key_effects(rows: list[dict], swept: list[str]) -> list[dict]:
    """Per swept key and step between neighbouring values: mean accuracy change (points) and time factors."""
    effects = []
    for key in swept:
        others = [k for k in swept if k != key]
        vals = list(dict.fromkeys(r[key] for r in rows))
        if all(_number(v) is not None for v in vals):
            vals.sort(key=_number)
        for lo, hi in zip(vals, vals[1:]):
            pairs = [(a, b) for a in rows for b in rows if a[key] == lo and b[key] == hi
                     and all(a[k] == b[k] for k in others)]
            if not pairs:
                continue
            n = len(pairs)
            effects.append({
                "key": key, "step": f"{lo} -> {hi}", "pairs": n,
                "acc_points": 100 * sum(b["acc"] - a["acc"] for a, b in pairs) / n,
                "infer_factor": math.exp(sum(math.log(b["infer_ms_per_shape"] / a["infer_ms_per_shape"])
                                             for a, b in pairs) / n),
                "train_factor": math.exp(sum(math.log(b["train_seconds_per_shape"] / a["train_seconds_per_shape"])
                                             for a, b in pairs) / n)})
    return sorted(effects, key=lambda e: -abs(e["acc_points"]))


def _label(row: dict, swept: list[str]) -> str:
    return ",".join(f"{k.split('.')[-1]}={row[k]}" for k in swept) or row["setting"]


def pareto_png(rows: list[dict], swept: list[str], path, metric: str = "test_acc") -> Path:
    from ..viz.plots import pyplot, save_figure

    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(13, 5.5))
    for ax, key, flag, xlabel in ((axes[0], "infer_ms_per_shape", "pareto_infer", "inference ms per shape"),
                                  (axes[1], "train_seconds_per_shape", "pareto_train", "training s per shape")):
        for front in (False, True):
            pts = [r for r in rows if r[flag] == front]
            if pts:
                ax.errorbar([r[key] for r in pts], [r["acc"] for r in pts], yerr=[r["acc_std"] for r in pts],
                            fmt="o" if front else ".", color="C3" if front else "0.55", capsize=2,
                            label="Pareto-optimal" if front else "other settings")
        line = sorted((r for r in rows if r[flag]), key=lambda r: r[key])
        ax.plot([r[key] for r in line], [r["acc"] for r in line], "-", color="C3", alpha=0.6)
        for r in line:
            ax.annotate(_label(r, swept), (r[key], r["acc"]), fontsize=7, xytext=(3, 3),
                        textcoords="offset points")
        ax.set_xscale("log")
        ax.xaxis.set_minor_formatter(plt.NullFormatter())  # minor labels overlap on short ranges
        ax.margins(x=0.25)  # room for the labels of the last points
        ax.set_xlabel(xlabel)
        ax.set_ylabel(f"{'validation' if metric == 'best_val_acc' else 'test'} accuracy (mean, std over runs)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="best")
    return save_figure(fig, path)


def _csv(path: Path, rows: list[dict], fields: list[str]) -> None:
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)


def _metric_rows(sweep_dir: Path, metric: str, retimed: bool = False, seed: int | None = None) -> list[dict]:
    if metric not in METRICS:
        raise TradeoffError(f"--metric {metric}: expected one of {', '.join(METRICS)}")
    rows = job_rows(sweep_dir, retimed, seed)
    for r in rows:
        if r.get("status") == "ok" and r.get(metric) is None:
            raise TradeoffError(f"{sweep_dir / r['job'] / METRICS_FILE}: no {metric}")
    return rows


def _timing_line(retimed: bool) -> str:
    return ("Inference ms per shape: each run's test pass timed again, one run at a time in one process "
            "(`retimed.json`: the median of its passes after a warm-up), not as timed inside the training job."
            if retimed else "Inference ms per shape: as timed inside each training job (beside whatever ran there).")


def write_tradeoff(sweep_dir, metric: str = "test_acc", retimed: bool = False, seed: int | None = None) -> dict:
    """Write the four files (module docstring) into ``sweep_dir``; returns their paths, the setting
    rows, the key effects and the failed jobs. Raises ``TradeoffError`` for a folder it cannot read.
    ``retimed`` / ``seed``: inference times from the jobs' ``retimed.json``, one seed's jobs (``job_rows``)."""
    sweep_dir = Path(sweep_dir)
    rows = _metric_rows(sweep_dir, metric, retimed, seed)
    per_setting, swept = settings(rows, metric)
    effects = key_effects(per_setting, swept)
    failed = failed_jobs(sweep_dir, rows)
    val = metric == "best_val_acc"
    jobs = [{**_override_values(r["overrides"]), **r} for r in rows]
    name = {n: sweep_dir / output_name(n, seed) for n in ("tradeoff_jobs.csv", "tradeoff.csv", "tradeoff.md", "pareto.png")}
    _csv(name["tradeoff_jobs.csv"], jobs, ["job", *swept, "seed", "status", "best_val_acc", "test_acc", *COST_FIELDS])
    _csv(name["tradeoff.csv"], per_setting, [*swept, "seeds", *(("acc", "acc_std") if val else ()), "test_acc",
                                                   "test_acc_std", *COST_FIELDS, "pareto_infer", "pareto_train"])
    head = "val acc | test acc" if val else "test acc"
    lines = ["# Speed/accuracy trade", "", f"{len(rows)} jobs in `{sweep_dir}`"
             f"{'' if seed is None else f' (those of seed {seed})'}, {len(per_setting)} settings, "
             f"dataset `{next(r['dataset'] for r in rows if r.get('status') == 'ok')}`; the front on "
             f"{'validation accuracy (test accuracy beside it, read once per run)' if val else 'test accuracy'}.", "",
             "P: Pareto-optimal (inference / training time): no setting is at least as accurate and as fast.",
             _timing_line(retimed), "",
             "| " + " | ".join(swept) + f" | runs | {head} | infer ms/shape | train s/shape | train / infer peak MiB "
             "| params G / C | GFLOPs G / C per shape | render ms/shape | P |",
             "|" + "---|" * (len(swept) + 9 + val)]
    for r in sorted(per_setting, key=lambda r: r["infer_ms_per_shape"]):
        p = ("I" if r["pareto_infer"] else "-") + ("T" if r["pareto_train"] else "-")
        acc = (f"{r['acc']:.3f} ± {r['acc_std']:.3f} | " if val else "") + f"{r['test_acc']:.3f} ± {r['test_acc_std']:.3f}"
        lines.append("| " + " | ".join(str(r[k]) for k in swept) + f" | {r['seeds']} | {acc} | "
                     f"{r['infer_ms_per_shape']:.2f} | {r['train_seconds_per_shape']:.3f} | "
                     f"{r['train_peak_mib']:.0f} / {r['infer_peak_mib']:.0f} | {r['params_selector']:.0f} / "
                     f"{r['params_mvnet']:.0f} | {r['flops_selector_per_shape'] / 1e9:.3g} / "
                     f"{r['flops_mvnet_per_shape'] / 1e9:.3g} | {r['render_ms_per_shape']:.1f} | {p} |")
    lines += ["", "## Which keys matter (mean over settings that differ only in the key)", "",
              f"| key | step | pairs | {'val' if val else 'test'} acc change (points) | inference time x | training time x |",
              "|---|---|---|---|---|---|"]
    lines += [f"| {e['key']} | {e['step']} | {e['pairs']} | {e['acc_points']:+.1f} | {e['infer_factor']:.2f} | "
              f"{e['train_factor']:.2f} |" for e in effects]
    if failed:
        lines += ["", f"## Failed jobs ({len(failed)}, not in the tables)", ""] + [f"- {f}" for f in failed]
    md = name["tradeoff.md"]
    md.write_text("\n".join(lines) + "\n")
    png = pareto_png(per_setting, swept, name["pareto.png"], metric)
    return {"csv": name["tradeoff.csv"], "jobs_csv": name["tradeoff_jobs.csv"], "md": md, "png": png,
            "settings": per_setting, "effects": effects, "failed": failed}


def hypervolume(points: list[tuple[float, float]], ref: tuple[float, float]) -> float:
    """The area dominated by ``points`` (accuracy up, time down) and bounded by ``ref`` = (accuracy,
    time), in accuracy points x decades of time (time on a log10 axis, as the trade is read).
    Points no better than ``ref`` in either objective add nothing."""
    ref_acc, ref_t = ref
    pts = sorted((t, a) for a, t in points if a > ref_acc and 0 < t < ref_t)
    area, best = 0.0, ref_acc
    for i, (t, a) in enumerate(pts):
        best = max(best, a)
        right = pts[i + 1][0] if i + 1 < len(pts) else ref_t
        area += 100 * (best - ref_acc) * (math.log10(right) - math.log10(t))
    return area


def _elapsed_s(sweep_dir: Path, rows: list[dict]) -> float:
    """From the first job's start (``folders.started_at``) to the last result (``folders.finished_at``)."""
    starts = [t for t in (started_at(sweep_dir / r["job"]) for r in rows) if t is not None]
    ends = [finished_at(sweep_dir / r["job"]) for r in rows if r.get("status") == "ok"]
    return max(ends) - min(starts) if starts and ends else float("nan")


def _job_seconds(rows: list[dict]) -> float | None:
    """The finished jobs' ``train_wall_seconds`` summed; None when one lacks it (runs before it was recorded)."""
    walls = [r.get("train_wall_seconds") for r in rows if r.get("status") == "ok"]
    return None if any(w is None for w in walls) else float(sum(walls))


def _minutes(seconds) -> str:
    return "n/a" if seconds is None or seconds != seconds else f"{seconds / 60:.1f} min"


def compare_fronts(dirs, metric: str = "best_val_acc", retimed: bool = False, seed: int | None = None) -> dict:
    """The inference-time fronts of several folders (a search against a grid) by hypervolume, all
    with one reference point: the lowest accuracy and the longest inference time of any setting
    of any folder. Returns ``rows`` (folder, jobs, settings, front size, hypervolume, elapsed s)
    and ``md`` (the table)."""
    found = []
    for d in map(Path, dirs):
        rows = _metric_rows(d, metric, retimed, seed)
        found.append((d, rows, settings(rows, metric)[0]))
    every = [s for _, _, per in found for s in per]
    ref = (min(s["acc"] for s in every), max(s["infer_ms_per_shape"] for s in every))
    out = []
    for d, rows, per in found:
        front = [s for s in per if s["pareto_infer"]]
        out.append({"dir": str(d), "jobs": len(rows), "finished": sum(r.get("status") == "ok" for r in rows),
                    "settings": len(per), "front": len(front), "elapsed_s": _elapsed_s(d, rows),
                    "job_s": _job_seconds(rows),
                    "hypervolume": hypervolume([(s["acc"], s["infer_ms_per_shape"]) for s in front], ref),
                    "best_acc": max(s["acc"] for s in per)})
    lines = [f"Hypervolume of each folder's front ({'validation' if metric == 'best_val_acc' else 'test'} accuracy "
             f"against inference ms per shape), in accuracy points x decades of time, from the common reference "
             f"(accuracy {ref[0]:.3f}, {ref[1]:.2f} ms: the worst of every setting)"
             f"{'' if seed is None else f', the runs of seed {seed} only'}. {_timing_line(retimed)}", "",
             "Job time: the finished jobs' training and validation seconds summed (`train_wall_seconds`); elapsed: "
             "from the first job's start to the last result, pauses included.", "",
             "| folder | jobs (finished) | settings | front | best acc | hypervolume | job time | elapsed |",
             "|---|---|---|---|---|---|---|---|"]
    lines += [f"| `{r['dir']}` | {r['jobs']} ({r['finished']}) | {r['settings']} | {r['front']} | {r['best_acc']:.3f} | "
              f"{r['hypervolume']:.2f} | {_minutes(r['job_s'])} | {_minutes(r['elapsed_s'])} |" for r in out]
    return {"rows": out, "ref": ref, "md": "\n".join(lines) + "\n"}
