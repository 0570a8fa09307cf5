"""``mvtn-tradeoff DIR``: the speed/accuracy trade of a sweep folder (``engine/tradeoff.py``).

Writes ``tradeoff.csv`` (per setting), ``tradeoff_jobs.csv`` (per job), ``tradeoff.md`` and
``pareto.png`` into DIR, prints the Markdown and, last, the path of ``tradeoff.md``. A folder with
no finished job, with jobs from different datasets or with a job whose metrics lack the cost
fields: one line on stderr naming it, exit code 2. Failed jobs are listed, not dropped.
"""
from __future__ import annotations

import argparse
import sys

from ..engine.provenance import package_version
from ..engine.tradeoff import TradeoffError, write_tradeoff


def main(argv=None) -> None:
    p = argparse.ArgumentParser(prog="mvtn-tradeoff", description=__doc__.splitlines()[0].split(": ", 1)[1])
    p.add_argument("sweep_dir", metavar="DIR", help="a sweep folder written by mvtn-train -m")
    p.add_argument("--version", action="version", version=f"mvtn-tradeoff (mvtn-exp {package_version()})")
    args = p.parse_args(argv)
    try:
        out = write_tradeoff(args.sweep_dir)
    except (TradeoffError, OSError) as e:
        print(f"mvtn-tradeoff: {e}", file=sys.stderr)
        raise SystemExit(2) from None
    print(out["md"].read_text())
    if out["failed"]:
        print(f"mvtn-tradeoff: {len(out['failed'])} failed job(s) left out: " + "; ".join(out["failed"]), file=sys.stderr)
    print(out["md"])


if __name__ == "__main__":
    main()
