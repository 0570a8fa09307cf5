"""Hydra's Optuna sweeper made for a search that runs for hours (``hydra/sweeper=mvtn_optuna``,
used by ``+experiment=tradeoff_search``; the plugin class: ``hydra_plugins/mvtn_exp_search_sweeper``).

Three things the plugin's own loop (hydra-optuna-sweeper 1.3) does not do:

- **start points**: ``hydra.sweeper.start_points`` (a list of ``{key: value}``) are the study's
  first trials (Optuna's ``enqueue_trial``), e.g. the cheapest setting of each selector, so the
  search's first generation is not all chance;
- **no setting trained twice**: a trial whose parameters equal a finished trial's is told that
  trial's objectives and launches nothing; ``n_trials`` counts the trials that train (a repeat is a
  ``repeat`` line in ``search.csv``), and the search stops after ``max_repeats`` repeats in a row
  (the space, or what NSGA-II will propose from it, is used up);
- **resumable as printed**: the sampler is seeded and every objective comes back from the trial's
  ``metrics.json``, so the same command into the same ``hydra.sweep.dir`` (``mvtn-train
  --resume-sweep DIR``) proposes the same trials in the same order: a finished trial is kept (not
  trained again), an interrupted one goes on from its ``last.pt`` (``cli/train.py``). A job folder
  that holds another setting than the trial proposed for it (the search space, the sampler or the
  code changed between the two runs) stops the search with one line naming the folder before
  anything is launched into it.

Job ``k`` of the sweep folder is the k-th trial that trains; ``search.csv`` lists every trial
(number, job, parameters, objectives, state) as it is told.
"""
from __future__ import annotations

import csv
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

from hydra.core.config_store import ConfigStore
from hydra_plugins.hydra_optuna_sweeper.config import OptunaSweeperConf

log = logging.getLogger(__name__)


@dataclass
class SearchSweeperConf(OptunaSweeperConf):
    """``OptunaSweeperConf`` plus the start points and the repeat limit of the module docstring."""

    _target_: str = "hydra_plugins.mvtn_exp_search_sweeper.SearchSweeper"
    start_points: List[Dict[str, Any]] = field(default_factory=list)
    max_repeats: int = 50


# hydra/sweeper=mvtn_optuna: stored when Hydra's plugin scan imports hydra_plugins/mvtn_exp_search_sweeper
ConfigStore.instance().store(group="hydra/sweeper", name="mvtn_optuna", node=SearchSweeperConf, provider="mvtn_exp")


class SearchRefused(RuntimeError):
    """A job folder holds a run of another setting than its trial's, or a start point is not a
    setting of the search: one line for the user, nothing launched."""


def settings_key(params: Dict[str, Any]) -> tuple:
    """A trial's parameters as a hashable key (values compared as the text Hydra is given)."""
    return tuple(sorted((str(k), str(v)) for k, v in params.items()))


def check_job_dir(sweep_dir: Path, job: int, overrides: Sequence[str]) -> None:
    """Raise ``SearchRefused`` when a folder of job number ``job`` in ``sweep_dir`` (``K`` or
    ``K_<overrides>``, ``conf/hydra/default.yaml``) holds a run whose recorded overrides lack one of
    ``overrides`` (the trial's ``key=value``); no such folder, or an empty one, passes."""
    import yaml

    for folder in [sweep_dir / str(job), *sweep_dir.glob(f"{job}_*")]:
        record = folder / ".hydra" / "overrides.yaml"
        if not record.is_file():
            continue
        held = {str(o) for o in (yaml.safe_load(record.read_text()) or [])}
        missing = [o for o in overrides if o not in held]
        if missing:
            raise SearchRefused(f"{folder} holds another setting than trial job {job} proposed ({', '.join(missing)} "
                                 "not among its overrides): the search space, sampler or code changed since it ran; "
                                 "resume with the same command and code, or search into a new hydra.sweep.dir")


def _values(ret, n_objectives: int) -> List[float]:
    """The objectives a job returned (``cli/train.py: objective_values``); raises when it has none."""
    out = ret.return_value  # re-raises the job's own error
    values = [float(v) for v in (out if isinstance(out, (list, tuple)) else [out])]
    if len(values) != n_objectives:
        raise ValueError(f"the run returned {len(values)} objective(s), the search has {n_objectives}")
    return values


class _Record:
    """``search.csv`` in the sweep folder: one row per told trial (written anew by each run of the
    search: a resumed search replays every trial, so the file is whole again)."""

    def __init__(self, sweep_dir: Path, objectives: int) -> None:
        sweep_dir.mkdir(parents=True, exist_ok=True)
        self.path = sweep_dir / "search.csv"
        self._write(["trial", "job", "state", *[f"objective{i}" for i in range(objectives)], "params"], "w")

    def _write(self, row: list, mode: str = "a") -> None:
        with open(self.path, mode, newline="") as f:
            csv.writer(f).writerow(row)

    def row(self, trial: int, job, state: str, values, params: dict) -> None:
        self._write([trial, "" if job is None else job, state, *(list(values) if values is not None else []),
                     " ".join(f"{k}={v}" for k, v in sorted(params.items()))])


