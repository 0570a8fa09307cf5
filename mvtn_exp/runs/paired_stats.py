"""The statistics of a paired comparison over seeds: the paired-t interval of a difference, the
geometric mean of paired ratios, counted outcomes with their Wilson interval, and mean +- sample std."""
from __future__ import annotations

import math
import operator
import re

from scipy import stats

from .sides import CompareError


def paired(ref: list[float], other: list[float]) -> dict:
    """Paired statistics of ``other - ref`` (same seeds, same order): mean, sample std, the 95%
    paired-t interval and the counts of seeds ahead / tied / behind."""
    d = [b - a for a, b in zip(ref, other)]
    n, mean = len(d), sum(d) / len(d)
    sd = math.sqrt(sum((x - mean) ** 2 for x in d) / (n - 1))
    half = float(stats.t.ppf(0.975, n - 1)) * sd / math.sqrt(n)
    return {"diff": mean, "diff_sd": sd, "low": mean - half, "high": mean + half,
            "ahead": sum(x > 0 for x in d), "tied": sum(x == 0 for x in d), "behind": sum(x < 0 for x in d)}


COMPARISONS = {">=": operator.ge, "<=": operator.le, ">": operator.gt, "<": operator.lt}


def parse_count(text: str) -> tuple[str, str, float]:
    """``'METRIC>=VALUE'`` (or ``<=``, ``>``, ``<``) -> ``(metric, operator, value)``."""
    m = re.fullmatch(r"\s*([A-Za-z_][\w.]*)\s*(>=|<=|>|<)\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*", text)
    if not m:
        raise CompareError(f"--count {text!r}: expected METRIC>=VALUE (or <=, >, <), e.g. test_detail_seen>=0.5")
    return m.group(1), m.group(2), float(m.group(3))


def wilson(k: int, n: int) -> tuple[float, float]:
    """The Wilson score 95% interval of a share ``k / n``."""
    z = float(stats.norm.ppf(0.975))
    p, d = k / n, 1 + z * z / n
    centre, half = (p + z * z / (2 * n)) / d, z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    return max(0.0, centre - half), min(1.0, centre + half)


def count(values: list[float], op: str, bound: float) -> dict:
    """How many ``values`` meet ``value op bound`` (``parse_count``), of how many, with the Wilson interval."""
    k = sum(COMPARISONS[op](v, bound) for v in values)
    low, high = wilson(k, len(values))
    return {"k": k, "n": len(values), "low": low, "high": high}


def mean_sd(x: list[float]) -> tuple[float, float]:
    m = sum(x) / len(x)
    return m, (math.sqrt(sum((v - m) ** 2 for v in x) / (len(x) - 1)) if len(x) > 1 else 0.0)


def ratio(ref: list[float], side: list[float]) -> dict:
    """``side / ref`` over paired seeds: the geometric mean of the per-seed ratios and its 95% paired-t
    interval (on the logarithms); every value must be > 0."""
    if min(ref + side) <= 0:
        raise CompareError("--ratio: the metric must be > 0 on every run to form ratios")
    logs = [math.log(b / a) for a, b in zip(ref, side)]
    m, sd = mean_sd(logs)
    half = stats.t.ppf(0.975, len(logs) - 1) * sd / math.sqrt(len(logs))
    return {"ratio": math.exp(m), "ratio_low": math.exp(m - half), "ratio_high": math.exp(m + half)}
