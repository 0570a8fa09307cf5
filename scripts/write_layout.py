"""Write docs/layout.md's module list from the package itself: each package's docstring, then each
module's first docstring sentence (``python scripts/write_layout.py``; ``--check`` exits 1 when the
page differs, which tests/test_docs.py asserts)."""
from __future__ import annotations

import argparse
import ast
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "layout.md"
BEGIN, END = "<!-- scripts/write_layout.py -->", "<!-- end scripts/write_layout.py -->"


def first_sentence(path: Path) -> str:
    doc = ast.get_docstring(ast.parse(path.read_text())) or ""
    para = " ".join(doc.split("\n\n")[0].split())
    m = re.match(r"(.+?[.!?])(\s+[A-Z`(]|$)", para)
    return (m.group(1) if m else para).rstrip(".") if para else ""


def name(path: Path, package: Path) -> str:
    """A module's name within its top-level package: ``trainer.py``, ``strategies/race.py``
    (a subpackage by its folder: ``strategies/``)."""
    rel = path.relative_to(package).as_posix()
    return rel[: -len("__init__.py")] if path.name == "__init__.py" else rel


def block() -> str:
    out = []
    top = sorted(p for p in (ROOT / "mvtn_exp").glob("*.py") if p.name != "__init__.py")
    packages = sorted(p.parent for p in (ROOT / "mvtn_exp").glob("*/__init__.py"))
    out.append("| module | role |\n|---|---|")
    out += [f"| `mvtn_exp/{p.name}` | {first_sentence(p)} |" for p in top]
    for pkg in packages:
        out.append(f"\n### `mvtn_exp/{pkg.name}/`\n\n{first_sentence(pkg / '__init__.py')}.\n")
        modules = [p for p in sorted(pkg.rglob("*.py")) if p.name != "__init__.py" or p.parent != pkg]
        if modules:
            out.append("| module | role |\n|---|---|")
            out += [f"| `{name(p, pkg)}` | {first_sentence(p)} |" for p in modules]
    return "\n".join(out).replace("\n\n\n", "\n\n")


def render(page: str) -> str:
    head, rest = page.split(BEGIN, 1)
    tail = rest.split(END, 1)[1]
    return f"{head}{BEGIN}\n{block()}\n{END}{tail}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="exit 1 if docs/layout.md is not up to date")
    args = parser.parse_args()
    page = PAGE.read_text()
    new = render(page)
    if args.check:
        if new != page:
            print("docs/layout.md is out of date: run python scripts/write_layout.py", file=sys.stderr)
            return 1
        return 0
    PAGE.write_text(new)
    return 0


if __name__ == "__main__":
    sys.exit(main())
