"""``mvtn-compare``: two or more configurations over the same seeds, paired (``runs/compare.py``).

Read finished runs:   ``mvtn-compare DIR [DIR ...] [--where "KEY=VALUE ..."]... [--group KEY]``
Run, then read:       ``mvtn-compare --run "OVERRIDES" --run "OVERRIDES" --seeds 0-9 [--jobs 2] COMMON ...``

Without ``--where`` every distinct configuration under the folders is a side (runs that differ
only in ``seed`` are one side); ``--where`` picks one side per condition on the stored config
(``selector=poi`` reads as ``selector.name=poi``). The first side is the reference
(``--reference "KEY=VALUE"`` picks another). ``--run`` trains each side at each seed into
``OUT/side<i>/seed<s>`` (``mvtn-train COMMON SIDE seed=<s>``); a run already finished there is
read, an interrupted one goes on from its ``last.pt``, so the same command completes a comparison.

Prints ``compare.md`` and writes it with ``compare.json`` into ``--out`` (default: the one folder
given, else ``outputs/compare/<time>``); the last line printed is the path of ``compare.md``.
Mismatched data / split / epochs / seeds, fewer than 2 common seeds, or nothing to read: one line
on stderr naming the key, exit 2. Unfinished and failed runs are listed and left out.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from ..runs.compare import compare
from ..runs.compare_md import to_markdown, write
from ..runs.paired_stats import parse_count
from ..runs.sides import CompareError, Side, _check_pair
from ..runs.folders import FolderError, find_runs, flatten, has_metrics, read_status


def parse_seeds(text: str) -> list[int]:
    """``"0-9"`` or ``"0,1,5"`` (or a mix: ``"0-3,7"``) -> sorted distinct seeds."""
    seeds: set[int] = set()
    try:
        for part in text.split(","):
            lo, dash, hi = part.strip().partition("-")
            seeds.update(range(int(lo), int(hi) + 1) if dash else [int(lo)])
    except ValueError:
        raise CompareError(f"--seeds {text!r}: expected seeds like 0-9 or 0,1,2") from None
    return sorted(seeds)


def _settings(overrides: list[str]) -> dict:
    """The composed ``mvtn-train`` config of ``overrides``, flattened, without run-local keys (a bad
    key is refused as mvtn-train refuses it: one line, exit 2)."""
    from ..runs.settings import is_local
    from ..config.compose import compose_train_config

    cfg = compose_train_config(overrides, prog="mvtn-compare")
    return {k: v for k, v in flatten(dataclasses.asdict(cfg)).items() if not is_local(k)}


def plan_runs(sides: list[str], seeds: list[int], common: list[str], out: Path, keys) -> list[tuple]:
    """Check every side's config before any training (bad keys, sides that differ in data, split or
    epochs, two sides with one config) -> ``[(side index, seed, run dir, argv)]``."""
    settings = [_settings([*common, *s.split()]) for s in sides]
    built = [Side(s, st) for s, st in zip(sides, settings)]
    for i, side in enumerate(built[1:], 1):
        if not _check_pair(built[0], side, keys, ""):
            raise CompareError(f"--run {sides[i]!r} gives the same configuration as --run {sides[0]!r}")
    tasks = []
    for i, side in enumerate(sides, 1):
        for s in seeds:
            run_dir = out / f"side{i}" / f"seed{s}"
            tasks.append((i, s, run_dir, [*common, *side.split(), f"seed={s}"]))
    return tasks


def _status(run_dir: Path) -> str | None:
    """The outcome ``run_dir``'s ``status.json`` records; None without one."""
    try:
        record = read_status(run_dir)
        return None if record is None else str(record.get("status"))
    except (OSError, ValueError, AttributeError):
        return "unreadable"


def _train(run_dir: Path, argv: list[str], log: Path, threads: int | None) -> str:
    """One ``mvtn-train`` run into ``run_dir`` (or its resumption); returns ok | failed | done."""
    if has_metrics(run_dir):
        return "done"
    if (run_dir / "last.pt").is_file():  # interrupted: go on from the last finished epoch
        argv = [f"ckpt_path={run_dir / 'last.pt'}"]
    elif _status(run_dir) not in (None, "interrupted"):
        return "failed"  # (interrupted before its first epoch ended: started again)
    env = dict(os.environ)
    if threads:
        env["OMP_NUM_THREADS"] = str(threads)
        argv = [*argv, f"threads={threads}"]
    cmd = [sys.executable, "-m", "mvtn_exp.cli.train", *argv, f"hydra.run.dir={run_dir}"]
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "a") as f:
        f.write(" ".join(cmd) + "\n")
        f.flush()
        rc = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT, env=env).returncode
    return "ok" if rc == 0 else "failed"


def run_all(tasks: list[tuple], out: Path, jobs: int) -> list[str]:
    """Train every task, ``jobs`` at once (one torch thread each when more than one); returns
    ``"side<i> seed<s>: failed (log)"`` for each run that did not finish."""
    from tqdm.auto import tqdm

    threads = 1 if jobs > 1 else None
    bar = tqdm(total=len(tasks), desc="mvtn-compare", unit="run", disable=None)

    def one(task):
        i, s, run_dir, argv = task
        log = out / "logs" / f"side{i}_seed{s}.log"
        status = _train(run_dir, argv, log, threads)
        bar.update()
        return f"side{i} seed{s}: {status} (see {log})" if status == "failed" else None

    with ThreadPoolExecutor(max_workers=jobs) as pool:
        failed = [m for m in pool.map(one, tasks) if m]
    bar.close()
    return failed


