"""The trade searched (``+experiment=tradeoff_search``): runs return their objectives to Optuna's
NSGA-II, keys only some options have are sampled only for them, test metrics are refused as
objectives, and ``mvtn-tradeoff`` draws the front on validation and sets fronts side by side by
hypervolume (hand-worked)."""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import pytest
import yaml

from mvtn_exp.engine.jobs import objective_values
from mvtn_exp.cli.tradeoff import main as tradeoff_main
from mvtn_exp.plugins.trade_search import CONDITIONAL, conditional_keys
from mvtn_exp.runs.tradeoff import compare_fronts, hypervolume, write_tradeoff

from test_sweep_summary import _job
from test_tradeoff import _metrics


def test_hypervolume_matches_hand_work():
    ref = (0.4, 100.0)
    # sorted by time: (1 ms, 0.5) over [1, 10): 10 points x 1 decade; (10 ms, 0.7) over [10, 100): 30 x 1
    assert math.isclose(hypervolume([(0.5, 1.0), (0.7, 10.0)], ref), 40.0)
    # a dominated point, a point below the reference accuracy and one past the reference time add nothing
    assert math.isclose(hypervolume([(0.5, 1.0), (0.7, 10.0), (0.45, 5.0), (0.3, 0.5), (0.9, 200.0)], ref), 40.0)
    # a faster point of equal accuracy widens the area by its extra decade
    assert math.isclose(hypervolume([(0.5, 0.1), (0.7, 10.0)], ref), 40.0 + 10.0)
    assert hypervolume([], ref) == 0.0


def _trial_dir(root, rows):
    """rows: (job name, overrides, val acc, test acc, inference ms)"""
    for name, overrides, val, test, ms in rows:
        m = _metrics(test, ms, 0.01)
        m["best_val_acc"], m["train_wall_seconds"] = val, 30.0
        _job(root, name, overrides, m)
    return root


def test_front_on_validation_and_fronts_by_hypervolume(tmp_path, capsys):
    search = _trial_dir(tmp_path / "search", [
        ("0", ["views=1", "image_size=32"], 0.60, 0.90, 1.0),   # best on test, not on validation
        ("1", ["views=2", "image_size=32"], 0.70, 0.50, 2.0),
        ("2", ["views=4", "image_size=64"], 0.65, 0.95, 8.0),   # beaten on validation by views=2
    ])
    grid = _trial_dir(tmp_path / "grid", [
        (f"{i}", [f"views={v}", "image_size=32", f"seed={s}"], acc, acc, ms)
        for i, (v, s, acc, ms) in enumerate([(1, 0, 0.50, 1.0), (1, 1, 0.60, 1.0), (2, 0, 0.60, 4.0), (2, 1, 0.60, 4.0)])])
    out = write_tradeoff(search, "best_val_acc")
    front = {r["views"] for r in out["settings"] if r["pareto_infer"]}
    assert front == {"1", "2"}  # on test views=4 (0.95) would be on it
    md = out["md"].read_text()
    assert "val acc | test acc" in md and "0.700 ± 0.000 | 0.500 ± 0.000" in md
    assert {r["views"] for r in write_tradeoff(search, "test_acc")["settings"] if r["pareto_infer"]} == {"1", "4"}
    fronts = compare_fronts([search, grid])
    # common reference: the worst accuracy (grid views=1: mean 0.55) and the longest time (8 ms)
    assert fronts["ref"] == (pytest.approx(0.55), 8.0)
    hv = {r["dir"]: r["hypervolume"] for r in fronts["rows"]}
    want_search = 100 * (0.60 - 0.55) * math.log10(2) + 100 * (0.70 - 0.55) * math.log10(8 / 2)
    want_grid = 100 * (0.60 - 0.55) * math.log10(8 / 4)  # views=1 sits at the reference accuracy
    assert hv[str(search)] == pytest.approx(want_search) and hv[str(grid)] == pytest.approx(want_grid)
    # job time: the jobs' own seconds summed (3 and 4 jobs of 30 s), not the folder's elapsed time
    assert {r["dir"]: r["job_s"] for r in fronts["rows"]} == {str(search): 90.0, str(grid): 120.0}
    assert "| 1.5 min |" in fronts["md"] and "| 2.0 min |" in fronts["md"]
    tradeoff_main([str(search), "--metric", "best_val_acc", "--against", str(grid)])
    printed = capsys.readouterr().out
    assert "## Fronts" in printed and f"{want_search:.2f}" in printed and (search / "fronts.md").is_file()


