"""A published name keeps its meaning: every selector option and packaged experiment composes to
the config recorded in tests/recipes.json (``scripts/freeze_recipes.py``), and a change is named."""
from __future__ import annotations

import importlib.util
import json
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("freeze_recipes", ROOT / "scripts" / "freeze_recipes.py")
freeze = importlib.util.module_from_spec(spec)
spec.loader.exec_module(freeze)


def test_every_recipe_means_what_was_recorded():
    recorded = json.loads(freeze.RECORD.read_text())
    now = freeze.recipes()
    lines = freeze.changes(recorded, now)
    assert not lines, ("\n".join(lines) + "\nA changed recipe gets a new name (poi_v2, or an experiment file); "
                       "re-freeze (python scripts/freeze_recipes.py) only a name with no published result")
    unrecorded = sorted(set(now) - set(recorded))
    assert not unrecorded, f"new recipes not recorded yet: {unrecorded} (python scripts/freeze_recipes.py)"


def test_a_changed_default_is_named_with_its_old_and_new_value():
    old = {"selector=poi": {"selector.hypotheses": 8, "selector.gain": 32.0}, "+experiment=gone": {"views": 1}}
    new = {"selector=poi": {"selector.hypotheses": 4, "selector.gain": 32.0}}
    lines = freeze.changes(old, new)
    assert lines[0] == "selector=poi changed meaning (selector.hypotheses: 8 -> 4)"
    assert lines[1].startswith("+experiment=gone: gone")
