"""How a run and a sweep of runs stop on SIGINT (Ctrl-C) and SIGTERM (``kill``, ``timeout``, Slurm).

A job (``job_signals``): inside it the first SIGINT / SIGTERM raises ``Interrupted`` (the caller
writes the job's line and status; ``last.pt`` of the last finished epoch stays as it is); later
ones are ignored while that is handled; on leaving, the handlers it replaced are back. A process
forked inside it (a data loader worker) ignores both: the job shuts it down.

A sweep's own process (``SweepStop``, around a multirun): on the first signal it writes the
sweep's stop file, sends the signal on to every process that holds a job's run-dir lock (so
SIGTERM to the sweep's process alone stops the jobs too), and waits (``WAIT_S``) until those
locks are free: each job has written its line and ended. It then lets the launcher go on: every
job that starts afterwards finds the stop file and returns at once, so the launcher ends as
usual (no killed worker, no traceback) and the sweep prints one line (``cli/train.py``).

Launcher workers (joblib's loky processes): between jobs, ``between_jobs`` leaves SIGINT and
SIGTERM to the sweep's process while it lives and ends the worker by the signal once it is gone
(an orphan stops like any process). ``joblib_workers_wait_between_jobs`` makes it the handler
of each fresh worker; ``submitit_controllers_leave_signals_to_jobs`` does the same for submitit's
local job controllers. Both adjust the launcher's library in the sweep's own process only.
"""
from __future__ import annotations

import functools
import os
import signal
import socket
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

STOP_ENV = "MVTN_SWEEP_STOP"  # "<host>\t<sweep pid>\t<stop file>": set by the sweep's process for its jobs
SIGNALS = (signal.SIGINT, signal.SIGTERM)
WAIT_S = 60.0  # longest wait for the running jobs to write their line and end


