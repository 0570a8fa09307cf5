"""The research probes of ``scripts/studies/`` as modules, for their tests: ``study("axis_views")``."""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

STUDIES = Path(__file__).resolve().parents[1] / "scripts" / "studies"


def study(name: str):
    """Import ``scripts/studies/<name>.py`` once (as module ``studies_<name>``) and return it."""
    key = f"studies_{name}"
    if key not in sys.modules:
        spec = importlib.util.spec_from_file_location(key, STUDIES / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules[key] = module
        spec.loader.exec_module(module)
    return sys.modules[key]
