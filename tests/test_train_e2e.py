"""End-to-end training: artefacts, learning of the selector G, exact resume, config checks, the CLI."""
from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from mvtn_exp.engine import train
from mvtn_exp.runtime import checkpoint
from mvtn_exp.runtime.checkpoint import CheckpointMismatch, save_atomic
from mvtn_exp.engine.trainer import as_config
from mvtn_exp.selectors.training import LearnedTraining
from mvtn_exp.render import layouts
from mvtn_exp.model import build_mvtn

from conftest import tiny_config as tiny

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def cache(tmp_path_factory) -> str:
    return str(tmp_path_factory.mktemp("synthetic_cache"))


def tiny_model(cache, **kw):
    cfg = as_config(tiny(cache, **kw))
    torch.manual_seed(cfg.seed)
    return cfg, build_mvtn(cfg, num_classes=12)


@pytest.fixture(scope="module")
def full_run(cache, tmp_path_factory):
    run = tmp_path_factory.mktemp("full")
    return run, train(tiny(cache), run)


def test_artifacts_and_metrics(full_run):
    run, m = full_run
    for name in ("best.pt", "last.pt", "metrics.json", "confusion.json", "confusion.png"):
        assert (run / name).is_file(), name
    conf_file = json.loads((run / "confusion.json").read_text())
    assert conf_file["matrix"] == m["confusion_matrix"] and conf_file["classes"] == m["classes"]
    split = m["step_seconds"]
    assert set(split) == {"data", "selector", "render", "backbone", "optimizer", "total"}
    assert all(v >= 0 for v in split.values()) and split["render"] > 0 and split["backbone"] > 0
    assert abs(sum(v for k, v in split.items() if k != "total") - split["total"]) < 1e-9
    assert split["total"] * m["steps"] <= sum(m["epoch_seconds"]) + 1e-6  # steps fit inside the epochs
    assert not list(run.glob("*.tmp"))
    disk = json.loads((run / "metrics.json").read_text())
    assert disk["test_acc"] == m["test_acc"]
    for key in ("test_acc", "test_mean_class_acc", "best_val_acc"):
        assert 0.0 <= m[key] <= 1.0, key
    conf = torch.tensor(m["confusion_matrix"])
    assert conf.shape == (12, 12) and int(conf.sum()) == m["test_size"] == 12 * 2
    assert abs(float(conf.diag().sum()) / m["test_size"] - m["test_acc"]) < 1e-12
    assert m["epochs"] == 2 and len(m["epoch_seconds"]) == 2 and m["skipped_steps"] == 0
    assert m["train_wall_seconds"] == pytest.approx(sum(m["epoch_seconds"])) and m["train_wall_seconds"] > 0
    last = torch.load(run / "last.pt", weights_only=False)
    assert last["epoch"] == 2 and last["config"]["views"] == 2  # epochs completed, as metrics.json counts
    assert last["best_epoch"] == m["best_epoch"] and last["format"] == checkpoint.FORMAT == 4
    assert {"model", "optimizer", "scheduler", "rng", "best_val_acc"} <= set(last)
    assert last["best_val_acc"] == m["best_val_acc"]


def test_selector_learns(cache, full_run):
    """G's parameters move: gradients reach the selector through the renderer and C."""
    run, _ = full_run
    _, model = tiny_model(cache)
    init = model.state_dict()
    trained = torch.load(run / "last.pt", weights_only=False)["model"]
    sel = [f"selector.{k}" for k, _ in model.selector.named_parameters()]  # parameters, not BN statistics
    assert sel
    moved = max(float((trained[k] - init[k]).abs().max()) for k in sel)
    assert moved > 1e-6
    # control: with lr_selector=0 (and so no decay) G stays at the same initialisation
    frozen_run = run.parent / "frozen"
    train(tiny(cache, epochs=1, **{"selector.lr": 0.0}), frozen_run)
    frozen = torch.load(frozen_run / "last.pt", weights_only=False)["model"]
    assert max(float((frozen[k] - init[k]).abs().max()) for k in sel) == 0.0


