"""The one reader of run and sweep folders: what ``mvtn-compare``, ``mvtn-report``, ``mvtn-tradeoff``,
sweep summaries and re-timing know of a run comes from here.

A run folder holds, as far as the run got: ``.hydra/config.yaml`` and ``.hydra/overrides.yaml``
(Hydra writes them as the run starts), ``status.json`` (its last outcome, ``engine/run_dir.py``) and
``metrics.json`` (written when it finished, its config included). ``read_run`` reads them into a
``Run``:

- ``status``: ``ok`` when ``metrics.json`` is there; else the outcome ``status.json`` records (``failed``
  when it names none; ``incomplete`` for a recorded ``ok`` whose ``metrics.json`` is gone); else
  ``incomplete``; ``unreadable`` when one of its files cannot be parsed (``error`` says why);
- its config: the one ``metrics.json`` records for a finished run, else Hydra's ``.hydra/config.yaml``;
  ``seed`` is the config's, ``settings`` the config flattened without the keys ``runs/settings.py``
  calls local (None without a config);
- ``overrides``: the Hydra overrides that made it (``.hydra/overrides.yaml``; without that file, the
  folder's name, so that a job still has a setting of its own).

``find_runs`` finds every run at or below some folders, for comparisons (a run without a config is
listed with why, never compared); ``sweep_jobs`` reads the jobs of one sweep folder in natural order.
"""
from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from ..engine.provenance import machine
from ..engine.run_dir import STATUS_FILE  # status.json: a run's last outcome
from .settings import is_local

METRICS_FILE = "metrics.json"  # a finished run's record
HYDRA_DIR = ".hydra"  # Hydra's record of how a run was started: config.yaml, overrides.yaml
NO_CONFIG = "no config in its record"


class FolderError(ValueError):
    """A folder of runs that is not there."""


@dataclass
class Run:
    """One run folder (module docstring): ``status`` ok | failed | incomplete | unreadable (or another
    outcome its ``status.json`` records); ``settings``: its config, flattened to dotted keys, without
    ``RUN_LOCAL`` keys (None when no config could be read)."""

    path: Path
    status: str
    seed: int | None = None
    settings: dict | None = None
    metrics: dict = field(default_factory=dict)
    commit: str | None = None
    error: str = ""
    machine: str | None = None  # the hardware behind its float rounding (None: not recorded)
    filled: list = field(default_factory=list)  # keys its record lacked, read as today's defaults
    overrides: list = field(default_factory=list)  # the Hydra overrides that made it

    @property
    def job(self) -> str:
        """Its name in a sweep: the folder's name."""
        return self.path.name


def flatten(node, prefix: str = "") -> dict:
    """``{"a": {"b": 1}}`` -> ``{"a.b": 1}`` (lists stay values)."""
    out = {}
    for k, v in node.items():
        key = f"{prefix}.{k}" if prefix else str(k)
        out.update(flatten(v, key) if isinstance(v, dict) and v else {key: v})
    return out


def has_metrics(path) -> bool:
    """Whether the run in ``path`` finished (its ``metrics.json`` is there)."""
    return (Path(path) / METRICS_FILE).is_file()


def read_metrics(path) -> dict:
    """The run's ``metrics.json`` (OSError when it is not there, ValueError when it is no JSON)."""
    return json.loads((Path(path) / METRICS_FILE).read_text())


def read_status(path):
    """The run's ``status.json`` record, None without one (ValueError when it is no JSON)."""
    status_file = Path(path) / STATUS_FILE
    return json.loads(status_file.read_text()) if status_file.is_file() else None


def started_at(path) -> float | None:
    """When the run started (Hydra wrote its ``.hydra/config.yaml``); None without that file."""
    config_file = Path(path) / HYDRA_DIR / "config.yaml"
    return config_file.stat().st_mtime if config_file.is_file() else None


def finished_at(path) -> float:
    """When the run finished (it wrote ``metrics.json``; OSError when it did not)."""
    return (Path(path) / METRICS_FILE).stat().st_mtime


