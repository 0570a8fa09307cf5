"""The data loaders of a run: shuffled train batches per epoch, ordered evaluation passes.

An epoch's train order depends only on (seed, epoch) (``EpochBatches``), with or without worker
processes and with one or several training processes, so resume is exact and
``dataset.num_workers`` changes no result (tested). With ``num_workers > 0`` each dataset's loader
is built once and keeps its workers between epochs (``persistent_workers``: a new epoch only
sets the sampler's epoch), instead of starting them again for every epoch and every validation
pass. Host memory is pinned when training on CUDA, and ``num_workers=null`` (the default) gives
workers there (``workers``) and none on CPU. ``release`` ends a run's workers.
"""
from __future__ import annotations

import os

import torch
from torch.utils.data import DataLoader, Sampler

from ..data.collate import collate_shapes
from ..config.schema import TrainConfig, resolve_device
from ..runtime import distributed

# attribute under which a dataset keeps its persistent loaders (they live and die with it)
_SHARDS = "_mvtn_shards"  # rank shares of a dataset (shard_of)
_CACHE = "_mvtn_loaders"


class EpochBatches(Sampler[list[int]]):
    """The train batches of one epoch as lists of dataset indices ``[batch_size]`` (this rank's share).

    Order: ``torch.randperm`` from a generator seeded by ``seed * 100003 + epoch``. In one process
    the generator first makes the two int64 draws that the loader this project used before made
    from it before shuffling (``DataLoader(shuffle=True, generator=g)``: every new iterator draws
    its workers' base seed, and ``tqdm.auto`` makes one iterator it discards before the one it
    uses), so runs keep their numbers. The last batch is dropped when it would hold a single shape
    (BatchNorm needs two). With several processes (``world``) each takes its share of every
    global batch of ``batch_size`` (``distributed.shard``), and a last batch that cannot give each
    rank two shapes is dropped.
    """

    def __init__(self, size: int, batch_size: int, seed: int, world: distributed.World = distributed.World()):
        self.size, self.batch_size, self.seed, self.world = size, batch_size, seed, world
        self.epoch = 0

    def set_epoch(self, epoch: int) -> "EpochBatches":
        self.epoch = epoch
        return self

    def batches(self) -> list[list[int]]:
        g = torch.Generator().manual_seed(self.seed * 100003 + self.epoch)
        if not self.world.enabled:
            torch.empty(2, dtype=torch.int64).random_(generator=g)
        order = torch.randperm(self.size, generator=g).tolist()
        out = [order[i:i + self.batch_size] for i in range(0, self.size, self.batch_size)]
        if self.world.enabled:
            return [distributed.shard(b, self.world) for b in out if len(b) >= 2 * self.world.size]
        return out[:-1] if out and len(out[-1]) == 1 else out

    def __iter__(self):
        return iter(self.batches())

    def __len__(self) -> int:  # the count alone, without drawing the order
        full, last = divmod(self.size, self.batch_size)
        if self.world.enabled:  # batches that give every rank two shapes
            least = 2 * self.world.size
            return full * (self.batch_size >= least) + (last >= least)
        count = full + (last > 0)
        return count - (count > 0 and (last or self.batch_size) == 1)  # a last batch of one is dropped


class _Loader(DataLoader):
    """A DataLoader whose every pass draws what a fresh one draws: a new iterator takes one int64 from
    ``generator`` (the global one when None) for its workers' base seed, and a kept one (persistent
    workers) takes nothing. So keeping the workers moves no random stream."""

    def __iter__(self):
        if self.persistent_workers and self._iterator is not None:
            torch.empty((), dtype=torch.int64).random_(generator=self.generator)
        return super().__iter__()


def _pin(cfg: TrainConfig) -> bool:
    """Pinned host memory when training on CUDA (faster copies to the device)."""
    return resolve_device(cfg.device).startswith("cuda")


# automatic workers on CUDA: enough to hide the loading of a batch behind a GPU step
CUDA_WORKERS = 4