def test_selector_gradient_nonzero(cache):
    from mvtn_exp.data.collate import collate_shapes
    from mvtn_exp.data.synthetic import SyntheticShapes

    _, model = tiny_model(cache)
    model.train()
    ds = SyntheticShapes(cache, "train", num_per_class=[4, 2, 2], seed=0, progress=False)
    batch = collate_shapes([ds[i] for i in range(4)])
    out = model(batch)
    torch.nn.functional.cross_entropy(out["logits"], batch["labels"]).backward()
    g = model.parameter_groups()["selector"]
    norm = torch.sqrt(sum((p.grad ** 2).sum() for p in g if p.grad is not None))
    assert torch.isfinite(norm) and float(norm) > 0


def test_resume_reproduces(cache, full_run, tmp_path):
    """Epoch-boundary resume: 1 epoch, then resume to 2 -> the same metrics as 2 epochs straight."""
    _, full = full_run
    first = train(tiny(cache, epochs=1), tmp_path / "a")
    resumed = train(tiny(cache, epochs=2, ckpt_path=str(tmp_path / "a" / "last.pt")), tmp_path / "b")
    _assert_same_run(resumed, full)
    assert first["epochs"] == 1


def _assert_same_run(a: dict, b: dict) -> None:
    assert a["confusion_matrix"] == b["confusion_matrix"]
    for key in ("test_acc", "test_mean_class_acc", "best_val_acc", "test_loss"):
        assert abs(a[key] - b[key]) <= 1e-6, key
    for h_a, h_b in zip(a["history"], b["history"], strict=True):
        assert abs(h_a["train_loss"] - h_b["train_loss"]) <= 1e-6
        assert abs(h_a["val_acc"] - h_b["val_acc"]) <= 1e-12


class Killed(Exception):
    """Stands in for a kill signal arriving mid-epoch."""


