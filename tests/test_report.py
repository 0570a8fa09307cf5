"""``mvtn-report``: the paper's tables filled from finished runs and evaluations, and the packaged
tables consistent with the experiment files they name."""
from __future__ import annotations

import itertools
import json
import math
import subprocess
import sys

import pytest
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf

from mvtn_exp.runs.folders import find_runs, flatten
from mvtn_exp.runs.report import ReportError, load_tables, metric_value, report, row_matches, to_markdown
from mvtn_exp.engine.trainer import config_dict
from mvtn_exp.config.store import register_configs

register_configs()
GCN = {"dataset": {"name": "modelnet40"}, "mvnet": {"name": "viewgcn"}, "selector": {"name": "mvtn_spherical", "from_ckpt": None},
       "views": 12}
CIRC = {"dataset": {"name": "modelnet40"}, "mvnet": {"name": "mvcnn"}, "selector": {"name": "mvtn_circular"}, "views": 12}


def _run(folder, config, seed, **metrics):
    folder.mkdir(parents=True)
    (folder / "metrics.json").write_text(json.dumps({"config": {**config, "seed": seed}, **metrics}))
    return folder


def test_rows_filled_from_training_runs_and_evaluations(tmp_path):
    """Training runs fill the classification rows; an evaluation fills only what training does not
    write, once per checkpoint, on the test split; other runs are listed as unmatched."""
    _run(tmp_path / "a", GCN, 0, test_acc=0.90, test_mean_class_acc=0.88)
    _run(tmp_path / "b", GCN, 1, test_acc=0.92, test_mean_class_acc=0.90)
    rot = {"90": {"mean_acc": 0.7}, "180": {"mean_acc": 0.5}}
    _run(tmp_path / "c", CIRC, 0, test_acc=0.91)
    _run(tmp_path / "eval1", CIRC, 0, test_acc=0.1, ckpt="c/best.pt", split="test", rotation=rot)
    _run(tmp_path / "eval1_again", CIRC, 0, test_acc=0.1, ckpt="c/best.pt", split="test",
         rotation={"90": {"mean_acc": 0.0}, "180": {"mean_acc": 0.0}})
    _run(tmp_path / "eval_val", CIRC, 1, ckpt="c/best.pt", split="val", rotation=rot)
    soo = {"dataset": {"name": "scanobjectnn", "variant": "pb_t50_rs"}, "mvnet": {"name": "viewgcn"},
           "selector": {"name": "mvtn_spherical"}, "views": 12}
    _run(tmp_path / "pb", soo, 0, test_acc=0.80)
    _run(tmp_path / "other", {**GCN, "views": 3}, 0, test_acc=0.5)
    (tmp_path / "failed").mkdir()
    (tmp_path / "failed" / "status.json").write_text(json.dumps({"status": "error", "error": "boom"}))
    result = report(load_tables(), find_runs([tmp_path]))
    rows = {(t["id"], r["label"]): r for t in result["tables"] for r in t["rows"]}
    acc = rows["modelnet40-classification", "MVTN-spherical + ViewGCN, M = 12, instance accuracy"]
    assert acc["n"] == 2 and acc["mean"] == pytest.approx(91.0) and acc["sd"] == pytest.approx(math.sqrt(2))
    assert sorted(acc["seeds"]) == [0, 1]  # the evaluations' test_acc is not a training result
    r90 = rows["rotation", "MVTN-circular + MVCNN, M = 12, rotations in [-90, 90] degrees"]
    assert r90["n"] == 1 and r90["mean"] == pytest.approx(70.0)  # the first evaluation of c.pt; val ignored
    pb = rows["scanobjectnn-classification", "PB_T50_RS"]
    assert pb["n"] == 1 and pb["paper"] is not None and pb["diff"] == pytest.approx(80.0 - pb["paper"])
    assert rows["views", "fixed circular, M = 1"]["n"] == 0
    assert any(p.endswith("other") for p in result["unmatched"])
    assert any("failed (error)" in p for p in result["not_finished"])
    md = to_markdown(result)
    assert f"| PB_T50_RS | {pb['paper']:g} |" in md and "| 80.0 | 1 | 80.0 (of 1) |" in md and "91.0 ± 1.4" in md
    assert "not run (needs ModelNet40 and a GPU)" in md


