"""One run per run dir, and a ``status.json`` that states the run's last outcome.

- ``lock(run_dir)``: an exclusive ``flock`` on ``run_dir/.mvtn-run.lock`` held for the process's
  life (the kernel drops it when the process ends, ``kill -9`` included); a second process asking
  for it gets ``RunDirBusy`` naming the holder's pid. Asking again in the same process is a no-op.
  Where ``fcntl`` is missing (Windows) there is no lock.
- ``check_new_run(run_dir, overwrite)``: a new (not resumed) run into a folder that holds a run's
  ``last.pt`` is refused (``RunDirTaken``) unless ``overwrite``; with it the old run's results are
  removed first, so nothing of the old run is read as the new one's.
- ``write_status(run_dir, status, error)`` / ``clear_status(run_dir)``: ``status.json`` is
  ``{"status": ok | error | interrupted | training diverged, "error": text}``; it is cleared when a
  run starts training (a run killed outright then reads as incomplete: ``last.pt`` without
  ``metrics.json``) and written when it ends.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

try:
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None

LOCK_FILE = ".mvtn-run.lock"
STATUS_FILE = "status.json"
RESULTS = ("last.pt", "best.pt", "metrics.json", STATUS_FILE, "confusion.json", "confusion.png")
_held: dict[str, int] = {}


class RunDirBusy(RuntimeError):
    """Another process holds the run dir's lock."""


class RunDirTaken(RuntimeError):
    """A new run was pointed at a folder holding another run."""


def lock(run_dir) -> None:
    """Hold ``run_dir``'s lock until this process ends (module docstring); makes the folder."""
    path = Path(run_dir).resolve()
    if str(path) in _held or fcntl is None:
        return
    path.mkdir(parents=True, exist_ok=True)
    fd = os.open(path / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
        os.close(fd)
        raise RunDirBusy(f"hydra.run.dir={path}: another run is using this folder (pid {holder}); "
                         "give this run another hydra.run.dir") from None
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    _held[str(path)] = fd


def release(run_dir) -> None:
    """Give up this process's lock on ``run_dir`` (tests; a run keeps it for its life)."""
    fd = _held.pop(str(Path(run_dir).resolve()), None)
    if fd is not None:
        os.close(fd)


def check_new_run(run_dir, overwrite: bool) -> None:
    """Refuse a new run into a folder holding a run's ``last.pt`` unless ``overwrite`` (then the old
    run's results go first)."""
    path = Path(run_dir)
    if not (path / "last.pt").is_file():
        return
    if not overwrite:
        raise RunDirTaken(f"hydra.run.dir={path}: holds a run (last.pt); resume it with "
                          f"ckpt_path={path / 'last.pt'}, or pass overwrite=true to start a new run there")
    for name in RESULTS:
        (path / name).unlink(missing_ok=True)


def write_status(run_dir, status: str, error: str = "") -> None:
    """``run_dir/status.json``; an unwritable folder is left as it is (the caller has said why on stderr)."""
    try:
        (Path(run_dir) / STATUS_FILE).write_text(json.dumps({"status": status, "error": error}))
    except OSError:
        pass


def clear_status(run_dir) -> None:
    """A run starts training: the folder's earlier outcome no longer describes it."""
    (Path(run_dir) / STATUS_FILE).unlink(missing_ok=True)