def test_crash_mid_epoch_then_resume_matches(cache, full_run, tmp_path, monkeypatch):
    """Kill the run in the middle of epoch 2 (after 1 of its 3 steps); resuming from last.pt gives
    exactly the metrics of the uninterrupted run."""
    import mvtn_exp.engine.trainer as trainer
    from mvtn_exp.model import MVTN

    _, full = full_run
    calls = {"n": 0}
    real_render = MVTN.render
    steps_per_epoch = -(-12 * 4 // 8)  # 48 shapes, batch 8

    def render(self, batch, *views):
        if self.training:
            calls["n"] += 1
            if calls["n"] == steps_per_epoch + 2:
                raise Killed()
        return real_render(self, batch, *views)

    monkeypatch.setattr(MVTN, "render", render)
    with pytest.raises(Killed):
        trainer.train(tiny(cache), tmp_path / "crashed")
    monkeypatch.setattr(MVTN, "render", real_render)
    last = torch.load(tmp_path / "crashed" / "last.pt", weights_only=False)
    assert last["epoch"] == 1  # only epoch 1 was completed and saved
    assert not (tmp_path / "crashed" / "metrics.json").exists()
    resumed = train(tiny(cache, ckpt_path=str(tmp_path / "crashed" / "last.pt")), tmp_path / "resumed")
    _assert_same_run(resumed, full)


def test_resume_config_mismatch(cache, full_run):
    run, _ = full_run
    with pytest.raises(CheckpointMismatch, match="views"):
        train(tiny(cache, views=3, ckpt_path=str(run / "last.pt")), run.parent / "mismatch")


def test_bad_values_rejected(cache, tmp_path):
    with pytest.raises(ValueError, match="selector"):
        train(tiny(cache, **{"selector.name": "nope"}), tmp_path)
    with pytest.raises(Exception):
        as_config({"viewz": 3})


def test_atomic_save_leaves_no_temp(tmp_path):
    p = save_atomic(tmp_path / "x.pt", {"a": torch.ones(2)})
    assert torch.load(p)["a"].sum() == 2 and [f.name for f in tmp_path.iterdir()] == ["x.pt"]


def _cli(args, cwd, module="train"):
    return subprocess.run([sys.executable, "-m", f"mvtn_exp.cli.{module}", *args], cwd=cwd, capture_output=True,
                          text=True, timeout=300)


def _clis(arg_lists, cwd, module="train") -> list[subprocess.CompletedProcess]:
    """``_cli`` for several argument lists at once (each process starts in a few seconds, mostly imports)."""
    procs = [subprocess.Popen([sys.executable, "-m", f"mvtn_exp.cli.{module}", *args], cwd=cwd, text=True,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE) for args in arg_lists]
    out = []
    for args, p in zip(arg_lists, procs):
        stdout, stderr = p.communicate(timeout=300)
        out.append(subprocess.CompletedProcess(p.args, p.returncode, stdout, stderr))
    return out


def _tiny_args(cache) -> list[str]:
    return ["epochs=1", "views=2", "image_size=32", "dataset.num_per_class=[4,2,2]", "batch_size=8",
            f"dataset.root={cache}", "logger.progress=false", "logger.log_every=1"]


def test_cli_train_then_eval(cache, tmp_path):
    """mvtn-train prints metrics.json's path last and logs to TensorBoard; mvtn-eval rebuilds the
    model from best.pt's config and reproduces the test metrics."""
    run = tmp_path / "run"
    r = _cli([*_tiny_args(cache), f"hydra.run.dir={run}"], ROOT)
    assert r.returncode == 0, r.stderr[-2000:]
    last = r.stdout.strip().splitlines()[-1]
    assert Path(last) == run / "metrics.json" and Path(last).is_file()
    origin = json.loads((run / "provenance.json").read_text())
    assert origin["version"] and origin["torch"] == torch.__version__ and origin["host"]
    assert origin["command"][0].endswith("train.py") or "train" in origin["command"][0]
    assert origin["commit"] is None or len(origin["commit"]) == 40
    record = (run / "train.log").read_text()  # the console lines are in the run's log too
    # device=auto (the default) says on the log's first line which device ran, and provenance keeps both
    expect = "cuda" if torch.cuda.is_available() else "cpu"
    assert origin["device_requested"] == "auto" and origin["device"].startswith(expect)
    assert record.splitlines()[0].endswith(f"device: {origin['device']}" + (
        f" ({torch.cuda.get_device_name()})" if expect == "cuda" else "") + " (device=auto)"), record.splitlines()[0]
    assert "epoch 1/1: train loss" in record and "test accuracy" in record
    assert list((run / "tb").glob("events.out.tfevents.*")), "no TensorBoard event file"
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    tags = EventAccumulator(str(run / "tb")).Reload().Tags()
    for tag in ("train/loss", "val/acc", "lr/mvnet", "lr/selector", "grad_norm/selector", "views/offset_azim"):
        assert tag in tags["scalars"], (tag, tags["scalars"])
    assert "views/val" in tags["images"] and {"views/azim", "views/elev"} <= set(tags["histograms"])
    trained = json.loads(Path(last).read_text())

    out = tmp_path / "eval"
    r = _cli([f"ckpt={run / 'best.pt'}", "progress=false", f"hydra.run.dir={out}"], ROOT, module="eval")
    assert r.returncode == 0, r.stderr[-2000:]
    assert Path(r.stdout.strip().splitlines()[-1]) == out / "metrics.json"
    ev = json.loads((out / "metrics.json").read_text())
    assert trained["provenance"] == origin and ev["ckpt_provenance"] == origin and ev["provenance"]["torch"]
    assert ev["confusion_matrix"] == trained["confusion_matrix"]
    assert abs(ev["test_acc"] - trained["test_acc"]) < 1e-12 and ev["split"] == "test"
    assert (out / "confusion.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_eval_checkpoint_with_other_schema_names_the_key(cache, full_run, tmp_path):
    run, _ = full_run
    state = torch.load(run / "best.pt", weights_only=False)
    state["config"]["backbone"]["depth"] = 18  # a key this version does not know
    save_atomic(tmp_path / "old.pt", state)
    r = _cli([f"ckpt={tmp_path / 'old.pt'}", f"hydra.run.dir={tmp_path / 'e'}"], ROOT, module="eval")
    assert r.returncode == 2 and "depth" in r.stderr and "old.pt" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


def test_cli_config_errors_are_one_line_exit_2(tmp_path):
    cases = {"viewz=3": ["viewz", "allowed keys", "views"],
             "selector=nope": ["selector/nope", "mvtn_spherical", "circular"],
             "optim.lr=abc": ["optim.lr", "optim/adamw.yaml"],
             "selector.name=nope": ["selector=", "expected one of", "selector/mvtn_spherical.yaml"]}
    results = _clis([[arg, f"hydra.run.dir={tmp_path / 'run'}"] for arg in cases], ROOT)
    for (arg, needles), r in zip(cases.items(), results):
        err = r.stderr.strip().splitlines()
        assert r.returncode == 2 and len(err) == 1 and "Traceback" not in r.stderr, (arg, r.stderr[-1000:])
        assert err[0].startswith("mvtn-train: config error in mvtn_exp/conf/"), err
        for needle in needles:
            assert needle in err[0], (arg, needle, err[0])
    assert not (tmp_path / "run").exists()


def test_cli_real_dataset_missing(tmp_path):
    r = _cli(["+experiment=modelnet_spherical", "backbone.weights=null", f"paths.data_dir={tmp_path / 'nodata'}",
              f"hydra.run.dir={tmp_path / 'run'}"], ROOT)
    assert r.returncode == 2
    assert "dataset modelnet40 not found at" in r.stderr and "expected layout" in r.stderr
    assert "dataset modelnet40 not found at" in (tmp_path / "run" / "train.log").read_text()  # the record says why
    status = json.loads((tmp_path / "run" / "status.json").read_text())  # and the run dir is marked failed
    assert status["status"] == "error" and "not found at" in status["error"]


@pytest.mark.slow  # 13 s: the launcher tests' sweeps write and check a summary too
def test_cli_multirun_summary(cache, tmp_path):
    sweep = tmp_path / "sweep"
    r = _cli(["-m", *_tiny_args(cache), "selector=circular,spherical", "seed=0,1", "logger.tensorboard=false",
              f"hydra.sweep.dir={sweep}"], ROOT)
    assert r.returncode == 0, r.stderr[-2000:]
    jobs = sorted(p.name for p in sweep.iterdir() if p.is_dir())
    assert len(jobs) == 4 and all("selector=" in j and "seed=" in j for j in jobs), jobs
    rows = list(csv.DictReader(open(sweep / "summary.csv")))
    assert len(rows) == 4 and all(r_["status"] == "ok" for r_ in rows)
    for row in rows:
        m = json.loads((sweep / row["job"] / "metrics.json").read_text())
        assert abs(float(row["test_acc"]) - m["test_acc"]) < 1e-4
    md = (sweep / "summary.md").read_text()
    settings = [ln for ln in md.splitlines() if ln.startswith("| ") and "± " in ln]
    assert len(settings) == 2 and all("| 2 | 0 |" in ln for ln in settings), settings


@pytest.mark.slow  # (longer than 15 s on 2 cores: make test-all)
def test_cli_resume_from_the_checkpoint_alone_goes_on_in_place(cache, tmp_path):
    """``mvtn-train ckpt_path=RUN/last.pt epochs=2``: the checkpoint's own config (no retyping),
    the same run dir, the first run's results kept."""
    run = tmp_path / "run"
    r, bad = _clis([[*_tiny_args(cache), "logger.tensorboard=false", f"hydra.run.dir={run}"],
                    [f"ckpt_path={tmp_path / 'nope.pt'}"]], ROOT)
    assert r.returncode == 0, r.stderr[-2000:]
    first = json.loads((run / "metrics.json").read_text())
    r = _cli([f"ckpt_path={run / 'last.pt'}", "epochs=2"], tmp_path)  # another cwd: nothing else retyped
    assert r.returncode == 0, r.stderr[-2000:]
    assert Path(r.stdout.strip().splitlines()[-1]) == run / "metrics.json"
    m = json.loads((run / "metrics.json").read_text())
    assert m["epochs"] == 2 and len(m["history"]) == 2 and m["config"]["views"] == 2 and m["config"]["image_size"] == 32
    assert m["history"][0] == first["history"][0]
    kept = list(run.glob("metrics-before-resume-*.json"))
    assert len(kept) == 1 and json.loads(kept[0].read_text())["epochs"] == 1
    assert (run / ".hydra" / "config.yaml").is_file() and list((run / ".hydra").glob("resumed-*/overrides.yaml"))
    assert "resumed from" in (run / "train.log").read_text()
    assert bad.returncode == 2 and bad.stderr.strip().count("\n") == 0 and "no such checkpoint file" in bad.stderr


@pytest.mark.slow  # (longer than 15 s on 2 cores: make test-all)
def test_cli_sigterm_keeps_the_last_epoch_and_says_how_to_resume(cache, tmp_path):
    import signal
    import time

    run = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "mvtn_exp.cli.train", *_tiny_args(cache), "epochs=200",
                             "logger.tensorboard=false", f"hydra.run.dir={run}"], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 240
    while not (run / "last.pt").is_file() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.2)
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signal.SIGTERM, err[-2000:]
    line = err.strip().splitlines()[-1]
    assert line.startswith("mvtn-train: interrupted by SIGTERM") and f"ckpt_path={run / 'last.pt'}" in line
    assert torch.load(run / "last.pt", weights_only=True)["epoch"] >= 1 and not (run / "metrics.json").exists()
    assert json.loads((run / "status.json").read_text())["status"] == "interrupted"
    done = torch.load(run / "last.pt", weights_only=True)["epoch"]
    r = _cli([f"ckpt_path={run / 'last.pt'}", f"epochs={done + 1}"], tmp_path)  # the resume that finishes it
    assert r.returncode == 0, r.stderr[-2000:]
    assert json.loads((run / "status.json").read_text()) == {"status": "ok", "error": ""}  # the last outcome


