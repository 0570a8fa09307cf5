"""``mvtn-train``: train MVTN (selector G + renderer R + multi-view net C).

Examples: ``mvtn-train``, ``mvtn-train +experiment=synthetic_circular views=1``,
``mvtn-train -m selector=circular,spherical,mvtn_spherical views=1,4 seed=0,1,2``; resume with
``ckpt_path=outputs/train/runs/<run>/last.pt``. The last printed line is the path of metrics.json.
"""
from __future__ import annotations

import os
import signal
import sys
import time
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import OmegaConf

from ..data.shapes import ShapeError
from ..engine import checkpoint
from ..engine.checkpoint import CheckpointMismatch
from ..engine.trainer import TrainingDiverged, as_config, train
from ..schema import TrainConfig, register_configs
from .common import check_overrides, check_writable, mark_failed

register_configs()
EXIT_CODES = {TrainingDiverged: 3}


class Interrupted(Exception):
    """SIGINT / SIGTERM arrived: stop now; ``last.pt`` of the last finished epoch stays intact."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def _raise_interrupted(signum, frame):
    raise Interrupted(signum)


def resume_config(cfg, overrides: list[str]) -> TrainConfig:
    """``ckpt_path=...``: the checkpoint's own config, with only the keys this command line sets
    (e.g. ``epochs=20``) taken from the composed ``cfg``; no need to retype the original overrides."""
    state = checkpoint.load(cfg.ckpt_path)
    saved = OmegaConf.create(state["config"])
    composed = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
    for o in overrides:
        key = o.lstrip("+~").split("=", 1)[0].split("@", 1)[0]
        if key in ("ckpt_path", "hydra") or key.startswith(("hydra.", "hydra/")):
            continue
        if key == "experiment":
            raise ValueError(f"ckpt_path={cfg.ckpt_path}: resuming takes the checkpoint's own setup; "
                             f"drop {o!r} (or set its keys one by one)")
        OmegaConf.update(saved, key, OmegaConf.select(composed, key), merge=False)
    saved.ckpt_path = cfg.ckpt_path
    return as_config(OmegaConf.to_container(saved, resolve=True))


@hydra.main(version_base="1.3", config_path="../conf", config_name="train")
def _app(cfg) -> None:
    hc = HydraConfig.get()
    run_dir = Path(hc.runtime.output_dir)
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, _raise_interrupted)
    try:
        if cfg.ckpt_path:
            tcfg = resume_config(cfg, list(hc.overrides.task))
            if (run_dir / "metrics.json").is_file():  # a finished run goes on: keep its results
                (run_dir / "metrics.json").rename(run_dir / f"metrics-before-resume-{time.strftime('%Y%m%d-%H%M%S')}.json")
        else:
            tcfg = OmegaConf.to_object(cfg)
        train(tcfg, run_dir)
    except Interrupted as exc:
        last = run_dir / "last.pt"
        how = (f"resume with: mvtn-train ckpt_path={last}" if last.is_file()
               else "no epoch had finished, nothing to resume: start again")
        print(f"mvtn-train: interrupted by {exc}; the last finished epoch is saved, {how}", file=sys.stderr)
        with open(run_dir / "train.log", "a") as f:
            f.write(f"mvtn-train: interrupted by {exc}; {how}\n")
        sys.exit(128 + exc.signum)
    except (CheckpointMismatch, OSError, NotImplementedError, ShapeError, ValueError, TrainingDiverged) as exc:
        if os.environ.get("HYDRA_FULL_ERROR") == "1":
            raise  # the full traceback, on request
        kind = "training diverged" if isinstance(exc, TrainingDiverged) else "error"
        print(f"mvtn-train: {kind}: {exc}", file=sys.stderr)
        with open(run_dir / "train.log", "a") as f:  # the run's record keeps the reason too
            f.write(f"mvtn-train: {kind}: {exc}\n")
        mark_failed(run_dir, kind, str(exc))  # no run dir is left looking like an unfinished run
        if hc.mode == RunMode.MULTIRUN:  # recorded for the sweep summary: go on with the next job
            return
        sys.exit(EXIT_CODES.get(type(exc), 1 if isinstance(exc, OSError) and not isinstance(exc, FileNotFoundError) else 2))
    print(run_dir / "metrics.json")


def resume_in_place(argv: list[str]) -> list[str]:
    """``ckpt_path=RUN/last.pt`` (single run, no ``hydra.run.dir``): go on in RUN itself, so its
    TensorBoard curves and train.log continue; this command's Hydra record goes to
    ``RUN/.hydra/resumed-<time>`` beside the original one. A missing file stops here, in one line."""
    ckpt = next((a.split("=", 1)[1] for a in argv if a.startswith("ckpt_path=")), None)
    if not ckpt or ckpt == "null" or any(a in ("-m", "--multirun") for a in argv):
        return argv
    if not Path(ckpt).is_file():
        print(f"mvtn-train: error: ckpt_path={ckpt}: no such checkpoint file", file=sys.stderr)
        sys.exit(2)
    if any(a.startswith("hydra.run.dir=") for a in argv):
        return argv
    return [*argv, f"hydra.run.dir={Path(ckpt).resolve().parent}",
            f"hydra.output_subdir=.hydra/resumed-{time.strftime('%Y%m%d-%H%M%S')}"]


def main() -> None:
    check_overrides("mvtn-train", "train", TrainConfig, sys.argv[1:], validate=TrainConfig.validate)
    sys.argv[1:] = resume_in_place(sys.argv[1:])
    check_writable("mvtn-train", sys.argv[1:])
    _app()


if __name__ == "__main__":
    main()
