"""Faults a run meets at run time: a full disk (a small tmpfs, where this machine lets us mount one)."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TINY = ["epochs=1", "views=2", "image_size=32", "dataset.num_per_class=[4,2,2]", "batch_size=8",
        "logger.progress=false", "logger.tensorboard=false"]


@pytest.fixture()
def small_disk(tmpfs):
    """A 600 KiB tmpfs: room for a run's records, not for its checkpoints."""
    return tmpfs("600k")


def test_a_full_disk_is_one_line_with_the_run_records_written(small_disk, tmp_path):
    run = small_disk / "run"
    r = subprocess.run([sys.executable, "-m", "mvtn_exp.cli.train", *TINY, f"dataset.root={tmp_path / 'cache'}",
                        f"hydra.run.dir={run}"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    err = r.stderr.strip().splitlines()
    assert r.returncode == 1 and len(err) == 1, r.stderr[-3000:]
    assert err[0].startswith("mvtn-train: error: no space left on the device (writing ") and ".pt)" in err[0]
    assert json.loads((run / "status.json").read_text())["status"] == "error"
    assert "no space left" in (run / "train.log").read_text()
    assert not list(run.glob(".*.tmp"))  # the half-written checkpoint is gone


def _train(args, cwd=ROOT):
    return subprocess.run([sys.executable, "-m", "mvtn_exp.cli.train", *args], cwd=cwd, capture_output=True, text=True,
                          timeout=300)


@pytest.mark.slow  # three tiny trainings (~40 s): make test-all
@pytest.mark.parametrize("delay", [0.3])
def test_kill_9_at_some_step_then_resume_equals_the_uninterrupted_run(tmp_path, delay):
    """SIGKILL (no handler runs) at some step after the first checkpoint: the folder reads as
    incomplete, and resuming from its last.pt ends exactly where the uninterrupted run does."""
    import signal
    import time

    import torch

    args = [*TINY, "epochs=3", f"dataset.root={tmp_path / 'cache'}"]
    full = tmp_path / "full"
    assert _train([*args, f"hydra.run.dir={full}"]).returncode == 0
    run = tmp_path / "killed"
    proc = subprocess.Popen([sys.executable, "-m", "mvtn_exp.cli.train", *args, f"hydra.run.dir={run}"], cwd=ROOT,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 240
    while not (run / "last.pt").is_file() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.05)
    time.sleep(delay)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=60)
    if (run / "metrics.json").is_file():
        pytest.skip("the run finished before the kill landed")
    assert not (run / "status.json").exists()  # no outcome: incomplete (last.pt, no metrics.json)
    assert torch.load(run / "last.pt", weights_only=True)["epoch"] >= 1  # whole, never half a file
    r = _train([f"ckpt_path={run / 'last.pt'}"], cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    a, b = (json.loads((d / "metrics.json").read_text()) for d in (full, run))
    assert a["test_acc"] == b["test_acc"] and [h["val_acc"] for h in a["history"]] == [h["val_acc"] for h in b["history"]]
    assert [h["train_loss"] for h in a["history"]] == [h["train_loss"] for h in b["history"]]


SIGTERM_IN_SECOND_WRITE = """
import os, signal, time
import mvtn_exp.runtime.checkpoint as ck
_replace, _calls = os.replace, [0]

def replace(src, dst):  # SIGTERM while a checkpoint is half way: written to its temp file, not yet in place
    if str(dst).endswith("last.pt"):
        _calls[0] += 1
        if _calls[0] == 2:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5)
    return _replace(src, dst)
ck.os = type("os", (), {**{k: getattr(os, k) for k in dir(os) if not k.startswith("__")}, "replace": staticmethod(replace)})
"""


@pytest.mark.slow  # (longer than 15 s on 2 cores: make test-all)
def test_sigterm_while_a_checkpoint_is_written_keeps_the_previous_one_and_resume_is_exact(tmp_path):
    """SIGTERM lands while epoch 2's last.pt is being written (its temp file full, not yet moved):
    one line, exit 143, no temp file left, last.pt is epoch 1's whole file, and resuming from it
    ends exactly where the uninterrupted run does."""
    import os

    import torch

    args = [*TINY, "epochs=2", f"dataset.root={tmp_path / 'cache'}"]
    full = tmp_path / "full"
    assert _train([*args, f"hydra.run.dir={full}"]).returncode == 0
    from conftest import injected

    run = tmp_path / "run"
    r = subprocess.run([sys.executable, "-m", "mvtn_exp.cli.train", *args, f"hydra.run.dir={run}"], cwd=ROOT,
                       capture_output=True, text=True, timeout=300,
                       env={**os.environ, **injected(tmp_path, SIGTERM_IN_SECOND_WRITE)})
    err = r.stderr.strip().splitlines()
    assert r.returncode == 143 and len(err) == 1 and err[0].startswith("mvtn-train: interrupted by SIGTERM"), r.stderr
    assert f"resume with: mvtn-train ckpt_path={run / 'last.pt'}" in err[0]
    assert not list(run.glob(".*.tmp")) and not (run / "metrics.json").exists()
    assert torch.load(run / "last.pt", weights_only=True)["epoch"] == 1
    assert json.loads((run / "status.json").read_text())["status"] == "interrupted"
    again = _train([f"ckpt_path={run / 'last.pt'}"], cwd=tmp_path)
    assert again.returncode == 0, again.stderr[-3000:]
    a, b = (json.loads((d / "metrics.json").read_text()) for d in (full, run))
    assert a["test_acc"] == b["test_acc"] and [h["train_loss"] for h in a["history"]] == [h["train_loss"] for h in b["history"]]


@pytest.mark.slow  # (longer than 15 s on 2 cores: make test-all)
def test_two_sweeps_started_at_once_on_one_folder_train_each_job_once_and_lose_nothing(tmp_path):
    """The same two-job sweep started twice at the same moment into one sweep folder: each job
    is trained by one of them (the other finds its folder busy or finished), both jobs end with
    their results, and the folder's summary lists both as finished."""
    import os

    sweep = tmp_path / "sweep"
    args = ["-m", *TINY, "seed=0,1", f"dataset.root={tmp_path / 'cache'}", f"hydra.sweep.dir={sweep}"]
    assert _train([*TINY, f"dataset.root={tmp_path / 'cache'}", f"hydra.run.dir={tmp_path / 'warm'}"]).returncode == 0
    procs = [subprocess.Popen([sys.executable, "-m", "mvtn_exp.cli.train", *args], cwd=ROOT, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
             for _ in range(2)]
    errs = [p.communicate(timeout=300)[1] for p in procs]
    assert all("Traceback" not in e for e in errs), errs
    jobs = sorted(p for p in sweep.iterdir() if p.is_dir() and not p.name.startswith("."))
    assert len(jobs) == 2
    for job in jobs:
        assert json.loads((job / "metrics.json").read_text())["config"]["seed"] in (0, 1)
        assert (job / "train.log").read_text().count("epoch 1/1:") == 1  # trained once, not twice over each other
        assert json.loads((job / "status.json").read_text())["status"] == "ok"
    r = _train(["--summary", str(sweep)])
    assert r.returncode == 0, r.stderr
    rows = (sweep / "summary.csv").read_text().splitlines()[1:]
    assert len(rows) == 2 and all(",ok," in row for row in rows)