def _configure(impl, trial, space: dict, fixed: dict) -> tuple:
    """The trial's overrides (the plugin's ``_configure_trials``); a start point (an enqueued trial)
    whose value is not among its key's choices, or with a key the search neither samples for it nor
    is given on the command line (which wins), raises ``SearchRefused``."""
    point = trial.system_attrs.get("fixed_params") or {}
    try:
        (overrides,) = impl._configure_trials([trial], space, fixed)
    except ValueError as exc:
        if not point:
            raise
        raise SearchRefused(f"hydra.sweeper.start_points: {point}: {exc} (a value of the key's choices expected)") from None
    unused = sorted(set(point) - set(trial.params) - set(fixed))  # a key given on the command line wins
    if unused:
        raise SearchRefused(f"hydra.sweeper.start_points: {point}: {', '.join(unused)} is not a key the search samples "
                            f"for this point (it samples {', '.join(sorted(trial.params))})")
    return overrides


def _tell_repeat(study, record: _Record, trial, told: dict, key: tuple, params: dict) -> None:
    """A repeated setting: told the objectives its first trial got (failed if that one failed)."""
    import optuna

    if key in told:
        study.tell(trial, told[key])
        record.row(trial.number, None, "repeat", told[key], params)
    else:
        study.tell(trial, state=optuna.trial.TrialState.FAIL)
        record.row(trial.number, None, "failed", None, params)


def _ask_batch(study, impl, space, fixed, record, told: dict, size: int, repeats: int, max_repeats: int):
    """Up to ``size`` trials of new settings: ``(batch, overrides, echoes, repeats)``. A repeat of a
    trained setting is told at once; a repeat of a setting in this batch (an echo) after it ran."""
    batch, overrides, echoes = [], [], []
    while len(batch) < size and repeats < max_repeats:
        trial = study.ask()
        trial_overrides = _configure(impl, trial, space, fixed)
        params = dict(trial.params)
        key = settings_key(params)
        if key in told or key in {k for _, k, _ in batch}:  # trained before or now: nothing launched
            if key in told:
                _tell_repeat(study, record, trial, told, key, params)
            else:
                echoes.append((trial, key, params))
            repeats += 1
            continue
        repeats = 0
        batch.append((trial, key, params))
        overrides.append(trial_overrides)
    return batch, overrides, echoes, repeats


def _run_batch(study, impl, sweep_dir: Path, record: _Record, told: dict, batch: list, overrides: list,
               n_objectives: int) -> None:
    """Launch ``batch`` (job folders checked first) and tell each trial its objectives, or failed."""
    import optuna

    for i, (trial, _, params) in enumerate(batch):
        check_job_dir(sweep_dir, impl.job_idx + i, [f"{k}={v}" for k, v in params.items()])
    returns = impl.launcher.launch(overrides, initial_job_idx=impl.job_idx)
    failures = 0
    for i, ((trial, key, params), ret) in enumerate(zip(batch, returns)):
        try:
            values = _values(ret, n_objectives)
        except Exception as exc:  # the job's failure is recorded; the search goes on
            study.tell(trial, state=optuna.trial.TrialState.FAIL)
            record.row(trial.number, impl.job_idx + i, "failed", None, params)
            log.warning(f"Failed experiment: {exc}")
            failures += 1
            continue
        study.tell(trial, values)
        told[key] = values
        record.row(trial.number, impl.job_idx + i, "run", values, params)
    impl.job_idx += len(returns)
    if failures / len(returns) > impl.max_failure_rate:
        for ret in returns:
            ret.return_value  # raise with the job's own traceback


def search(impl, arguments: List[str], start_points: list, max_repeats: int) -> None:
    """The plugin's ``OptunaSweeperImpl.sweep`` with start points, repeats told without training and
    job folders checked before launch (module docstring). ``impl``: the plugin's sweeper, set up."""
    import optuna
    from hydra_plugins.hydra_optuna_sweeper._impl import create_params_from_overrides
    from omegaconf import OmegaConf

    impl._process_searchspace_config()
    space, fixed = create_params_from_overrides(impl._parse_sweeper_params_config() + list(arguments))
    for name in fixed:
        space.pop(name, None)
    directions = impl._get_directions()
    study = optuna.create_study(study_name=impl.study_name, storage=impl.storage, sampler=impl.sampler,
                                directions=directions, load_if_exists=True)
    if not study.trials:
        for point in start_points:
            study.enqueue_trial(point)
    sweep_dir = Path(impl.config.hydra.sweep.dir)
    record = _Record(sweep_dir, len(directions))
    OmegaConf.save(impl.config, sweep_dir / "multirun.yaml")  # the command, for mvtn-train --resume-sweep
    told: Dict[tuple, List[float]] = {}
    trained = repeats = 0
    while trained < impl.n_trials and repeats < max_repeats:
        batch, overrides, echoes, repeats = _ask_batch(study, impl, space, fixed, record, told,
                                                       min(impl.n_jobs, impl.n_trials - trained), repeats, max_repeats)
        if not batch:
            break
        _run_batch(study, impl, sweep_dir, record, told, batch, overrides, len(directions))
        for trial, key, params in echoes:  # told what their batch-mate got
            _tell_repeat(study, record, trial, told, key, params)
        trained += len(batch)
    if repeats >= max_repeats:
        log.info(f"{max_repeats} proposals in a row repeated a trained setting: the search stops after {trained} trials")
    best = study.best_trials if len(directions) > 1 else [study.best_trial]
    front = [{"params": t.params, "values": t.values} for t in best]
    OmegaConf.save(OmegaConf.create({"name": "optuna", "trained": trained, "solutions": front}),
                   sweep_dir / "optimization_results.yaml")
