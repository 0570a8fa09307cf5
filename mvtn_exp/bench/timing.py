"""The benchmark's clocks: seconds of a call (synchronised on CUDA), runs within a time budget, two
sides timed in alternation and their paired ratio, and the extra peak memory of one run."""
from __future__ import annotations

import gc
import statistics
import time
from typing import Callable

import torch

from ..runtime.memory import PeakMemory


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def timed(fn: Callable[[], object], device: torch.device) -> float:
    _sync(device)
    t0 = time.perf_counter()
    fn()
    _sync(device)
    return time.perf_counter() - t0


def paired_times(a: Callable[[], object], b: Callable[[], object], device: torch.device, repeats: int,
                 budget_s: float) -> tuple[list[float], list[float]]:
    """Seconds of ``a`` and ``b`` timed in alternation (one warm-up each; the side that goes first
    alternates), at least 5 rounds and up to ``repeats`` within ``budget_s`` a round: a load change
    hits both sides alike, and ``paired_ratio`` takes the median of the rounds' ratios."""
    a(), b()
    ta, tb = [timed(a, device)], [timed(b, device)]
    n = max(5, min(int(repeats), int(budget_s / max(ta[0] + tb[0], 1e-9))))
    while len(ta) < n:
        first, second = ((a, ta), (b, tb)) if len(ta) % 2 == 0 else ((b, tb), (a, ta))
        for fn, out in (first, second):
            out.append(timed(fn, device))
    return ta, tb


def time_runs(fn: Callable[[], object], device: torch.device, repeats: int, budget_s: float) -> list[float]:
    """Seconds of up to ``repeats`` runs (the caller has warmed ``fn`` up); slow functions run fewer times."""
    times = [timed(fn, device)]
    n = max(1, min(int(repeats), int(budget_s / max(times[0], 1e-9))))
    while len(times) < n:
        times.append(timed(fn, device))
    return times


def paired_ratio(times: tuple[list[float], list[float]]) -> float:
    """Ratio of side a to side b: the median of the per-round ratios when both were timed in
    alternation (``paired_times``: equal lengths), else the ratio of the medians. Each round times
    both sides within a moment, so a load that changes between rounds cancels in its ratio; the
    ratio of medians can pair one side's quiet rounds with the other's loaded ones."""
    a, b = times
    if len(a) == len(b) and len(a) > 1:
        return statistics.median(x / y for x, y in zip(a, b))
    return statistics.median(a) / statistics.median(b)


def med_ms(times_s: list[float] | None) -> float:
    return float("nan") if not times_s else 1000.0 * statistics.median(times_s)


def peak_of(fn: Callable[[], object], device: torch.device) -> tuple[float, float]:
    """(extra peak MiB, seconds) of one run of ``fn``."""
    gc.collect()
    with PeakMemory(device) as pm:
        t = timed(fn, device)
    return pm.peak_mib, t