def test_cli_multirun_keeps_jobs_apart_and_fails_loudly(tmp_path):
    """Jobs differing only in an excluded key (a path) get their own folders; failed jobs make the
    sweep exit 1 naming them, after the summary is written."""
    sweep = tmp_path / "sweep"
    r = _cli(["-m", "+experiment=modelnet_spherical", "backbone.weights=null", f"paths.data_dir={tmp_path / 'a'},{tmp_path / 'b'}",
              f"hydra.sweep.dir={sweep}"], ROOT)
    assert r.returncode == 1, r.stderr[-2000:]
    jobs = sorted(p.name for p in sweep.iterdir() if p.is_dir())
    assert jobs == ["0_+experiment-modelnet_spherical_backbone.weights-null",
                    "1_+experiment-modelnet_spherical_backbone.weights-null"], jobs
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith("mvtn-train: 2 of 2 sweep jobs failed: 0_+experiment-") and "not found at" in last
    assert (sweep / "summary.csv").is_file()


def _patched_build(monkeypatch, patch):
    import mvtn_exp.engine.trainer as trainer

    real = trainer.build_mvtn

    def build(*a, **kw):
        model = real(*a, **kw)
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
    _, fresh = tiny_model(cache)
    assert torch.equal(torch.load(tmp_path / "last.pt", weights_only=False)["model"]["mvnet.head.weight"],
                       fresh.state_dict()["mvnet.head.weight"])


