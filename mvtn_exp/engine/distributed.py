"""Distributed data parallel with torchrun: one process per device, the global batch split between them.

Launch: ``torchrun --nproc_per_node=N $(which mvtn-train) ...`` (several nodes: torchrun's own
``--nnodes``, ``--node_rank``, ``--rdzv_*`` flags). What each part does:

- backend: NCCL on CUDA (each process on ``cuda:LOCAL_RANK``), gloo on CPU;
- ``batch_size`` stays the global batch: every rank draws the same shuffled order (seeded by
  seed and epoch, so resume stays exact) and takes its contiguous share of each global batch
  (``shard``: the first ranks get one shape more when the batch does not divide);
- after the backward pass the gradients of G and C are averaged over the ranks, weighted by each
  rank's share of the batch (one flat all-reduce), so every rank takes the same step on the
  gradient of the whole batch's mean loss;
- BatchNorm normalises over each rank's share (DDP without SyncBatchNorm); before validation rank
  0's running statistics are copied to every rank, and those are the ones saved;
- evaluation is sharded: each rank classifies its own shapes of the split, every shape exactly
  once, and the confusion matrices, losses and per-shape views are gathered (accuracy over the
  whole split);
- rank 0 alone writes the run dir: logs, checkpoints, TensorBoard, metrics.json.
"""
from __future__ import annotations

import os
from dataclasses import dataclass

import torch
import torch.distributed as dist


@dataclass(frozen=True)
class World:
    """This process's place: ``size`` processes, this one ``rank`` (``local_rank`` on its node)."""

    size: int = 1
    rank: int = 0
    local_rank: int = 0

    @property
    def enabled(self) -> bool:
        return self.size > 1

    @property
    def main(self) -> bool:
        return self.rank == 0


def from_env() -> World:
    """The world torchrun describes in ``WORLD_SIZE`` / ``RANK`` / ``LOCAL_RANK`` (one process without it)."""
    size = int(os.environ.get("WORLD_SIZE", "1"))
    return World(size, int(os.environ.get("RANK", "0")), int(os.environ.get("LOCAL_RANK", "0")))


def init(world: World, device: str) -> str:
    """Join the process group (once) and return this rank's device (``cuda`` -> ``cuda:LOCAL_RANK``)."""
    if not world.enabled:
        return device
    cuda = str(device).startswith("cuda")
    if not dist.is_initialized():
        dist.init_process_group("nccl" if cuda else "gloo")
    if cuda:
        torch.cuda.set_device(world.local_rank)
        return f"cuda:{world.local_rank}"
    return device


def shard(items: list, world: World) -> list:
    """This rank's contiguous share of ``items`` (sizes differ by at most one, the first ranks larger)."""
    n, k = len(items), world.size
    start = world.rank * (n // k) + min(world.rank, n % k)
    return items[start:start + n // k + (1 if world.rank < n % k else 0)]


def average_gradients(params: list[torch.nn.Parameter], weight: float, world: World) -> None:
    """Replace every gradient by the weighted sum over ranks (``weight``: this rank's share of the
    global batch, so the result is the gradient of the whole batch's mean loss). Parameters without
    a gradient on this rank count as zeros; they get one if any rank has one."""
    if not world.enabled or not params:
        return
    flat = torch.cat([(p.grad if p.grad is not None else torch.zeros_like(p)).reshape(-1) * weight for p in params])
    has = torch.tensor([float(p.grad is not None) for p in params], device=flat.device)
    dist.all_reduce(flat)
    dist.all_reduce(has)
    offset = 0
    for p, h in zip(params, has.tolist()):
        n = p.numel()
        if h > 0:
            p.grad = flat[offset:offset + n].view_as(p).clone()
        offset += n


def broadcast_buffers(module: torch.nn.Module, world: World) -> None:
    """Copy rank 0's buffers (BatchNorm running statistics, ...) to every rank."""
    if world.enabled:
        for b in module.buffers():
            dist.broadcast(b, 0)


def all_sum(t: torch.Tensor, world: World) -> torch.Tensor:
    """``t`` summed over the ranks (``t`` itself with one process)."""
    if world.enabled:
        t = t.clone()
        dist.all_reduce(t)
    return t


def gather(obj, world: World) -> list:
    """Every rank's ``obj``, in rank order (``[obj]`` with one process)."""
    if not world.enabled:
        return [obj]
    out = [None] * world.size
    dist.all_gather_object(out, obj)
    return out


def broadcast(obj, world: World):
    """Rank 0's ``obj`` on every rank."""
    if not world.enabled:
        return obj
    box = [obj if world.main else None]
    dist.broadcast_object_list(box, 0)
    return box[0]


def barrier(world: World) -> None:
    """Wait until every rank is here."""
    if world.enabled:
        dist.barrier()


def close(world: World) -> None:
    if world.enabled and dist.is_initialized():
        dist.destroy_process_group()
