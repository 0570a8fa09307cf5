"""What is a setting: the one definition every reader of finished runs uses (``mvtn-compare``, sweep
summaries, ``mvtn-tradeoff``).

A run's setting is its config without the keys that say where or how it ran (``RUN_LOCAL``: the
seed, which runs are aggregated over, the device, threads, paths, logging, the data's location and
the loader's workers). Two runs that differ only in those keys are the same setting; a key is
local when it is one of them or lies below one (``logger.tensorboard``). Override keys are read
without Hydra's ``+`` / ``~`` prefixes.
"""
from __future__ import annotations

RUN_LOCAL = ("seed", "device", "ckpt_path", "threads", "overwrite", "logger", "paths", "hydra", "dataset.root",
             "dataset.cache_dir", "dataset.num_workers")


def is_local(key: str) -> bool:
    """Whether the dotted ``key`` (a config key or an override's left side) is not part of a setting."""
    key = key.lstrip("+~")
    return any(key == p or key.startswith(p + ".") for p in RUN_LOCAL)
