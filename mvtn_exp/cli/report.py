"""``mvtn-report [DIR ...]``: the paper's tables next to this project's finished runs (``runs/report.py``).

Reads every run and evaluation below the folders (``mvtn-train`` and ``mvtn-eval`` run dirs, sweep
dirs), fills each row of ``paper_tables.yaml`` from the runs that match it, prints the Markdown
and writes ``report.md`` / ``report.json`` into ``--out`` (default: ``outputs/report``). Without a
folder it prints the tables with what each row needs; ``--paper`` prints the paper's numbers alone
(each with where the paper gives it: the text of ``docs/paper.md``). A missing folder, a folder
with no run in it or a malformed tables file: one line ``mvtn-report: error: ...`` on stderr, exit
code 2, nothing written.
"""
from __future__ import annotations

import argparse
import sys

from ..runs.sides import CompareError
from ..runs.folders import FolderError
from ..engine.provenance import package_version
from ..runs.report import (TABLES_FILE, ReportError, load_tables, paper_markdown, read_folders, report, to_markdown,
                           write)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="mvtn-report", description=__doc__.splitlines()[0].split(": ", 1)[1])
    p.add_argument("folders", nargs="*", metavar="DIR", help="folders of finished runs, sweeps and evaluations")
    p.add_argument("--tables", default=str(TABLES_FILE), help="the tables file (default: the packaged paper_tables.yaml)")
    p.add_argument("--out", default="outputs/report", help="folder for report.md / report.json")
    p.add_argument("--paper", action="store_true", help="print the paper's numbers alone (no runs read, nothing written)")
    p.add_argument("--version", action="version", version=f"mvtn-report (mvtn-exp {package_version()})")
    return p


def main(argv=None) -> None:
    args = build_parser().parse_args(argv)
    try:
        tables = load_tables(args.tables)
        if args.paper:
            print(paper_markdown(tables), end="")
            return
        runs = read_folders(args.folders)
        result = report(tables, runs)
        md, _ = write(result, args.out)
    except (ReportError, CompareError, FolderError, OSError) as e:
        print(f"mvtn-report: error: {e}", file=sys.stderr)
        raise SystemExit(2) from None
    print(to_markdown(result))
    if args.folders and result["unmatched"]:
        print(f"mvtn-report: {len(result['unmatched'])} finished run(s) match no row of the tables", file=sys.stderr)
    print(md)


if __name__ == "__main__":
    main()
