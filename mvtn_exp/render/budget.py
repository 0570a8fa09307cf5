"""How much memory one render may hold: ``renderer.memory_budget_mb`` -> groups of shapes rendered
one after another, and the candidate chunk of each group's search.

A render holds three kinds of memory while it runs:
- per image pixel: the dense per-pixel buffers of the search and the images themselves
  (``PIXEL_BYTES``, for all M x H x W pixels of every shape of the group being searched);
- per primitive-view (a face or point seen in one view): projected corners, face tables, culling
  flags (``PRIM_BYTES``);
- per candidate (a primitive-pixel pair the search enumerates): its indices, pixel centre and the
  maths that tests it (``CANDIDATE_BYTES``), for one chunk of candidates at a time.

With a budget, what the backward pass keeps of every group (``SAVED_BYTES`` per pixel, with the
images themselves) is set aside first; when that alone would take more than ``RECOMPUTE_SHARE`` of
the budget, each group keeps only its selection and outputs (``KEPT_BYTES``) and its
differentiable part is computed again in the backward pass (``Plan.recompute``:
``torch.utils.checkpoint``): less memory for more time. Of what is left, shapes are grouped so
that a group's pixel and primitive state takes at most ``GROUP_SHARE``, and the rest bounds the
candidates of one chunk. A group renders whole (search, then its differentiable pixels), so only
what the backward pass needs of finished groups stays while the next group is searched. Results
do not depend on the grouping (each pixel belongs to one image, each image to one shape): hard
and point images are identical, soft ones equal to float rounding.

Without a budget (``memory_budget_mb=null``): on CUDA a budget of ``CUDA_SHARE`` of the memory
free to this process is chosen at each call; on CPU nothing is grouped and the chunk is
``renderer.max_candidates``, a size that suits CPU caches.

The byte constants are measured peaks per unit (``mvtn-bench``'s budget rows check that a render
stays within its budget), rounded up.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

# peak bytes per unit, by kind of render: the slope and intercept of a render's forward+backward
# peak against its chunk size (CPU, 20k-face torus / 2,048 points, 12 x 224 px), rounded up.
# Candidates are counted as the search budgets them: pixels of the primitives' (dilated) boxes
PIXEL_BYTES = {"hard": 32, "soft": 320, "points": 80}
PRIM_BYTES = {"hard": 40, "soft": 160, "points": 64}
CANDIDATE_BYTES = {"hard": 64, "soft": 80, "points": 64}
# per image pixel, what the backward pass keeps of a group (its differentiable slots), and what it
# keeps when the group is recomputed in the backward pass instead (the selection and the outputs),
# the dense images and alpha (16 bytes a pixel) included
SAVED_BYTES = {"hard": 32, "soft": 400, "points": 64}
KEPT_BYTES = {"hard": 32, "soft": 96, "points": 40}
RECOMPUTE_SHARE = 0.25  # kept state over this share of the budget: recompute instead
GROUP_SHARE = 0.5  # of what the kept state leaves: a group's state at most, the rest for a chunk
CUDA_SHARE = 0.5
MiB = 1 << 20


class BudgetTooSmall(ValueError):
    """``renderer.memory_budget_mb`` cannot hold the smallest unit of work; names the smallest that can."""


@dataclass
class Plan:
    """groups: ``[(start, stop)]`` consecutive shape ranges rendered one after another (one group
    ``(0, B)`` when everything fits); max_candidates: the candidate chunk; budget_mb: the budget
    planned for (None: no budget); strict: an explicit budget, refused when a tile overflows it;
    recompute: what the backward pass needs of every group would not fit beside a group being
    searched, so each group's differentiable part is computed again in the backward pass."""

    groups: list
    max_candidates: int
    budget_mb: float | None = None
    strict: bool = False
    recompute: bool = False


def available_mb(device: torch.device) -> float:
    """Memory this process could still allocate on a CUDA ``device``, in MiB: the driver's free
    memory plus what PyTorch's caching allocator holds but does not use."""
    free, _ = torch.cuda.mem_get_info(device)
    cached = torch.cuda.memory_reserved(device) - torch.cuda.memory_allocated(device)
    return (free + cached) / MiB


def budget_mb(setting: float | None, device: torch.device) -> float | None:
    """The budget a render plans for: the setting, else ``CUDA_SHARE`` of the available memory
    on CUDA, else None (CPU: no budget, chunks of ``max_candidates``)."""
    if setting is not None:
        return float(setting)
    if device.type == "cuda":
        return CUDA_SHARE * available_mb(device)
    return None


