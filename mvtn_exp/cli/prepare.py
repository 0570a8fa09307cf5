"""``mvtn-prepare dataset=modelnet40 dataset.root=PATH``: preprocess every split of a dataset into its
cache once (what training otherwise does on first use), then print the counts, the skipped shapes
and the cache files. The last printed line is the path of the written ``prepare.json``."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import OmegaConf

from ..data.datasets import build_dataset
from ..data.shapes import ShapeError
from ..config.schema import TrainConfig
from ..config.store import register_configs
from ..config.compose import check_overrides

register_configs()


def prepare(cfg: TrainConfig) -> dict:
    """Build every split of ``cfg.dataset`` (preprocessing what is not cached) -> a summary dict."""
    out = {"dataset": cfg.dataset.name, "root": cfg.dataset.root, "splits": {}}
    for split in ("train", "val", "test"):
        ds = build_dataset(cfg.dataset, split, progress=cfg.logger.progress)
        skipped = list(getattr(ds, "skipped", []))
        out["splits"][split] = {"shapes": len(ds), "classes": len(ds.classes), "skipped": skipped,
                                "cache": str(getattr(ds, "cache_path", ""))}
        print(f"{split}: {len(ds)} shapes, {len(ds.classes)} classes, {len(skipped)} skipped", flush=True)
    return out


@hydra.main(version_base="1.3", config_path="../conf", config_name="prepare")
def _app(cfg) -> None:
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    try:
        summary = prepare(TrainConfig.validate(OmegaConf.to_object(cfg)))
    except (FileNotFoundError, NotImplementedError, ShapeError, ValueError) as exc:
        print(f"mvtn-prepare: error: {exc}", file=sys.stderr)
        sys.exit(2)
    path = run_dir / "prepare.json"
    path.write_text(json.dumps(summary, indent=2))
    print(path)


def main() -> None:
    check_overrides("mvtn-prepare", "prepare", TrainConfig, sys.argv[1:], validate=TrainConfig.validate)
    _app()


if __name__ == "__main__":
    main()