def test_metric_paths_and_any_value():
    m = {"occlusion": {"0.1": {"mean_acc": 0.6}}, "retrieval": {"shrec17": {"micro": {"P@N": 0.3}}}, "flag": True}
    assert metric_value(m, "occlusion.0.1.mean_acc") == 0.6 and metric_value(m, "retrieval.shrec17.micro.P@N") == 0.3
    assert metric_value(m, "occlusion.0.2.mean_acc") is None and metric_value(m, "flag") is None
    assert row_matches({"selector.from_ckpt": "x.pt", "views": 12}, {"selector.from_ckpt": "<set>", "views": 12})
    assert not row_matches({"selector.from_ckpt": None, "views": 12}, {"selector.from_ckpt": "<set>"})
    assert row_matches({"selector.name": "poi"}, {"selector": "poi"})
    fsl = {"backbone.weights": "*/best.pt"}  # a pattern: the FSL rows' finished-run checkpoint
    assert row_matches({"backbone.weights": "outputs/train/runs/x/best.pt"}, fsl)
    assert not row_matches({"backbone.weights": "imagenet"}, fsl) and not row_matches({"backbone.weights": None}, fsl)


def test_welch_interval_matches_scipy_on_raw_samples():
    """The two-sample interval from means and stds equals scipy's Welch interval on the samples."""
    from scipy import stats

    from mvtn_exp.runs.paired_stats import mean_sd
    from mvtn_exp.runs.report import welch

    a, b = [90.1, 91.3, 89.7, 92.0, 90.8], [92.5, 93.1, 92.2, 93.8]
    (ma, sa), (mb, sb) = mean_sd(a), mean_sd(b)
    ci = stats.ttest_ind(a, b, equal_var=False).confidence_interval(0.95)
    w = welch(ma, sa, len(a), mb, sb, len(b))
    assert w["diff"] == pytest.approx(ma - mb) and (w["low"], w["high"]) == pytest.approx((ci.low, ci.high), rel=1e-9)
    assert welch(ma, sa, 1, mb, sb, 4) is None  # one run: no spread to estimate
    same = welch(90.0, 0.0, 3, 91.0, 0.0, 4)  # no spread on either side: the point interval, no division by 0
    assert (same["low"], same["high"]) == (-1.0, -1.0)
    one_sided = welch(90.0, 0.0, 3, 91.0, 0.5, 4)  # only the paper varies: its t interval
    assert one_sided["high"] - one_sided["diff"] == pytest.approx(stats.t.ppf(0.975, 3) * 0.5 / 2)


def test_ours_against_the_papers_best_of_four_and_its_mean_and_spread(tmp_path):
    """A row with the supplement's mean +- std: our mean against it with an interval and the spread
    verdict, our best against the best of four; a row with only the headline: the difference to it."""
    tables = tmp_path / "t.yaml"
    tables.write_text(
        "- {id: t, title: T, experiment: e, needs: a GPU, rows: [\n"
        "   {label: with mean, command: c, where: {views: 12}, metric: test_acc, paper: 93.8, paper_mean: 93.0, paper_std: 0.5,"
        " cite: L1},\n"
        "   {label: headline only, command: c, where: {views: 12}, metric: test_acc, paper: 93.8},\n"
        "   {label: not run, command: c, where: {views: 20}, metric: test_acc, paper: 93.5}]}\n")
    for seed, acc in enumerate([0.925, 0.93, 0.935]):
        _run(tmp_path / "runs" / str(seed), {"views": 12}, seed, test_acc=acc)
    result = report(load_tables(tables), find_runs([tmp_path / "runs"]))
    with_mean, headline, not_run = result["tables"][0]["rows"]
    assert with_mean["mean"] == pytest.approx(93.0) and with_mean["best"] == pytest.approx(93.5)
    assert with_mean["mean_diff"] == pytest.approx(0.0) and with_mean["within_spread"] is True
    assert with_mean["interval"]["low"] < 0 < with_mean["interval"]["high"]
    assert with_mean["best_diff"] == pytest.approx(93.5 - 93.8) and with_mean["diff"] == pytest.approx(93.0 - 93.8)
    assert headline["mean_diff"] is None and headline["within_spread"] is None
    md = to_markdown(result)
    assert "| with mean | 93.8 | 93.0 ± 0.5 | 93.0 ± 0.5 | 3 | 93.5 (of 3) | +0.0 [" in md and "| yes |" in md
    assert "| headline only | 93.8 | - | 93.0 ± 0.5 | 3 | 93.5 (of 3) | -0.8 (vs best of 4) |" in md
    assert "| not run | 93.5 | - | not run (needs a GPU) |" in md
    # far outside the paper's spread
    for seed, acc in enumerate([0.899, 0.90, 0.901]):
        _run(tmp_path / "low" / str(seed), {"views": 12}, seed, test_acc=acc)
    far = report(load_tables(tables), find_runs([tmp_path / "low"]))["tables"][0]["rows"][0]
    assert far["within_spread"] is False and far["interval"]["high"] < 0


