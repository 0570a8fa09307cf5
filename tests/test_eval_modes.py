"""mvtn-eval modes end to end on a tiny trained checkpoint: rotation, occlusion, retrieval."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from mvtn_exp.engine import train
from mvtn_exp.evaluation.evaluate import evaluate_checkpoint
from mvtn_exp.config.eval_schema import EvalConfig, OcclusionEvalConfig, RetrievalEvalConfig, RotationEvalConfig

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory) -> Path:
    run = tmp_path_factory.mktemp("trained")
    cfg = {"views": 2, "image_size": 32, "epochs": 1, "batch_size": 8, "seed": 0,
           "dataset": {"root": str(tmp_path_factory.mktemp("cache")), "num_per_class": [4, 2, 2]},
           "logger": {"progress": False, "tensorboard": False}}
    train(cfg, run)
    return run / "best.pt"


def _eval(ckpt, tmp_path, **kw) -> dict:
    return evaluate_checkpoint(EvalConfig(ckpt=str(ckpt), progress=False, **kw), tmp_path)


def test_rotation(ckpt, tmp_path):
    m = _eval(ckpt, tmp_path, robustness="rotation", rotation=RotationEvalConfig(thetas=[0.0, 180.0], repeats=2))
    rot = m["rotation"]
    assert set(rot) == {"0", "180"} and len(rot["180"]["accs"]) == 2
    # theta = 0 is no rotation at all: exactly the plain accuracy, with no spread
    assert rot["0"]["accs"] == [m["test_acc"]] * 2 and rot["0"]["std_acc"] == 0.0
    assert "## Rotation" in (tmp_path / "results.md").read_text() and m["seconds"]["rotation"] > 0


def test_occlusion(ckpt, tmp_path):
    m = _eval(ckpt, tmp_path, robustness="occlusion", occlusion=OcclusionEvalConfig(ratios=[0.0, 0.5]))
    occ = m["occlusion"]
    assert set(occ) == {"0", "0.5"} and len(occ["0.5"]["per_direction"]) == 6
    assert all(acc == m["test_acc"] for acc in occ["0"]["per_direction"].values())  # ratio 0: untouched
    assert (tmp_path / "occlusion.png").read_bytes()[:4] == b"\x89PNG"
    assert m["occlusion_frame"] == "unit_sphere" and set(occ["0.5"]["floored_shapes"]) == set(occ["0.5"]["per_direction"])
    ext = _eval(ckpt, tmp_path / "ext", robustness="occlusion", occlusion=OcclusionEvalConfig(ratios=[0.5], frame="extent"))
    assert ext["occlusion_frame"] == "extent" and sum(ext["occlusion"]["0.5"]["floored_shapes"].values()) == 0


def test_retrieval(ckpt, tmp_path):
    m = _eval(ckpt, tmp_path, task="retrieval", retrieval=RetrievalEvalConfig(dim=8))
    r = m["retrieval"]
    assert 0 < r["map_raw"] <= 1 and 0 < r["map_lfda"] <= 1
    assert r["queries"] == 24 and r["database"] == 48  # every test shape queries the whole train split
    assert (tmp_path / "precision_recall.png").read_bytes()[:4] == b"\x89PNG"


def test_cli_modes_and_bad_combination(ckpt, tmp_path):
    # both at once: each process spends most of its time starting
    procs = [subprocess.Popen([sys.executable, "-m", "mvtn_exp.cli.eval", f"ckpt={ckpt}", *args], cwd=ROOT, text=True,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE)
             for args in (["robustness=occlusion", "occlusion.ratios=[0.3]", "progress=false", f"hydra.run.dir={tmp_path / 'e'}"],
                          ["task=retrieval", "robustness=rotation", f"hydra.run.dir={tmp_path / 'b'}"])]
    (out, err), (_, bad_err) = (p.communicate(timeout=300) for p in procs)
    assert procs[0].returncode == 0, err[-2000:]
    assert Path(out.strip().splitlines()[-1]) == tmp_path / "e" / "metrics.json"
    assert "occlusion" in json.loads((tmp_path / "e" / "metrics.json").read_text())
    assert procs[1].returncode == 2 and "robustness" in bad_err


def test_view_analysis(ckpt, tmp_path):
    m = _eval(ckpt, tmp_path, views=True)
    va = m["view_analysis"]
    assert va["acc_per_instance"] == m["test_acc"] and 0 <= va["acc_class_mean_views"] <= 1
    for name in ("view_histograms.png", "cameras.png"):
        assert (tmp_path / name).read_bytes()[:4] == b"\x89PNG", name
    assert "## Views" in (tmp_path / "results.md").read_text()


def test_retrieval_refuses_the_train_split(ckpt, tmp_path):
    with pytest.raises(ValueError, match="split=train"):
        _eval(ckpt, tmp_path, task="retrieval", split="train")


def test_eval_writes_under_output_dir_and_refuses_a_foreign_root(ckpt, tmp_path):
    """Runs go under paths.output_dir; ``root=`` pointing a synthetic checkpoint at a real
    dataset's folder is refused in one line, and nothing is written into that folder."""
    import torch

    saved = torch.load(ckpt, weights_only=True)["config"]
    assert Path(saved["dataset"]["root"]).is_absolute() and Path(saved["paths"]["cache_dir"]).is_absolute()
    out = tmp_path / "elsewhere"
    r = subprocess.run([sys.executable, "-m", "mvtn_exp.cli.eval", f"ckpt={ckpt}", "progress=false",
                        f"paths.output_dir={out}"], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    metrics = Path(r.stdout.strip().splitlines()[-1])
    assert metrics.is_file() and metrics.parent.parent == out / "eval" / "runs"
    real = tmp_path / "ModelNet10"
    (real / "chair" / "train").mkdir(parents=True)
    (real / "chair" / "train" / "chair_0001.off").write_text("OFF\n0 0 0\n")
    before = sorted(p.relative_to(real) for p in real.rglob("*"))
    bad = subprocess.run([sys.executable, "-m", "mvtn_exp.cli.eval", f"ckpt={ckpt}", f"root={real}",
                          f"paths.output_dir={out}"], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1, bad.stderr
    assert "not a synthetic cache file" in bad.stderr and str(real) in bad.stderr
    assert sorted(p.relative_to(real) for p in real.rglob("*")) == before


def test_a_compiled_run_evaluates_eagerly_where_compile_cannot_run(ckpt, tmp_path, monkeypatch, capsys):
    """``renderer.compile`` is an accelerator, not part of the model: a checkpoint trained with it is
    evaluated eagerly, with a note, on a machine where torch.compile cannot run."""
    import torch

    from mvtn_exp.runtime import checkpoint
    from mvtn_exp.render import accel

    state = checkpoint.load(str(ckpt))
    state["config"]["renderer"]["compile"] = True
    compiled_ckpt = tmp_path / "compiled.pt"
    torch.save(state, compiled_ckpt)
    monkeypatch.setattr(accel, "unavailable", lambda device_type: "renderer.compile=true needs a C++ compiler on CPU")
    out = _eval(compiled_ckpt, tmp_path / "eval")
    assert "rendering eagerly" in capsys.readouterr().err
    assert out["test_acc"] == _eval(ckpt, tmp_path / "eager")["test_acc"]
