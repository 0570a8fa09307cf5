"""Global seeding and RNG state capture/restore (python, numpy, torch) for exact resume."""
from __future__ import annotations

import contextlib
import logging
import os
import random

import numpy as np
import torch

log = logging.getLogger(__name__)


def seed_everything(seed: int) -> None:
    """Seed python's ``random``, numpy's global generator and torch (CPU and CUDA)."""
    random.seed(seed)
    np.random.seed(seed % (2 ** 32))
    torch.manual_seed(seed)


@contextlib.contextmanager
def deterministic(on: bool):
    """Within the block (a run with ``deterministic=true``), torch's deterministic algorithms:
    cuBLAS with a fixed workspace, cuDNN without autotuning, float ``index_add`` / scatter sums in
    a fixed order. Warn-only: an operator with no deterministic CUDA implementation (for example
    the backward of adaptive average pooling in ResNets) warns once, naming itself, and runs anyway;
    the log says so. Restores the previous settings at the end."""
    if not on:
        yield
        return
    os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
    before = (torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled(),
              torch.backends.cudnn.benchmark, torch.backends.cudnn.deterministic)
    torch.use_deterministic_algorithms(True, warn_only=True)
    torch.backends.cudnn.benchmark, torch.backends.cudnn.deterministic = False, True
    log.info("deterministic=true: torch's deterministic algorithms are on (an operator without one warns, "
             "naming itself, and runs nondeterministically)")
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(before[0], warn_only=before[1])
        torch.backends.cudnn.benchmark, torch.backends.cudnn.deterministic = before[2], before[3]


def for_rank(seed: int, rank: int, size: int) -> int:
    """The seed of process ``rank``'s own random stream in a run of ``size`` processes: ``seed``
    itself in one process, else a seed drawn from (seed, rank), so that no two ranks draw the same
    rotation, light, colour or perturbation for their i-th shape."""
    if size <= 1:
        return int(seed)
    return int(np.random.SeedSequence([int(seed) % (2 ** 63), int(rank)]).generate_state(1, np.uint64)[0] % (2 ** 63))


def rng_state() -> dict:
    """Every global RNG state as plain Python values and tensors, so that a checkpoint holding it
    loads with ``torch.load(weights_only=True)`` (numpy's key array becomes a list)."""
    name, keys, pos, has_gauss, cached = np.random.get_state()
    state = {"python": random.getstate(), "numpy": (name, keys.tolist(), int(pos), int(has_gauss), float(cached)),
             "torch": torch.get_rng_state()}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict) -> None:
    """Restore what ``rng_state`` captured."""
    py = state["python"]
    random.setstate((py[0], tuple(py[1]), py[2]))  # a saved tuple may come back as lists
    name, keys, pos, has_gauss, cached = state["numpy"]
    np.random.set_state((name, np.asarray(keys, dtype=np.uint32), int(pos), int(has_gauss), float(cached)))
    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():  # the devices saved that are visible now (a checkpoint
        for i, s in enumerate(state["cuda"][:torch.cuda.device_count()]):  # of an 8-GPU machine on a 2-GPU one)
            torch.cuda.set_rng_state(s, i)
