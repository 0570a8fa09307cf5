"""One run per run dir (a lock, no new run over an old one) and records that a refused command leaves alone."""
from __future__ import annotations

import hashlib
import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from mvtn_exp.engine import run_dir as rd

ROOT = Path(__file__).resolve().parents[1]
TINY = ["epochs=1", "views=2", "image_size=32", "dataset.num_per_class=[4,2,2]", "batch_size=8",
        "logger.progress=false", "logger.tensorboard=false"]


def _cli(args, cwd=ROOT, timeout=300):
    return subprocess.run([sys.executable, "-m", "mvtn_exp.cli.train", *args], cwd=cwd, capture_output=True,
                          text=True, timeout=timeout)


def _snapshot(folder: Path) -> dict:
    """Every file under ``folder`` (lock file aside) -> its content's hash."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file() and p.name != rd.LOCK_FILE}


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    base = tmp_path_factory.mktemp("rundir")
    run = base / "run"
    r = _cli([*TINY, f"dataset.root={base / 'cache'}", f"hydra.run.dir={run}"])
    assert r.returncode == 0, r.stderr[-2000:]
    return base, run


def test_a_finished_run_says_ok_and_a_refused_resume_changes_nothing(finished):
    base, run = finished
    assert json.loads((run / "status.json").read_text())["status"] == "ok"
    before = _snapshot(run)
    r = _cli([f"ckpt_path={run / 'last.pt'}", "epochs=2", "views=4"], cwd=base)
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0 and "views" in r.stderr, r.stderr
    assert _snapshot(run) == before  # metrics.json, status.json, provenance, .hydra: as they were


@pytest.mark.slow  # a second training (make test-all); the refusal itself: test_lock_is_per_process_...
def test_a_new_run_into_a_run_dir_is_refused_unless_overwrite(finished, tmp_path):
    base, run = finished
    before = _snapshot(run)
    r = _cli([*TINY, f"dataset.root={base / 'cache'}", f"hydra.run.dir={run}"])
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0, r.stderr
    assert "holds a run (last.pt)" in r.stderr and f"ckpt_path={run / 'last.pt'}" in r.stderr
    assert _snapshot(run) == before
    other = tmp_path / "other"  # overwrite=true: a new run there, the old results gone first
    other.mkdir()
    (other / "last.pt").write_bytes((run / "last.pt").read_bytes())
    (other / "metrics.json").write_text('{"test_acc": 0.99}')
    (other / "status.json").write_text('{"status": "error", "error": "old"}')
    r = _cli([*TINY, f"dataset.root={base / 'cache'}", f"hydra.run.dir={other}", "overwrite=true", "seed=3"])
    assert r.returncode == 0, r.stderr[-2000:]
    m = json.loads((other / "metrics.json").read_text())
    assert m["config"]["seed"] == 3 and m["test_acc"] != 0.99
    assert json.loads((other / "status.json").read_text())["status"] == "ok"


def test_a_second_run_into_a_busy_run_dir_is_refused(tmp_path):
    busy = tmp_path / "busy"
    holder = subprocess.Popen([sys.executable, "-c", textwrap.dedent(f"""
        import sys, time
        from mvtn_exp.engine import run_dir
        run_dir.lock({str(busy)!r})
        print("locked", flush=True)
        time.sleep(60)
        """)], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        r = _cli([*TINY, f"dataset.root={tmp_path / 'cache'}", f"hydra.run.dir={busy}"])
        assert r.returncode == 2 and r.stderr.strip().count("\n") == 0, r.stderr
        assert f"another run is using this folder: pid {holder.pid} (" in r.stderr
        assert f"stop it with `kill {holder.pid}`" in r.stderr and "give this run another hydra.run.dir" in r.stderr
        assert sorted(p.name for p in busy.iterdir()) == [rd.LOCK_FILE]  # no Hydra record written over it
    finally:
        holder.kill()
        holder.wait()
    rd.lock(busy)  # the lock died with its process
    rd.release(busy)


def test_lock_is_per_process_and_check_new_run_removes_only_results(tmp_path):
    rd.lock(tmp_path)
    rd.lock(tmp_path)  # again in the same process: a no-op
    rd.release(tmp_path)
    for name in ("last.pt", "best.pt", "metrics.json", "status.json", "train.log"):
        (tmp_path / name).write_text("x")
    with pytest.raises(rd.RunDirTaken, match="overwrite=true"):
        rd.check_new_run(tmp_path, overwrite=False)
    (tmp_path / "tb").mkdir()
    (tmp_path / "tb" / "events.out.tfevents.1").write_text("x")
    rd.check_new_run(tmp_path, overwrite=True)  # the new run's log and curves start empty
    assert sorted(p.name for p in tmp_path.iterdir()) == [rd.LOCK_FILE, "train.log"]
    assert (tmp_path / "train.log").read_text() == ""
    rd.check_new_run(tmp_path / "empty", overwrite=False)  # nothing there: nothing to refuse