def test_nonfinite_loss_stops_run(cache, tmp_path, monkeypatch):
    from mvtn_exp.engine import TrainingDiverged

    _patched_build(monkeypatch, lambda model: model.mvnet.register_forward_hook(
        lambda mod, inp, out: (out[0] * float("nan"), out[1])))
    with pytest.raises(TrainingDiverged, match="non-finite loss"):
        train(tiny(cache, epochs=1), tmp_path)
    assert not (tmp_path / "last.pt").exists() and not list(tmp_path.glob("*.tmp"))


def test_resume_from_last_pt_alone(cache, full_run, tmp_path):
    """Only last.pt travelled (no best.pt beside it): model selection restarts, the run completes."""
    import shutil

    run, _ = full_run
    lone = tmp_path / "moved"
    lone.mkdir()
    state = torch.load(run / "last.pt", weights_only=False)
    state["epoch"] = 1  # pretend epoch 1 of 2 was the last one written
    save_atomic(lone / "last.pt", state)
    m = train(tiny(cache, ckpt_path=str(lone / "last.pt")), tmp_path / "resumed")
    assert (tmp_path / "resumed" / "best.pt").is_file() and m["best_epoch"] == 2
    # and with nothing left to train, the last model is tested
    shutil.copyfile(run / "last.pt", lone / "last.pt")
    m2 = train(tiny(cache, ckpt_path=str(lone / "last.pt")), tmp_path / "done")
    assert m2["test_size"] == 24 and (tmp_path / "done" / "best.pt").is_file()


