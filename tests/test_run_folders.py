"""One reader of run and sweep folders (``runs/folders.py``): sweep summaries, ``mvtn-tradeoff`` and
``mvtn-compare`` see the same jobs, statuses, seeds and overrides, and no other module reads them."""
from __future__ import annotations

import ast
import json
from pathlib import Path

import pytest

from mvtn_exp.runs import sweep, tradeoff
from mvtn_exp.runs.folders import NO_CONFIG, find_runs, sweep_jobs

PACKAGE = Path(__file__).resolve().parents[1] / "mvtn_exp"


def _job(root: Path, name: str, overrides: list[str], seed: int, metrics=None, status=None) -> Path:
    job = root / name
    (job / ".hydra").mkdir(parents=True)
    config = {"seed": seed, "views": int(overrides[0].split("=")[1]), "threads": 1, "dataset": {"name": "synthetic"}}
    (job / ".hydra" / "config.yaml").write_text(json.dumps(config))  # (JSON is YAML)
    (job / ".hydra" / "overrides.yaml").write_text("".join(f"- {o}\n" for o in overrides))
    if metrics is not None:
        (job / "metrics.json").write_text(json.dumps({**metrics, "config": config}))
    if status is not None:
        (job / "status.json").write_text(json.dumps(status))
    return job


def _sweep(root: Path) -> Path:
    """Jobs 10, 2, 1, 0 (made in that order): finished, failed, ok but its metrics gone, killed."""
    _job(root, "10", ["views=8"], seed=0)  # killed before any record; its seed only in its config
    _job(root, "2", ["views=4", "seed=1"], seed=1, status={"status": "ok", "error": ""})
    _job(root, "1", ["views=8", "seed=1"], seed=1, status={"status": "failed", "error": "boom"})
    cost = dict.fromkeys(tradeoff.COST_FIELDS, 1.0)
    _job(root, "0", ["views=4", "seed=0"], seed=0, metrics={"test_acc": 0.75, "best_val_acc": 0.7, "cost": cost})
    (root / "notes").mkdir()  # a folder without .hydra/: no job
    (root / "notes" / "readme.txt").write_text("not a job")
    return root


def test_one_reader_for_sweeps_tradeoff_and_compare(tmp_path):
    jobs = sweep_jobs(_sweep(tmp_path))
    assert [j.job for j in jobs] == ["0", "1", "2", "10"]  # natural order, not 0, 1, 10, 2
    assert [j.status for j in jobs] == ["ok", "failed", "incomplete", "incomplete"]
    assert [j.error for j in jobs] == ["", "boom", "", ""]
    assert [j.seed for j in jobs] == [0, 1, 1, 0]
    assert [j.overrides for j in jobs] == [["views=4", "seed=0"], ["views=8", "seed=1"], ["views=4", "seed=1"],
                                           ["views=8"]]
    assert jobs[0].metrics["test_acc"] == 0.75 and jobs[0].settings == {"views": 4, "dataset.name": "synthetic"}

    rows = sweep.collect(tmp_path)
    assert [(r["job"], r["status"], r["overrides"]) for r in rows] == [(j.job, j.status, j.overrides) for j in jobs]
    assert rows[0]["test_acc"] == 0.75 and rows[1]["error"] == "boom" and "error" not in rows[2]
    assert sweep.failed_jobs(tmp_path) == ["1: failed: boom", "2: incomplete", "10: incomplete"]

    assert [tradeoff.job_seed(j) for j in jobs] == [j.seed for j in jobs]
    assert [r["job"] for r in tradeoff.job_rows(tmp_path, seed=0)] == ["0", "10"]
    with pytest.raises(tradeoff.TradeoffError, match="among 2 of seed 1"):
        tradeoff.job_rows(tmp_path, seed=1)

    runs = {r.path.name: r for r in find_runs([tmp_path])}
    assert sorted(runs) == sorted(j.job for j in jobs)
    for j in jobs:
        r = runs[j.job]
        assert (r.status, r.seed, r.overrides, r.settings, r.error) == (j.status, j.seed, j.overrides, j.settings,
                                                                        j.error)


