"""Paired comparison of two settings over the same seeds, from finished run / sweep folders.

``python scripts/studies/compare_seeds.py DIR [DIR ...] --a KEY=VALUE --b KEY=VALUE [--group KEY]``
reads every ``metrics.json`` below the folders, takes the runs whose stored config has ``KEY=VALUE``
(dotted keys, e.g. ``selector.name=spherical``) as side A or B, groups them by ``--group``
(default ``views``), pairs them by ``seed`` and prints, per group, each side's test accuracy per
seed, mean +- sample std, the paired difference B - A in points with its 95% paired-t interval
(Student's t, n - 1 degrees of freedom) and how many seeds B is ahead, tied and behind.

A stand-in for the project-wide ``mvtn-compare`` (not built yet): it does not check that the two
sides differ in nothing else.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from scipy import stats


def get(config: dict, dotted: str):
    node = config
    for part in dotted.split("."):
        if not isinstance(node, dict) or part not in node:
            return None
        node = node[part]
    return node


def matches(config: dict, condition: str) -> bool:
    key, value = condition.split("=", 1)
    return str(get(config, key)) == value


def read_runs(folders: list[str]) -> list[dict]:
    runs = []
    for folder in folders:
        for path in sorted(Path(folder).rglob("metrics.json")):
            metrics = json.loads(path.read_text())
            if "config" in metrics and "test_acc" in metrics:
                runs.append(metrics)
    return runs


def compare(runs: list[dict], a: str, b: str, group: str) -> list[dict]:
    """One result per group value: seeds, accuracies of A and B, and the paired statistics."""
    sides: dict = {}
    for run in runs:
        cfg = run["config"]
        for side, cond in (("a", a), ("b", b)):
            if matches(cfg, cond):
                sides.setdefault((get(cfg, group), side), {})[cfg["seed"]] = run["test_acc"]
    out = []
    for g in sorted({k[0] for k in sides}, key=str):
        A, B = sides.get((g, "a"), {}), sides.get((g, "b"), {})
        seeds = sorted(set(A) & set(B))
        if len(seeds) < 2:
            continue
        xa, xb = [A[s] for s in seeds], [B[s] for s in seeds]
        d = [y - x for x, y in zip(xa, xb)]
        n, mean = len(d), sum(d) / len(d)
        sd = math.sqrt(sum((v - mean) ** 2 for v in d) / (n - 1))
        half = stats.t.ppf(0.975, n - 1) * sd / math.sqrt(n)
        out.append({"group": g, "seeds": seeds, "a": xa, "b": xb, "diff": mean, "diff_sd": sd,
                    "low": mean - half, "high": mean + half, "ahead": sum(v > 0 for v in d),
                    "tied": sum(v == 0 for v in d), "behind": sum(v < 0 for v in d)})
    return out


def mean_sd(x: list[float]) -> str:
    m = sum(x) / len(x)
    return f"{m:.3f} +- {math.sqrt(sum((v - m) ** 2 for v in x) / (len(x) - 1)):.3f}"


def report(results: list[dict], a: str, b: str, group: str) -> str:
    lines = []
    for r in results:
        lines += [f"{group}={r['group']}, seeds {', '.join(map(str, r['seeds']))} (n={len(r['seeds'])})",
                  f"  A {a}: " + " / ".join(f"{x:.3f}" for x in r["a"]) + f" = {mean_sd(r['a'])}",
                  f"  B {b}: " + " / ".join(f"{x:.3f}" for x in r["b"]) + f" = {mean_sd(r['b'])}",
                  f"  B - A {100 * r['diff']:+.1f} +- {100 * r['diff_sd']:.1f} points, 95% paired-t "
                  f"[{100 * r['low']:+.1f}, {100 * r['high']:+.1f}]; B ahead {r['ahead']}, tied {r['tied']}, "
                  f"behind {r['behind']}"]
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python scripts/studies/compare_seeds.py", description=__doc__.splitlines()[0])
    p.add_argument("folders", nargs="+")
    p.add_argument("--a", required=True, help="KEY=VALUE of side A's stored config, e.g. selector.name=spherical")
    p.add_argument("--b", required=True, help="KEY=VALUE of side B's stored config")
    p.add_argument("--group", default="views", help="config key whose values are compared separately")
    args = p.parse_args(argv)
    for cond in (args.a, args.b):
        if "=" not in cond:
            print(f"compare_seeds: --a/--b take KEY=VALUE, got {cond!r}", file=sys.stderr)
            return 2
    results = compare(read_runs(args.folders), args.a, args.b, args.group)
    if not results:
        print(f"compare_seeds: no group has both {args.a} and {args.b} at two or more common seeds under "
              f"{', '.join(args.folders)}", file=sys.stderr)
        return 2
    print(report(results, args.a, args.b, args.group))
    return 0


if __name__ == "__main__":
    sys.exit(main())
