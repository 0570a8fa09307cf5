"""``mvtn-train``: train MVTN (selector G + renderer R + multi-view net C).

Examples: ``mvtn-train``, ``mvtn-train +experiment=synthetic_circular views=1``,
``mvtn-train -m selector=circular,spherical,mvtn_spherical views=1,4 seed=0,1,2``; resume with
``ckpt_path=outputs/train/runs/<run>/last.pt``. The last printed line is the path of metrics.json.
"""
from __future__ import annotations

import os
import re
import signal
import sys
import time
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import OmegaConf

from ..data.shapes import ShapeError
from ..runtime import checkpoint, distributed
from ..engine import run_dir as run_dir_state
from ..engine import stopping
from ..engine.jobs import keep_finished_job, launcher_device, launcher_threads, objective_values, usable_cores
from ..runtime.checkpoint import CheckpointMismatch
from ..engine.trainer import TrainingDiverged, as_config, train
from ..config.schema import TrainConfig, resolve_device
from ..config.store import register_configs
from ..models import pretrained
from ..render import accel
from ..config.compose import check_overrides, given, override_key
from .common import check_writable, mark_failed, os_error_text

register_configs()
EXIT_CODES = {TrainingDiverged: 3}


def who() -> str:
    """`` (rank R)`` in a run of several processes (torchrun), else nothing: each process's line names it."""
    world = distributed.from_env()
    return f" (rank {world.rank})" if world.enabled else ""


def peer_stopped(exc: BaseException) -> bool:
    """A collective failed because another process of this torchrun run stopped (gloo: the
    connection closed; NCCL: a ``DistError``); that process's own line says why."""
    import torch.distributed as dist

    text = str(exc)
    return distributed.from_env().enabled and (
        isinstance(exc, dist.DistError) or any(s in text for s in ("Connection closed by peer", "Connection reset by peer",
                                                                   "gloo", "NCCL", "ProcessGroup")))


def resume_config(cfg, overrides: list[str], own_command: bool = False) -> TrainConfig:
    """``ckpt_path=...``: the checkpoint's own config, with only the keys this command line sets
    (e.g. ``epochs=20``) taken from the composed ``cfg``; no need to retype the original overrides.
    ``own_command``: a sweep or cluster job started again with the command that wrote the checkpoint
    (``keep_finished_job``): its experiment override is the checkpoint's own, not a change."""
    state = checkpoint.load(cfg.ckpt_path)
    saved = OmegaConf.create(state["config"])
    composed = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
    for o in overrides:
        key = override_key(o)
        if key in ("ckpt_path", "hydra") or key.startswith(("hydra.", "hydra/")):
            continue
        if key == "experiment":
            if own_command:
                continue
            raise ValueError(f"ckpt_path={cfg.ckpt_path}: resuming takes the checkpoint's own setup; "
                             f"drop {o!r} (or set its keys one by one)")
        OmegaConf.update(saved, key, OmegaConf.select(composed, key), merge=False)
    saved.ckpt_path = cfg.ckpt_path
    return as_config(OmegaConf.to_container(saved, resolve=True))


@hydra.main(version_base="1.3", config_path="../conf", config_name="train")
def _app(cfg) -> list[float] | None:
    """One run, or one job of a sweep (in a launcher's worker, or in the sweep's own process one
    after the other). A sweep job ends by returning, whatever happened (its status says what),
    with its signal handlers and its run dir's lock given back (``engine/stopping.py``)."""
    hc = HydraConfig.get()
    run_dir, multirun = Path(hc.runtime.output_dir), hc.mode == RunMode.MULTIRUN
    if multirun and stopping.sweep_stopping():
        return None  # the sweep was stopped before this job started: it resumes with --resume-sweep
    with stopping.job_signals():
        try:
            return _job(cfg, hc, run_dir, multirun)
        finally:
            if multirun:
                run_dir_state.release(run_dir)