def test_a_finished_job_without_a_config_counts_in_its_sweep_and_is_unreadable_to_comparisons(tmp_path):
    job = tmp_path / "0"
    (job / ".hydra").mkdir(parents=True)
    (job / "metrics.json").write_text(json.dumps({"test_acc": 0.5}))
    (tmp_path / "1" / ".hydra").mkdir(parents=True)
    (tmp_path / "1" / "metrics.json").write_text("{not json")
    ok, broken = sweep_jobs(tmp_path)
    assert (ok.status, ok.settings, ok.overrides, ok.metrics) == ("ok", None, ["0"], {"test_acc": 0.5})
    assert broken.status == "unreadable" and broken.error
    assert [r["status"] for r in sweep.collect(tmp_path)] == ["ok", "unreadable"]
    compared = {r.path.name: r for r in find_runs([tmp_path])}
    assert (compared["0"].status, compared["0"].error, compared["0"].metrics) == ("unreadable", NO_CONFIG, {})
    assert compared["1"].status == "unreadable" and compared["1"].error == broken.error


RUN_FILES = {"metrics.json", "status.json", ".hydra", "config.yaml", "overrides.yaml"}
RUN_FILE_NAMES = {"STATUS_FILE", "METRICS_FILE", "HYDRA_DIR"}  # folders.py's constants for them
READS = {"loads", "load", "safe_load", "read_text", "read_bytes", "open", "is_file", "exists", "stat", "rglob", "glob"}


def _reads_of_run_files(path: Path) -> list[str]:
    """Every place in ``path`` that reads a run folder's file: a call that parses, opens, stats or
    finds one named in it (``json.loads((d / "metrics.json").read_text())``), or a path to one or its
    name outside an f-string (``metrics_file = d / "metrics.json"``: messages may name the file)."""
    src = path.read_text()
    tree = ast.parse(src)
    in_message = {id(n) for f in ast.walk(tree) if isinstance(f, ast.JoinedStr) for n in ast.walk(f)}
    found = []
    def text(node) -> str:  # (the segment only where needed: it rescans the source each time)
        return ast.get_source_segment(src, node) or ""

    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            name = node.func.attr if isinstance(node.func, ast.Attribute) else getattr(node.func, "id", "")
            hit = name in READS and any(f in text(node) for f in RUN_FILES | RUN_FILE_NAMES)
        else:
            hit = id(node) not in in_message and (isinstance(node, ast.Constant) and node.value in RUN_FILES
                                                  or isinstance(node, ast.Name) and node.id in RUN_FILE_NAMES)
        if hit:
            found.append(f"{path.relative_to(PACKAGE)}:{node.lineno}: {text(node)[:80]}")
    return found


def test_no_second_reader_of_run_folders():
    readers = [p for p in sorted((PACKAGE / "runs").glob("*.py")) if p.name != "folders.py"]
    readers += [PACKAGE / "cli" / f"{name}.py" for name in ("compare", "report", "tradeoff")]
    found = [hit for p in readers for hit in _reads_of_run_files(p)]
    assert not found, f"a second reader of run folders: {found}; read them through runs/folders.py"
    assert _reads_of_run_files(PACKAGE / "runs" / "folders.py")  # the check sees the one reader's reads


def test_an_old_record_with_every_options_keys_pairs_with_a_new_one():
    """A record from before datasets had one schema per option holds keys its dataset never had
    (``dataset.family``): they are left out, named, so old and new runs of one setting pair."""
    from mvtn_exp.runs.folders import Run
    from mvtn_exp.runs.sides import fill_added_keys

    new = {"dataset.name": "modelnet40", "dataset.format": "off", "views": 4}
    old = Run(Path("old"), "ok", seed=0, settings={**new, "dataset.family": "", "dataset.num_per_class": [24, 12, 24]})
    now = Run(Path("new"), "ok", seed=0, settings=dict(new))
    fill_added_keys([old, now])
    assert old.settings == now.settings
    assert sorted(old.filled) == ["-dataset.family", "-dataset.num_per_class"] and now.filled == []