@pytest.mark.parametrize("text, match", [
    ("- {id: a, title: t, experiment: e, needs: n, rows: [{label: l, command: c, where: {views: 1}, metric: m, papr: 1}]}",
     "unknown key 'papr'"),
    ("- {id: a, title: t, experiment: e, needs: n, rows: [{label: l, command: c, where: {views: 1}, metric: m, paper: high}]}",
     "paper='high': expected a number"),
    ("- {id: a, title: t, experiment: e, rows: []}", "missing key 'needs'"),
    ("- {id: a, title: t, experiment: e, needs: n, rows: [{label: l, command: c, where: {}, metric: m}]}", "where: expected"),
    ("{a: 1}", "expected a list of tables"),
    ("- {id: a, title: t, experiment: e, needs: n, rows: [{label: l, command: c, where: {views: 1}, metric: m, paper_mean: 90}]}",
     "paper_mean and paper_std: expected both"),
    ("- {id: a, title: t, experiment: e, needs: n, rows: [{label: l, command: c, where: {views: 1}, metric: m, paper_std: true,"
     " paper_mean: 1}]}", "paper_std=True: expected a number"),
])
def test_a_malformed_tables_file_is_one_line_naming_it(tmp_path, text, match):
    path = tmp_path / "tables.yaml"
    path.write_text(text)
    with pytest.raises(ReportError, match=match) as e:
        load_tables(path)
    assert str(path) in str(e.value)


