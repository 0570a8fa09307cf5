"""``mvtn-eval ckpt=PATH [robustness=rotation|occlusion] [task=retrieval] [split=test] [device=cuda]``:
evaluate a checkpoint written by ``mvtn-train``.

The model is rebuilt from the config stored in the checkpoint. Writes metrics.json, confusion.json
and confusion.png under ``outputs/eval/runs/<time>-<pid>``; the last printed line is metrics.json's path.
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import OmegaConf

from ..data.shapes import ShapeError
from ..runtime.checkpoint import CheckpointMismatch
from ..evaluation.evaluate import evaluate_checkpoint
from ..config.store import register_configs
from ..config.eval_schema import EvalConfig
from ..config.compose import check_overrides
from .common import check_writable, mark_failed

register_configs()


@hydra.main(version_base="1.3", config_path="../conf/evaluate", config_name="eval")
def _app(cfg) -> None:
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    try:
        evaluate_checkpoint(OmegaConf.to_object(cfg), run_dir)
    except (CheckpointMismatch, OSError, NotImplementedError, ShapeError, ValueError) as exc:
        if os.environ.get("HYDRA_FULL_ERROR") == "1":
            raise  # the full traceback, on request
        print(f"mvtn-eval: error: {exc}", file=sys.stderr)
        mark_failed(run_dir, "error", str(exc))
        sys.exit(2)
    print(run_dir / "metrics.json")


def main() -> None:
    check_overrides("mvtn-eval", "eval", EvalConfig, sys.argv[1:], validate=EvalConfig.validate,
                    config_module="mvtn_exp.conf.evaluate")
    check_writable("mvtn-eval", sys.argv[1:])
    _app()


if __name__ == "__main__":
    main()
