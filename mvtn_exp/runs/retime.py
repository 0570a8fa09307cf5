"""Inference time of finished runs measured again, one run at a time, in this process
(``mvtn-tradeoff --retime``).

A run's own ``infer_ms_per_shape`` (``engine/cost.py``) is one test pass timed inside the training
job: on whatever machine the job ran on and beside whatever else ran there (the other jobs of a
joblib sweep, a test suite). Fronts of two folders trained on different machines or days (a grid
and a search, a resumed search) are only comparable in time when their points are timed the same
way; re-timing does that: the job's ``best.pt`` is rebuilt from its stored config, and its test
pass (G, R, C at the run's batch size and torch threads, data loading included, as in training)
runs once to warm up and then ``passes`` times; the median pass, per test shape, is the time.

The pass must reproduce the run's test accuracy (the same weights, data and views); a job whose
accuracy differs is refused (its record and its checkpoint disagree). The result is written to the
job folder as ``retimed.json`` (milliseconds, every pass, threads, machine, commit) beside the
untouched ``metrics.json``.
"""
from __future__ import annotations

import json
import statistics
import time
from pathlib import Path

import torch

from ..data.datasets import build_dataset
from ..render import accel
from ..config.schema import resolve_device
from ..tasks import classification
from ..runtime import checkpoint
from ..engine.provenance import provenance
from .folders import METRICS_FILE, read_metrics

RETIMED = "retimed.json"


class RetimeError(ValueError):
    """A finished job that cannot be timed again (no ``best.pt``, its accuracy not reproduced)."""


def retime_job(job_dir, passes: int = 3) -> dict:
    """Time ``job_dir``'s test pass again (module docstring); returns and writes ``retimed.json``:
    ``infer_ms_per_shape`` (median of ``passes`` after one warm-up), ``passes_ms`` (each pass, ms
    per shape), ``threads``, ``test_acc`` (reproduced), ``provenance`` (machine and commit)."""
    from ..evaluation.evaluate import config_from_checkpoint, load_model  # (evaluation imports the trainer)
    from ..engine.trainer import eval_loader

    job_dir = Path(job_dir)
    path = job_dir / "best.pt"
    if not path.is_file():
        raise RetimeError(f"{path}: not found; re-timing needs the run's best checkpoint")
    recorded = read_metrics(job_dir)
    state = checkpoint.load(path, map_location="cpu")
    cfg = config_from_checkpoint(state, path)
    cfg.device = resolve_device(cfg.device)
    problem = accel.unavailable(torch.device(cfg.device).type) if cfg.renderer.compile else None
    if problem:  # a compiled run's time is its compiled renderer's: refused rather than timed eagerly
        raise RetimeError(f"{job_dir}: renderer.compile=true, and {problem}; re-time it where it trained")
    threads = torch.get_num_threads()
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    try:
        dataset = build_dataset(cfg.dataset, "test", progress=False)
        model = load_model(cfg, state, len(dataset.classes), path, torch.device(cfg.device))
        times, acc = [], None
        for _ in range(passes + 1):
            t0 = time.perf_counter()
            res = classification.evaluate(model, eval_loader(cfg, dataset), len(dataset.classes), desc="test",
                                          progress=False)
            times.append(1000.0 * (time.perf_counter() - t0) / max(res["n"], 1))
            acc = res["acc"]
        out = {"infer_ms_per_shape": statistics.median(times[1:]), "passes_ms": times[1:], "warmup_ms": times[0],
               "threads": torch.get_num_threads(), "test_acc": acc, "provenance": provenance(cfg.device)}
    finally:
        torch.set_num_threads(threads)
    if abs(acc - float(recorded["test_acc"])) > 1e-9:
        raise RetimeError(f"{job_dir}: the re-timed test pass reached accuracy {acc:.4f}, the run recorded "
                          f"{float(recorded['test_acc']):.4f}; its checkpoint and {METRICS_FILE} disagree")
    (job_dir / RETIMED).write_text(json.dumps(out, indent=1))
    return out


def retime_jobs(jobs, passes: int = 3, progress: bool = True) -> None:
    """``retime_job`` on each finished job folder of ``jobs``, one after another (a bar on a terminal)."""
    from tqdm.auto import tqdm

    for job in tqdm(list(jobs), desc="re-timing", disable=None if progress else True):
        retime_job(job, passes)
