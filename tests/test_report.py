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

from mvtn_exp.engine.compare import find_runs, flatten
from mvtn_exp.engine.report import ReportError, load_tables, metric_value, report, row_matches, to_markdown
from mvtn_exp.engine.trainer import config_dict
from mvtn_exp.schema import register_configs

register_configs()
GCN = {"dataset": {"name": "modelnet40"}, "mvnet": {"name": "viewgcn"}, "selector": {"name": "mvtn_spherical", "from_ckpt": None},
       "views": 12}


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
    _run(tmp_path / "eval1", GCN, 0, test_acc=0.1, ckpt="a/best.pt", split="test", rotation=rot)
    _run(tmp_path / "eval1_again", GCN, 0, test_acc=0.1, ckpt="a/best.pt", split="test",
         rotation={"90": {"mean_acc": 0.0}, "180": {"mean_acc": 0.0}})
    _run(tmp_path / "eval_val", GCN, 1, ckpt="b/best.pt", split="val", rotation=rot)
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
    r90 = rows["rotation", "rotations in [-90, 90] degrees"]
    assert r90["n"] == 1 and r90["mean"] == pytest.approx(70.0)  # the first evaluation of a.pt; val ignored
    pb = rows["scanobjectnn-classification", "PB_T50_RS"]
    assert pb["n"] == 1 and pb["diff"] == pytest.approx(80.0 - 82.8)
    assert rows["views", "fixed circular, M = 1"]["n"] == 0
    assert any(p.endswith("other") for p in result["unmatched"])
    assert any("failed (error)" in p for p in result["not_finished"])
    md = to_markdown(result)
    assert "| PB_T50_RS | 82.8 | 80.0 | 1 | -2.8 |" in md and "91.0 ± 1.4" in md
    assert "not run (needs ModelNet40 and a GPU)" in md


def test_metric_paths_and_any_value():
    m = {"occlusion": {"0.1": {"mean_acc": 0.6}}, "retrieval": {"shrec17": {"micro": {"P@N": 0.3}}}, "flag": True}
    assert metric_value(m, "occlusion.0.1.mean_acc") == 0.6 and metric_value(m, "retrieval.shrec17.micro.P@N") == 0.3
    assert metric_value(m, "occlusion.0.2.mean_acc") is None and metric_value(m, "flag") is None
    assert row_matches({"selector.from_ckpt": "x.pt", "views": 12}, {"selector.from_ckpt": "<set>", "views": 12})
    assert not row_matches({"selector.from_ckpt": None, "views": 12}, {"selector.from_ckpt": "<set>"})
    assert row_matches({"selector.name": "poi"}, {"selector": "poi"})


@pytest.mark.parametrize("text, match", [
    ("- {id: a, title: t, experiment: e, needs: n, rows: [{label: l, command: c, where: {views: 1}, metric: m, papr: 1}]}",
     "unknown key 'papr'"),
    ("- {id: a, title: t, experiment: e, needs: n, rows: [{label: l, command: c, where: {views: 1}, metric: m, paper: high}]}",
     "paper='high': expected a number"),
    ("- {id: a, title: t, experiment: e, rows: []}", "missing key 'needs'"),
    ("- {id: a, title: t, experiment: e, needs: n, rows: [{label: l, command: c, where: {}, metric: m}]}", "where: expected"),
    ("{a: 1}", "expected a list of tables"),
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
    assert "| MVTN-spherical + ViewGCN, M = 12, instance accuracy | 93.8 | 90.0 | 1 | -3.8 |" in out.stdout  # (paper: Table 1, L273)
    assert json.loads((tmp_path / "rep" / "report.json").read_text())["tables"][0]["rows"][0]["n"] == 1
    bad = subprocess.run([sys.executable, "-m", "mvtn_exp.cli.report", str(tmp_path / "nope"), "--out", str(tmp_path / "r2")],
                         capture_output=True, text=True)
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "nope: no such folder" in bad.stderr


# ----------------------------------------------------------------------------- the packaged tables

def _grid(name: str, command: str) -> list[list[str]]:
    """The jobs of an experiment: its sweep grid (seeds left out) crossed with the command's own keys."""
    params = OmegaConf.load(f"mvtn_exp/conf/experiment/{name}.yaml").get("hydra", {}).get("sweeper", {}).get("params", {})
    keys = {k: str(v).split(",") for k, v in params.items() if k != "seed"}
    for tok in command.split("#")[0].split()[1:]:
        if "=" in tok and not tok.startswith(("+experiment", "ckpt", "seed", "robustness", "task")):
            k, v = tok.split("=", 1)
            keys[k] = [v.split(",")[0]]
    if "from_ckpt" in command:
        keys["selector.from_ckpt"] = ["run/best.pt"]
    if "backbone.weights" in command:
        keys["backbone.weights"] = ["w.pth"]
    return [[f"{k}={v.strip()}" for k, v in zip(keys, combo)] for combo in itertools.product(*keys.values())]


def test_every_row_is_what_its_experiment_runs():
    """Each row's conditions are met by at least one job of the experiment its table names, as its
    command gives it (a row naming a key or value that the experiment never produces fails)."""
    from mvtn_exp.schema import TrainConfig

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
