"""Sweeps beyond one process at a time: the joblib and submitit launchers, the threads each job
takes, a requeued cluster job going on from its last.pt, and the sweep summary written on demand."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from unittest import mock

import pytest
from omegaconf import OmegaConf

from mvtn_exp.engine.jobs import launcher_threads, usable_cores

ROOT = Path(__file__).resolve().parents[1]
JOBLIB = "hydra_plugins.hydra_joblib_launcher.joblib_launcher.JoblibLauncher"
LOCAL = "hydra_plugins.hydra_submitit_launcher.submitit_launcher.LocalLauncher"
SLURM = "hydra_plugins.hydra_submitit_launcher.submitit_launcher.SlurmLauncher"


@pytest.fixture(scope="module")
def cache(tmp_path_factory) -> str:
    return str(tmp_path_factory.mktemp("synthetic_cache"))


def _cli(args, env=None, timeout=300):
    return subprocess.run([sys.executable, "-m", "mvtn_exp.cli.train", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=timeout, env={**os.environ, **(env or {})})


def _tiny(cache) -> list[str]:
    return ["epochs=1", "views=2", "image_size=32", "dataset.num_per_class=[4,2,2]", "batch_size=8",
            f"dataset.root={cache}", "logger=none"]


@pytest.mark.parametrize("target,n_jobs,cores,threads", [
    (JOBLIB, -1, 16, 1), (JOBLIB, -2, 16, 1), (JOBLIB, 1, 16, 16), (JOBLIB, 2, 16, 8), (JOBLIB, 3, 16, 5),
    (JOBLIB, 32, 16, 1), (JOBLIB, -2, 2, 2), (JOBLIB, 2, 2, 1), (LOCAL, None, 16, 1), (SLURM, None, 16, None),
    ("hydra._internal.core_plugins.basic_launcher.BasicLauncher", None, 16, None),
])
def test_jobs_sharing_the_cores_split_them(target, n_jobs, cores, threads):
    launcher = OmegaConf.create({"_target_": target, **({"n_jobs": n_jobs} if n_jobs is not None else {})})
    assert launcher_threads(launcher, cores) == threads


def test_submitit_local_cpus_per_task_sets_the_threads():
    assert launcher_threads(OmegaConf.create({"_target_": LOCAL, "cpus_per_task": 3}), 16) == 3


@pytest.fixture(scope="module")
def sweeps(cache, tmp_path_factory) -> dict:
    """The tiny two-seed sweep under each launcher, run once for the tests below."""
    out, procs = {}, []
    for name, launcher in (("joblib", ["hydra/launcher=joblib", "hydra.launcher.n_jobs=2"]),
                           ("submitit_local", ["hydra/launcher=submitit_local"])):
        sweep = tmp_path_factory.mktemp(name) / "sweep"
        procs.append(subprocess.Popen([sys.executable, "-m", "mvtn_exp.cli.train", "-m", *launcher, *_tiny(cache),
                                       "seed=0,1", f"hydra.sweep.dir={sweep}"], cwd=ROOT,
                                      stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
        out[name] = sweep
    for p in procs:  # the two sweeps run side by side
        _, err = p.communicate(timeout=300)
        assert p.returncode == 0, err[-3000:]
    return out


@pytest.mark.slow  # (longer than 15 s on 2 cores: make test-all)
@pytest.mark.parametrize("name,threads", [("joblib", max(1, usable_cores() // 2)), ("submitit_local", 1)])
def test_parallel_sweep_runs_every_job_with_its_share_of_the_cores(sweeps, name, threads):
    """Two jobs side by side: each finishes, records the threads it ran with, and the sweep
    summary is written when the sweep ends (by the submitting process)."""
    sweep = sweeps[name]
    jobs = sorted(p for p in sweep.iterdir() if p.is_dir() and not p.name.startswith("."))
    assert len(jobs) == 2
    for job in jobs:
        m = json.loads((job / "metrics.json").read_text())
        assert m["config"]["threads"] == threads and m["provenance"]["threads"] == threads
    rows = (sweep / "summary.csv").read_text().splitlines()
    assert len(rows) == 3 and all(",ok," in row for row in rows[1:])


def test_a_requeued_cluster_job_goes_on_from_its_last_checkpoint(tmp_path, monkeypatch):
    """Started again by submitit (SUBMITIT_EXECUTOR set) in a run dir holding last.pt and no
    metrics.json, the job resumes from it (the resume itself: test_train_e2e's CLI resume tests);
    a first start, a finished run, or a run outside submitit does not."""
    from mvtn_exp.engine.jobs import requeued_checkpoint

    run = tmp_path / "run"
    run.mkdir()
    monkeypatch.setenv("SUBMITIT_EXECUTOR", "slurm")
    assert requeued_checkpoint(run) is None  # first start
    (run / "last.pt").write_bytes(b"x")
    assert requeued_checkpoint(run) == run / "last.pt"
    (run / "metrics.json").write_text("{}")
    assert requeued_checkpoint(run) is None  # finished
    (run / "metrics.json").unlink()
    monkeypatch.delenv("SUBMITIT_EXECUTOR")
    assert requeued_checkpoint(run) is None  # not a cluster job


@pytest.mark.slow  # (longer than 15 s on 2 cores: make test-all)
def test_summary_on_demand_lists_unfinished_jobs_and_refuses_a_non_sweep(sweeps, tmp_path, capsys):
    import shutil

    sweep = tmp_path / "sweep"
    shutil.copytree(sweeps["joblib"], sweep)
    job = next(p for p in sorted(sweep.iterdir()) if p.name.startswith("1_"))
    (job / "metrics.json").unlink()  # a job the cluster has not finished yet
    for name in ("summary.csv", "summary.md"):
        (sweep / name).unlink()
    r = _cli(["--summary", str(sweep)])
    assert r.returncode == 1 and (sweep / "summary.csv").is_file()
    assert r.stderr.strip().splitlines()[-1].startswith("mvtn-train: 1 of 2 sweep jobs did not finish: 1_")
    assert ",incomplete," in (sweep / "summary.csv").read_text()
    shutil.rmtree(job)  # a job that never started (an interrupted sweep): counted from multirun.yaml
    r = _cli(["--summary", str(sweep)])
    last = r.stderr.strip().splitlines()[-1]
    assert r.returncode == 1 and last.startswith("mvtn-train: 1 of 2 sweep jobs did not finish: 1 job(s): never started")
    r = _cli(["--summary", str(tmp_path / "nope")])
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "no such folder" in r.stderr, r.stderr
    from mvtn_exp.cli.train import summary

    for args, needle in (([str(tmp_path)], "no sweep jobs"), ([], "takes one sweep folder")):
        assert summary(args) == 2
        assert needle in capsys.readouterr().err


def test_a_launcher_that_is_not_installed_is_one_line(tmp_path):
    r = _cli(["-m", "hydra/launcher=ray", "seed=0,1", f"hydra.sweep.dir={tmp_path / 'sweep'}"])
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert "hydra/launcher=ray" in r.stderr and "basic, joblib, slurm, submitit_local, submitit_slurm" in r.stderr
    assert not (tmp_path / "sweep").exists()


def test_slurm_launcher_config_carries_the_cluster_settings():
    from hydra import compose, initialize_config_module

    from mvtn_exp.config.store import register_configs

    register_configs()  # (the schemas the config files name; the CLI registers them at import)

    with initialize_config_module(version_base="1.3", config_module="mvtn_exp.conf"):
        cfg = compose("train", overrides=["hydra/launcher=slurm", "hydra.launcher.partition=gpu"],
                      return_hydra_config=True)
    launcher = cfg.hydra.launcher
    assert launcher._target_ == SLURM and launcher.partition == "gpu"
    for key in ("gpus_per_node", "cpus_per_task", "mem_gb", "timeout_min", "array_parallelism"):
        assert launcher[key] >= 1, key
    assert launcher.max_num_timeout >= 1  # requeued after a timeout or preemption


def _cli_in(cwd, args, env=None, timeout=300):
    return subprocess.run([sys.executable, "-m", "mvtn_exp.cli.train", *args], cwd=cwd, capture_output=True, text=True,
                          timeout=timeout, env={**os.environ, "OMP_NUM_THREADS": "1", **(env or {})})


def _one_sweep_dir(cwd: Path) -> Path:
    dirs = list((cwd / "outputs" / "train" / "multiruns").iterdir())
    assert len(dirs) == 1, dirs  # every job in the announced sweep folder, none scattered
    return dirs[0]


@pytest.fixture(scope="module")
def default_folder_sweeps(cache, tmp_path_factory):
    """joblib and submitit_local sweeps with the default folders (no hydra.sweep.dir), from their
    own working directories, each run when a test first asks for it; each has a job that fails
    (an unwritable dataset root)."""
    out = {}

    def get(name):
        if name not in out:
            cwd = tmp_path_factory.mktemp(name)
            args = ["-m", f"hydra/launcher={name}", *_tiny(cache)[:-2], "logger=none", "seed=0",
                    f"dataset.root={cache},/proc/mvtn-unwritable"]
            out[name] = (cwd, _cli_in(cwd, args + (["hydra.launcher.n_jobs=2"] if name == "joblib" else [])))
        return out[name]

    return get


@pytest.mark.parametrize("name", [pytest.param("joblib", marks=pytest.mark.slow), pytest.param("submitit_local", marks=pytest.mark.slow)])
def test_launcher_jobs_land_in_the_announced_sweep_dir_with_a_complete_summary(default_folder_sweeps, name):
    cwd, r = default_folder_sweeps(name)
    assert r.returncode == 1, r.stderr[-3000:]  # one job failed: the sweep says so
    sweep = _one_sweep_dir(cwd)
    jobs = sorted(p.name for p in sweep.iterdir() if p.is_dir() and not p.name.startswith("."))
    assert len(jobs) == 2 and all("=" not in j and "," not in j for j in jobs), jobs
    rows = (sweep / "summary.csv").read_text().splitlines()[1:]
    assert len(rows) == 2 and sum(",ok," in row for row in rows) == 1 and sum(",error," in row for row in rows) == 1


@pytest.mark.slow  # a submitit sweep and its requeue (~40 s): make test-all
def test_a_requeued_submitit_job_resumes_in_its_own_dir(default_folder_sweeps):
    """A requeue runs the job's pickled call again in a new process (new pid): it lands in the same
    job dir (the cached sweep folder) and goes on from its last.pt."""
    cwd, _ = default_folder_sweeps("submitit_local")
    sweep = _one_sweep_dir(cwd)
    job = next(p for p in sweep.iterdir() if p.name.startswith("0_"))
    (job / "metrics.json").unlink()  # as if preempted after its last epoch was saved
    (job / "status.json").write_text(json.dumps({"status": "interrupted", "error": ""}))
    pickled = sorted(sweep.glob(".submitit/*/*_submitted.pkl"))[0]
    job_id = pickled.name.split("_")[0]
    code = ("import sys\nfrom submitit.core.utils import DelayedSubmission\n"
            "DelayedSubmission.load(sys.argv[1]).result()\n")
    r = subprocess.run([sys.executable, "-c", code, str(pickled)], cwd=cwd, capture_output=True, text=True, timeout=300,
                       env={**os.environ, "SUBMITIT_EXECUTOR": "local", "SUBMITIT_LOCAL_JOB_ID": job_id})
    assert r.returncode == 0, r.stderr[-3000:]
    assert _one_sweep_dir(cwd) == sweep
    assert "started again: going on from" in (job / "train.log").read_text() and (job / "metrics.json").is_file()
    assert json.loads((job / "status.json").read_text())["status"] == "ok"


@pytest.mark.slow  # a sweep run again and a resume (~30 s): make test-all
def test_an_interrupted_sweep_resumes_its_unfinished_jobs_only(default_folder_sweeps, tmp_path):
    import shutil

    cwd, _ = default_folder_sweeps("joblib")
    sweep = tmp_path / "sweep"
    shutil.copytree(_one_sweep_dir(cwd), sweep)
    done = next(p for p in sweep.iterdir() if p.name.startswith("0_"))
    stamp = (done / "metrics.json").stat().st_mtime_ns
    for name in ("summary.csv", "summary.md"):
        (sweep / name).unlink()  # an interrupted sweep wrote none
    r = _cli_in(cwd, ["--resume-sweep", str(sweep)])
    assert r.returncode == 1, r.stderr[-3000:]  # the failed job fails again (its root is still unwritable)
    assert f"{done} finished before; kept" in r.stderr and (done / "metrics.json").stat().st_mtime_ns == stamp
    rows = (sweep / "summary.csv").read_text().splitlines()[1:]
    assert len(rows) == 2 and sum(",ok," in row for row in rows) == 1
    last = done / "last.pt"  # a sweep job's resume command works as printed (no quoting needed)
    r = _cli_in(tmp_path, [f"ckpt_path={last}", "epochs=2"])
    assert r.returncode == 0 and "resumed from" in (done / "train.log").read_text(), r.stderr[-3000:]
    for bad in ([], [str(sweep), "epochs=3"], [str(tmp_path / "nope")]):
        r = _cli_in(tmp_path, ["--resume-sweep", *bad])
        assert r.returncode == 2 and r.stderr.count("\n") == 1 and "--resume-sweep" in r.stderr, r.stderr


def test_joblib_jobs_spread_over_the_visible_gpus():
    from mvtn_exp.engine.jobs import launcher_device

    joblib = OmegaConf.create({"_target_": JOBLIB, "n_jobs": 4})
    assert [launcher_device(joblib, "cuda", n, gpus=2) for n in range(4)] == ["cuda:0", "cuda:1", "cuda:0", "cuda:1"]
    assert launcher_device(joblib, "cuda", 3, gpus=1) == "cuda"  # one GPU: nothing to spread
    assert launcher_device(joblib, "cuda:1", 0, gpus=2) == "cuda:1"  # an explicit GPU is kept
    assert launcher_device(joblib, "cpu", 1, gpus=2) == "cpu"
    assert launcher_device(OmegaConf.create({"_target_": SLURM}), "cuda", 1, gpus=2) == "cuda"  # a job per node
    assert launcher_device(joblib, "cuda", None, gpus=2) == "cuda"  # not a sweep job
    # device=auto spreads like cuda where CUDA is, and stays auto (CPU) where it is not
    import torch

    with mock.patch.object(torch.cuda, "is_available", lambda: True):
        assert launcher_device(joblib, "auto", 1, gpus=2) == "cuda:1"
    with mock.patch.object(torch.cuda, "is_available", lambda: False):
        assert launcher_device(joblib, "auto", 1, gpus=2) == "auto"
