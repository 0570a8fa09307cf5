"""``mvtn-tradeoff DIR``: the speed/accuracy trade of a sweep folder (``runs/tradeoff.py``).

Writes ``tradeoff.csv`` (per setting), ``tradeoff_jobs.csv`` (per job), ``tradeoff.md`` and
``pareto.png`` into DIR, prints the Markdown and, last, the path of ``tradeoff.md``.
``--metric best_val_acc`` draws the front on validation accuracy (a search or grid that chooses
on validation); ``--against OTHER ...`` also prints the hypervolume of DIR's front and of each
OTHER's with one reference point (a search against a grid) and writes it to DIR/fronts.md.
``--seed N`` reads only the runs of seed N (a grid's seed-0 runs against a search's one run per
setting), its files named ``tradeoff-seedN.md`` etc.
``--retime`` first times every finished job's test pass again, one at a time in this process
(``runs/retime.py``), and draws the fronts on those times: folders trained on different
machines, or beside other jobs, become comparable in time; ``--retimed`` reads those times again
(another ``--seed`` or ``--metric``) without timing anything. A
folder with no finished job, with jobs from different datasets or with a job whose metrics lack
the cost fields or the metric: one line on stderr naming it, exit code 2. Failed jobs are
listed, not dropped.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..data.shapes import ShapeError
from ..runtime.checkpoint import CheckpointMismatch
from ..engine.provenance import package_version
from ..runs.retime import RetimeError, retime_jobs
from ..runs.tradeoff import METRICS, TradeoffError, compare_fronts, job_rows, output_name, write_tradeoff


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="mvtn-tradeoff", description=__doc__.splitlines()[0].split(": ", 1)[1])
    p.add_argument("sweep_dir", metavar="DIR", help="a sweep folder written by mvtn-train -m")
    p.add_argument("--metric", default="test_acc", choices=METRICS, help="the accuracy of the front (default test_acc)")
    p.add_argument("--against", nargs="+", default=[], metavar="OTHER", help="folders whose fronts to set beside DIR's")
    p.add_argument("--retime", action="store_true",
                   help="time every finished job's test pass again here, one at a time, and use those times")
    p.add_argument("--retimed", action="store_true",
                   help="use the times an earlier --retime wrote (each job's retimed.json) without timing again")
    p.add_argument("--seed", type=int, default=None,
                   help="only the runs of this seed (e.g. a grid's seed-0 runs against a search's one run per "
                        "setting); files get a -seedN suffix")
    p.add_argument("--passes", type=int, default=3, help="timed test passes per job with --retime (default 3)")
    p.add_argument("--version", action="version", version=f"mvtn-tradeoff (mvtn-exp {package_version()})")
    return p


def main(argv=None) -> None:
    args = build_parser().parse_args(argv)
    if args.passes < 1:
        print(f"mvtn-tradeoff: --passes {args.passes}: expected at least 1", file=sys.stderr)
        raise SystemExit(2)
    dirs = [args.sweep_dir, *args.against]
    try:
        if args.retime:
            jobs = [Path(d) / r["job"] for d in dict.fromkeys(dirs) for r in job_rows(d, seed=args.seed)
                    if r.get("status") == "ok"]
            retime_jobs(jobs, args.passes)  # (every folder read before anything is timed)
        retimed = args.retime or args.retimed
        out = write_tradeoff(args.sweep_dir, args.metric, retimed, args.seed)
        fronts = compare_fronts(dirs, args.metric, retimed, args.seed) if args.against else None
        if fronts:
            (out["md"].parent / output_name("fronts.md", args.seed)).write_text(fronts["md"])
    except (TradeoffError, RetimeError, CheckpointMismatch, ShapeError, OSError) as e:
        print(f"mvtn-tradeoff: {e}", file=sys.stderr)
        raise SystemExit(2) from None
    print(out["md"].read_text())
    if fronts:
        print("## Fronts\n\n" + fronts["md"])
    if out["failed"]:
        print(f"mvtn-tradeoff: {len(out['failed'])} failed job(s) left out: " + "; ".join(out["failed"]), file=sys.stderr)
    print(out["md"])


if __name__ == "__main__":
    main()
