"""``mvtn-train``: train MVTN (selector G + renderer R + multi-view net C) on the synthetic dataset.

Example: ``mvtn-train views=4 epochs=8 selector=mvtn_spherical``; resume with
``ckpt_path=outputs/train/runs/<run>/last.pt``. The last printed line is the path of metrics.json.
"""
from __future__ import annotations

import sys
from pathlib import Path

import hydra
from hydra.core.config_store import ConfigStore
from hydra.core.hydra_config import HydraConfig
from omegaconf import OmegaConf

from ..data.shapes import ShapeError
from .common import check_overrides
from ..engine.checkpoint import CheckpointMismatch
from ..engine.trainer import TrainConfig, TrainingDiverged, train

ConfigStore.instance().store(name="train_schema", node=TrainConfig)


@hydra.main(version_base="1.3", config_path="../conf", config_name="train")
def _app(cfg) -> None:
    try:
        obj: TrainConfig = OmegaConf.to_object(cfg)
        run_dir = Path(HydraConfig.get().runtime.output_dir)
        train(obj, run_dir)
    except (CheckpointMismatch, FileNotFoundError, ShapeError, ValueError) as exc:
        print(f"mvtn-train: error: {exc}", file=sys.stderr)
        sys.exit(2)
    except TrainingDiverged as exc:
        print(f"mvtn-train: training diverged: {exc}", file=sys.stderr)
        sys.exit(3)
    print(run_dir / "metrics.json")


def main() -> None:
    check_overrides("mvtn-train", "train", TrainConfig, sys.argv[1:])
    _app()


if __name__ == "__main__":
    main()
