"""Distributed data parallel with torchrun: one process per device, the global batch split between them.

Launch: ``torchrun --nproc_per_node=N $(which mvtn-train) ...`` (several nodes: torchrun's own
``--nnodes``, ``--node_rank``, ``--rdzv_*`` flags), or ``srun --ntasks=N mvtn-train ...`` on Slurm
(the step's tasks are one run: ``from_env``). What each part does:

- backend: NCCL on CUDA (each process on ``cuda:LOCAL_RANK``), gloo on CPU;
- ``batch_size`` stays the global batch: every rank draws the same shuffled order (seeded by
  seed and epoch, so resume stays exact) and takes its contiguous share of each global batch
  (``shard``: the first ranks get one shape more when the batch does not divide);
- each rank's loss is weighted by its share of the global batch before the backward pass, and the
  gradients of G and C are then summed over the ranks (one flat all-reduce), so every rank takes
  the same step on the gradient of the whole batch's mean loss;
- every process draws its own random stream (augmentation, light, colour, point samples,
  perturbations), seeded from (seed, rank) after the model is built (``seeding.for_rank``); the
  checkpoint keeps every rank's stream, so resuming with the same number of processes is exact,
  and another number is refused in one line;
- BatchNorm normalises over the whole global batch (``sync_bn=true``, the default:
  ``models/sync_bn.py``); with ``sync_bn=false`` over each rank's share. Before validation rank
  0's running statistics are copied to every rank, and those are the ones saved;
- evaluation is sharded: each rank classifies its own shapes of the split, every shape exactly
  once, and the confusion matrices, losses and per-shape views are gathered (accuracy over the
  whole split);
- rank 0 alone writes the run dir: logs, checkpoints, TensorBoard, metrics.json.
"""
from __future__ import annotations

import os
import re
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
    """This process's world: torchrun's ``WORLD_SIZE`` / ``RANK`` / ``LOCAL_RANK``; else a Slurm
    step of several tasks (``srun --ntasks=N mvtn-train ...``, or the submitit launcher with
    ``tasks_per_node`` > 1): ``SLURM_STEP_NUM_TASKS`` / ``SLURM_PROCID`` / ``SLURM_LOCALID``, one
    run on N processes; else one process."""
    if "WORLD_SIZE" in os.environ:
        size = int(os.environ["WORLD_SIZE"])
        return World(size, int(os.environ.get("RANK", "0")), int(os.environ.get("LOCAL_RANK", "0")))
    tasks = int(os.environ.get("SLURM_STEP_NUM_TASKS", "1") or 1)
    if tasks > 1 and "SLURM_PROCID" in os.environ:
        return World(tasks, int(os.environ["SLURM_PROCID"]), int(os.environ.get("SLURM_LOCALID", "0")))
    return World()


def first_host(nodelist: str) -> str:
    """The first host of a Slurm node list: ``gpu[07-09,12],cpu3`` -> ``gpu07``."""
    m = re.match(r"([^,\[]+)(?:\[([^\]]+)\])?", nodelist.strip())
    if not m:
        raise ValueError(f"SLURM_STEP_NODELIST={nodelist!r}: not a Slurm node list")
    prefix, ranges = m.group(1), m.group(2)
    return prefix + (ranges.split(",")[0].split("-")[0] if ranges else "")


def slurm_rendezvous() -> dict:
    """``MASTER_ADDR`` / ``MASTER_PORT`` for a Slurm step: the step's first node, and a port from
    the job id (20000-39999), unless already set."""
    env = {}
    if "MASTER_ADDR" not in os.environ:
        env["MASTER_ADDR"] = first_host(os.environ.get("SLURM_STEP_NODELIST") or os.environ.get("SLURM_NODELIST", "localhost"))
    if "MASTER_PORT" not in os.environ:
        env["MASTER_PORT"] = str(20000 + int(os.environ.get("SLURM_JOB_ID", "0") or 0) % 20000)
    return env


def join(world: World, backend: str | None = None) -> None:
    """Join the process group once (gloo for CPU tensors, NCCL for CUDA ones when CUDA is there).
    Under torchrun the rendezvous keys get a prefix per restart (``TORCHELASTIC_RESTART_COUNT``):
    a job restarted by ``--max-restarts`` otherwise read its previous attempt's addresses from the
    agent's store and failed to connect ("Connection refused", pytorch/pytorch#167288)."""
    if not world.enabled or dist.is_initialized():
        return
    backend = backend or ("cpu:gloo,cuda:nccl" if torch.cuda.is_available() else "gloo")
    if "WORLD_SIZE" not in os.environ:  # a Slurm step of several tasks (from_env)
        os.environ.update(slurm_rendezvous())
        dist.init_process_group(backend, init_method="env://", rank=world.rank, world_size=world.size)
        return
    if "TORCHELASTIC_RUN_ID" not in os.environ or "MASTER_ADDR" not in os.environ:
        dist.init_process_group(backend)  # env:// set by hand
        return
    agent_store = os.environ.get("TORCHELASTIC_USE_AGENT_STORE") == "True"
    store = dist.TCPStore(os.environ["MASTER_ADDR"], int(os.environ["MASTER_PORT"]), world.size,
                          is_master=not agent_store and world.rank == 0, **({} if agent_store else {"multi_tenant": True}))
    store = dist.PrefixStore(f"mvtn/attempt{os.environ.get('TORCHELASTIC_RESTART_COUNT', '0')}", store)
    dist.init_process_group(backend, store=store, rank=world.rank, world_size=world.size)


def init(world: World, device: str) -> str:
    """Join the process group (once) and return this rank's device (``cuda`` -> ``cuda:LOCAL_RANK``)."""
    if not world.enabled:
        return device
    cuda = str(device).startswith("cuda")
    join(world, "nccl" if cuda else "gloo")
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
