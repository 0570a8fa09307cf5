"""The run's data loaders: epoch order from (seed, epoch) alone, and workers kept between epochs."""
from __future__ import annotations

from dataclasses import replace

import torch
from torch.utils.data import DataLoader, Dataset
from tqdm.auto import tqdm

from conftest import tiny_config
from mvtn_exp.engine import loaders
from mvtn_exp.runtime.distributed import World
from mvtn_exp.engine.loaders import EpochBatches
from mvtn_exp.engine.trainer import as_config


def test_epoch_batches_depend_on_seed_and_epoch_only_and_cover_the_split():
    a = EpochBatches(50, 8, seed=3).set_epoch(2).batches()
    assert a == EpochBatches(50, 8, seed=3).set_epoch(2).batches()
    assert a != EpochBatches(50, 8, seed=3).set_epoch(1).batches()
    assert a != EpochBatches(50, 8, seed=4).set_epoch(2).batches()
    assert sorted(i for b in a for i in b) == list(range(50))  # a last batch of 2 is kept
    odd = EpochBatches(49, 8, seed=3).batches()  # a last batch of 1 is dropped (BatchNorm)
    assert [len(b) for b in odd] == [8] * 6 and len(set(i for b in odd for i in b)) == 48


def test_epoch_batches_are_the_batches_the_trainer_had_before():
    # the trainer used DataLoader(shuffle=True, generator=g) through tqdm.auto, which makes one
    # iterator it discards: two draws from g before the shuffle. Runs keep their numbers.
    for epoch in (0, 1, 5):
        g = torch.Generator().manual_seed(7 * 100003 + epoch)
        old = [b.tolist() for b in tqdm(DataLoader(range(45), batch_size=8, shuffle=True, generator=g), disable=True)]
        assert EpochBatches(45, 8, seed=7).set_epoch(epoch).batches() == old


def test_epoch_batches_shares_of_several_processes():
    shares = [EpochBatches(45, 8, seed=1, world=World(size=2, rank=r)).set_epoch(3).batches() for r in (0, 1)]
    assert len(shares[0]) == len(shares[1]) == 6  # the last global batch of 5 gives each rank 2
    for b0, b1 in zip(*shares):
        assert abs(len(b0) - len(b1)) <= 1 and not set(b0) & set(b1)
    assert len({i for s in shares for b in s for i in b}) == 45


def _with_workers(cfg, n):
    return replace(cfg, dataset=replace(cfg.dataset, num_workers=n))


class _Items(Dataset):
    def __len__(self):
        return 20

    def __getitem__(self, i):
        return {"points": torch.full((4, 3), float(i)), "label": i % 3, "name": f"s{i}"}


def test_workers_are_kept_between_epochs_and_released(tmp_path):
    cfg = as_config(tiny_config(str(tmp_path), batch_size=4, **{"dataset.num_workers": 2}))
    ds = _Items()
    first = loaders.train_loader(cfg, ds, 0)
    names0 = [n for b in first for n in b["names"]]
    pids = [w.pid for w in first._iterator._workers]
    second = loaders.train_loader(cfg, ds, 1)
    names1 = [n for b in second for n in b["names"]]
    assert second is first and [w.pid for w in second._iterator._workers] == pids
    # each epoch its own order, the same one a loader without workers gives
    plain = _with_workers(cfg, 0)
    assert names0 == [n for b in loaders.train_loader(plain, _Items(), 0) for n in b["names"]]
    assert names1 == [n for b in loaders.train_loader(plain, _Items(), 1) for n in b["names"]]
    assert names0 != names1 and sorted(names0) == sorted(names1)
    ev = loaders.eval_loader(cfg, ds)
    assert loaders.eval_loader(cfg, ds) is ev
    assert [n for b in ev for n in b["names"]] == [f"s{i}" for i in range(20)]
    workers = first._iterator._workers
    loaders.release(ds)
    assert all(not w.is_alive() for w in workers)
    assert loaders.train_loader(cfg, ds, 0) is not first


def test_a_ranks_share_keeps_its_eval_workers_between_passes_and_releases_them(tmp_path):
    """Under torchrun each rank validates its own share: the same Subset every pass, so its loader
    and workers are kept (they were rebuilt at every validation), and release stops them."""
    cfg = as_config(tiny_config(str(tmp_path), batch_size=4, **{"dataset.num_workers": 2}))
    ds, world = _Items(), World(2, 1)
    share = loaders.shard_of(ds, world)
    assert loaders.shard_of(ds, world) is share and loaders.shard_of(ds, World(2, 0)) is not share
    ev = loaders.eval_loader(cfg, share)
    assert [n for b in ev for n in b["names"]] == [f"s{i}" for i in range(10, 20)]
    pids = [w.pid for w in ev._iterator._workers]
    again = loaders.eval_loader(cfg, loaders.shard_of(ds, world))
    assert again is ev and [n for b in again for n in b["names"]] == [f"s{i}" for i in range(10, 20)]
    assert [w.pid for w in again._iterator._workers] == pids
    workers = ev._iterator._workers
    loaders.release(ds)
    assert all(not w.is_alive() for w in workers) and loaders.shard_of(ds, world) is not share


def test_automatic_workers_and_pinning_follow_the_device(tmp_path, monkeypatch):
    """num_workers=null: none on CPU; on CUDA up to 4 within the process's cores (threads when
    set), with pinned memory; an explicit count is kept on either."""
    cfg = as_config(tiny_config(str(tmp_path), device="cpu"))
    assert cfg.dataset.num_workers is None and loaders.workers(cfg) == 0 and not loaders._pin(cfg)
    assert loaders.workers(_with_workers(cfg, 3)) == 3
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    auto = replace(cfg, device="auto")
    assert loaders._pin(auto) and loaders.workers(replace(auto, threads=16)) == loaders.CUDA_WORKERS
    assert loaders.workers(replace(auto, threads=3)) == 2 and loaders.workers(replace(auto, threads=1)) == 0
    assert loaders.workers(_with_workers(auto, 0)) == 0