def plan(kind: str, prims_per_shape: torch.Tensor, views: int, image_size: int, max_candidates: int,
         setting: float | None, device: torch.device) -> Plan:
    """The groups and chunk of a render of ``kind`` (hard | soft | points) of shapes with
    ``prims_per_shape`` ``[B]`` faces or points each, ``views`` views of ``image_size`` px.
    Reads the counts on the host once when there is a budget (none otherwise)."""
    B = len(prims_per_shape)
    budget = budget_mb(setting, device)
    if budget is None:
        return Plan([(0, B)] if B else [], max_candidates)
    pixels = views * image_size * image_size
    prims = prims_per_shape.tolist()
    total = budget * MiB
    recompute = B * pixels * SAVED_BYTES[kind] > RECOMPUTE_SHARE * total
    room = total - B * pixels * (KEPT_BYTES if recompute else SAVED_BYTES)[kind]  # for a group and a chunk
    fixed = [_group_bytes(kind, pixels, n * views, recompute) for n in prims]
    if fixed and 2 * max(fixed) > room:
        need = smallest_mb(kind, views, image_size, B, max(prims))
        raise BudgetTooSmall(f"renderer.memory_budget_mb={budget:g}: one shape's {views} views of {image_size} px "
                             f"({max(prims)} primitives, {B} in the batch) need {need} MiB at least; set "
                             f"renderer.memory_budget_mb >= {need} (or null: automatic)")
    groups, start, used = [], 0, 0.0
    for b, f in enumerate(fixed):
        if b > start and used + f > GROUP_SHARE * room:
            groups.append((start, b))
            start, used = b, 0.0
        used += f
    if B:
        groups.append((start, B))
    largest = max((sum(fixed[a:b]) for a, b in groups), default=0)
    chunk = max(1, int((room - largest) / CANDIDATE_BYTES[kind]))
    return Plan(groups, chunk, budget, strict=setting is not None, recompute=recompute)


def _group_bytes(kind: str, pixels: int, prim_views: int, recompute: bool) -> int:
    """A shape's share of a group's state while it is searched: its pixels (with the saved
    differentiable part, recomputed groups hold it only then) and primitive-views."""
    return pixels * (PIXEL_BYTES[kind] + (SAVED_BYTES[kind] if recompute else 0)) + prim_views * PRIM_BYTES[kind]


def smallest_mb(kind: str, views: int, image_size: int, batch: int, prims: int = 0) -> int:
    """The smallest ``memory_budget_mb`` that ``plan`` accepts for ``batch`` shapes of ``prims``
    primitives at ``views`` x ``image_size`` px (with 0 primitives: a lower bound for any batch):
    the kept state of the batch (recomputed when that is the cheaper way to fit), then room for one
    shape's group and a chunk as large."""
    pixels = views * image_size * image_size
    need = []
    for recompute in (False, True):
        kept = batch * pixels * (KEPT_BYTES if recompute else SAVED_BYTES)[kind]
        total = kept + 2 * _group_bytes(kind, pixels, prims * views, recompute)
        if (batch * pixels * SAVED_BYTES[kind] > RECOMPUTE_SHARE * total) == recompute:
            need.append(total)
    return math.ceil(min(need) / MiB)


def tile_too_large(plan_or_budget: float | None, kind: str, candidates: int) -> str:
    """The one-line refusal when one tile's ``candidates`` exceed an explicit budget's chunk."""
    need = math.ceil(candidates * CANDIDATE_BYTES[kind] / GROUP_SHARE / MiB)
    return (f"renderer.memory_budget_mb={plan_or_budget:g}: one screen tile holds {candidates} candidate pairs, "
            f"which need {need} MiB at least; set renderer.memory_budget_mb >= {need}, lower "
            "renderer.tile_size, or null (automatic)")


def render_bytes(kind: str, views: int, image_size: int, prims: int = 0, max_candidates: int = 0) -> int:
    """Peak bytes of rendering one shape's ``views`` views at ``image_size`` px at once, with
    ``prims`` faces or points and no budget: the per-pixel state of the search and the images
    (``PIXEL_BYTES``), the primitive-views (``PRIM_BYTES``) and one chunk of ``max_candidates``
    candidates (``CANDIDATE_BYTES``). Without autograd an upper bound (the constants are
    forward+backward peaks)."""
    return (views * image_size * image_size * PIXEL_BYTES[kind] + prims * views * PRIM_BYTES[kind]
            + max_candidates * CANDIDATE_BYTES[kind])