def test_a_run_without_the_metric_is_one_line_exit_2(tmp_path, capsys):
    _job(tmp_path, "0", ["views=1"], {k: v for k, v in _metrics(0.5, 1.0, 0.1).items() if k != "best_val_acc"})
    with pytest.raises(SystemExit) as e:
        tradeoff_main([str(tmp_path), "--metric", "best_val_acc"])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 1 and "no best_val_acc" in err[0] and "metrics.json" in err[0]


def test_objective_values_read_the_metrics(tmp_path):
    (tmp_path / "metrics.json").write_text(json.dumps({"best_val_acc": 0.75, "test_acc": 0.9,
                                                       "cost": {"infer_ms_per_shape": 2.5}}))
    assert objective_values(tmp_path, ["best_val_acc", "cost.infer_ms_per_shape"]) == [0.75, 2.5]
    assert objective_values(tmp_path, ["cost.infer_ms_per_shape", "best_val_acc"]) == [2.5, 0.75]  # in order
    assert objective_values(tmp_path, []) is None
    assert objective_values(tmp_path, ["cost.train_peak_mib"]) is None  # not recorded: a failed trial
    assert objective_values(tmp_path / "missing", ["best_val_acc"]) is None


@pytest.mark.parametrize("value, needle", [("[test_acc]", "reads the test split"),
                                           ("[val_acc]", "expected one of best_val_acc")])
