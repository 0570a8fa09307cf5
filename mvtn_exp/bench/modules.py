"""The paper's module table in ``mvtn-bench``: parameters, FLOPs and time per shape of R, G and C.

One row per module and setting: the renderer R (2,048-face torus, soft K=8 smooth as in training
and hard K=1; 2,048 points, 8 per pixel) at M = 1, 4, 12 (quick: 1, 4); G (``mvtn_spherical``:
PointNet + regressor on 1,024 and 256 points, the regressor alone on given features, and
``mvtn_poi`` on 256 points) at M = 12 (quick: 4); C (MVCNN with ResNet-18 and with the small CNN)
at M = 1, 4, 12. Image size 224 px (quick: 64). Per shape: R renders one shape; G and C run a
batch of ``BATCH`` shapes in train mode and the times are divided by it. Forward under
``no_grad``; forward+backward of the sum of the outputs (R: with camera gradients). FLOPs are
``torch.utils.flop_counter`` forward counts (matrix products and convolutions) per shape; the
renderer has none that describe it (its work is face search, sorting and scattering).
"""
from __future__ import annotations

import torch
from torch.utils.flop_counter import FlopCounterMode

from ..models.multiview import build_multiview
from ..selectors import build_selector
from .scenes import Views, render_fns, renderer_for, torus, torus_points
from .timing import med_ms, time_runs

BATCH = 4
NUM_CLASSES = 40


def _flops(fn) -> float:
    with torch.no_grad(), FlopCounterMode(display=False) as count:
        fn()
    return float(count.get_total_flops())


def _time_pair(fwd, fwd_bwd, device, repeats, budget_s) -> tuple[list[float], list[float]]:
    fwd(), fwd_bwd()  # warm-up
    return time_runs(fwd, device, repeats, budget_s), time_runs(fwd_bwd, device, repeats, budget_s)


def _row(module, setting, params, flops, fwd_s, fwd_bwd_s, per) -> dict:
    return dict(module=module, setting=setting, params=params, flops_per_shape=None if flops is None else flops / per,
                fwd_ms_per_shape=med_ms(fwd_s) / per, fwd_bwd_ms_per_shape=med_ms(fwd_bwd_s) / per, runs=len(fwd_bwd_s))


def _net_row(module, setting, net, make_input, device, repeats, budget_s) -> dict:
    """A G or C row: ``net(x)`` returns a tensor or a tuple whose first entries are summed for the backward."""
    net = net.to(device).train()
    x = make_input()

    def out_sum():
        out = net(x)
        return sum(o.sum() for o in (out if isinstance(out, tuple) else (out,)) if torch.is_tensor(o))

    def fwd():
        with torch.no_grad():
            net(x)

    def fwd_bwd():
        net.zero_grad(set_to_none=True)
        out_sum().backward()

    params = sum(p.numel() for p in net.parameters() if p.requires_grad)
    flops = _flops(lambda: net(x))
    return _row(module, setting, params, flops, *_time_pair(fwd, fwd_bwd, device, repeats, budget_s), BATCH)


class RegressorAlone(torch.nn.Module):
    """G's regressor alone: given point features (and u0), the views (``MVTNSelector.forward`` after the encoder)."""

    def __init__(self, g):
        super().__init__()
        self.regressor = g.regressor

    def forward(self, feats):
        return torch.tanh(self.regressor(feats))


def module_rows(quick: bool, device, repeats: int, budget_s: float, seed: int = 0) -> list[dict]:
    device = torch.device(device)
    size, views, g_views = (64, (1, 4), 4) if quick else (224, (1, 4, 12), 12)
    rows = []
    mesh, points = torus("torus-2k", device), torus_points(2048, seed, device)
    for label, shape, K, shading in (("R mesh, soft K=8 smooth", mesh, 8, "smooth"), ("R mesh, hard", mesh, 1, "flat"),
                                     ("R points, 8 per pixel", points, 8, "flat")):
        for M in views:
            fwd, fwd_bwd, _ = render_fns(renderer_for(shape, size, K, shading), shape, Views(M, 1, device))
            rows.append(_row(label, f"M={M}, {size} px, {2048} {'faces' if shape is mesh else 'points'}", 0, None,
                             *_time_pair(fwd, fwd_bwd, device, repeats, budget_s), 1))
    gen = torch.Generator().manual_seed(seed)
    for label, name, n, kw in (("G mvtn_spherical (PointNet + regressor)", "mvtn_spherical", 1024, {}),
                               ("G mvtn_spherical (PointNet + regressor)", "mvtn_spherical", 256, {}),
                               ("G mvtn_poi", "mvtn_poi", 256, {})):
        torch.manual_seed(seed)
        g = build_selector(name, g_views, **kw)
        pts = torch.randn(BATCH, n, 3, generator=gen).to(device)
        rows.append(_net_row(label, f"M={g_views}, {n} points", g, lambda p=pts: p, device, repeats, budget_s))
        if name == "mvtn_spherical" and n == 256:
            reg = RegressorAlone(g)
            feats = torch.randn(BATCH, g.regressor[0].in_features, generator=gen).to(device)
            rows.append(_net_row("G regressor alone (features given)", f"M={g_views}", reg, lambda f=feats: f, device,
                                 repeats, budget_s))
    for label, backbone in (("C MVCNN, ResNet-18", "resnet18"), ("C MVCNN, small CNN", "small_cnn")):
        for M in views:
            torch.manual_seed(seed)
            c = build_multiview("mvcnn", backbone, NUM_CLASSES)
            imgs = torch.rand(BATCH, M, 3, size, size, generator=gen).to(device)
            rows.append(_net_row(label, f"M={M}, {size} px", c, lambda x=imgs: x, device, repeats, budget_s))
    return rows


def markdown(rows: list[dict]) -> str:
    from .render_report import md_table

    body = [[r["module"], r["setting"], f"{r['params']:,}",
             "n/a (not FLOPs)" if r["flops_per_shape"] is None else f"{r['flops_per_shape'] / 1e9:.3g}",
             f"{r['fwd_ms_per_shape']:.2f}", f"{r['fwd_bwd_ms_per_shape']:.2f}", r["runs"]] for r in rows]
    return (f"## Modules (the paper's performance table): per shape; R one shape, G and C a batch of {BATCH} shapes "
            "in train mode, times divided by it\n\n"
            + md_table(["module", "setting", "parameters", "GFLOPs / shape (forward)", "fwd ms / shape",
                        "fwd+bwd ms / shape", "runs"], body))
