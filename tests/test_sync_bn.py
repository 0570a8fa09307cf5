"""models/sync_bn.py: BatchNorm over the global batch of several processes, against one process
holding the whole batch (float64, unequal shares); exactly BatchNorm in one process."""
from __future__ import annotations

import socket

import pytest
import torch
from torch import nn

from mvtn_exp.models import sync_bn

SHARES = [4, 3]  # 7 shapes: rank 0 takes 4, rank 1 takes 3 (the trainer's `shard`)


def _net(dims: int, momentum) -> nn.Module:
    torch.manual_seed(0)
    bn = nn.BatchNorm1d(5, momentum=momentum) if dims == 1 else nn.BatchNorm2d(5, momentum=momentum)
    body = nn.Linear(3, 5) if dims == 1 else nn.Conv2d(3, 5, 1)
    head = nn.Linear(5, 2) if dims == 1 else nn.Sequential(nn.Flatten(2), nn.Linear(4, 1), nn.Flatten(1), nn.Linear(5, 2))
    return nn.Sequential(body, bn, nn.ReLU(), head).double()


def _batch(dims: int):
    g = torch.Generator().manual_seed(1)
    x = (torch.randn(7, 3, generator=g) if dims == 1 else torch.randn(7, 3, 2, 2, generator=g)).double() * 3 + 10
    return x, torch.arange(7) % 2


def _steps(net, x, y, weight=1.0, reduce=None):
    """Two training steps (outputs, input and parameter gradients of the first; stats after both)."""
    x = x.clone().requires_grad_(True)
    out = net(x)
    (nn.functional.cross_entropy(out, y) * weight).backward()
    if reduce:
        reduce()
    grads = [x.grad.clone()] + [p.grad.clone() for p in net.parameters()]
    net(x.detach() * 0.5)
    bn = net[1]
    return out.detach(), grads, [bn.running_mean.clone(), bn.running_var.clone(), bn.num_batches_tracked.clone()]


def _rank(rank: int, port: int, dims: int, momentum, out: str) -> None:
    import torch.distributed as dist

    from mvtn_exp.runtime import distributed

    dist.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{port}", rank=rank, world_size=2)
    net = sync_bn.convert(_net(dims, momentum))
    x, y = _batch(dims)
    mine = slice(0, SHARES[0]) if rank == 0 else slice(SHARES[0], 7)
    world = distributed.World(2, rank)
    got = _steps(net, x[mine], y[mine], SHARES[rank] / 7,
                 lambda: distributed.average_gradients(list(net.parameters()), 1.0, world))
    torch.save(got, out)
    dist.destroy_process_group()


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("dims,momentum", [(1, 0.1), (2, None)])
def test_two_processes_normalise_and_step_as_one_process_with_the_whole_batch(tmp_path, dims, momentum):
    from conftest import run_in_processes

    port = _port()
    run_in_processes(_rank, [(r, port, dims, momentum, str(tmp_path / f"r{r}.pt")) for r in range(2)])
    x, y = _batch(dims)
    ref_out, ref_grads, ref_stats = _steps(_net(dims, momentum), x, y)
    r0, r1 = (torch.load(tmp_path / f"r{r}.pt") for r in range(2))
    torch.testing.assert_close(torch.cat([r0[0], r1[0]]), ref_out)  # the whole batch's statistics normalised both
    torch.testing.assert_close(torch.cat([r0[1][0], r1[1][0]]), ref_grads[0])  # input gradients cross the ranks
    for rank in (r0, r1):
        for got, ref in zip(rank[1][1:], ref_grads[1:]):
            torch.testing.assert_close(got, ref)  # every parameter's gradient: the whole batch's mean loss
        for got, ref in zip(rank[2], ref_stats):
            torch.testing.assert_close(got, ref)  # running statistics of the global batch, on every rank


def test_in_one_process_it_is_batchnorm_and_keeps_the_names():
    plain = _net(2, 0.1)
    synced = sync_bn.convert(_net(2, 0.1))
    assert isinstance(synced[1], sync_bn.SyncBatchNorm) and not isinstance(plain[1], sync_bn.SyncBatchNorm)
    assert list(synced.state_dict()) == list(plain.state_dict())
    x, y = _batch(2)
    for a, b in zip(_steps(plain, x, y), _steps(synced, x, y)):
        for u, v in zip(a if isinstance(a, list) else [a], b if isinstance(b, list) else [b]):
            assert torch.equal(u, v)
    synced.eval(), plain.eval()
    assert torch.equal(synced(x), plain(x))


def test_convert_keeps_weights_device_dtype_and_frozen_parameters():
    net = _net(1, 0.1)
    net[1].weight.requires_grad_(False)
    with torch.no_grad():
        net[1].running_mean.fill_(2.5)
    out = sync_bn.convert(net)
    bn = out[1]
    assert isinstance(bn, sync_bn.SyncBatchNorm) and bn.running_mean.dtype == torch.float64
    assert float(bn.running_mean[0]) == 2.5 and not bn.weight.requires_grad and bn.bias.requires_grad
    assert isinstance(sync_bn.convert(nn.BatchNorm1d(3)), sync_bn.SyncBatchNorm)