def _lock(run_dir: Path, multirun: bool) -> bool:
    """Take the run dir's lock (held since ``main`` for a named run dir; sweep jobs take theirs
    here); False when another process holds it (said in one line)."""
    sweep = run_dir.parent
    advice = (f"let the sweep that runs it end (or stop it), then: mvtn-train --resume-sweep {sweep}" if multirun
              else "give this run another hydra.run.dir")
    try:
        note = run_dir_state.lock(run_dir, advice) if distributed.from_env().main else None
    except run_dir_state.RunDirBusy as exc:
        print(f"mvtn-train: error: {exc}", file=sys.stderr)
        return False
    if note:
        print(f"mvtn-train: {note}", file=sys.stderr)
    return True


def _job(cfg, hc, run_dir: Path, multirun: bool) -> list[float] | None:
    if not _lock(run_dir, multirun):
        if multirun:
            return None
        sys.exit(2)
    try:
        given = cfg.ckpt_path
        if keep_finished_job(cfg, run_dir, multirun):
            return objective_values(run_dir, cfg.objectives)
        if cfg.ckpt_path:  # (a finished run's metrics.json is kept aside once the resume is accepted)
            tcfg = resume_config(cfg, list(hc.overrides.task), own_command=not given)
        else:
            tcfg = OmegaConf.to_object(cfg)
        if tcfg.threads is None:  # parallel local sweep: split the cores between the jobs
            tcfg.threads = launcher_threads(hc.launcher, usable_cores())
        tcfg.device = launcher_device(hc.launcher, tcfg.device, hc.job.num if multirun else None)
        train(tcfg, run_dir)
    except stopping.Interrupted as exc:
        interrupted(exc, run_dir, multirun)
        if multirun:
            return None
        sys.exit(128 + exc.signum)
    except RuntimeError as exc:
        if not peer_stopped(exc) or os.environ.get("HYDRA_FULL_ERROR") == "1":
            raise
        first = " ".join(str(exc).split())[:160]
        print(f"mvtn-train: error{who()}: another process of this run stopped, so this one stops too; that "
              f"process's own line says why ({first})", file=sys.stderr)
        if not (run_dir / "status.json").is_file():  # the failing process's reason stays the run's status
            mark_failed(run_dir, "error", f"another process of this run stopped ({first})")
        sys.exit(1)
    except (CheckpointMismatch, OSError, NotImplementedError, ShapeError, ValueError, TrainingDiverged) as exc:
        if os.environ.get("HYDRA_FULL_ERROR") == "1":
            raise  # the full traceback, on request
        code = failed(exc, cfg, hc, run_dir)
        if multirun:  # recorded for the sweep summary: go on with the next job
            return None
        sys.exit(code)
    if distributed.from_env().main:
        print(run_dir / "metrics.json")
    return objective_values(run_dir, tcfg.objectives)


def interrupted(exc: stopping.Interrupted, run_dir: Path, multirun: bool) -> None:
    """The run's one line (stderr and ``train.log``) and its status; a sweep job also stops the
    sweep when it ran in the sweep's own process (the next jobs must not start)."""
    last = run_dir / "last.pt"
    if multirun:
        how = ("the last finished epoch is saved" if last.is_file() else "no epoch had finished") + \
            f"; the sweep resumes with: mvtn-train --resume-sweep {run_dir.parent}"
        stopping.stop_sweep(exc.signum)
    else:
        how = (f"the last finished epoch is saved, resume with: mvtn-train ckpt_path={last}" if last.is_file()
               else "no epoch had finished, nothing is saved to resume from: start again")
    line = f"mvtn-train: {f'job {run_dir.name} ' if multirun else ''}interrupted by {exc}; {how}"
    print(line, file=sys.stderr)
    try:
        with open(run_dir / "train.log", "a") as f:
            f.write(line + "\n")
    except OSError:
        pass
    if not (who() and (run_dir / "status.json").is_file()):  # (torchrun stops the others when one fails:
        mark_failed(run_dir, "interrupted", how)               # that one's reason stays the run's status)


