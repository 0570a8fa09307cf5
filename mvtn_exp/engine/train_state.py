"""A run's state between epochs: its counters, the checkpoint payload they make, and resume.

``TrainState`` owns what a checkpoint must hold to go on exactly: the model, optimizer, schedule,
loss scaler and weight average it was given, the epoch counters (``start``: the 0-based epoch to
run next; ``best_epoch`` 0-based, -1 before any), the skipped steps, the per-epoch history, the
global step and this process's training time and shapes (``engine/cost.py``). Checkpoints count
epochs from 1 as ``metrics.json`` does: ``"epoch"`` = epochs completed, ``"best_epoch"`` 1-based
(0: none).
"""
from __future__ import annotations

import logging
import shutil
from dataclasses import dataclass, field
from pathlib import Path

from ..models import precise_bn
from ..runtime import checkpoint, distributed, seeding

log = logging.getLogger("mvtn-train")


@dataclass
class TrainState:
    model: object
    opt: object
    sched: object
    scaler: object
    ema: object
    world: distributed.World
    config: dict  # the run's config as plain data (``config_dict``)
    classes: list
    origin: dict  # the run's provenance record
    start: int = 0
    best_acc: float = -1.0
    best_epoch: int = -1
    skipped: int = 0
    history: list = field(default_factory=list)
    step: int = 0
    train_seconds: float = 0.0
    train_shapes: int = 0
    head: object = None  # the task head (tasks/heads.py); best_acc is its validation score (accuracy, instance mIoU)

    def payload(self, epoch: int, rngs: list | None = None) -> dict:
        """The checkpoint after 0-based ``epoch``; ``rngs``: every process's RNG state in rank order
        (``distributed.gather``; this one's alone by default)."""
        rngs = rngs or [seeding.rng_state()]
        world = self.world
        return {"model": self.model.state_dict(), "optimizer": self.opt.state_dict(),
                "scheduler": self.sched.state_dict(), "format": checkpoint.FORMAT, "epoch": epoch + 1,
                "step": self.step, "rng": rngs[0], "world_size": world.size,
                **({"rng_ranks": rngs} if world.enabled and len(rngs) == world.size else {}),
                "config": self.config, "best_val_acc": self.best_acc, "best_epoch": self.best_epoch + 1,
                "skipped_steps": self.skipped, "history": self.history, "scaler": self.scaler.state_dict(),
                **({"ema": self.ema.state_dict()} if self.ema else {}), "classes": self.classes,
                "provenance": self.origin}

    def improve(self, score: float, epoch: int) -> bool:
        """Record ``score`` (validation accuracy after 0-based ``epoch``); True when it is the best yet."""
        if score <= self.best_acc:
            return False
        self.best_acc, self.best_epoch = score, epoch
        return True

    def save(self, run_dir: Path, epoch: int, improved: bool, use_ema: bool, train_bn: dict | None) -> None:
        """``last.pt`` after ``epoch`` and, when ``improved``, ``best.pt`` (the weight average's
        weights when ``use_ema``); every rank takes part in gathering the RNG streams, rank 0 writes."""
        rngs = distributed.gather(seeding.rng_state(), self.world)
        state = {**self.payload(epoch, rngs), **({"train_bn": train_bn} if train_bn is not None else {})}
        if not self.world.main:
            return
        if improved:
            checkpoint.save_atomic(run_dir / "best.pt", {**state, "model": self.ema.state_dict(), "ema_selected": True}
                                   if use_ema else state)
        checkpoint.save_atomic(run_dir / "last.pt", state)

    def resume(self, state: dict, ckpt_path: str, run_dir: Path, group_factor, seed: int) -> None:
        """Go on from ``state`` (a last.pt read from ``ckpt_path``): weights, optimizer, schedule
        re-derived for the configured epochs (``group_factor(name, epoch)``), RNG streams and
        counters; ``best.pt`` copied beside the run. A checkpoint that does not fit this run is
        refused (``CheckpointMismatch``, one line) before anything changes."""
        self._check_fits(state, ckpt_path)
        self._load_weights(state, ckpt_path)
        self.start = int(state["epoch"])  # epochs completed = the 0-based index of the next one
        for g, base in zip(self.opt.param_groups, self.sched.base_lrs):
            g["lr"] = base * group_factor(g["name"], self.start)
        self.sched.last_epoch = self.start
        self._restore_rng(state, seed)
        self._take_best(state, ckpt_path, run_dir)
        self.skipped, self.history, self.step = int(state["skipped_steps"]), list(state["history"]), int(state.get("step", 0))

    def _check_fits(self, state: dict, ckpt_path: str) -> None:
        saved, size = int(state.get("world_size", 1)), self.world.size
        if saved != size:  # each process's random stream is in the checkpoint: the same number of processes
            raise checkpoint.CheckpointMismatch(
                f"checkpoint {ckpt_path!r} was written by a run of {saved} process(es) and this run has {size}: "
                f"resume it with {saved} (torchrun --nproc_per_node={saved}, or no torchrun for 1) to go on exactly, "
                f"or start a new run")
        if list(state.get("classes", self.classes)) != self.classes:
            raise checkpoint.CheckpointMismatch(f"checkpoint {ckpt_path!r} was trained on classes "
                                                f"{state['classes']} but the dataset has {self.classes}")
        if self.ema is not None and "ema" not in state:
            raise checkpoint.CheckpointMismatch(f"checkpoint {ckpt_path!r} holds no weight average: it was trained "
                                                "without optim.ema_decay; resume without it or start a new run")

    def _load_weights(self, state: dict, ckpt_path: str) -> None:
        try:
            self.model.load_state_dict(state["model"])
        except RuntimeError as exc:  # weights of another shape: one line, not a traceback
            raise checkpoint.CheckpointMismatch(f"checkpoint {ckpt_path!r}: weights do not fit the model its config "
                                                f"builds ({' '.join(str(exc).split())[:300]})") from exc
        if "scaler" in state:
            self.scaler.load_state_dict(state["scaler"])
        if self.ema is not None:
            self.ema.load_state_dict(state["ema"])
        if "train_bn" in state:  # bn_recalibrate_scope=eval: training goes on from its own statistics
            precise_bn.restore(self.model, state["train_bn"])
        self.opt.load_state_dict(state["optimizer"])
        self.sched.load_state_dict(state["scheduler"])

    def _restore_rng(self, state: dict, seed: int) -> None:
        world = self.world
        if not world.enabled:
            seeding.set_rng_state(state["rng"])
        elif "rng_ranks" in state:
            seeding.set_rng_state(state["rng_ranks"][world.rank])
        else:  # a best.pt written at the end without the other ranks' streams: a fresh stream per rank
            seeding.seed_everything(seeding.for_rank(seed + self.start, world.rank, world.size))

    def _take_best(self, state: dict, ckpt_path: str, run_dir: Path) -> None:
        src_best = Path(ckpt_path).with_name("best.pt")
        if self.world.main and src_best.is_file() and src_best.resolve() != (run_dir / "best.pt").resolve():
            shutil.copyfile(src_best, run_dir / "best.pt")
        distributed.barrier(self.world)  # rank 0 has copied best.pt beside the run
        self.best_acc, self.best_epoch = float(state["best_val_acc"]), int(state["best_epoch"]) - 1
        if not (run_dir / "best.pt").is_file():  # best.pt did not travel with last.pt: select anew
            log.warning("no best.pt beside %s: model selection starts again from the resumed epoch", ckpt_path)
            self.best_acc, self.best_epoch = -1.0, -1
