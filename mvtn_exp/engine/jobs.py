"""A training job started by a launcher: the cores and device it may use beside the sweep's other
jobs, whether it runs again in its own folder (a finished job kept, an unfinished one going on
from its ``last.pt``), and the objective values an optimising sweeper reads back."""
from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

from omegaconf import OmegaConf

from ..config.schema import resolve_device
from ..runtime import distributed
from ..runtime.dotted import lookup
from . import run_dir as run_dir_state


def usable_cores() -> int:
    """CPU cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def launcher_threads(launcher, cores: int) -> int | None:
    """Torch threads for one job of a sweep whose jobs share this machine's cores: under the joblib
    launcher the cores divided by the jobs that run at once (``n_jobs``; -1 = one per core, -2 =
    all cores but one); under submitit_local, which starts every job at once, its ``cpus_per_task``
    or 1. None otherwise (one job alone, or a cluster job on the cores it was given)."""
    target = str(OmegaConf.select(launcher, "_target_", default="") or "")
    if target.endswith("JoblibLauncher"):
        n = int(OmegaConf.select(launcher, "n_jobs", default=-1))
        at_once = cores + 1 + n if n < 0 else n
        return max(1, cores // max(1, at_once))
    if target.endswith("submitit_launcher.LocalLauncher"):
        return int(OmegaConf.select(launcher, "cpus_per_task", default=None) or 1)
    return None


def launcher_device(launcher, device: str, job_num: int | None, gpus: int | None = None) -> str:
    """The device of one job of a joblib sweep whose jobs share this machine: ``device=cuda`` (no
    index) goes to GPU ``job_num mod (visible GPUs)``, so the jobs spread over the GPUs instead of
    all landing on ``cuda:0`` (``device=auto`` on a machine with CUDA too); anything else, or another
    launcher, is left as it is."""
    target = str(OmegaConf.select(launcher, "_target_", default="") or "")
    if device == "auto" and resolve_device(device) == "cuda":
        device = "cuda"
    if device != "cuda" or job_num is None or not target.endswith("JoblibLauncher"):
        return device
    if gpus is None:
        import torch

        gpus = torch.cuda.device_count()
    return f"cuda:{job_num % gpus}" if gpus > 1 else device


def requeued_checkpoint(run_dir: Path, sweep_job: bool = False) -> Path | None:
    """A job started again in its own run dir: a cluster job (submitit requeues a preempted or
    timed-out job with the same command) or a sweep job run again (``--resume-sweep``, or the same
    sweep into the same ``hydra.sweep.dir``): its ``last.pt``, to go on from; None for a first
    start or a run that finished."""
    last = run_dir / "last.pt"
    if (sweep_job or os.environ.get("SUBMITIT_EXECUTOR") or torchrun_job()) and last.is_file() \
            and not (run_dir / "metrics.json").is_file():
        return last
    return None


def torchrun_job() -> bool:
    """A torchrun run in its own folder (``shared_run_dir``): a restart (``--max-restarts``) or the
    same job started again (a requeued Slurm job with the same ``--rdzv-id``) goes on from there."""
    return distributed.from_env().enabled and "TORCHELASTIC_RUN_ID" in os.environ


def keep_finished_job(cfg, run_dir: Path, multirun: bool) -> bool:
    """A sweep or cluster job started again in its own run dir: True when it finished before (its
    result is kept, nothing to do); with ``last.pt`` and no result it goes on from there
    (``cfg.ckpt_path`` set); ``overwrite=true`` starts it over instead."""
    if cfg.ckpt_path or not (multirun or os.environ.get("SUBMITIT_EXECUTOR") or torchrun_job()):
        return False
    if cfg.overwrite:
        run_dir_state.check_new_run(run_dir, overwrite=True)
        return False
    if (run_dir / "metrics.json").is_file():
        if distributed.from_env().main:
            print(f"mvtn-train: {run_dir} finished before; kept (overwrite=true trains it again)", file=sys.stderr)
        return True
    requeued = requeued_checkpoint(run_dir, multirun)
    if requeued is not None:
        cfg.ckpt_path = str(requeued)
        if distributed.from_env().main:
            with open(run_dir / "train.log", "a") as f:
                f.write(f"[{time.strftime('%Y-%m-%d %H:%M:%S')}] started again: going on from {requeued}\n")
    return False


def objective_values(run_dir: Path, names) -> list[float] | None:
    """The run's ``objectives`` (``TrainConfig``) read from its metrics.json, for an optimising
    sweeper; None when none are asked for or the run has no result (the sweeper records a failed trial)."""
    path = run_dir / "metrics.json"
    if not names or not path.is_file():
        return None
    metrics = json.loads(path.read_text())
    out = []
    for name in names:
        value = lookup(metrics, str(name))
        if value is None:
            return None
        out.append(float(value))
    return out
