"""The package's layering (``.importlinter``): every contract holds, and a backwards import breaks
one, naming the import."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LINT = [sys.executable, "-c", "import sys; from importlinter.cli import lint_imports_command; "
        "sys.exit(lint_imports_command())", "--no-cache"]

pytest.importorskip("importlinter", reason="import-linter is a test dependency (pip install -e '.[test]')")


def lint(where: Path, config: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(where)}
    return subprocess.run([*LINT, "--config", str(config)], cwd=where, env=env, capture_output=True, text=True,
                          timeout=300)


def copy_tree(tmp_path: Path) -> Path:
    for pkg in ("mvtn_exp", "hydra_plugins"):
        shutil.copytree(ROOT / pkg, tmp_path / pkg, ignore=shutil.ignore_patterns("__pycache__", "*.yaml"))
    shutil.copy(ROOT / ".importlinter", tmp_path / ".importlinter")
    return tmp_path


def test_the_package_keeps_every_contract():
    out = lint(ROOT, ROOT / ".importlinter")
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-2000:]
    assert "BROKEN" not in out.stdout and out.stdout.count("KEPT") == 3


@pytest.mark.parametrize("module,line,broken", [
    ("config/options.py", "from ..engine import trainer as _t", "mvtn_exp.config.options -> mvtn_exp.engine.trainer"),
    ("runtime/seeding.py", "from ..selectors import config as _c", "mvtn_exp.runtime.seeding -> mvtn_exp.selectors.config"),
    ("engine/ema.py", "from ..selectors import poi as _p", "mvtn_exp.engine.ema -> mvtn_exp.selectors.poi"),
])
def test_a_backwards_import_breaks_a_contract(tmp_path, module, line, broken):
    where = copy_tree(tmp_path)
    path = where / "mvtn_exp" / module
    path.write_text(path.read_text() + f"\n{line}\n")
    out = lint(where, where / ".importlinter")
    assert out.returncode == 1 and "BROKEN" in out.stdout
    assert broken in out.stdout, out.stdout[-3000:]


def test_short_modules_and_functions():
    """No module of the package over 400 lines; no function over 60 lines where the loop, the
    commands and the selectors live (``scripts/code_shape.py`` prints the longest)."""
    import ast

    package = ROOT / "mvtn_exp"
    long_modules = [f"{p.relative_to(package)} ({n})" for p in package.rglob("*.py")
                    if (n := len(p.read_text().splitlines())) > 400]
    assert not long_modules, f"modules over 400 lines: {long_modules}"
    long_functions = []
    for part in ("engine", "cli", "selectors"):
        for path in (package / part).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.end_lineno - node.lineno >= 60:
                    long_functions.append(f"{path.relative_to(package)}:{node.lineno} {node.name}")
    assert not long_functions, f"functions over 60 lines: {long_functions}"
