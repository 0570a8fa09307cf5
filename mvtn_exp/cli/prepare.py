"""``mvtn-prepare dataset=modelnet40 dataset.root=PATH``: preprocess every split of a dataset into its
cache once (what training otherwise does on first use), then print the counts, the skipped shapes and
the cache files. Per split it prints its shapes, classes and files skipped, each skipped file counted
once in all (ModelNet's val split is carved out of the official train split: the files skipped there
are counted under train), then the total; the readers log each skipped file once, as they skip it,
and ``prepare.json`` lists them with the cache files. The last printed line is the path of the
written ``prepare.json``. Bad input: one line, exit 2; a cache that cannot be written (a full disk):
one line naming the file, exit 1."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import OmegaConf

from ..data.datasets import build_dataset
from ..data.packed import writing
from ..data.shapes import ShapeError
from ..config.schema import TrainConfig
from ..config.store import register_configs
from ..config.compose import check_overrides
from .common import os_error_text

register_configs()


def prepare(cfg: TrainConfig) -> dict:
    """Build every split of ``cfg.dataset`` (preprocessing what is not cached) -> a summary dict:
    per split its shapes, classes, cache and ``skipped`` (the reasons of files left out that no
    earlier split reported), and ``skipped`` (all of them, each once)."""
    out = {"dataset": cfg.dataset.name, "root": cfg.dataset.root, "splits": {}, "skipped": []}
    for split in ("train", "val", "test"):
        ds = build_dataset(cfg.dataset, split, progress=cfg.logger.progress)
        seen = set(out["skipped"])
        new = list(dict.fromkeys(str(r) for r in getattr(ds, "skipped", []) if str(r) not in seen))
        out["skipped"] += new
        out["splits"][split] = {"shapes": len(ds), "classes": len(ds.classes), "skipped": new,
                                "cache": str(getattr(ds, "cache_path", ""))}
        print(f"{split}: {len(ds)} shapes, {len(ds.classes)} classes, {len(new)} skipped", flush=True)
    print(f"{len(out['skipped'])} skipped in all", flush=True)
    return out


@hydra.main(version_base="1.3", config_path="../conf", config_name="prepare")
def _app(cfg) -> None:
    path = Path(HydraConfig.get().runtime.output_dir) / "prepare.json"
    try:
        summary = prepare(TrainConfig.validate(OmegaConf.to_object(cfg)))
        with writing(path):
            path.write_text(json.dumps(summary, indent=2))
    except (FileNotFoundError, NotImplementedError, ShapeError, ValueError) as exc:
        print(f"mvtn-prepare: error: {exc}", file=sys.stderr)
        sys.exit(2)
    except OSError as exc:  # a file that cannot be written (a full disk): which, and why
        print(f"mvtn-prepare: error: {os_error_text(exc)}", file=sys.stderr)
        sys.exit(1)
    print(path)


def main() -> None:
    check_overrides("mvtn-prepare", "prepare", TrainConfig, sys.argv[1:], validate=TrainConfig.validate)
    _app()


if __name__ == "__main__":
    main()
