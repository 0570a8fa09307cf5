"""mvtn-tradeoff: settings over seeds, the Pareto front and key effects against hand-worked sweeps; bad folders exit 2."""
from __future__ import annotations

import csv
import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from mvtn_exp.cli.tradeoff import main
from mvtn_exp.engine.cost import RENDERER_NOTE
from mvtn_exp.runs.tradeoff import COST_FIELDS, write_tradeoff

from test_sweep_summary import _job


def _metrics(acc, infer_ms, train_s, dataset="synthetic"):
    cost = dict.fromkeys(COST_FIELDS, 1.0)
    cost.update(infer_ms_per_shape=infer_ms, train_seconds_per_shape=train_s, renderer_note=RENDERER_NOTE)
    return {"test_acc": acc, "test_mean_class_acc": acc, "best_val_acc": acc, "mean_epoch_seconds": 1.0,
            "cost": cost, "config": {"dataset": {"name": dataset}}}


# views x image_size, two seeds each: (acc seed 0, acc seed 1, inference ms, training s)
GRID = {(1, 32): (0.50, 0.60, 1.0, 0.10), (1, 64): (0.70, 0.70, 3.0, 0.30),
        (4, 32): (0.60, 0.70, 4.0, 0.20), (4, 64): (0.90, 0.80, 12.0, 0.60)}


def _sweep(root):
    i = 0
    for (v, s), (a0, a1, ms, ts) in GRID.items():
        for seed, acc in ((0, a0), (1, a1)):
            _job(root, f"{i}_views={v},image_size={s},seed={seed}", [f"views={v}", f"image_size={s}", f"seed={seed}",
                 "logger.progress=false"], _metrics(acc, ms * (1 + 0.1 * seed), ts))
            i += 1
    return root


def test_settings_front_and_effects_match_hand_work(tmp_path):
    _sweep(tmp_path)
    _job(tmp_path, "8_views=12,image_size=64,seed=0", ["views=12", "image_size=64", "seed=0"],
         status={"status": "training diverged", "error": "non-finite loss"})
    out = write_tradeoff(tmp_path)
    rows = {(r["views"], r["image_size"]): r for r in out["settings"]}
    assert set(rows) == {("1", "32"), ("1", "64"), ("4", "32"), ("4", "64")}
    r = rows[("4", "64")]
    assert r["seeds"] == 2 and math.isclose(r["test_acc"], 0.85) and math.isclose(r["test_acc_std"], math.sqrt(0.005))
    assert math.isclose(r["infer_ms_per_shape"], 12.0 * 1.05)
    # inference front: 1x32 (0.55, 1.05 ms), 1x64 (0.70, 3.15), 4x64 (0.85, 12.6); 4x32 (0.65, 4.2) is beaten by 1x64
    assert {k for k, r in rows.items() if r["pareto_infer"]} == {("1", "32"), ("1", "64"), ("4", "64")}
    # training time: 0.1 / 0.2 / 0.3 / 0.6 s for 0.55 / 0.65 / 0.70 / 0.85: every setting is on the front
    assert {k for k, r in rows.items() if r["pareto_train"]} == {("1", "32"), ("4", "32"), ("1", "64"), ("4", "64")}
    eff = {(e["key"], e["step"]): e for e in out["effects"]}
    views = eff[("views", "1 -> 4")]  # pairs at 32 px (+0.10) and 64 px (+0.15)
    assert views["pairs"] == 2 and math.isclose(views["acc_points"], 12.5)
    assert math.isclose(views["infer_factor"], math.sqrt(4.0 * 4.0)) and math.isclose(views["train_factor"], 2.0)
    size = eff[("image_size", "32 -> 64")]  # +0.15 and +0.20
    assert math.isclose(size["acc_points"], 17.5) and math.isclose(size["infer_factor"], 3.0)
    assert out["effects"][0]["key"] == "image_size"  # the larger accuracy change first
    jobs = list(csv.DictReader(open(out["jobs_csv"])))
    assert len(jobs) == 9 and sum(j["status"] != "ok" for j in jobs) == 1
    assert len(list(csv.DictReader(open(out["csv"])))) == 4
    md = out["md"].read_text()
    assert "8_views=12,image_size=64,seed=0: training diverged" in md and out["failed"]
    assert out["png"].stat().st_size > 10_000


def test_one_seed_reads_only_that_seeds_runs_into_files_of_its_own(tmp_path, capsys):
    """--seed 1: each setting is its seed-1 run (the hand-made grid's second accuracy and time), the
    front and the hypervolume are that seed's, and the all-seed tables are left as they were."""
    _sweep(tmp_path)
    main([str(tmp_path)])
    whole = (tmp_path / "tradeoff.md").read_text()
    main([str(tmp_path), "--seed", "1", "--against", str(tmp_path)])
    assert (tmp_path / "tradeoff.md").read_text() == whole
    rows = {(r["views"], r["image_size"]): r for r in csv.DictReader(open(tmp_path / "tradeoff-seed1.csv"))}
    assert set(rows) == {(str(v), str(s)) for v, s in GRID}
    for (v, s), (_, a1, ms, _) in GRID.items():
        r = rows[(str(v), str(s))]
        assert (float(r["test_acc"]), float(r["infer_ms_per_shape"]), r["seeds"]) == pytest.approx((a1, ms * 1.1, "1"))
    # seed 1's inference front: 1x32 (0.60, 1.1 ms), 1x64 (0.70, 3.3), 4x64 (0.80, 13.2); 4x32 (0.70, 4.4) is beaten
    assert {k for k, r in rows.items() if r["pareto_infer"] == "True"} == {("1", "32"), ("1", "64"), ("4", "64")}
    assert "seed 1 only" in (tmp_path / "fronts-seed1.md").read_text() and (tmp_path / "pareto-seed1.png").is_file()
    with pytest.raises(SystemExit) as e:
        main([str(tmp_path), "--seed", "7"])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 1 and "among 0 of seed 7" in err[0], err


