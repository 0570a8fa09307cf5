"""Sweep summaries: after ``mvtn-train -m ...``, one table of every job's metrics (``summary.csv``,
``summary.md``) and one of mean +- std over seeds per setting, in the sweep folder."""
from __future__ import annotations

import csv
import math
import sys
from pathlib import Path

from hydra.experimental.callback import Callback

from ..config.compose import override_key
from ..engine import stopping
from .folders import STATUS_FILE, Run, sweep_jobs  # noqa: F401 (STATUS_FILE re-exported)
from .settings import is_local

COLUMNS = ("test_acc", "test_mean_class_acc", "best_val_acc", "mean_epoch_seconds", "test_view_offset_azim",
           "test_view_offset_elev", "test_view_spread", "test_view_separation")


def job_row(run: Run) -> dict:
    """A job's row: ``job`` (its folder's name), ``overrides``, ``status``, then its ``COLUMNS``
    metrics when it finished, or its ``error`` when one is recorded."""
    row = {"job": run.job, "overrides": run.overrides, "status": run.status}
    if run.status == "ok":
        row.update({k: run.metrics.get(k) for k in COLUMNS})
    elif run.error:
        row["error"] = run.error
    return row


def collect(sweep_dir) -> list[dict]:
    """One row per job of the sweep in ``sweep_dir`` (``folders.sweep_jobs``: natural order), ``job_row``."""
    return [job_row(run) for run in sweep_jobs(sweep_dir)]


def _setting(overrides: list[str]) -> str:
    """The overrides that define a setting (``run_keys``: jobs that differ only in ``seed``, the
    device, threads, paths or logging are one setting)."""
    keys = [o for o in overrides if not is_local(o.split("=", 1)[0])]
    return ",".join(keys) or "(defaults)"


def aggregate(rows: list[dict]) -> list[dict]:
    """Mean and sample std (n-1) of each metric over the successful jobs of each setting."""
    groups: dict[str, list[dict]] = {}
    for r in rows:
        groups.setdefault(_setting(r["overrides"]), []).append(r)
    out = []
    for setting, members in groups.items():
        ok = [r for r in members if r.get("status") == "ok"]
        agg = {"setting": setting, "runs": len(ok), "failed": len(members) - len(ok)}
        for key in COLUMNS:
            vals = [float(r[key]) for r in ok if r.get(key) is not None]
            mean = sum(vals) / len(vals) if vals else float("nan")
            std = math.sqrt(sum((v - mean) ** 2 for v in vals) / (len(vals) - 1)) if len(vals) > 1 else 0.0
            agg[key] = mean
            agg[f"{key}_std"] = std
        out.append(agg)
    return out


def _fmt(v) -> str:
    return f"{v:.4f}" if isinstance(v, float) else str(v)


def _override_values(overrides: list[str]) -> dict[str, str]:
    """``["+a.b=1", "c=x"]`` -> ``{"a.b": "1", "c": "x"}`` (in order; entries without ``=`` skipped)."""
    return {override_key(o): o.split("=", 1)[1] for o in overrides if "=" in o}


def write_summary(sweep_dir) -> tuple[Path, Path]:
    """Write ``summary.csv`` (one row per job, one column per overridden key, then status and
    metrics) and ``summary.md`` (per job and mean +- std per setting) into ``sweep_dir``; returns
    their paths."""
    sweep_dir = Path(sweep_dir)
    rows = collect(sweep_dir)
    csv_path, md_path = sweep_dir / "summary.csv", sweep_dir / "summary.md"
    values = [_override_values(r["overrides"]) for r in rows]
    keys = list(dict.fromkeys(k for v in values for k in v))  # one column per overridden key, first-seen order
    fields = ["job", *keys, "status", *COLUMNS, "error"]
    with open(csv_path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields, extrasaction="ignore")
        w.writeheader()
        for r, v in zip(rows, values):
            w.writerow({**{k: r.get(k, "") for k in fields if k not in keys}, **{k: v.get(k, "") for k in keys}})
    aggs = aggregate(rows)
    lines = ["# Sweep summary", "", f"{len(rows)} jobs in `{sweep_dir}`.", "",
             "## Mean +- std over seeds (sample std)", "",
             "| setting | runs | failed | test acc | mean class acc | best val acc | s/epoch | mean view offset azim (deg) | mean view offset elev (deg) | view spread over shapes (deg) | nearest two views of a shape (deg) |",
             "|---|---|---|" + "---|" * len(COLUMNS)]
    for a in aggs:
        cells = [f"{a[k]:.3f} ± {a[k + '_std']:.3f}" for k in COLUMNS]
        lines.append(f"| {a['setting']} | {a['runs']} | {a['failed']} | " + " | ".join(cells) + " |")
    lines += ["", "## Jobs", "", "| job | status | " + " | ".join(COLUMNS) + " |",
              "|---|---|" + "---|" * len(COLUMNS)]
    for r in rows:
        lines.append(f"| {r['job']} | {r.get('status')} | " + " | ".join(_fmt(r.get(k, '')) for k in COLUMNS) + " |")
    md_path.write_text("\n".join(lines) + "\n")
    return csv_path, md_path


def failed_jobs(sweep_dir, rows: list[dict] | None = None) -> list[str]:
    """``"<job>: <status>[: <error>]"`` for every job of the sweep (``rows``: its ``collect``) that
    did not finish with metrics."""
    return [f"{r['job']}: {r.get('status')}" + (f": {r['error']}" if r.get("error") else "")
            for r in (collect(sweep_dir) if rows is None else rows) if r.get("status") != "ok"]


def expected_jobs(sweep_dir) -> int | None:
    """How many jobs the sweep in ``sweep_dir`` launches (the product of its swept values, from its
    ``multirun.yaml``); None without that record."""
    import yaml
    from hydra.core.override_parser.overrides_parser import OverridesParser

    record = Path(sweep_dir) / "multirun.yaml"
    if not record.is_file():
        return None
    task = ((yaml.safe_load(record.read_text()) or {}).get("hydra") or {}).get("overrides", {}).get("task") or []
    n = 1
    for o in OverridesParser.create().parse_overrides([str(t) for t in task]):
        if o.is_sweep_override():
            n *= len(list(o.sweep_string_iterator()))
    return n


def never_started(sweep_dir, rows: list[dict]) -> list[str]:
    """``"<k> job(s): never started"`` when the sweep's record promises more jobs than have folders."""
    n = expected_jobs(sweep_dir)
    missing = (n or 0) - len(rows)
    return [f"{missing} job(s): never started (mvtn-train --resume-sweep {sweep_dir})"] if missing > 0 else []


class SweepSummary(Callback):
    """Hydra callback: write the sweep summary when a multirun ends; exit 1 naming the failed jobs
    (after the summary is written) when any job failed."""

    def on_multirun_start(self, config, **kwargs) -> None:
        stopping.sweep_started(config.hydra.sweep.dir)  # where a Ctrl-C finds the jobs to stop

    def on_multirun_end(self, config, **kwargs) -> None:
        sweep_dir = Path(config.hydra.sweep.dir)
        if not sweep_dir.is_dir():
            return
        _, md = write_summary(sweep_dir)
        if stopping.sweep_stopping():  # interrupted: mvtn-train says so in one line
            return
        print(md.read_text())
        print(md)
        rows = collect(sweep_dir)
        failed = failed_jobs(sweep_dir, rows)
        if failed:
            print(f"mvtn-train: {len(failed)} of {len(rows)} sweep jobs failed: " + "; ".join(failed), file=sys.stderr)
            sys.exit(1)