def test_resume_refuses_other_classes(cache, full_run, tmp_path):
    run, _ = full_run
    state = torch.load(run / "last.pt", weights_only=False)
    state["classes"] = list(reversed(state["classes"]))
    save_atomic(tmp_path / "other.pt", state)
    with pytest.raises(CheckpointMismatch, match="classes"):
        train(tiny(cache, ckpt_path=str(tmp_path / "other.pt")), tmp_path / "x")


def test_learned_selector_needs_batches_of_two(cache, tmp_path):
    with pytest.raises(ValueError, match="batch_size=1"):
        as_config(tiny(cache, batch_size=1))
    assert as_config(tiny(cache, batch_size=1, **{"selector.name": "circular"})).batch_size == 1


def test_selector_warmup_freezes_g_then_trains_it(cache, tmp_path):
    """selector.warmup_epochs: G is untouched while C warms up (on u0, random or 5 spherical
    views), then moves."""
    _, model = tiny_model(cache)
    init = model.state_dict()
    sel = [f"selector.{k}" for k, _ in model.selector.named_parameters()]
    for views, count in (("u0", None), ("random", None), ("spherical", 5)):
        warm = train(tiny(cache, epochs=1, **{"selector.warmup_epochs": 1, "selector.warmup_views": views,
                                              "selector.warmup_num_views": count}), tmp_path / views)
        state = torch.load(tmp_path / views / "last.pt", weights_only=False)["model"]
        assert max(float((state[k] - init[k]).abs().max()) for k in sel) == 0.0, views
        assert warm["history"][0]["grad_norm_selector"] == 0.0
    train(tiny(cache, epochs=2, **{"selector.warmup_epochs": 1}), tmp_path / "after")
    state = torch.load(tmp_path / "after" / "last.pt", weights_only=False)["model"]
    assert max(float((state[k] - init[k]).abs().max()) for k in sel) > 1e-6


def test_warmup_views_count_and_layout(cache):
    """The warm-up views: ``selector.warmup_num_views`` of them, the spherical layout for every shape,
    or uniform random ones; u0 keeps G's own M."""
    batch = {"points": torch.zeros(3, 16, 3)}
    for kind, count, M in (("spherical", 12, 12), ("random", 7, 7), ("u0", None, 2), ("spherical", None, 2)):
        cfg, model = tiny_model(cache, **{"selector.warmup_epochs": 1, "selector.warmup_views": kind,
                                          "selector.warmup_num_views": count})
        azim, elev, dist = LearnedTraining(cfg).warmup_views(model, batch)
        assert azim.shape == elev.shape == dist.shape == (3, M), kind
        if kind == "spherical":
            ref = layouts.spherical(M, 3, cfg.selector.distance, sphere=cfg.selector.sphere)
            assert torch.allclose(azim, ref[0]) and torch.allclose(elev, ref[1])