def _relabel(result: dict, out: Path, sides: list[str]) -> None:
    """Run mode: each side is named by its ``--run`` overrides."""
    for grp in result["groups"]:
        for entry in grp["sides"]:
            for i, text in enumerate(sides, 1):
                if entry["paths"] and Path(entry["paths"][0]).parent == out / f"side{i}":
                    entry["label"] = text


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="mvtn-compare", description=__doc__.splitlines()[0].split(": ", 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split("\n\n", 1)[1])
    p.add_argument("items", nargs="*", metavar="DIR | OVERRIDE",
                   help="folders of finished runs / sweeps; with --run: overrides common to every side")
    p.add_argument("--where", action="append", metavar="'KEY=VALUE ...'", help="one side: runs whose config has these values")
    p.add_argument("--reference", metavar="'KEY=VALUE ...'", help="the side compared against (default: the first)")
    p.add_argument("--group", metavar="KEY", help="compare separately at each value of KEY (e.g. views)")
    p.add_argument("--key", action="append", default=[], metavar="KEY",
                   help="a data / split / epochs key the sides may differ in (the key under comparison)")
    p.add_argument("--metric", default="test_acc", help="metrics.json number to compare (best_val_acc: choose on validation)")
    p.add_argument("--also", action="append", default=[], metavar="METRIC", help="more metrics.json numbers to show (mean ± std)")
    p.add_argument("--ratio", action="append", default=[], metavar="METRIC",
                   help="metrics.json numbers (times, costs: train_wall_seconds) shown as each side's paired ratio "
                        "to the reference")
    p.add_argument("--count", action="append", default=[], metavar="'METRIC>=VALUE'",
                   help="count each side's seeds that meet the condition (>=, <=, >, <), with the Wilson 95%% interval "
                        "of the share, e.g. 'test_detail_seen>=0.5' (the run's views found the detail)")
    p.add_argument("--run", action="append", metavar="'OVERRIDES'", help="one side to train: its mvtn-train overrides")
    p.add_argument("--seeds", help="with --run: the seeds every side trains at, e.g. 0-9")
    p.add_argument("--jobs", type=int, default=1, help="with --run: runs at once (one torch thread each when > 1)")
    p.add_argument("--out", help="folder for compare.md / compare.json (and the runs of --run)")
    return p


def main(argv=None) -> None:
    args = build_parser().parse_args(argv)
    try:
        if args.jobs < 1:
            raise CompareError(f"--jobs {args.jobs}: expected 1 or more")
        for condition in args.count:  # before anything is trained
            parse_count(condition)
        if args.run:
            if len(args.run) < 2 or not args.seeds:
                raise CompareError("--run: give at least two sides (--run 'A' --run 'B') and --seeds, e.g. --seeds 0-9")
            seeds = parse_seeds(args.seeds)
            if len(seeds) < 2:
                raise CompareError(f"--seeds {args.seeds!r}: a paired comparison needs at least 2 seeds")
            out = Path(args.out or f"outputs/compare/{time.strftime('%Y-%m-%d_%H-%M-%S')}")
            tasks = plan_runs(args.run, seeds, args.items, out, args.key)
            out.mkdir(parents=True, exist_ok=True)
            (out / "command.txt").write_text(" ".join(["mvtn-compare", *(argv if argv is not None else sys.argv[1:])]) + "\n")
            failed = run_all(tasks, out, args.jobs)
            if failed:
                print("mvtn-compare: runs that did not finish: " + "; ".join(failed), file=sys.stderr)
            folders = [out / f"side{i}" for i in range(1, len(args.run) + 1)]
        else:
            if not args.items:
                raise CompareError("give the folders of finished runs (mvtn-compare DIR [DIR ...]) or sides to run (--run)")
            folders = [Path(d) for d in args.items]
            out = Path(args.out) if args.out else (folders[0] if len(folders) == 1 else
                                                   Path(f"outputs/compare/{time.strftime('%Y-%m-%d_%H-%M-%S')}"))
        result = compare(find_runs(folders), args.metric, args.where, args.group, args.key, args.also, args.reference,
                         args.ratio, args.count)
        if args.run:
            _relabel(result, out, args.run)
        md, _ = write(result, out)
    except (CompareError, FolderError) as exc:
        print(f"mvtn-compare: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    except OSError as exc:
        print(f"mvtn-compare: cannot write under {exc.filename or args.out}: {exc.strerror or exc}", file=sys.stderr)
        raise SystemExit(2) from None
    print(to_markdown(result))
    if result["not_finished"]:
        print(f"mvtn-compare: {len(result['not_finished'])} run(s) not finished, left out: "
              + "; ".join(f"{r['path']} ({r['status']})" for r in result["not_finished"]), file=sys.stderr)
    print(md)


if __name__ == "__main__":
    main()