def test_objectives_refuse_test_metrics_and_unknown_names(value, needle):
    r = subprocess.run([sys.executable, "-m", "mvtn_exp.cli.train", f"objectives={value}"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and needle in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr


class _Trial:
    def __init__(self, params):
        self.params = dict(params)
        self.user_attrs = {}

    def suggest_categorical(self, name, choices):
        self.params[name] = choices[-1]
        return choices[-1]


@pytest.mark.parametrize("selector, renderer, want", [
    ("spherical", "hard", set()),
    ("mvtn_spherical", "hard", {"selector.num_points"}),
    ("spherical", "soft", {"renderer.faces_per_pixel"}),
    ("mvtn_poi", "soft", {"selector.num_points", "renderer.faces_per_pixel"}),
])
def test_conditional_keys_only_where_the_option_uses_them(selector, renderer, want):
    trial = _Trial({"selector": selector, "renderer": renderer})
    conditional_keys(None, trial)
    assert set(trial.params) - {"selector", "renderer"} == want


def test_conditional_keys_read_options_fixed_on_the_command_line():
    """``selector=`` given on the command line (the sweeper keeps it as a user attribute) decides
    as a sampled one does; an option in neither place leaves its key alone."""
    trial = _Trial({"renderer": "hard"})
    trial.user_attrs = {"selector": "mvtn_spherical"}
    conditional_keys(None, trial)
    assert set(trial.params) == {"renderer", "selector.num_points"}
    trial = _Trial({"selector": "spherical"})
    conditional_keys(None, trial)
    assert set(trial.params) == {"selector"}


def test_every_value_of_the_search_space_composes():
    """Every choice of every key, and of each conditional key with an option that uses it, composes
    and validates (so no trial of the search is refused)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    from test_config import _compose

    conf = yaml.safe_load(open("mvtn_exp/conf/experiment/tradeoff_search.yaml"))
    parsed = OverridesParser.create().parse_overrides([f"{k}={v}" for k, v in conf["hydra"]["sweeper"]["params"].items()])
    seen = 0
    for o in parsed:
        for value in o.sweep_string_iterator():
            cfg = _compose(["+experiment=tradeoff_search", f"{o.get_key_element()}={value}"])
            assert cfg.objectives == ["best_val_acc", "cost.infer_ms_per_shape"]
            seen += 1
    assert seen == 2 + 2 + 5 + 3 + 2
    for key, (choices, _) in CONDITIONAL.items():
        for value in choices:
            cfg = _compose(["+experiment=tradeoff_search", "selector=mvtn_spherical", "renderer=soft", f"{key}={value}"])
            part, leaf = key.split(".")
            assert getattr(getattr(cfg, part), leaf) == value


TINY = ["epochs=1", "views=1", "image_size=16", "backbone=small_cnn", "dataset.num_per_class=[2,2,2]", "threads=1",
        "logger.progress=false"]


def _search(tmp_path, *args):
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, "-m", "mvtn_exp.cli.train", "-m", "+experiment=tradeoff_search", *TINY, *args,
                           f"paths.cache_dir={tmp_path / 'cache'}", f"hydra.sweep.dir={tmp_path / 'sweep'}"],
                          capture_output=True, text=True, timeout=600, env=env)


def _rows(sweep):
    import csv

    return list(csv.DictReader(open(sweep / "search.csv")))


@pytest.mark.slow  # (longer than 15 s on 2 cores: make test-all)
def test_the_search_starts_at_its_points_hands_optuna_the_objectives_and_resumes(tmp_path):
    """One-epoch trials through the project's Optuna sweeper: the first trials are the start points,
    the Pareto solutions it records are the objectives the trials' metrics.json hold, and the same
    command with a larger budget into the same folder keeps the finished trials (the same settings
    in the same folders, not trained again) and trains only the new ones."""
    r = _search(tmp_path, "hydra.sweeper.n_trials=3", "hydra.sweeper.n_jobs=3")
    assert r.returncode == 0, r.stderr[-2000:]
    sweep = tmp_path / "sweep"
    jobs = sorted(p for p in sweep.iterdir() if (p / "metrics.json").is_file())
    assert len(jobs) == 3
    recorded = [[m["best_val_acc"], m["cost"]["infer_ms_per_shape"]]
                for m in (json.loads((p / "metrics.json").read_text()) for p in jobs)]
    solutions = yaml.safe_load(open(sweep / "optimization_results.yaml"))["solutions"]
    assert solutions and all(s["values"] in recorded for s in solutions)
    overrides = {p.name.split("_")[0]: dict(x.split("=", 1) for x in yaml.safe_load(open(p / ".hydra" / "overrides.yaml")))
                 for p in jobs}
    for o in overrides.values():
        assert ("selector.num_points" in o) == (o["selector"] == "mvtn_spherical")
        assert ("renderer.faces_per_pixel" in o) == (o["renderer"] == "soft")
    # the start points (conf/experiment/tradeoff_search.yaml) are jobs 0 and 1
    assert (overrides["0"]["selector"], overrides["0"]["renderer"]) == ("spherical", "hard")
    assert (overrides["1"]["selector"], overrides["1"]["renderer"], overrides["1"]["selector.num_points"]) == \
        ("mvtn_spherical", "hard", "256")
    assert [row["state"] for row in _rows(sweep)] == ["run"] * 3
    cut = next(p for p in jobs if p.name.startswith("2_"))  # as if the search was stopped during job 2's last epoch
    (cut / "metrics.json").unlink()
    (cut / "status.json").write_text(json.dumps({"status": "interrupted", "error": ""}))
    before = {p.name: (p / "metrics.json").stat().st_mtime_ns for p in jobs if p != cut}

    r = _search(tmp_path, "hydra.sweeper.n_trials=4", "hydra.sweeper.n_jobs=3")
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stderr.count("finished before; kept") == 2
    assert "started again: going on from" in (cut / "train.log").read_text() and (cut / "metrics.json").is_file()
    after = sorted(p for p in sweep.iterdir() if (p / "metrics.json").is_file())
    assert len(after) == 4 and all((sweep / name / "metrics.json").stat().st_mtime_ns == t for name, t in before.items())
    assert [row["job"] for row in _rows(sweep) if row["state"] == "run"] == ["0", "1", "2", "3"]
    # as printed: --resume-sweep runs the folder's own command again and trains nothing
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    r = subprocess.run([sys.executable, "-m", "mvtn_exp.cli.train", "--resume-sweep", str(sweep)],
                       capture_output=True, text=True, timeout=600, env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stderr.count("finished before; kept") == 4


@pytest.mark.slow  # (about 10 s each on 2 cores: make test-all)
@pytest.mark.parametrize("jobs", [1, 2])
def test_a_setting_proposed_again_is_told_its_objectives_without_training(tmp_path, jobs):
    """A space of one setting: the first trial trains, every later proposal repeats it and launches
    nothing (with two trials asked at once, also the second of the first pair: told what the first
    got), and the search stops after max_repeats repeats in a row."""
    one = [f"hydra.sweeper.params.{k}={v}" for k, v in
           (("selector", "spherical"), ("renderer", "hard"), ("views", 1), ("image_size", 16), ("backbone", "small_cnn"))]
    r = _search(tmp_path, *one, "hydra.sweeper.start_points=[]", "hydra.sweeper.n_trials=3",
                f"hydra.sweeper.n_jobs={jobs}", "hydra.sweeper.max_repeats=4")
    assert r.returncode == 0, r.stderr[-2000:]
    sweep = tmp_path / "sweep"
    assert len([p for p in sweep.iterdir() if (p / ".hydra").is_dir()]) == 1
    rows = _rows(sweep)
    assert [row["state"] for row in rows] == ["run"] + ["repeat"] * 4
    assert len({(row["objective0"], row["objective1"]) for row in rows}) == 1
    assert yaml.safe_load(open(sweep / "optimization_results.yaml"))["trained"] == 1


@pytest.mark.parametrize("point, needle", [
    ("{renderer:wire}", "not in"),
    ("{colour:red}", "colour is not a key the search samples"),
])
@pytest.mark.slow  # (longer than 15 s on 2 cores: make test-all)
def test_a_start_point_outside_the_space_is_one_line_exit_2(tmp_path, point, needle):
    r = _search(tmp_path, "hydra.sweeper.n_trials=1", "hydra.sweeper.n_jobs=1", f"hydra.sweeper.start_points=[{point}]")
    assert r.returncode == 2, r.stderr[-2000:]
    line = r.stderr.strip().splitlines()[-1]
    assert line.startswith("mvtn-train: error: hydra.sweeper.start_points") and needle in line, r.stderr[-2000:]
    assert "Traceback" not in r.stderr
    assert not any(p.is_dir() and (p / ".hydra").is_dir() for p in (tmp_path / "sweep").iterdir())


def test_a_job_folder_of_another_setting_stops_the_search_before_launch(tmp_path):
    """The folder a trial would train in holds a run of another setting (the search changed since):
    one line naming the folder, exit 2, and that run is left as it was."""
    sweep = tmp_path / "sweep"
    _job(sweep, "0_other", ["selector=mvtn_spherical", "renderer=soft", "views=12"], {"best_val_acc": 0.5})
    r = _search(tmp_path, "hydra.sweeper.n_trials=1", "hydra.sweeper.n_jobs=1")
    assert r.returncode == 2
    line = r.stderr.strip().splitlines()[-1]
    assert line.startswith("mvtn-train: error: ") and "0_other" in line and "selector=spherical" in line
    assert "Traceback" not in r.stderr
    assert json.loads((sweep / "0_other" / "metrics.json").read_text()) == {"best_val_acc": 0.5}
    assert sorted(p.name for p in sweep.iterdir() if p.is_dir()) == ["0_other"]