@pytest.mark.parametrize("make, needle", [
    (lambda d: None, "no finished job"),
    (lambda d: _job(d, "0_seed=0", ["seed=0"], status={"status": "failed", "error": "x"}), "no finished job"),
    (lambda d: (_job(d, "0_a=1", ["a=1"], _metrics(0.5, 1, 1)), _job(d, "1_a=2", ["a=2"], _metrics(0.5, 1, 1, "modelnet40"))),
     "jobs from different datasets"),
    (lambda d: _job(d, "0_a=1", ["a=1"], {"test_acc": 0.5, "config": {"dataset": {"name": "synthetic"}}}),
     "no cost fields"),
])
def test_bad_folders_are_one_line_and_exit_2(tmp_path, capsys, make, needle):
    make(tmp_path)
    with pytest.raises(SystemExit) as e:
        main([str(tmp_path)])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0] and str(tmp_path) in err[0] and err[0].startswith("mvtn-tradeoff: ")
    assert not (tmp_path / "tradeoff.md").exists()


def test_cli_prints_the_table_and_the_path_last(tmp_path):
    _sweep(tmp_path)
    out = subprocess.run([sys.executable, "-m", "mvtn_exp.cli.tradeoff", str(tmp_path)], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.strip().splitlines()
    assert lines[-1] == str(tmp_path / "tradeoff.md") and "| views | image_size | runs |" in out.stdout


@pytest.fixture(scope="module")
def trained_sweep(tmp_path_factory):
    """Two one-epoch runs (fixed and learned views) of a real sweep."""
    import os

    root = tmp_path_factory.mktemp("retime")
    r = subprocess.run([sys.executable, "-m", "mvtn_exp.cli.train", "-m", "selector=spherical,mvtn_spherical", "epochs=1",
                        "views=1", "image_size=16", "backbone=small_cnn", "dataset.num_per_class=[2,2,2]", "threads=1",
                        "logger.progress=false", f"paths.cache_dir={root / 'cache'}", f"hydra.sweep.dir={root / 'sweep'}"],
                       capture_output=True, text=True, timeout=600, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert r.returncode == 0, r.stderr[-2000:]
    return root / "sweep"


def _copy(sweep, tmp_path):
    import shutil

    return Path(shutil.copytree(sweep, tmp_path / "sweep"))


def test_retime_times_each_run_again_and_the_fronts_use_those_times(trained_sweep, tmp_path, capsys):
    """--retime rebuilds each finished run from its best.pt, reproduces its test accuracy, and the
    tables and fronts carry the new times (the runs' own, here made absurd, are not used)."""
    sweep = _copy(trained_sweep, tmp_path)
    jobs = sorted(p for p in sweep.iterdir() if (p / "metrics.json").is_file())
    assert len(jobs) == 2
    for job in jobs:
        m = json.loads((job / "metrics.json").read_text())
        m["cost"]["infer_ms_per_shape"] = 12345.0
        (job / "metrics.json").write_text(json.dumps(m))
    main([str(sweep), "--retime", "--passes", "2", "--metric", "best_val_acc", "--against", str(sweep)])
    out = capsys.readouterr().out
    assert "timed again" in out and "12345" not in out
    timed = {}
    for job in jobs:
        rec = json.loads((job / "retimed.json").read_text())
        assert len(rec["passes_ms"]) == 2 and rec["infer_ms_per_shape"] == pytest.approx(sum(rec["passes_ms"]) / 2)
        assert rec["test_acc"] == json.loads((job / "metrics.json").read_text())["test_acc"] and rec["threads"] == 1
        assert 0 < rec["infer_ms_per_shape"] < 12345.0
        timed[job.name] = rec["infer_ms_per_shape"]
    rows = {r["job"]: float(r["infer_ms_per_shape"]) for r in csv.DictReader(open(sweep / "tradeoff_jobs.csv"))}
    assert rows == pytest.approx(timed)
    assert "timed again" in (sweep / "fronts.md").read_text()
    # --retimed reads those times again without timing: the records stay as they were
    stamps = {job.name: (job / "retimed.json").stat().st_mtime_ns for job in jobs}
    main([str(sweep), "--retimed", "--seed", "0"])
    assert {job.name: (job / "retimed.json").stat().st_mtime_ns for job in jobs} == stamps
    rows = {r["job"]: float(r["infer_ms_per_shape"]) for r in csv.DictReader(open(sweep / "tradeoff_jobs-seed0.csv"))}
    assert rows == pytest.approx(timed)
    (jobs[0] / "retimed.json").unlink()
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        main([str(sweep), "--retimed"])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 1 and "retimed.json: not found" in err[0], err


@pytest.mark.parametrize("spoil, needle", [
    (lambda job: (job / "best.pt").unlink(), "best.pt: not found"),
    (lambda job: (job / "metrics.json").write_text(json.dumps({**json.loads((job / "metrics.json").read_text()),
                                                               "test_acc": 0.123456})), "disagree"),
])
def test_retime_refuses_a_run_it_cannot_reproduce_in_one_line(trained_sweep, tmp_path, capsys, spoil, needle):
    sweep = _copy(trained_sweep, tmp_path)
    job = sorted(p for p in sweep.iterdir() if (p / "metrics.json").is_file())[0]
    spoil(job)
    with pytest.raises(SystemExit) as e:
        main([str(sweep), "--retime"])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 1 and needle in err[0] and err[0].startswith("mvtn-tradeoff: "), err
    assert not (sweep / "tradeoff.md").exists()
