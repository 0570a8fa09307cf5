"""A sweep stopped by SIGINT (Ctrl-C: the terminal signals the whole process group) or SIGTERM
(``kill``, ``timeout``, Slurm: to the group or to the sweep's process alone) stops like one run:
each job writes its line and status, the workers end, the locks are free, the sweep prints one
line, and ``--resume-sweep`` gives the uninterrupted result."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from mvtn_exp.engine import run_dir as rd
from mvtn_exp.engine import stopping

ROOT = Path(__file__).resolve().parents[1]
JOBLIB = ["hydra/launcher=joblib", "hydra.launcher.n_jobs=2"]


def _tiny(cache, epochs: int) -> list[str]:
    return [f"epochs={epochs}", "views=2", "image_size=32", "dataset.num_per_class=[4,2,2]", "batch_size=8",
            f"dataset.root={cache}", "logger.progress=false", "logger.tensorboard=false"]


def _children(pid: int) -> set[int]:
    """Every process below ``pid`` now (workers, their data loader workers)."""
    parent = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            parent[int(stat.parent.name)] = int(stat.read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
    out, todo = set(), [pid]
    while todo:
        here = todo.pop()
        below = {c for c, p in parent.items() if p == here} - out
        out |= below
        todo += below
    return out


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def _interrupt(sweep: Path, cache, how: str, epochs: int = 8, launcher=JOBLIB, seeds: str = "0,1", extra=()):
    """Start the sweep, send ``how`` once every job has finished an epoch; returns (exit code,
    stderr, the sweep's child processes seen while it ran)."""
    p = subprocess.Popen([sys.executable, "-m", "mvtn_exp.cli.train", "-m", *launcher, *_tiny(cache, epochs), *extra,
                          f"seed={seeds}", f"hydra.sweep.dir={sweep}"], cwd=ROOT, stdout=subprocess.DEVNULL,
                         stderr=subprocess.PIPE, text=True, start_new_session=True)
    jobs = len(seeds.split(","))
    children: set[int] = set()
    deadline = time.monotonic() + 240
    while len(list(sweep.glob("*/last.pt"))) < jobs:
        assert p.poll() is None and time.monotonic() < deadline, p.communicate()[1][-3000:]
        children |= _children(p.pid)
        time.sleep(0.2)
    {"group-int": lambda: os.killpg(p.pid, signal.SIGINT), "group-term": lambda: os.killpg(p.pid, signal.SIGTERM),
     "main-term": lambda: os.kill(p.pid, signal.SIGTERM)}[how]()
    _, err = p.communicate(timeout=120)
    return p.returncode, err, children


def _no_orphans(children: set[int]) -> None:
    deadline = time.monotonic() + 15
    while any(_alive(c) for c in children) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not any(_alive(c) for c in children), [Path(f"/proc/{c}/cmdline").read_bytes() for c in children if _alive(c)]


def _check_stopped(sweep: Path, code: int, err: str, signum: int, children: set[int]) -> None:
    lines = err.strip().splitlines()
    assert code == 128 + signum, err[-3000:]
    assert "Traceback" not in err and "leaked" not in err, err[-3000:]
    name = signal.Signals(signum).name
    assert lines[-1] == (f"mvtn-train: sweep interrupted by {name}: 0 of 2 jobs finished (summary: "
                         f"{sweep / 'summary.md'}); the others resume with: mvtn-train --resume-sweep {sweep}"), err
    jobs = sorted(p for p in sweep.iterdir() if p.is_dir() and not p.name.startswith("."))
    assert len(jobs) == 2 and len(lines) <= 3  # at most one line per job, then the sweep's
    for job in jobs:
        assert json.loads((job / "status.json").read_text())["status"] == "interrupted"
        assert (job / "last.pt").is_file() and not (job / "metrics.json").exists()
        assert rd.holder(job / rd.LOCK_FILE) is None  # the lock is free
        assert f"interrupted by {name}" in (job / "train.log").read_text()
    assert (sweep / "summary.md").is_file()
    _no_orphans(children)


def test_ctrl_c_on_a_joblib_sweep_stops_every_job_with_one_line_and_no_orphans(tmp_path):
    """Each job also has two data loader workers (forked: they leave the signal to their job)."""
    sweep = tmp_path / "sweep"
    code, err, children = _interrupt(sweep, tmp_path / "cache", "group-int", extra=["dataset.num_workers=2"])
    _check_stopped(sweep, code, err, signal.SIGINT, children)


@pytest.mark.slow  # (longer than 15 s on 2 cores: make test-all)
@pytest.mark.parametrize("how,signum", [("group-int", signal.SIGINT), ("group-term", signal.SIGTERM),
                                        ("main-term", signal.SIGTERM)])
def test_an_interrupted_joblib_sweep_resumes_at_once_to_the_uninterrupted_result(tmp_path, how, signum):
    cache = tmp_path / "cache"
    sweep, whole = tmp_path / "sweep", tmp_path / "whole"
    code, err, children = _interrupt(sweep, cache, how, epochs=4)
    _check_stopped(sweep, code, err, signum, children)
    r = subprocess.run([sys.executable, "-m", "mvtn_exp.cli.train", "--resume-sweep", str(sweep)], cwd=ROOT,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    r = subprocess.run([sys.executable, "-m", "mvtn_exp.cli.train", "-m", *JOBLIB, *_tiny(cache, 4), "seed=0,1",
                        f"hydra.sweep.dir={whole}"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    for a, b in zip(sorted(sweep.glob("*/metrics.json")), sorted(whole.glob("*/metrics.json")), strict=True):
        ma, mb = json.loads(a.read_text()), json.loads(b.read_text())
        assert (ma["test_acc"], ma["best_val_acc"]) == (mb["test_acc"], mb["best_val_acc"])


@pytest.mark.slow  # (longer than 15 s on 2 cores: make test-all)
@pytest.mark.parametrize("how", ["group-int", "main-term"])
def test_a_submitit_local_sweep_stops_the_same_way(tmp_path, how):
    sweep = tmp_path / "sweep"
    code, err, children = _interrupt(sweep, tmp_path / "cache", how, launcher=["hydra/launcher=submitit_local"])
    _check_stopped(sweep, code, err, signal.SIGINT if how == "group-int" else signal.SIGTERM, children)


def test_a_job_restores_the_signal_handlers_and_ignores_a_second_signal():
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(stopping.Interrupted) as exc:
        with stopping.job_signals():
            try:
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(1)
            except stopping.Interrupted:
                os.kill(os.getpid(), signal.SIGINT)  # while the first is handled: ignored
                time.sleep(0.1)
                raise
    assert exc.value.signum == signal.SIGTERM and signal.getsignal(signal.SIGTERM) is before


def test_a_worker_between_jobs_waits_for_its_sweep_and_ends_once_it_is_gone(tmp_path):
    """The worker (a grandchild here) ignores SIGTERM while its sweep process lives; once that
    process is gone it ends by the signal."""
    code = textwrap.dedent(f"""
        import os, socket, subprocess, sys, time
        os.environ["{stopping.STOP_ENV}"] = f"{{socket.gethostname()}}\\t{{os.getpid()}}\\t{tmp_path / 'stop'}"
        worker = subprocess.Popen([sys.executable, "-c", "from mvtn_exp.engine import stopping; import time; "
                                   "stopping.worker_started(); print('ready', flush=True); time.sleep(60)"],
                                  stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        assert worker.stdout.readline().strip() == "ready"
        worker.terminate()
        time.sleep(1.0)
        print(worker.pid, worker.poll(), flush=True)
        os._exit(0)  # the sweep process is gone: the worker is an orphan
        """)
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    pid, status = r.stdout.split()
    assert status == "None", r.stderr  # ignored while its sweep lived
    os.kill(int(pid), signal.SIGTERM)
    deadline = time.monotonic() + 10
    while _alive(int(pid)) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not _alive(int(pid))


def test_a_lock_left_by_a_killed_run_is_taken_over_with_one_line(tmp_path):
    holder = subprocess.Popen([sys.executable, "-c", f"from mvtn_exp.engine import run_dir; run_dir.lock({str(tmp_path)!r}); "
                               "print('locked', flush=True); import time; time.sleep(60)"],
                              cwd=ROOT, stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "locked"
    with pytest.raises(rd.RunDirBusy, match=rf"pid {holder.pid} \(.*python.*\); stop it with `kill {holder.pid}`.*resume later"):
        rd.lock(tmp_path, advice="resume later")
    holder.kill()
    holder.wait()
    assert rd.lock(tmp_path) == f"took over the lock of {tmp_path.resolve()} from pid {holder.pid} (no longer holding it)"
    rd.release(tmp_path)
    assert rd.lock(tmp_path) is None  # released cleanly: nothing to take over
    rd.release(tmp_path)


def test_a_process_forked_from_the_holder_does_not_keep_the_lock(tmp_path):
    code = textwrap.dedent(f"""
        import os, time
        from mvtn_exp.engine import run_dir
        run_dir.lock({str(tmp_path)!r})
        if os.fork() == 0:  # a data loader worker, say, that outlives its run
            os.close(1), os.close(2)
            time.sleep(20)
            os._exit(0)
        print("forked", flush=True)
        os._exit(0)
        """)
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert r.stdout.strip() == "forked", r.stderr
    assert rd.holder(tmp_path / rd.LOCK_FILE) is None


def test_the_advice_for_a_busy_folder_matches_the_command(tmp_path, capsys):
    from mvtn_exp.cli.train import claim_run_dir

    holder = subprocess.Popen([sys.executable, "-c", f"from mvtn_exp.engine import run_dir; run_dir.lock({str(tmp_path)!r}); "
                               "print('locked', flush=True); import time; time.sleep(60)"],
                              cwd=ROOT, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        for argv, advice in (([f"hydra.run.dir={tmp_path}"], "give this run another hydra.run.dir"),
                             ([f"ckpt_path={tmp_path / 'last.pt'}", f"hydra.run.dir={tmp_path}"],
                              f"once it has ended, resume with: mvtn-train ckpt_path={tmp_path / 'last.pt'}")):
            with pytest.raises(SystemExit) as exc:
                claim_run_dir(argv)
            err = capsys.readouterr().err.strip().splitlines()
            assert exc.value.code == 2 and len(err) == 1 and err[0].endswith(advice), err
    finally:
        holder.kill()
        holder.wait()
