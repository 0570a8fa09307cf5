"""Print the package's shape: files and lines per package, modules over 400 lines, and the
longest functions (all of ``mvtn_exp/`` and the three packages held to 60 lines).

    python scripts/code_shape.py [--top 10]

Lines are physical lines of the ``.py`` files; a function's length runs from its ``def`` line to
its last line (decorators excluded), nested functions counted inside their parent too.
"""
from __future__ import annotations

import argparse
import ast
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1] / "mvtn_exp"
HELD = ("engine", "cli", "selectors")


def package_of(path: Path) -> str:
    parts = path.relative_to(ROOT).parts
    return "mvtn_exp" if len(parts) == 1 else f"mvtn_exp/{parts[0]}"


def functions(path: Path):
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            yield node.name, node.lineno, node.end_lineno - node.lineno + 1


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--top", type=int, default=10)
    args = parser.parse_args()
    files = sorted(ROOT.rglob("*.py"))
    per_package = defaultdict(lambda: [0, 0])
    for f in files:
        per_package[package_of(f)][0] += 1
        per_package[package_of(f)][1] += len(f.read_text().splitlines())
    print("| package | files | lines |\n|---|---:|---:|")
    for name, (n, lines) in sorted(per_package.items()):
        print(f"| {name} | {n} | {lines} |")
    total = sum(v[1] for v in per_package.values())
    print(f"| **total** | {len(files)} | {total} |\n")
    big = [(len(f.read_text().splitlines()), f) for f in files]
    print("Modules over 400 lines: "
          + (", ".join(f"{f.relative_to(ROOT.parent)} ({n})" for n, f in sorted(big, reverse=True) if n > 400) or "none"))
    rows = [(n, f"{f.relative_to(ROOT.parent)}:{line} {name}", package_of(f))
            for f in files for name, line, n in functions(f)]
    rows.sort(reverse=True)
    for title, keep in (("all of mvtn_exp", lambda p: True),
                        ("engine, cli, selectors", lambda p: p.split("/")[-1] in HELD)):
        print(f"\nLongest functions ({title}):\n\n| lines | function |\n|---:|---|")
        for n, where, _ in [r for r in rows if keep(r[2])][:args.top]:
            print(f"| {n} | `{where}` |")


if __name__ == "__main__":
    main()