def _overrides(path: Path) -> list[str]:
    overrides_file = path / HYDRA_DIR / "overrides.yaml"
    if overrides_file.is_file():
        return [str(o) for o in (yaml.safe_load(overrides_file.read_text()) or [])]
    return [path.name]


def _hydra_config(path: Path):
    config_file = path / HYDRA_DIR / "config.yaml"
    return yaml.safe_load(config_file.read_text()) if config_file.is_file() else None


def _outcome(record) -> tuple[str, str]:
    """``(status, error)`` of an unfinished run from its ``status.json`` record (None: no record)."""
    if record is None:
        return "incomplete", ""
    status, error = str(record.get("status", "failed")), str(record.get("error", ""))
    return ("incomplete" if status == "ok" else status), error  # ok, but its metrics.json is gone


def _run(path: Path, status: str, error: str, config, metrics: dict, overrides: list[str]) -> Run:
    flat = flatten(config) if isinstance(config, dict) else None
    prov = metrics.get("provenance") or {}
    commit = (prov["commit"][:7] + ("+dirty" if prov.get("dirty") else "")) if prov.get("commit") else None
    return Run(path, status, seed=None if flat is None else flat.get("seed"),
               settings=None if flat is None else {k: v for k, v in flat.items() if not is_local(k)},
               metrics=metrics, commit=commit, error=error, machine=machine(prov), overrides=overrides)


def read_run(path) -> Run:
    """The record of the run folder ``path`` (module docstring); a file it cannot parse makes the
    run ``unreadable``, never an exception."""
    path = Path(path)
    overrides = [path.name]
    try:
        overrides = _overrides(path)
        if has_metrics(path):
            metrics = read_metrics(path)
            return _run(path, "ok", "", metrics.get("config"), metrics, overrides)
        status, error = _outcome(read_status(path))
        return _run(path, status, error, _hydra_config(path), {}, overrides)
    except (OSError, ValueError, AttributeError, yaml.YAMLError) as exc:
        return Run(path, "unreadable", error=str(exc), overrides=overrides)


def _comparable(run: Run) -> Run:
    """A run as comparisons read it: without a config it cannot join a side, so it is listed with
    why (a finished one as ``unreadable``) and carries nothing else."""
    if run.settings is not None or run.status == "unreadable":
        return run
    return Run(run.path, "unreadable" if run.status == "ok" else run.status, error=run.error or NO_CONFIG,
               overrides=run.overrides)


def find_runs(folders) -> list[Run]:
    """Every run folder at or below ``folders`` (in the order given, paths sorted within each; a
    folder reached twice is read once), as comparisons read them (``_comparable``)."""
    runs, seen = [], set()
    for folder in folders:
        folder = Path(folder)
        if not folder.is_dir():
            raise FolderError(f"{folder}: no such folder")
        marks = [p.parent for name in (METRICS_FILE, STATUS_FILE) for p in folder.rglob(name)]
        marks += [p.parent for p in folder.rglob(HYDRA_DIR) if p.is_dir()]
        for path in sorted(set(marks)):
            if path.resolve() not in seen and HYDRA_DIR not in path.parts:
                seen.add(path.resolve())
                runs.append(_comparable(read_run(path)))
    return runs


def _natural(path: Path) -> list:
    """Sort key: ``2`` before ``10`` in folder names."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", path.name)]


def sweep_jobs(sweep_dir) -> list[Run]:
    """The jobs of a sweep: every folder directly under ``sweep_dir`` that has ``.hydra/`` (hidden
    folders skipped), in the natural order of their names (OSError when ``sweep_dir`` is no folder)."""
    jobs = [p for p in Path(sweep_dir).iterdir()
            if p.is_dir() and not p.name.startswith(".") and (p / HYDRA_DIR).is_dir()]
    return [read_run(p) for p in sorted(jobs, key=_natural)]