def failed(exc: Exception, cfg, hc, run_dir: Path) -> int:
    """A user's mistake or a failed run in one line (stderr and the run's ``train.log``), the run dir
    marked failed; returns the exit code. A refused resume changes nothing on disk."""
    if cfg.ckpt_path and isinstance(exc, CheckpointMismatch):
        print(f"mvtn-train: error: {exc}", file=sys.stderr)
        if BEFORE_RESUME:  # resumed in place: the folder goes back to what it held before this command
            run_dir_state.undo_since(run_dir, BEFORE_RESUME[0])
        return 2
    kind = "training diverged" if isinstance(exc, TrainingDiverged) else "error"
    text = os_error_text(exc) if isinstance(exc, OSError) else str(exc)
    if isinstance(exc, OSError) and (run_dir / "last.pt").is_file():  # (a full disk in epoch 2, say)
        text += "; the last finished epoch is saved, " + (
            f"the sweep resumes with: mvtn-train --resume-sweep {run_dir.parent}" if hc.mode == RunMode.MULTIRUN
            else f"resume with: mvtn-train ckpt_path={run_dir / 'last.pt'}")
    print(f"mvtn-train: {kind}{who()}: {text}", file=sys.stderr)
    try:
        with open(run_dir / "train.log", "a") as f:  # the run's record keeps the reason too
            f.write(f"mvtn-train: {kind}{who()}: {text}\n")
    except OSError:
        pass  # (a full disk: stderr is all there is)
    mark_failed(run_dir, kind, text)  # no run dir is left looking like an unfinished run
    return EXIT_CODES.get(type(exc), 1 if isinstance(exc, OSError) and not isinstance(exc, FileNotFoundError) else 2)


BEFORE_RESUME: list[dict] = []  # the run folder as it was before a resume in place (``run_dir.snapshot``)


def resume_in_place(argv: list[str]) -> list[str]:
    """``ckpt_path=RUN/last.pt`` (single run, no ``hydra.run.dir``): go on in RUN itself, so its
    TensorBoard curves and train.log continue; this command's Hydra record goes to
    ``RUN/.hydra/resumed-<time>`` beside the original one. A missing file stops here, in one line."""
    ckpt = given(argv).get("ckpt_path")  # (Hydra's quoting removed: ckpt_path='a=1,b/last.pt')
    if not ckpt or ckpt == "null" or any(a in ("-m", "--multirun") for a in argv):
        return argv
    if not Path(ckpt).is_file():
        print(f"mvtn-train: error: ckpt_path={ckpt}: no such checkpoint file", file=sys.stderr)
        sys.exit(2)
    try:
        checkpoint.load(ckpt)  # an unreadable or foreign file is refused before anything is written
    except (CheckpointMismatch, OSError) as exc:
        print(f"mvtn-train: error: ckpt_path={ckpt}: {exc}", file=sys.stderr)
        sys.exit(2)
    if any(a.startswith("hydra.run.dir=") for a in argv):
        return argv
    BEFORE_RESUME[:] = [run_dir_state.snapshot(Path(ckpt).resolve().parent)]
    return [*argv, f"hydra.run.dir={Path(ckpt).resolve().parent}",
            f"hydra.output_subdir=.hydra/resumed-{time.strftime('%Y%m%d-%H%M%S')}"]


def summary(argv: list[str]) -> int:
    """``mvtn-train --summary DIR``: (re)write a sweep folder's summary, e.g. after jobs ran on a
    cluster and the submitting process was gone when they finished. Exit 0, 1 when a job failed or
    did not finish, 2 for a folder that is not a sweep."""
    from ..runs.sweep import collect, expected_jobs, failed_jobs, never_started, write_summary

    if len(argv) != 1:
        print("mvtn-train: error: --summary takes one sweep folder: mvtn-train --summary DIR", file=sys.stderr)
        return 2
    sweep = Path(argv[0])
    if not sweep.is_dir():
        print(f"mvtn-train: error: --summary {sweep}: no such folder", file=sys.stderr)
        return 2
    rows = collect(sweep)
    if not rows:
        print(f"mvtn-train: error: --summary {sweep}: no sweep jobs in it (folders with a .hydra record)", file=sys.stderr)
        return 2
    _, md = write_summary(sweep)
    print(md.read_text())
    print(md)
    failed = failed_jobs(sweep, rows) + never_started(sweep, rows)
    if failed:
        total = max(len(rows), expected_jobs(sweep) or 0)
        unfinished = total - sum(r.get("status") == "ok" for r in rows)
        print(f"mvtn-train: {unfinished} of {total} sweep jobs did not finish: " + "; ".join(failed), file=sys.stderr)
        return 1
    return 0