class Interrupted(Exception):
    """SIGINT / SIGTERM arrived: stop now; ``last.pt`` of the last finished epoch stays intact."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


@contextmanager
def job_signals():
    """Within: the first SIGINT / SIGTERM raises ``Interrupted``, later ones are ignored (the
    first is being handled); on exit the previous handlers are restored."""
    raised = []

    def interrupt(signum, frame):
        if not raised:
            raised.append(signum)
            raise Interrupted(signum)

    previous = {sig: signal.signal(sig, interrupt) for sig in SIGNALS}
    _in_job[0] = True
    try:
        yield
    finally:
        _in_job[0] = False
        for sig, handler in previous.items():
            signal.signal(sig, handler)


_in_job = [False]


def _child_leaves_signals_to_the_job() -> None:
    """A process forked inside a job (a data loader worker) ignores SIGINT / SIGTERM: the job
    stops on them and shuts its workers down; a worker ending on its own would turn the job's
    clean stop into a 'worker exited unexpectedly' error."""
    if _in_job[0]:
        _in_job[0] = False
        try:
            for sig in SIGNALS:
                signal.signal(sig, signal.SIG_IGN)
        except ValueError:
            pass  # (forked from a thread other than the main one: nothing to set there)


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_child_leaves_signals_to_the_job)


def _sweep() -> tuple[int, Path] | None:
    """``(sweep pid, stop file)`` of the local sweep this process works for, None otherwise (a
    single run, or a cluster job on another host)."""
    value = os.environ.get(STOP_ENV, "")
    parts = value.split("\t")
    if len(parts) != 3 or parts[0] != socket.gethostname() or not parts[1].isdigit():
        return None
    return int(parts[1]), Path(parts[2])


def sweep_stopping() -> bool:
    """The local sweep this job belongs to was told to stop: the job must not start."""
    sweep = _sweep()
    return sweep is not None and sweep[1].is_file()


def stop_sweep(signum: int) -> None:
    """A job interrupted in the sweep's own process (the basic launcher runs jobs one by one in
    it): the jobs after it must not start either."""
    sweep = _sweep()
    if sweep is not None and sweep[0] == os.getpid() and not sweep[1].is_file():
        sweep[1].write_text(signal.Signals(signum).name)


def between_jobs(signum, frame) -> None:
    """A launcher worker between jobs: its sweep's process decides (ignore); once that process is
    gone (an orphan worker), end by the signal as any process would."""
    sweep = _sweep()
    if sweep is not None and os.getppid() == sweep[0]:
        return
    signal.signal(signum, signal.SIG_DFL)
    os.kill(os.getpid(), signum)


def worker_started() -> None:
    """Initializer of a launcher worker process: ``between_jobs`` handles SIGINT and SIGTERM."""
    for sig in SIGNALS:
        signal.signal(sig, between_jobs)


def joblib_workers_wait_between_jobs() -> None:
    """Give the workers of Hydra's joblib launcher ``worker_started`` as their initializer (it
    passes its config to ``joblib.Parallel``, which hands extra keys to loky's executor). A no-op
    where the launcher is not installed."""
    try:
        import joblib
        from hydra_plugins.hydra_joblib_launcher import _core
    except ImportError:
        return
    if not isinstance(_core.Parallel, functools.partial):
        _core.Parallel = functools.partial(joblib.Parallel, initializer=worker_started)


def submitit_controllers_leave_signals_to_jobs() -> None:
    """Start each submitit local job's controller process with SIGINT and SIGTERM ignored: it
    waits for its job, which stops itself (``job_signals``), instead of printing a
    ``KeyboardInterrupt`` traceback or dying before its job has written its result. A no-op where
    submitit is not installed."""
    try:
        from submitit.local import local
    except ImportError:
        return
    start = local.start_controller
    if getattr(start, "leaves_signals_to_jobs", False):
        return

    @functools.wraps(start)
    def start_controller(*args, **kwargs):
        previous = {sig: signal.signal(sig, signal.SIG_IGN) for sig in SIGNALS}  # inherited by the controller
        try:
            return start(*args, **kwargs)
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)

    start_controller.leaves_signals_to_jobs = True
    local.start_controller = start_controller


def lock_holders(sweep_dir: Path) -> dict[Path, int]:
    """``{lock file: holder pid}`` of the job folders in ``sweep_dir`` whose run-dir lock is held
    by another process now (``engine/run_dir.py``)."""
    from .run_dir import holder

    held = {}
    for lock in Path(sweep_dir).glob("*/.mvtn-run.lock"):
        pid = holder(lock)
        if pid is not None and pid != os.getpid():
            held[lock] = pid
    return held


_sweep_dir: list[Path] = []  # the folder of the sweep this process runs (``sweep_started``)


def sweep_started(sweep_dir) -> None:
    """The sweep's own process knows its folder (a Hydra callback's ``on_multirun_start``)."""
    _sweep_dir[:] = [Path(sweep_dir)]


def current_sweep_dir() -> Path | None:
    """The folder of the sweep this process runs, None before it has one."""
    return _sweep_dir[0] if _sweep_dir else None


class SweepStop:
    """The sweep's own process, around a multirun (module docstring). ``signum``: the signal that
    stopped the sweep (also when a job in this process was interrupted), None if none did."""

    def __init__(self):
        self.stop_file = Path(tempfile.gettempdir()) / f"mvtn-sweep-{os.getpid()}.stop"
        self.previous = {}
        self.signum: int | None = None

    def __enter__(self) -> "SweepStop":
        self.stop_file.unlink(missing_ok=True)
        os.environ[STOP_ENV] = f"{socket.gethostname()}\t{os.getpid()}\t{self.stop_file}"
        self.previous = {sig: signal.signal(sig, self.handle) for sig in SIGNALS}
        joblib_workers_wait_between_jobs()
        submitit_controllers_leave_signals_to_jobs()
        return self

    def __exit__(self, *exc) -> None:
        for sig, handler in self.previous.items():
            signal.signal(sig, handler)
        self.signum = self._stopped_by()
        os.environ.pop(STOP_ENV, None)
        self.stop_file.unlink(missing_ok=True)

    def _stopped_by(self) -> int | None:
        try:
            return signal.Signals[self.stop_file.read_text().strip()].value
        except (OSError, KeyError):
            return None

    def handle(self, signum, frame) -> None:
        if self.stop_file.is_file():
            return
        self.stop_file.write_text(signal.Signals(signum).name)
        sweep_dir = current_sweep_dir()
        if sweep_dir is None:
            return
        for pid in set(lock_holders(sweep_dir).values()):
            try:
                os.kill(pid, signum)
            except OSError:
                pass  # (ended meanwhile)
        deadline = time.monotonic() + WAIT_S
        while lock_holders(sweep_dir) and time.monotonic() < deadline:
            time.sleep(0.1)
