"""End-to-end training: artefacts, learning of the selector G, exact resume, config checks, the CLI."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from mvtn_exp.engine import train
from mvtn_exp.engine.checkpoint import CheckpointMismatch, save_atomic
from mvtn_exp.engine.trainer import as_config
from mvtn_exp.model import build_mvtn

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def cache(tmp_path_factory) -> str:
    return str(tmp_path_factory.mktemp("synthetic_cache"))


def tiny(cache, **kw) -> dict:
    cfg = dict(views=2, image_size=32, epochs=2, num_per_class=[4, 2, 2], backbone="small_cnn", batch_size=8,
               data_dir=cache, progress=False, seed=0)
    cfg.update(kw)
    return cfg


@pytest.fixture(scope="module")
def full_run(cache, tmp_path_factory):
    run = tmp_path_factory.mktemp("full")
    return run, train(tiny(cache), run)


def test_artifacts_and_metrics(full_run):
    run, m = full_run
    for name in ("best.pt", "last.pt", "metrics.json"):
        assert (run / name).is_file(), name
    assert not list(run.glob("*.tmp"))
    disk = json.loads((run / "metrics.json").read_text())
    assert disk["test_acc"] == m["test_acc"]
    for key in ("test_acc", "test_mean_class_acc", "best_val_acc"):
        assert 0.0 <= m[key] <= 1.0, key
    conf = torch.tensor(m["confusion_matrix"])
    assert conf.shape == (12, 12) and int(conf.sum()) == m["test_size"] == 12 * 2
    assert abs(float(conf.diag().sum()) / m["test_size"] - m["test_acc"]) < 1e-12
    assert m["epochs"] == 2 and len(m["epoch_seconds"]) == 2 and m["skipped_steps"] == 0
    last = torch.load(run / "last.pt", weights_only=False)
    assert last["epoch"] == 1 and last["config"]["views"] == 2
    assert {"model", "optimizer", "scheduler", "rng", "best_val_acc"} <= set(last)
    assert last["best_val_acc"] == m["best_val_acc"]


def test_selector_learns(cache, full_run):
    """G's parameters move: gradients reach the selector through the renderer and C."""
    run, _ = full_run
    cfg = as_config(tiny(cache))
    torch.manual_seed(cfg.seed)
    model = build_mvtn(views=2, selector="mvtn_spherical", backbone="small_cnn", num_classes=12,
                       renderer=cfg.renderer)
    init = model.state_dict()
    trained = torch.load(run / "last.pt", weights_only=False)["model"]
    sel = [f"selector.{k}" for k, _ in model.selector.named_parameters()]  # parameters, not BN statistics
    assert sel
    moved = max(float((trained[k] - init[k]).abs().max()) for k in sel)
    assert moved > 1e-6
    # control: with lr_selector=0 (and so no decay) G stays at the same initialisation
    frozen_run = run.parent / "frozen"
    train(tiny(cache, epochs=1, lr_selector=0.0), frozen_run)
    frozen = torch.load(frozen_run / "last.pt", weights_only=False)["model"]
    assert max(float((frozen[k] - init[k]).abs().max()) for k in sel) == 0.0


def test_selector_gradient_nonzero(cache):
    from mvtn_exp.data.collate import collate_shapes
    from mvtn_exp.data.synthetic import SyntheticShapes

    cfg = as_config(tiny(cache))
    torch.manual_seed(0)
    model = build_mvtn(views=2, selector="mvtn_spherical", backbone="small_cnn", num_classes=12, renderer=cfg.renderer)
    model.train()
    ds = SyntheticShapes(cache, "train", num_per_class=[4, 2, 2], seed=0, progress=False)
    batch = collate_shapes([ds[i] for i in range(4)])
    out = model(batch)
    torch.nn.functional.cross_entropy(out["logits"], batch["labels"]).backward()
    g = model.parameter_groups()["selector"]
    norm = torch.sqrt(sum((p.grad ** 2).sum() for p in g if p.grad is not None))
    assert torch.isfinite(norm) and float(norm) > 0