def shared_run_dir(argv: list[str]) -> list[str]:
    """Under torchrun (``WORLD_SIZE`` > 1): join the process group and give every rank the same run
    dir: ``hydra.run.dir`` if given, else ``<paths.output_dir>/train/runs/torchrun-<rdzv id>``, the
    same for every restart of the job (``--max-restarts``: ``keep_finished_job`` goes on from its
    ``last.pt``). The other ranks write no Hydra record and log to the console only
    (``runtime/distributed.py``: rank 0 alone writes the run). A sweep (``-m``) is refused."""
    world = distributed.from_env()
    if not world.enabled:
        return argv
    if any(a in ("-m", "--multirun") for a in argv):
        print("mvtn-train: error: torchrun runs one training job on several processes; sweep with a launcher "
              "(hydra/launcher=...) instead of -m", file=sys.stderr)
        sys.exit(2)
    distributed.join(world)
    if not any(a.startswith("hydra.run.dir=") for a in argv):  # one folder per torchrun job, kept over restarts
        run_id = re.sub(r"[^A-Za-z0-9_.-]", "_", os.environ.get("TORCHELASTIC_RUN_ID", ""))
        name = (f"torchrun-{run_id}" if run_id else
                distributed.broadcast(f"{time.strftime('%Y-%m-%d_%H-%M-%S')}-{os.getpid()}", world))
        argv = [*argv, f"hydra.run.dir=${{paths.output_dir}}/train/runs/{name}"]  # (paths.output_dir as composed)
    if not world.main:
        argv = [*argv, "hydra.output_subdir=null", "hydra/job_logging=stdout"]
    return argv


TRUE = ("true", "yes", "on", "1")


def claim_run_dir(argv: list[str]) -> None:
    """A single run into a named folder (``hydra.run.dir=``, or the folder of ``ckpt_path`` when
    resuming in place), before Hydra writes its record there: a new run into a folder holding a
    run's ``last.pt`` is refused unless ``overwrite=true``, and the folder's lock is taken for the
    run's life (a second run into a busy folder: one line, exit 2; ``engine/run_dir.py``)."""
    keys = given(argv)
    folder = keys.get("hydra.run.dir")
    if folder is None or any(a in ("-m", "--multirun") for a in argv) or not distributed.from_env().main:
        return
    try:
        restarted = int(os.environ.get("TORCHELASTIC_RESTART_COUNT", "0")) > 0  # torchrun --max-restarts: its own run
        ckpt = keys.get("ckpt_path", "null")
        if ckpt in ("null", "") and not restarted:
            run_dir_state.check_new_run(folder, keys.get("overwrite", "false").lower() in TRUE)
        advice = ("give this run another hydra.run.dir" if ckpt in ("null", "")
                  else f"once it has ended, resume with: mvtn-train ckpt_path={ckpt}")
        note = run_dir_state.lock(folder, advice)
    except (run_dir_state.RunDirBusy, run_dir_state.RunDirTaken) as exc:
        print(f"mvtn-train: error: {exc}", file=sys.stderr)
        sys.exit(2)
    if note:
        print(f"mvtn-train: {note}", file=sys.stderr)


