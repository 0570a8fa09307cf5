"""G's gradient from the task loss itself: a Gaussian-smoothed, antithetic estimate over the views.

``selector.grad=autograd`` (the paper's) trains G through the differentiable renderer:
dL/du = dL/dimages * dimages/du. ``selector.grad=smoothed`` replaces that by the gradient of
the loss smoothed over the views, estimated from loss *values* at perturbed views:

    L_sigma(u) = E_eps L(u + sigma eps),  eps ~ N(0, I) over every view's (azimuth, elevation)
    g(u) = 1 / (2 sigma K) sum_k [L(u + sigma eps_k) - L(u - sigma eps_k)] eps_k   (per degree)

with K antithetic pairs (``selector.probe_pairs``) and sigma in degrees (``selector.probe_sigma``),
per shape. G is then trained on ``sum(u * g) / B``, whose gradient with respect to G's parameters
is ``g`` chained through G, exactly as autograd would chain dL/du. The renderer is not
differentiated at all, so any renderer works (hard included), and no image gradient is kept.

Why (measured on ``synthetic_views`` with a C that reads the cup's detail at 0.95 from the cup's
axis; 96 test shapes, cameras 20 / 40 / 60 degrees off the axis): the loss rises steeply away
from the axis (0.15 on it, 1.7 at 20, 3.3 at 40 degrees), yet the renderer's camera gradient
has cosine 0.01 / 0.05 / -0.25 with the direction towards the axis (and still about 0 averaged
over 12 jittered views), while this estimate with K = 6, sigma = 12 has cosine 0.72 / 0.72 / 0.48
(towards the axis for 93 / 88 / 80% of the shapes; ``python scripts/studies/view_landscape.py``).

The perturbed renders run under ``torch.no_grad()`` with the whole model in eval mode (fixed light
and colour, BatchNorm running statistics, no dropout), so the two sides of a pair differ only in
the views and no running statistics or random streams of the training step move. The noise comes
from its own generator, seeded by (run seed, global step, and the rank with several processes):
resume stays exact.
"""
from __future__ import annotations

from contextlib import contextmanager
from typing import Callable, Iterator

import torch
from torch import Tensor, nn

from .hypotheses import join_views, split_images
from ..runtime import distributed, seeding


@contextmanager
def eval_mode(module: nn.Module) -> Iterator[nn.Module]:
    """``module`` and all its children in eval mode inside the block; every flag restored after."""
    flags = [(m, m.training) for m in module.modules()]
    module.eval()
    try:
        yield module
    finally:
        for m, flag in flags:
            m.training = flag


def noise_generator(seed: int, step: int) -> torch.Generator:
    """The perturbations' own CPU generator for global step ``step`` of a run seeded ``seed`` (each
    process of a several-process run its own: ``seeding.for_rank``)."""
    world = distributed.from_env()
    seed = seeding.for_rank(seed, world.rank, world.size)
    return torch.Generator().manual_seed((int(seed) * 1_000_003 + int(step)) % (2 ** 63))


def smoothed_view_gradient(render_loss: Callable[..., Tensor], views: tuple,
                           pairs: int, sigma: float, generator: torch.Generator, batched: bool = False) -> tuple[Tensor, Tensor]:
    """The antithetic estimate of dL_sigma/du (module docstring) for every shape and view.

    render_loss: ``(azim, elev, dist) [B, M] -> per-shape loss [B]`` (called 2 * pairs times, under
    no_grad); ``batched``: called once instead, as ``render_loss(azim, elev, dist, sets=2 * pairs)``
    on ``[B, 2 * pairs * M]`` views (set-major per shape: +pair 1, -pair 1, +pair 2, ...) returning
    ``[B, 2 * pairs]`` (one renderer call for every probe: the same noise, the same estimate up to
    float rounding). views: ``(azim, elev, dist)``, each ``[B, M]`` (degrees, world
    units; detached). Returns ``(g_azim, g_elev)``, each ``[B, M]``: loss per degree of each view's
    azimuth / elevation.
    """
    if pairs < 1 or not sigma > 0:
        raise ValueError(f"smoothed_view_gradient: need pairs >= 1 and sigma > 0, got {pairs}, {sigma}")
    azim, elev, dist = (v.detach() for v in views)
    with torch.no_grad():
        eps = [torch.randn((2, *azim.shape), generator=generator, dtype=torch.float64).to(azim) for _ in range(int(pairs))]
        if batched:
            probes = [(azim + s * sigma * e[0], elev + s * sigma * e[1]) for e in eps for s in (1.0, -1.0)]
            losses = render_loss(torch.cat([a for a, _ in probes], 1), torch.cat([b for _, b in probes], 1),
                                 dist.repeat(1, len(probes)), sets=len(probes))  # [B, 2 * pairs]
            plus, minus = losses[:, 0::2].T, losses[:, 1::2].T  # [pairs, B]
        else:
            plus = [render_loss(azim + sigma * e[0], elev + sigma * e[1], dist) for e in eps]
            minus = [render_loss(azim - sigma * e[0], elev - sigma * e[1], dist) for e in eps]
        g_azim, g_elev = torch.zeros_like(azim), torch.zeros_like(elev)
        for e, p, m in zip(eps, plus, minus):
            w = ((p - m) / (2.0 * sigma * pairs)).to(azim)[:, None]  # [B, 1]
            g_azim += w * e[0]
            g_elev += w * e[1]
    return g_azim, g_elev


def model_render_loss(model, batch: dict, labels: Tensor, per_shape_loss: Callable[[Tensor, Tensor], Tensor],
                      hypotheses: int = 1):
    """``render_loss`` for ``smoothed_view_gradient``: R then C of ``model`` (an ``MVTN``) in eval mode.

    hypotheses H > 1: the views come as ``[B * H, M]`` (``selectors.hypotheses.split_views``), each
    hypothesis's M views are classified as a shape of their own, and ``labels`` are ``[B * H]``.
    ``sets`` K > 1 (H = 1 only): the views come as ``[B, K * M]``, K probe sets rendered in one call,
    each classified alone (C on one set at a time); returns ``[B, K]``."""
    def render_loss(azim: Tensor, elev: Tensor, dist: Tensor, sets: int = 1) -> Tensor:
        if sets > 1 and hypotheses > 1:
            raise ValueError("model_render_loss: probe sets and hypotheses cannot be batched together")
        views = (azim, elev, dist) if hypotheses == 1 else join_views((azim, elev, dist), hypotheses)
        with eval_mode(model):
            images = model.render(batch, *views)
            if sets > 1:  # C per set: on a CPU, C on B shapes K times is faster than once on B * K
                B, M = azim.shape[0], azim.shape[1] // sets
                images = images.reshape(B, sets, M, *images.shape[2:])
                per_set = [tuple(v.reshape(B, sets, M)[:, k] for v in views) for k in range(sets)]
                return torch.stack([per_shape_loss(model.mvnet(images[:, k], per_set[k])[0], labels)
                                    for k in range(sets)], 1)
            logits, _ = (model.mvnet(images, views) if hypotheses == 1
                         else model.mvnet(split_images(images, hypotheses), (azim, elev, dist)))
        return per_shape_loss(logits, labels)
    return render_loss


def surrogate(views: tuple, g_azim: Tensor, g_elev: Tensor) -> Tensor:
    """Scalar whose gradient with respect to G's views is ``(g_azim, g_elev) / B`` (the batch-mean
    loss's share of each shape): add it to the task loss, computed on detached views."""
    B = views[0].shape[0]
    return ((views[0] * g_azim.detach()).sum() + (views[1] * g_elev.detach()).sum()) / B
