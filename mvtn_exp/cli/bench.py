"""``mvtn-bench``: renderer speed / memory benchmark -> Markdown tables on stdout, bench.md + bench.json.

Examples: ``mvtn-bench`` (full grid, a few minutes on 2 CPU cores), ``mvtn-bench quick=true``
(64 px, M in {1, 4}: seconds), ``mvtn-bench device=cuda repeats=10 threads=4``.
Files go into the Hydra run directory (``outputs/bench/runs/<time>-<pid>/``); the last printed line
is the path of bench.md. See ``mvtn_exp.bench.render_bench`` for what is measured.
"""
from __future__ import annotations

import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import hydra
import torch
from hydra.core.config_store import ConfigStore
from hydra.core.hydra_config import HydraConfig
from omegaconf import OmegaConf

from ..bench.render_bench import BenchOptions, run_bench
from ..config.schema import resolve_device
from ..config.compose import check_overrides

MALLOC_ENV = "MALLOC_MMAP_THRESHOLD_"
MALLOC_VALUE = "65536"


@dataclass
class BenchAppConfig:
    """``mvtn-bench`` settings.

    quick: tiny grid for tests (64 px, M in {1, 4}, 2k mesh and 2,048 points; no 100k mesh, LOD or batch of 8).
    repeats: most timed runs per measurement (median); time_budget_s: seconds a measurement aims for
    (slow configs run fewer times, at least once). device: auto (CUDA when available) | cpu | cuda. threads: torch.set_num_threads
    (null: leave torch's default). dense_max_pairs: run the dense reference only up to this many
    (pixel, face) pairs. progress: tqdm bar on stderr. compiled: the soft targets again with
    ``renderer.compile=true`` (skipped, with the reason, where torch.compile cannot run). paper_scale:
    the renderer at B = 32 x 12 x 224 px (kernel ops and syncs per call, peak memory under
    ``renderer.memory_budget_mb``, time per shape against ResNet-18; ``bench/paper_scale.py``);
    null: on CUDA only (about 15 minutes on 2 CPU cores).
    """

    quick: bool = False
    repeats: int = 5
    time_budget_s: float = 2.0
    device: str = "auto"
    threads: Optional[int] = None
    dense_max_pairs: float = 2.0e8
    seed: int = 0
    progress: bool = True
    modules: bool = True
    scaling: bool = True
    compiled: bool = True
    paper_scale: Optional[bool] = None

    def validate(self) -> "BenchAppConfig":
        from ..config.checks import at_least
        from ..config.schema import check_device

        check_device("device", self.device)
        if self.threads is not None:
            at_least("threads", self.threads, 1)
        at_least("repeats", self.repeats, 1)
        at_least("time_budget_s", self.time_budget_s, 0.0, strict=True)
        return self


ConfigStore.instance().store(name="bench_schema", node=BenchAppConfig)


def _started_as_bench() -> bool:
    """True when this process was launched as ``mvtn-bench`` or ``python -m mvtn_exp.cli.bench``."""
    if not sys.argv:
        return False
    arg0 = Path(sys.argv[0])
    try:
        if arg0.resolve() == Path(__file__).resolve():
            return True
    except OSError:
        pass
    return arg0.name.startswith("mvtn-bench")


def _reexec_with_pinned_malloc() -> None:
    # CPU memory is measured as the process RSS (mvtn_exp/runtime/memory.py). glibc's malloc adapts its
    # mmap threshold: after a large block (a tensor) is freed, the threshold grows (up to 32 MiB) and
    # later blocks of that size come from the heap, where freed memory is kept and reused without the
    # RSS going down -- so the peak of a later block looks smaller than it is, by however much an
    # earlier config left behind. The threshold is read once, when malloc initialises, so it must be
    # in the environment before the process starts: re-execute ourselves once with it pinned at
    # 64 KiB (every tensor of 64 KiB or more is mmap'ed and returned on free; RSS follows live memory).
    # Launched some other way (e.g. main() called from another program) we do not re-execute a
    # process we do not own; the report then says the variable is unset.
    if os.environ.get(MALLOC_ENV) or not _started_as_bench():
        return
    os.environ[MALLOC_ENV] = MALLOC_VALUE
    sys.stdout.flush()
    sys.stderr.flush()
    argv = list(getattr(sys, "orig_argv", None) or [sys.executable, *sys.argv])
    os.execv(sys.executable, [sys.executable, *argv[1:]])


@hydra.main(version_base="1.3", config_path="../conf", config_name="bench")
def _app(cfg) -> None:
    obj: BenchAppConfig = OmegaConf.to_object(cfg)
    if obj.threads is not None:
        torch.set_num_threads(obj.threads)
    device = resolve_device(obj.device)
    opts = BenchOptions(quick=obj.quick, repeats=obj.repeats, device=device, time_budget_s=obj.time_budget_s,
                        dense_max_pairs=obj.dense_max_pairs, seed=obj.seed, progress=obj.progress,
                        modules=obj.modules, scaling=obj.scaling, compiled=obj.compiled,
                        paper_scale=obj.paper_scale if obj.paper_scale is not None else device.startswith("cuda"))
    run_bench(opts, Path(HydraConfig.get().runtime.output_dir))


def main() -> None:
    check_overrides("mvtn-bench", "bench", BenchAppConfig, sys.argv[1:], validate=BenchAppConfig.validate)
    _reexec_with_pinned_malloc()
    _app()


if __name__ == "__main__":
    main()