def resume_sweep(argv: list[str]) -> list[str]:
    """``mvtn-train --resume-sweep DIR``: the command line of the sweep in DIR again (its
    ``multirun.yaml``: launcher and swept overrides), into DIR itself; each job then keeps a
    finished result, goes on from its ``last.pt``, or starts (``_app``), and the summary is
    rewritten whole."""
    import yaml

    if len(argv) != 1 or argv[0].startswith("-") or "=" in argv[0]:
        print("mvtn-train: error: --resume-sweep takes one sweep folder and nothing else: mvtn-train --resume-sweep DIR "
              "(other settings would give the jobs other folders)", file=sys.stderr)
        sys.exit(2)
    sweep = Path(argv[0])
    record = sweep / "multirun.yaml"
    if not record.is_file():
        print(f"mvtn-train: error: --resume-sweep {sweep}: no multirun.yaml there (not a sweep folder of mvtn-train -m)",
              file=sys.stderr)
        sys.exit(2)
    overrides = (yaml.safe_load(record.read_text()).get("hydra") or {}).get("overrides") or {}
    hydra_args = [o for o in overrides.get("hydra") or [] if not o.startswith(("hydra.mode=", "hydra.sweep.dir="))]
    return ["-m", *hydra_args, *(overrides.get("task") or []), f"hydra.sweep.dir={sweep}"]


def validate_for_training(cfg: TrainConfig) -> TrainConfig:
    """``TrainConfig.validate``, then the files a new run reads must exist: ``backbone.weights`` and
    ``selector.from_ckpt``, and ``renderer.compile=true`` must be able to run on ``device`` (one line
    naming the key; a stored config is not checked for them). A local ``backbone.weights`` file must
    load into the backbone (``pretrained.check_file``), else one line ``mvtn-train: error:
    backbone.weights=PATH: ...`` and exit code 2, before any run folder exists."""
    cfg.validate()
    if cfg.renderer.compile:
        accel.require(resolve_device(cfg.device))
    if pretrained.is_source(cfg.backbone.weights):  # downloaded once into torch's hub cache (before the run folder)
        pretrained.resolve(cfg.backbone.name, cfg.backbone.weights)
    elif cfg.backbone.weights:
        try:
            pretrained.check_file(cfg.backbone.name, cfg.backbone.weights)
        except pretrained.WeightsFileError as exc:
            print(f"mvtn-train: error: {exc}", file=sys.stderr)
            sys.exit(2)
    path = getattr(cfg.selector, "from_ckpt", None)
    if path and not Path(path).is_file():
        raise ValueError(f"selector.from_ckpt={path!r}: no such file (a local file)")
    return cfg


def main() -> None:
    if sys.argv[1:2] == ["--summary"]:
        sys.exit(summary(sys.argv[2:]))
    if sys.argv[1:2] == ["--resume-sweep"]:
        sys.argv[1:] = resume_sweep(sys.argv[2:])
    check_overrides("mvtn-train", "train", TrainConfig, sys.argv[1:], validate=validate_for_training)
    sys.argv[1:] = resume_in_place(sys.argv[1:])
    check_writable("mvtn-train", sys.argv[1:])
    claim_run_dir(sys.argv[1:])
    sys.argv[1:] = shared_run_dir(sys.argv[1:])
    if not any(a in ("-m", "--multirun") for a in sys.argv[1:]):
        _app()
        return
    with stopping.SweepStop() as stop:
        _app()
    if stop.signum is not None:
        sys.exit(sweep_interrupted(stop.signum))


def sweep_interrupted(signum: int) -> int:
    """The stopped sweep's one line (its summary is written): how many jobs finished and how the
    others resume; returns the exit code (128 + the signal's number)."""
    from ..runs.sweep import collect, expected_jobs

    sweep = stopping.current_sweep_dir()
    name = signal.Signals(signum).name
    if sweep is None or not sweep.is_dir():
        print(f"mvtn-train: sweep interrupted by {name} before any job started", file=sys.stderr)
        return 128 + signum
    rows = collect(sweep)
    total = max(len(rows), expected_jobs(sweep) or 0)
    done = sum(r.get("status") == "ok" for r in rows)
    print(f"mvtn-train: sweep interrupted by {name}: {done} of {total} jobs finished (summary: "
          f"{sweep / 'summary.md'}); the others resume with: mvtn-train --resume-sweep {sweep}", file=sys.stderr)
    return 128 + signum


if __name__ == "__main__":
    main()