def test_canonical_warmup_views_turn_with_the_shape(cache):
    """warmup_views=canonical: a ring at warmup_elevation in each shape's principal frame. Turning a
    shape by Q turns its views by Q (the same views of the shape); elevation 90 looks down the
    least-spread axis, i.e. along canonical +y."""
    from mvtn_exp.data.synthetic import random_rotation
    from mvtn_exp.render.cameras import view_directions
    from mvtn_exp.selectors.canonical import pca_frames

    g = torch.Generator().manual_seed(0)
    pts = torch.randn(1, 256, 3, generator=g, dtype=torch.float64) * torch.tensor([3.0, 0.5, 1.5], dtype=torch.float64)
    pts = pts + pts.pow(2) * 0.1  # skewed: a unique sign for every axis
    Q = torch.from_numpy(random_rotation("so3", np.random.default_rng(3)))
    batch = {"points": torch.cat([pts, pts @ Q.T]).float()}
    for elevation, M in ((30.0, 3), (90.0, 1)):
        cfg, model = tiny_model(cache, **{"selector.warmup_epochs": 1, "selector.warmup_views": "canonical",
                                          "selector.warmup_elevation": elevation, "selector.warmup_num_views": M})
        azim, elev, dist = LearnedTraining(cfg).warmup_views(model, batch)
        assert azim.shape == (2, M) and torch.all(dist == cfg.selector.distance)
        d = view_directions(azim.double(), elev.double())  # [2, M, 3]
        torch.testing.assert_close(d[1], d[0] @ Q.T, atol=1e-4, rtol=0)
        if elevation == 90.0:
            torch.testing.assert_close(d[:, 0], pca_frames(batch["points"].double())[:, 1], atol=1e-4, rtol=0)
    with pytest.raises(ValueError, match="selector.warmup_elevation"):
        tiny_model(cache, **{"selector.warmup_epochs": 1, "selector.warmup_elevation": 120.0})


def test_selector_epochs_freezes_g_afterwards(cache, tmp_path):
    """selector.stop_epoch=1: G moves in epoch 1 and not after; C keeps training."""
    train(tiny(cache, epochs=1), tmp_path / "one")
    train(tiny(cache, epochs=2, **{"selector.stop_epoch": 1}), tmp_path / "two")
    one, two = (torch.load(tmp_path / r / "last.pt", weights_only=False)["model"] for r in ("one", "two"))
    _, model = tiny_model(cache)
    sel = [f"selector.{k}" for k, _ in model.selector.named_parameters()]
    mv = [f"mvnet.{k}" for k, _ in model.mvnet.named_parameters()]
    assert max(float((one[k] - two[k]).abs().max()) for k in sel) == 0.0
    assert max(float((one[k] - two[k]).abs().max()) for k in mv) > 0.0


@pytest.mark.parametrize("renderer,warns", [({"mode": "hard"}, "renderer.mode=hard"),
                                            ({"mode": "soft", "sigma": 1e-8}, "renderer.sigma=1e-08"),
                                            ({"mode": "soft"}, None)])
def test_learned_views_without_camera_gradient_warn_once(cache, tmp_path, caplog, renderer, warns):
    import logging

    cfg = tiny(cache, epochs=1, selector={"name": "mvtn_spherical"}, renderer=renderer)
    with caplog.at_level(logging.WARNING, logger="mvtn-train"):
        train(cfg, tmp_path / "run")
    named = [r.getMessage() for r in caplog.records if "selector=mvtn_spherical with" in r.getMessage()]
    if warns is None:
        assert named == []
    else:
        assert len(named) == 1 and warns in named[0]


