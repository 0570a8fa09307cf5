"""Record what every selector option and packaged experiment means, so that a published name
never silently changes meaning (``tests/test_recipes.py`` compares the package against the record).

    python scripts/freeze_recipes.py            # write tests/recipes.json from the package as it is
    python scripts/freeze_recipes.py --check    # exit 1 naming each recipe whose meaning changed

A recipe's meaning is its composed config, flattened to dotted keys, without the run-local keys
(``runs/settings.py``: seed, device, paths, logging, ...): for ``selector=NAME`` its ``selector.*``
keys, for ``+experiment=NAME`` every key. When a recipe must change, give the new one a new name
(``poi_v2``, or an experiment file); re-freeze an existing name only while no result is published
under it.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RECORD = ROOT / "tests" / "recipes.json"


def recipes() -> dict[str, dict]:
    """``{"selector=NAME" | "+experiment=NAME": {dotted key: value}}`` for the package as it is."""
    from hydra import compose, initialize_config_module
    from omegaconf import OmegaConf

    from mvtn_exp.config.options import OPTIONS, load
    from mvtn_exp.config.store import register_configs
    from mvtn_exp.runs.folders import flatten
    from mvtn_exp.runs.settings import is_local

    register_configs()
    load()
    conf = ROOT / "mvtn_exp" / "conf"
    asks = {f"selector={n}": "selector." for n in sorted(OPTIONS["selector"]) if (conf / "selector" / f"{n}.yaml").is_file()}
    asks.update({f"+experiment={p.stem}": "" for p in sorted((conf / "experiment").glob("*.yaml"))})
    out = {}
    with initialize_config_module(version_base="1.3", config_module="mvtn_exp.conf"):
        for ask, prefix in asks.items():
            plain = OmegaConf.to_container(compose("train", overrides=[ask]), resolve=False)
            plain.pop("hydra", None)
            out[ask] = {k: v for k, v in flatten(plain).items() if k.startswith(prefix) and not is_local(k)}
    return out


def changes(old: dict, new: dict) -> list[str]:
    """One line per recorded recipe whose keys differ (or that is gone)."""
    lines = []
    for name, keys in old.items():
        if name not in new:
            lines.append(f"{name}: gone (a published name stays; keep its file)")
            continue
        diff = sorted(k for k in set(keys) | set(new[name]) if keys.get(k, "<absent>") != new[name].get(k, "<absent>"))
        if diff:
            shown = "; ".join(f"{k}: {keys.get(k, '<absent>')!r} -> {new[name].get(k, '<absent>')!r}" for k in diff[:6])
            lines.append(f"{name} changed meaning ({shown}{'; ...' if len(diff) > 6 else ''})")
    return lines


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="compare with tests/recipes.json instead of writing it")
    args = parser.parse_args()
    new = recipes()
    if not args.check:
        RECORD.write_text(json.dumps(new, indent=1, sort_keys=True) + "\n")
        print(f"{RECORD}: {len(new)} recipes")
        return 0
    lines = changes(json.loads(RECORD.read_text()), new)
    for line in lines:
        print(line, file=sys.stderr)
    return 1 if lines else 0


if __name__ == "__main__":
    sys.exit(main())
