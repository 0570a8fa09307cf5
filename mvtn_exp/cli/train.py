"""``mvtn-train``: train MVTN (selector G + renderer R + multi-view net C).

Examples: ``mvtn-train``, ``mvtn-train +experiment=synthetic_circular views=1``,
``mvtn-train -m selector=circular,spherical,mvtn_spherical views=1,4 seed=0,1,2``; resume with
``ckpt_path=outputs/train/runs/<run>/last.pt``. The last printed line is the path of metrics.json.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import OmegaConf

from ..data.shapes import ShapeError
from ..engine.checkpoint import CheckpointMismatch
from ..engine.sweep import STATUS_FILE
from ..engine.trainer import TrainingDiverged, train
from ..schema import TrainConfig, register_configs
from .common import check_overrides

register_configs()
EXIT_CODES = {TrainingDiverged: 3}


@hydra.main(version_base="1.3", config_path="../conf", config_name="train")
def _app(cfg) -> None:
    hc = HydraConfig.get()
    run_dir = Path(hc.runtime.output_dir)
    try:
        train(OmegaConf.to_object(cfg), run_dir)
    except (CheckpointMismatch, FileNotFoundError, NotImplementedError, ShapeError, ValueError,
            TrainingDiverged) as exc:
        kind = "training diverged" if isinstance(exc, TrainingDiverged) else "error"
        print(f"mvtn-train: {kind}: {exc}", file=sys.stderr)
        with open(run_dir / "train.log", "a") as f:  # the run's record keeps the reason too
            f.write(f"mvtn-train: {kind}: {exc}\n")
        if hc.mode == RunMode.MULTIRUN:  # record it for the sweep summary and go on with the next job
            (run_dir / STATUS_FILE).write_text(json.dumps({"status": kind, "error": str(exc)}))
            return
        sys.exit(EXIT_CODES.get(type(exc), 2))
    print(run_dir / "metrics.json")


def main() -> None:
    check_overrides("mvtn-train", "train", TrainConfig, sys.argv[1:], validate=TrainConfig.validate)
    _app()


if __name__ == "__main__":
    main()