def workers(cfg: TrainConfig) -> int:
    """``dataset.num_workers``, or when null: 0 on CPU (the step's threads need the cores), on
    CUDA ``min(CUDA_WORKERS, cores of this process - 1)`` (``threads`` when set)."""
    if cfg.dataset.num_workers is not None:
        return cfg.dataset.num_workers
    if not _pin(cfg):
        return 0
    cores = cfg.threads or (len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)
    return max(0, min(CUDA_WORKERS, cores - 1))


def _kept(dataset, key: tuple) -> DataLoader | None:
    return dataset.__dict__.get(_CACHE, {}).get(key)


def _keep(dataset, key: tuple, loader: DataLoader) -> DataLoader:
    """Remember ``loader`` for (dataset, key) when it keeps workers."""
    if loader.persistent_workers:
        dataset.__dict__.setdefault(_CACHE, {})[key] = loader
    return loader


def _common(cfg: TrainConfig) -> dict:
    n = workers(cfg)
    return dict(collate_fn=collate_shapes, num_workers=n, persistent_workers=n > 0, pin_memory=_pin(cfg),
                multiprocessing_context=_context() if n > 0 else None)


def _context():
    """The start method the workers would get in a plain process (the standard library's, ``fork``
    on Linux), also inside a joblib sweep's worker, whose default is loky's own context (a
    ``Process`` of it cannot start a data loader worker)."""
    import multiprocessing as mp

    method = mp.get_start_method(allow_none=True)
    return mp.get_context(method if method in mp.get_all_start_methods() else mp.get_all_start_methods()[0])


def train_loader(cfg: TrainConfig, dataset, epoch: int, world: distributed.World = distributed.World()) -> DataLoader:
    """The shuffled train loader of ``epoch`` (``EpochBatches``); reused across epochs with workers."""
    key = ("train", cfg.batch_size, cfg.seed, world.rank, world.size, workers(cfg), _pin(cfg))
    loader = _kept(dataset, key)
    if loader is not None:
        loader.batch_sampler.set_epoch(epoch)
        return loader
    sampler = EpochBatches(len(dataset), cfg.batch_size, cfg.seed, world).set_epoch(epoch)
    # a generator of its own: the train passes draw nothing from the global stream (as before, when
    # the shuffling generator took that draw)
    return _keep(dataset, key, _Loader(dataset, batch_sampler=sampler, generator=torch.Generator(), **_common(cfg)))


def eval_loader(cfg: TrainConfig, dataset) -> DataLoader:
    """The dataset in its own order, in batches of ``batch_size``; reused with workers."""
    key = ("eval", cfg.batch_size, workers(cfg), _pin(cfg))
    loader = _kept(dataset, key)
    if loader is not None:
        return loader
    # each pass takes one draw from the global stream, as this project's loaders always have
    return _keep(dataset, key, _Loader(dataset, batch_size=cfg.batch_size, shuffle=False, **_common(cfg)))


def shard_of(dataset, world: distributed.World):
    """This rank's contiguous share of ``dataset`` (``distributed.shard``) as a ``Subset``, the same
    object at every pass, so that its ``eval_loader`` and that loader's workers are kept too."""
    from torch.utils.data import Subset

    shards = dataset.__dict__.setdefault(_SHARDS, {})
    key = (world.rank, world.size)
    if key not in shards:
        shards[key] = Subset(dataset, distributed.shard(list(range(len(dataset))), world))
    return shards[key]


def release(*datasets) -> None:
    """Stop the worker processes of the datasets' persistent loaders (their shards' too)."""
    for ds in datasets:
        release(*ds.__dict__.pop(_SHARDS, {}).values())
        for loader in ds.__dict__.pop(_CACHE, {}).values():
            it = getattr(loader, "_iterator", None)
            if it is not None and hasattr(it, "_shutdown_workers"):
                it._shutdown_workers()
            loader._iterator = None