def test_cli_prints_writes_and_refuses_in_one_line(tmp_path):
    _run(tmp_path / "runs" / "a", GCN, 0, test_acc=0.9)
    out = subprocess.run([sys.executable, "-m", "mvtn_exp.cli.report", str(tmp_path / "runs"), "--out", str(tmp_path / "rep")],
                         capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    row = load_tables()[0].rows[0]
    assert row.label == "MVTN-spherical + ViewGCN, M = 12, instance accuracy" and row.paper == 93.8  # (paper: Table 1, L390)
    assert f"| {row.label} | 93.8 |" in out.stdout and "| 90.0 | 1 | 90.0 (of 1) |" in out.stdout
    assert json.loads((tmp_path / "rep" / "report.json").read_text())["tables"][0]["rows"][0]["n"] == 1
    bad = subprocess.run([sys.executable, "-m", "mvtn_exp.cli.report", str(tmp_path / "nope"), "--out", str(tmp_path / "r2")],
                         capture_output=True, text=True)
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "nope: no such folder" in bad.stderr


# ----------------------------------------------------------------------------- the packaged tables

def _grid(name: str, command: str) -> list[list[str]]:
    """The jobs of an experiment: its sweep grid (seeds left out) crossed with the command's own keys."""
    params = OmegaConf.load(f"mvtn_exp/conf/experiment/{name}.yaml").get("hydra", {}).get("sweeper", {}).get("params", {})
    keys = {k: str(v).split(",") for k, v in params.items() if k != "seed"}
    # (an mvtn-eval command's keys are the evaluation's, not the training run's)
    for tok in ([] if command.startswith("mvtn-eval") else command.split("#")[0].split()[1:]):
        if "=" in tok and not tok.startswith(("+experiment", "ckpt", "seed", "robustness", "task",
                                                                  "rotation.", "occlusion.", "retrieval.")):
            k, v = tok.split("=", 1)
            keys[k] = [v.split(",")[0]]
    if "from_ckpt" in command:
        keys["selector.from_ckpt"] = ["run/best.pt"]
    return [[f"{k}={v.strip()}" for k, v in zip(keys, combo)] for combo in itertools.product(*keys.values())]


@pytest.mark.slow  # (longer than 15 s on 2 cores: make test-all)
def test_every_row_is_what_its_experiment_runs():
    """Each row's conditions are met by at least one job of the experiment its table names, as its
    command gives it (a row naming a key or value that the experiment never produces fails)."""
    from mvtn_exp.config.schema import TrainConfig

    tables = load_tables()
    assert {t.experiment for t in tables} >= {"paper_modelnet40_classification", "paper_scanobjectnn_classification",
                                              "paper_shapenet_retrieval", "paper_views_ablation", "paper_ablation",
                                              "paper_noise_baseline", "paper_scene_optimisation", "paper_view_transfer",
                                              "paper_vit_pretraining"}
    cache: dict = {}
    with initialize_config_module(version_base="1.3", config_module="mvtn_exp.conf"):
        for t in tables:
            for row in t.rows:
                found, exp = False, row.experiment or t.experiment
                for job in _grid(exp, row.command):
                    key = (exp, tuple(job))
                    if key not in cache:
                        obj: TrainConfig = OmegaConf.to_object(compose("train", overrides=[f"+experiment={exp}", *job]))
                        cache[key] = flatten(config_dict(obj.validate()))
                    if row_matches(cache[key], row.where):
                        found = True
                        break
                assert found, (t.id, row.label)


def test_docs_paper_md_shows_every_number_of_the_tables():
    """docs/paper.md holds ``mvtn-report --paper`` as printed: every row's best of four, mean +- std
    and where the paper gives them (editing the tables without the doc, or the doc alone, fails)."""
    from pathlib import Path

    from mvtn_exp.runs.report import paper_markdown

    doc = (Path(__file__).resolve().parents[1] / "docs" / "paper.md").read_text()
    start, end = "<!-- mvtn-report --paper -->\n", "<!-- end mvtn-report --paper -->"
    assert start in doc and end in doc
    section = doc[doc.index(start) + len(start):doc.index(end)]
    assert section == paper_markdown(load_tables())
    numbers = [r.paper for t in load_tables() for r in t.rows if r.paper is not None]
    assert len(numbers) > 100 and all(f"| {n:g}" in section or f"| {n:.1f}" in section for n in numbers)


def test_each_paper_file_runs_the_setup_its_table_cites():
    """A ``paper_*`` file whose dataset, M, network, backbone, weights or learning rates differ from
    what the paper states for its table (``setup``, with the lines in ``setup_cite``) fails here."""
    from mvtn_exp.config.schema import TrainConfig

    checked = 0
    with initialize_config_module(version_base="1.3", config_module="mvtn_exp.conf"):
        for t in load_tables():
            if not t.setup:
                continue
            assert t.setup_cite and "L" in t.setup_cite, t.id
            obj: TrainConfig = OmegaConf.to_object(compose("train", overrides=[f"+experiment={t.experiment}"]))
            got = flatten(config_dict(obj.validate()))
            for key, want in t.setup.items():
                assert key in got, (t.id, key)
                if isinstance(want, float):
                    assert got[key] == pytest.approx(want), (t.id, key, got[key], want)
                else:
                    assert got[key] == want, (t.id, key, got[key], want)
                checked += 1
    assert checked >= 60