def test_resume_reproduces(cache, full_run, tmp_path):
    _, full = full_run
    first = train(tiny(cache, epochs=1), tmp_path / "a")
    resumed = train(tiny(cache, epochs=2, ckpt_path=str(tmp_path / "a" / "last.pt")), tmp_path / "b")
    assert resumed["confusion_matrix"] == full["confusion_matrix"]
    for key in ("test_acc", "test_mean_class_acc", "best_val_acc", "test_loss"):
        assert abs(resumed[key] - full[key]) <= 1e-6, key
    for h_full, h_res in zip(full["history"], resumed["history"]):
        assert abs(h_full["train_loss"] - h_res["train_loss"]) <= 1e-6
    assert first["epochs"] == 1


def test_resume_config_mismatch(cache, full_run):
    run, _ = full_run
    with pytest.raises(CheckpointMismatch, match="views"):
        train(tiny(cache, views=3, ckpt_path=str(run / "last.pt")), run.parent / "mismatch")


def test_bad_values_rejected(cache, tmp_path):
    with pytest.raises(ValueError, match="selector"):
        train(tiny(cache, selector="nope"), tmp_path)
    with pytest.raises(Exception):
        as_config({"viewz": 3})


def test_atomic_save_leaves_no_temp(tmp_path):
    p = save_atomic(tmp_path / "x.pt", {"a": torch.ones(2)})
    assert torch.load(p)["a"].sum() == 2 and [f.name for f in tmp_path.iterdir()] == ["x.pt"]


def _cli(args, cwd):
    return subprocess.run([sys.executable, "-m", "mvtn_exp.cli.train", *args], cwd=cwd, capture_output=True,
                          text=True, timeout=120)


def test_cli_prints_metrics_path_last(cache, tmp_path):
    run = tmp_path / "run"
    r = _cli(["epochs=1", "views=2", "image_size=32", "num_per_class=[4,2,2]", "batch_size=8", f"data_dir={cache}",
              "progress=false", f"hydra.run.dir={run}"], ROOT)
    assert r.returncode == 0, r.stderr[-2000:]
    last = r.stdout.strip().splitlines()[-1]
    assert Path(last) == run / "metrics.json" and Path(last).is_file()


def test_cli_unknown_key_fails(tmp_path):
    r = _cli(["viewz=3", f"hydra.run.dir={tmp_path / 'run'}"], ROOT)
    assert r.returncode != 0 and "viewz" in r.stderr


def test_cli_bad_value_one_line(tmp_path, cache):
    r = _cli(["selector=nope", f"data_dir={cache}", f"hydra.run.dir={tmp_path / 'run'}"], ROOT)
    assert r.returncode == 2 and r.stderr.strip().splitlines()[-1].startswith("mvtn-train: error: selector=")


def _patched_build(monkeypatch, patch):
    import mvtn_exp.engine.trainer as trainer

    real = trainer.build_mvtn

    def build(**kw):
        model = real(**kw)
        patch(model)
        return model

    monkeypatch.setattr(trainer, "build_mvtn", build)


def test_nonfinite_gradients_are_skipped(cache, tmp_path, monkeypatch):
    def poison(model):
        p = next(model.mvnet.head.parameters())
        p.register_hook(lambda g: g * float("nan"))
        model._watched = p

    _patched_build(monkeypatch, poison)
    m = train(tiny(cache, epochs=1), tmp_path)
    assert m["skipped_steps"] == 12 * 4 // 8  # every step of the one epoch
    # nothing was applied: the poisoned head weight equals its fresh initialisation
    cfg = as_config(tiny(cache))
    torch.manual_seed(cfg.seed)
    fresh = build_mvtn(views=2, selector="mvtn_spherical", backbone="small_cnn", num_classes=12, renderer=cfg.renderer)
    assert torch.equal(torch.load(tmp_path / "last.pt", weights_only=False)["model"]["mvnet.head.weight"],
                       fresh.state_dict()["mvnet.head.weight"])


def test_nonfinite_loss_stops_run(cache, tmp_path, monkeypatch):
    from mvtn_exp.engine import TrainingDiverged

    _patched_build(monkeypatch, lambda model: model.mvnet.register_forward_hook(
        lambda mod, inp, out: (out[0] * float("nan"), out[1])))
    with pytest.raises(TrainingDiverged, match="non-finite loss"):
        train(tiny(cache, epochs=1), tmp_path)
    assert not (tmp_path / "last.pt").exists() and not list(tmp_path.glob("*.tmp"))
