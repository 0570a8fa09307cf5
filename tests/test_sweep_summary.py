"""Sweep summary: rows per job, mean +- sample std per setting, failed jobs counted, files written."""
from __future__ import annotations

import csv
import json
import math

import pytest

from mvtn_exp.runs.sweep import STATUS_FILE, aggregate, write_summary


def _job(root, name, overrides, metrics=None, status=None):
    job = root / name
    (job / ".hydra").mkdir(parents=True)
    (job / ".hydra" / "overrides.yaml").write_text("".join(f"- {o}\n" for o in overrides))
    if metrics is not None:
        (job / "metrics.json").write_text(json.dumps(metrics))
    if status is not None:
        (job / STATUS_FILE).write_text(json.dumps(status))


def test_summary_groups_seeds_and_counts_failures(tmp_path):
    accs = {("circular", 0): 0.5, ("circular", 1): 0.7, ("circular", 2): 0.9, ("mvtn", 0): 0.8}
    for (sel, seed), acc in accs.items():
        _job(tmp_path, f"selector={sel},seed={seed}", [f"selector={sel}", f"seed={seed}", "dataset.root=/x/y"],
             {"test_acc": acc, "test_mean_class_acc": acc, "best_val_acc": acc, "mean_epoch_seconds": 2.0})
    _job(tmp_path, "selector=mvtn,seed=1", ["selector=mvtn", "seed=1"],
         status={"status": "training diverged", "error": "non-finite loss"})
    _job(tmp_path, "selector=mvtn,seed=2", ["selector=mvtn", "seed=2"])  # killed: no metrics, no status
    csv_path, md_path = write_summary(tmp_path)
    rows = list(csv.DictReader(open(csv_path)))
    assert len(rows) == 6
    assert sorted(r["status"] for r in rows) == ["incomplete", "ok", "ok", "ok", "ok", "training diverged"]
    assert list(rows[0])[:4] == ["job", "selector", "seed", "dataset.root"]  # one column per swept key
    assert {(r["selector"], r["seed"]) for r in rows} == {(s, str(i)) for s in ("circular", "mvtn") for i in range(3)}
    from mvtn_exp.runs.sweep import collect

    aggs = {a["setting"]: a for a in aggregate(collect(tmp_path))}
    assert set(aggs) == {"selector=circular", "selector=mvtn"}
    circ = aggs["selector=circular"]
    assert circ["runs"] == 3 and circ["failed"] == 0
    assert circ["test_acc"] == pytest.approx(0.7) and circ["test_acc_std"] == pytest.approx(0.2)
    mvtn = aggs["selector=mvtn"]
    assert mvtn["runs"] == 1 and mvtn["failed"] == 2 and mvtn["test_acc_std"] == 0.0
    assert math.isnan(mvtn["test_view_offset_azim"])  # not reported by these jobs
    md = md_path.read_text()
    assert "| selector=circular | 3 | 0 | 0.700 ± 0.200 |" in md
    for table in ("## Mean", "## Jobs"):  # every row of each table has the header's number of cells
        lines = [ln for ln in md.split(table, 1)[1].split("\n\n", 2)[1].splitlines() if ln.startswith("|")]
        assert len({ln.count("|") for ln in lines}) == 1, lines
    from mvtn_exp.runs.sweep import failed_jobs

    assert sorted(failed_jobs(tmp_path)) == ["selector=mvtn,seed=1: training diverged: non-finite loss",
                                             "selector=mvtn,seed=2: incomplete"]
