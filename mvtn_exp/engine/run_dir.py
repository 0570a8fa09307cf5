"""One run per run dir, and a ``status.json`` that states the run's last outcome.

- ``lock(run_dir)``: an exclusive ``flock`` on ``run_dir/.mvtn-run.lock``, held until ``release``
  or the process's end (the kernel drops it then, ``kill -9`` included). It cannot outlive its
  holder: a process forked from the holder (a data loader worker) closes its copy at once. A
  second process asking for it gets ``RunDirBusy`` naming the holder (pid, command, how to stop
  it) and the caller's advice; a lock file naming a process that no longer holds it is taken
  over (``lock`` returns the line to log). Asking again in the same process is a no-op. Where
  ``fcntl`` is missing (Windows) there is no lock.
- ``check_new_run(run_dir, overwrite)``: a new (not resumed) run into a folder that holds a run's
  ``last.pt`` is refused (``RunDirTaken``) unless ``overwrite``; with it the old run's results,
  log and TensorBoard events are removed first, so nothing of the old run is read as the new one's.
- ``write_status(run_dir, status, error)`` / ``clear_status(run_dir)``: ``status.json`` is
  ``{"status": ok | error | interrupted | training diverged, "error": text}``; it is cleared when a
  run starts training (a run killed outright then reads as incomplete: ``last.pt`` without
  ``metrics.json``) and written when it ends.
"""
from __future__ import annotations

import atexit
import json
import os
import shutil
from pathlib import Path

try:
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None

LOCK_FILE = ".mvtn-run.lock"
STATUS_FILE = "status.json"
LOG = "train.log"
RESULTS = ("last.pt", "best.pt", "metrics.json", STATUS_FILE, "confusion.json", "confusion.png", "provenance.json")
_held: dict[str, int] = {}


class RunDirBusy(RuntimeError):
    """Another process holds the run dir's lock."""


class RunDirTaken(RuntimeError):
    """A new run was pointed at a folder holding another run."""


def lock(run_dir, advice: str = "give this run another hydra.run.dir") -> str | None:
    """Hold ``run_dir``'s lock (module docstring); makes the folder. Returns a line to log when a
    lock left by a process that is gone was taken over, else None. ``advice``: what the refused
    command should do instead (``RunDirBusy``)."""
    path = Path(run_dir).resolve()
    if str(path) in _held or fcntl is None:
        return None
    path.mkdir(parents=True, exist_ok=True)
    fd = os.open(path / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        pid = _recorded_pid(fd)
        os.close(fd)
        raise RunDirBusy(f"hydra.run.dir={path}: another run is using this folder: {describe(pid)}; "
                         f"stop it with `kill {pid}` (it keeps its last finished epoch), or {advice}") from None
    before = _recorded_pid(fd)
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    _held[str(path)] = fd
    if before and before != os.getpid():
        return f"took over the lock of {path} from pid {before} (no longer holding it)"
    return None


def _recorded_pid(fd: int) -> int:
    """The pid a lock file records, 0 when it records none."""
    text = os.pread(fd, 32, 0).decode(errors="replace").strip()
    return int(text) if text.isdigit() else 0


def describe(pid: int) -> str:
    """``pid N (its command line, shortened)``; a joblib worker is named as the sweep's worker."""
    try:
        argv = Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace").split("\0")
        ppid = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1]
    except (OSError, IndexError):
        return f"pid {pid}" if pid else "a process that did not record its pid"
    command = " ".join(" ".join(argv).split())  # (one line, whatever the arguments hold)
    if "loky" in command:
        return f"pid {pid} (a joblib worker of the sweep in process {ppid})"
    return f"pid {pid} ({command[:100]}{'...' if len(command) > 100 else ''})"


def holder(lock_file) -> int | None:
    """The pid recorded by ``lock_file`` while another open file holds it (0: unrecorded); None
    when nobody holds it or it is not there."""
    if fcntl is None:
        return None
    try:
        fd = os.open(lock_file, os.O_RDONLY)
    except OSError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        return _recorded_pid(fd)
    else:
        fcntl.flock(fd, fcntl.LOCK_UN)
        return None
    finally:
        os.close(fd)


def release(run_dir) -> None:
    """Give up this process's lock on ``run_dir`` (a sweep job when it ends; tests)."""
    fd = _held.pop(str(Path(run_dir).resolve()), None)
    if fd is not None:
        try:
            os.ftruncate(fd, 0)  # a lock file that names a pid was left by a process that did not end well
        except OSError:
            pass
        os.close(fd)


def release_all() -> None:
    """Every lock this process holds (at its normal end)."""
    for path in list(_held):
        release(path)


def _forget_in_child() -> None:
    """In a process forked from a lock holder: close the copies, so the lock ends with its holder."""
    for fd in _held.values():
        try:
            os.close(fd)
        except OSError:
            pass
    _held.clear()


atexit.register(release_all)
if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_in_child)


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
    if (path / LOG).is_file():
        os.truncate(path / LOG, 0)  # (emptied, not removed: a log handler may hold it open already)
    shutil.rmtree(path / "tb", ignore_errors=True)  # TensorBoard events: the new run's curves alone


def snapshot(run_dir) -> dict[str, int]:
    """``{name: size}`` of what ``run_dir`` and its ``.hydra`` hold now (a folder: -1), for
    ``undo_since``."""
    path = Path(run_dir)
    entries = [*path.iterdir(), *(path / ".hydra").iterdir()] if (path / ".hydra").is_dir() else \
        list(path.iterdir()) if path.is_dir() else []
    return {p.relative_to(path).as_posix(): (-1 if p.is_dir() else p.stat().st_size) for p in entries}


def undo_since(run_dir, before: dict[str, int]) -> None:
    """A refused command leaves ``run_dir`` as ``snapshot`` found it: what it made is removed (its
    lock file and Hydra record included) and the log it appended to is cut back; nothing else is
    touched."""
    path = Path(run_dir)
    release(path)
    now = snapshot(path)
    for name in sorted(now, reverse=True):  # (.hydra's new records before .hydra itself)
        p = path / name
        if name not in before:
            shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink(missing_ok=True)
        elif name == LOG and 0 <= before[name] != now[name]:
            os.truncate(p, before[name])


def write_status(run_dir, status: str, error: str = "") -> None:
    """``run_dir/status.json``; an unwritable folder is left as it is (the caller has said why on stderr)."""
    try:
        (Path(run_dir) / STATUS_FILE).write_text(json.dumps({"status": status, "error": error}))
    except OSError:
        pass


def clear_status(run_dir) -> None:
    """A run starts training: the folder's earlier outcome no longer describes it."""
    (Path(run_dir) / STATUS_FILE).unlink(missing_ok=True)