def test_cli_unwritable_output_dir_is_one_line_before_any_work(tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    r, sweep = _clis([[f"paths.output_dir={blocker / 'out'}"], ["-m", f"hydra.sweep.dir={blocker / 'sweep'}", "seed=0,1"]],
                     ROOT)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "cannot write the run's output under" in r.stderr and "paths.output_dir" in r.stderr
    assert sweep.returncode == 2 and "cannot write" in sweep.stderr


def test_worker_processes_change_nothing(cache, full_run, tmp_path):
    """dataset.num_workers=2 (workers kept between epochs and validation passes): the same run."""
    _, full = full_run
    _assert_same_run(train(tiny(cache, **{"dataset.num_workers": 2}), tmp_path / "w"), full)


def test_resume_with_weights_of_another_shape_is_one_line(cache, full_run, tmp_path):
    run, _ = full_run
    state = torch.load(run / "last.pt", weights_only=True)
    name = next(k for k, v in state["model"].items() if v.dim() >= 2)
    state["model"][name] = torch.zeros(3, 3)  # same config, a weight of another shape
    torch.save(state, tmp_path / "bent.pt")
    with pytest.raises(CheckpointMismatch, match="weights do not fit the model its config builds") as e:
        train(tiny(cache, ckpt_path=str(tmp_path / "bent.pt")), tmp_path / "resumed")
    assert "\n" not in str(e.value) and name in str(e.value)
    assert not (tmp_path / "resumed" / "provenance.json").exists()  # refused before anything was written


def _scripted_validation(monkeypatch, accs):
    """Validation accuracy as scripted, epoch by epoch (the rest of validation runs as usual)."""
    import mvtn_exp.engine.trainer as trainer

    real, calls = trainer.validate, iter(accs)

    def validate(*a, **kw):
        val, val_ema = real(*a, **kw)
        return {**val, "acc": next(calls)}, val_ema

    monkeypatch.setattr(trainer, "validate", validate)


@pytest.mark.slow  # (longer than 15 s on 2 cores: make test-all)
def test_patience_stops_after_epochs_without_a_better_validation(cache, tmp_path, monkeypatch):
    """patience=2: best 0.5 at epoch 2, not beaten at 3 (0.4) or 4 (0.5, a tie): stop before epoch 5;
    best.pt (epoch 2) is tested; the stopped run, resumed, stops again without training."""
    _scripted_validation(monkeypatch, [0.3, 0.5, 0.4, 0.5, 0.9, 0.9])
    m = train(tiny(cache, epochs=6, patience=2), tmp_path / "a")
    assert (m["epochs"], m["epochs_trained"], m["stopped_early"]) == (6, 4, True)
    assert [h["val_acc"] for h in m["history"]] == [0.3, 0.5, 0.4, 0.5]
    assert (m["best_val_acc"], m["best_epoch"]) == (0.5, 2)
    assert torch.load(tmp_path / "a" / "best.pt", weights_only=True)["epoch"] == 2
    assert "validation accuracy has not improved for 2 epochs (patience=2" in (tmp_path / "a" / "train.log").read_text()
    again = train(tiny(cache, epochs=6, patience=2, ckpt_path=str(tmp_path / "a" / "last.pt")), tmp_path / "b")
    assert again["epochs_trained"] == 4 and again["test_acc"] == m["test_acc"]
    monkeypatch.undo()
    _scripted_validation(monkeypatch, [0.3, 0.5, 0.4, 0.5, 0.9, 0.9])  # without patience: every epoch
    full = train(tiny(cache, epochs=6), tmp_path / "c")
    assert (full["epochs_trained"], full["stopped_early"], full["best_epoch"]) == (6, False, 5)


def test_patience_must_be_at_least_one(cache, tmp_path):
    with pytest.raises(ValueError, match=r"patience=0: must be >= 1"):
        train(tiny(cache, patience=0), tmp_path)


def test_patience_waits_for_the_last_training_stage(cache, tmp_path, monkeypatch):
    """ViewGCN, stages [3, 2], patience 1: epochs 2-3 of the single-view stage do not improve, yet it
    runs whole; the whole-network stage restarts model selection (0.3 at epoch 4), then epoch 5 (0.2)
    exhausts the patience with no epoch left: 5 epochs trained, best from stage 2."""
    _scripted_validation(monkeypatch, [0.5, 0.1, 0.1, 0.3, 0.2])
    m = train(tiny(cache, epochs=5, patience=1, **{"mvnet.name": "viewgcn", "mvnet.stages": [3, 2]}), tmp_path)
    assert (m["epochs_trained"], m["stopped_early"], m["best_epoch"], m["best_val_acc"]) == (5, False, 4, 0.3)


def test_resuming_a_finished_run_says_nothing_is_left_to_train(cache, full_run, tmp_path):
    """A resume whose checkpoint already covers ``epochs`` trains nothing and says so, naming how
    to train longer (not "at epoch 3/2"); its test result is best.pt's again."""
    import shutil

    run, full = full_run
    copy = tmp_path / "copy"
    shutil.copytree(run, copy)
    again = train(tiny(cache, ckpt_path=str(copy / "last.pt"), **{"optim.lr": 0.5}), copy)
    log = (copy / "train.log").read_text()
    assert "nothing is left to train" in log and f"set epochs above {full['epochs']}" in log
    assert f"at epoch {full['epochs'] + 1}/{full['epochs']}" not in log
    assert again["test_acc"] == full["test_acc"] and again["epochs_trained"] == full["epochs_trained"]
