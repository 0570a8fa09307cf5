"""The renderer at the paper's training scale: B = 32 shapes x 12 views x 224 px, what a call costs a
GPU (kernel ops and host syncs, counted with ``kernel_ops.OpCounter`` on any device), its peak
memory, time per shape, and ResNet-18 forward+backward on the same images in the same run.

Rows (``mvtn-bench paper_scale=true``; on by default on CUDA):
- counts: hard (20k-face torus, K = 1), soft (K = 8, smooth) and points (2,048, K = 8), at B = 8 and
  32, with the memory budget the CUDA default would choose on an 80 GB device (``CUDA_80GB_MB``,
  set explicitly so a CPU counts what a GPU would run); forward and backward ops and syncs, and the
  peak memory and time of that (counted, so slower) call;
- budget: B = 32 under ``BUDGET_MB`` and without a budget: peak memory and time per shape;
- ResNet-18 forward+backward on 32 x 12 images of 224 px, per shape.
"""
from __future__ import annotations

import contextlib
import gc
import time

import torch

from ..data.shapes import Meshes, PointClouds
from ..render import budget, tiles
from .kernel_ops import OpCounter
from ..runtime.memory import PeakMemory

BATCH, VIEWS, SIZE = 32, 12, 224
MESH = "torus-20k"  # the benchmark mesh rendered (scenes.TORUS_SECTIONS)
MODES = {"hard": dict(mode="hard"), "soft": dict(mode="soft", faces_per_pixel=8, shading="smooth"),
         "points": dict(points_per_pixel=8)}
CUDA_80GB_MB = budget.CUDA_SHARE * 80 * 1024  # what memory_budget_mb=null picks with 80 GiB free
BUDGET_MB = {"hard": 2048, "soft": 6144, "points": 1024}
OP_LIMIT = {"hard": 800, "soft": 2500, "points": 500}
SYNC_LIMIT = 20
SLOWER_LIMIT = 1.10  # with a budget at most 10% slower per shape than without
GPU_MS_LIMIT = {"hard": 5.0, "soft": 20.0, "points": 3.0}  # per shape, fwd+bwd, on a GPU


@contextlib.contextmanager
def scale(batch: int, views: int, size: int, mesh: str = "torus-20k"):
    """Within the block the rows run at another scale (the device check's dry run: a few seconds)."""
    global BATCH, VIEWS, SIZE, MESH
    old = BATCH, VIEWS, SIZE, MESH
    BATCH, VIEWS, SIZE, MESH = batch, views, size, mesh
    try:
        yield
    finally:
        BATCH, VIEWS, SIZE, MESH = old


def scene(kind: str, B: int, device) -> Meshes | PointClouds:
    """B rotated copies of the benchmark's 20k-face torus, or of its 2,048 surface points."""
    from .scenes import rotated_copies_y, torus, torus_points

    if kind == "points":
        src = torus_points(2048, 0, device)
        return PointClouds.from_list(rotated_copies_y(src.points, B), names=[f"points-2048/{k}" for k in range(B)])
    src = torus(MESH, device)
    return Meshes.from_list(rotated_copies_y(src.verts, B), [src.faces] * B, names=[f"{MESH}/{k}" for k in range(B)])


def _sync(device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def call(kind: str, B: int, budget_mb: float | None, device, count: bool) -> dict:
    """One forward+backward render of ``kind`` at B x 12 x 224 px with camera gradients: its peak
    memory and seconds, and with ``count`` its kernel ops and syncs (forward, backward)."""
    from ..render.renderer import MultiViewRenderer
    from ..render.layouts import spherical

    shapes = scene(kind, B, device)
    # (eager: the kernels CUDA runs, where renderer.compile=null is eager)
    r = MultiViewRenderer(image_size=SIZE, memory_budget_mb=budget_mb, compile=False, **MODES[kind]).eval()
    azim, elev, dist = spherical(VIEWS, batch=B, distance=2.2, device=device, sphere="fibonacci")
    azim, elev = azim.clone().requires_grad_(True), elev.clone().requires_grad_(True)
    row = dict(kind=kind, batch=B, budget_mb=budget_mb, counted=count)
    gc.collect()
    # counted: the search's CUDA form on any device (``tiles.gpu_path``), the operators a GPU runs
    with PeakMemory(device) as pm, (tiles.gpu_path() if count else contextlib.nullcontext()):
        _sync(device)
        t0 = time.perf_counter()
        with (OpCounter() if count else _Null()) as fwd:
            out = r(shapes, azim, elev, dist)
        loss = out.images.sum()
        with (OpCounter() if count else _Null()) as bwd:
            loss.backward()
        _sync(device)
        row["seconds"] = time.perf_counter() - t0
    row.update(peak_mib=pm.peak_mib, groups=int(out.stats.get("groups", 1)), recomputed=bool(out.stats.get("recomputed")),
               ms_per_shape=1000 * row["seconds"] / B)
    if count:
        row.update(fwd_ops=fwd.ops, fwd_syncs=fwd.syncs, bwd_ops=bwd.ops, bwd_syncs=bwd.syncs,
                   fwd_sync_names=dict(fwd.sync_names))
    return row


class _Null:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def resnet_ms_per_shape(B: int, device, seed: int = 0, bf16: bool = False) -> float:
    """ResNet-18 forward+backward on B x 12 random images of 224 px (one warm-up), ms per shape;
    ``bf16``: its forward under bfloat16 autocast."""
    from ..models.backbones import resnet18

    torch.manual_seed(seed)
    net = resnet18(num_classes=40).to(device).train()
    x = torch.rand(B * VIEWS, 3, SIZE, SIZE).to(device)

    def step():
        net.zero_grad(set_to_none=True)
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16):
            y = net(x)
        y.float().sum().backward()

    step()
    _sync(device)
    t0 = time.perf_counter()
    step()
    _sync(device)
    return 1000 * (time.perf_counter() - t0) / B


def measure(device, batches=None, progress=None, resnet_bf16: bool = False, budget_rows: bool = True) -> dict:
    """Every row of the module docstring: ``{"counts": [...], "budget": [...], "resnet_ms": float}``
    (``batches``: of the counted rows, default 8 and ``BATCH``; ``budget_rows``: the rows with and
    without a budget, else the time without one only; ``resnet_bf16``: ResNet-18 under bf16 autocast)."""
    out = {"counts": [], "budget": [], "resnet_ms": None, "resnet_bf16": resnet_bf16,
           "scale": dict(batch=BATCH, views=VIEWS, size=SIZE)}
    for kind in MODES:
        for B in batches or (8, BATCH):
            _note(progress, f"paper scale: {kind} B={B} counted")
            out["counts"].append(call(kind, B, CUDA_80GB_MB, device, count=True))
    for kind in MODES:
        for limit in ((BUDGET_MB[kind], None) if budget_rows else (None,)):
            _note(progress, f"paper scale: {kind} B={BATCH} budget {limit}")
            try:
                out["budget"].append(call(kind, BATCH, limit, device, count=False))
            except budget.BudgetTooSmall as exc:  # recorded as the row's result: the budget was refused
                out["budget"].append(dict(kind=kind, batch=BATCH, budget_mb=limit, refused=str(exc)))
    _note(progress, "paper scale: ResNet-18")
    out["resnet_ms"] = resnet_ms_per_shape(BATCH, device, bf16=resnet_bf16)
    return out


def _note(progress, text: str) -> None:
    if progress is not None:
        progress(text)


def targets(res: dict, on_gpu: bool) -> list[tuple[str, str, str, bool | None]]:
    """(target, measured, limit, ok) rows of the issue's paper-scale targets."""
    rows = []
    for r in res["counts"]:
        if r["batch"] != BATCH:
            continue
        k = r["kind"]
        rows.append((f"{k}: kernel ops per forward render, B = {BATCH}, {VIEWS} x {SIZE} px, budget {CUDA_80GB_MB:.0f} MiB",
                     f"{r['fwd_ops']:,} (backward {r['bwd_ops']:,})", f"<= {OP_LIMIT[k]:,}", r["fwd_ops"] <= OP_LIMIT[k]))
        rows.append((f"{k}: ops that sync per forward render, B = {BATCH}", f"{r['fwd_syncs']} (backward {r['bwd_syncs']})",
                     f"<= {SYNC_LIMIT}", r["fwd_syncs"] <= SYNC_LIMIT))
    for k in MODES:
        pair = {r["budget_mb"]: r for r in res["budget"] if r["kind"] == k}
        with_b, without = pair.get(BUDGET_MB[k]), pair.get(None)
        if with_b is None or without is None:
            continue
        limit = BUDGET_MB[k]
        if "refused" in with_b:
            rows.append((f"{k}: render peak memory, B = {BATCH}, renderer.memory_budget_mb={limit}",
                         f"refused: {with_b['refused']}", f"<= {limit} MiB", False))
            continue
        rows.append((f"{k}: render peak memory, B = {BATCH}, renderer.memory_budget_mb={limit}",
                     f"{with_b['peak_mib']:.0f} MiB ({with_b['groups']} groups; without a budget {without['peak_mib']:.0f} MiB)",
                     f"<= {limit} MiB", with_b["peak_mib"] <= limit))
        ratio = with_b["ms_per_shape"] / without["ms_per_shape"]
        rows.append((f"{k}: time per shape with the budget against without, B = {BATCH}",
                     f"{with_b['ms_per_shape']:.1f} / {without['ms_per_shape']:.1f} ms: {ratio:.2f} x",
                     f"<= {SLOWER_LIMIT:.2f} x", ratio <= SLOWER_LIMIT))
        if on_gpu:
            ms = without["ms_per_shape"]
            rows.append((f"{k}: fwd+bwd per shape on this GPU, B = {BATCH} (ResNet-18 {res['resnet_ms']:.1f} ms)",
                         f"{ms:.2f} ms ({ms / res['resnet_ms']:.2f} x ResNet-18)", f"<= {GPU_MS_LIMIT[k]:g} ms",
                         ms <= GPU_MS_LIMIT[k]))
    return rows


def markdown(res: dict, on_gpu: bool) -> str:
    """The section's tables, as ``mvtn-bench`` prints them."""
    def table(headers, rows):
        return "\n".join(["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
                         + ["| " + " | ".join(str(c) for c in r) + " |" for r in rows])

    counts = [[r["kind"], r["batch"], f"{r['fwd_ops']:,}", r["fwd_syncs"], f"{r['bwd_ops']:,}", r["bwd_syncs"], r["groups"],
               f"{r['peak_mib']:.0f}"] for r in res["counts"]]
    per_shape = [[r["kind"], "null" if r["budget_mb"] is None else f"{r['budget_mb']:g}", "refused", "-", "-", "-"]
                 if "refused" in r else
                 [r["kind"], "null" if r["budget_mb"] is None else f"{r['budget_mb']:g}",
                  f"{r['groups']}{' (recomputed)' if r.get('recomputed') else ''}", f"{r['peak_mib']:.0f}",
                  f"{r['ms_per_shape']:.1f}", f"{r['ms_per_shape'] / res['resnet_ms']:.2f} x"] for r in res["budget"]]
    rows = [[t, m, lim, "PASS" if ok else "MISS"] for t, m, lim, ok in targets(res, on_gpu)]
    return (f"## Paper scale: {VIEWS} views x {SIZE} px (20k-face torus; 2,048 points)\n\n"
            f"Kernel ops and host syncs per render call (ATen operators that compute; views excluded), with "
            f"memory_budget_mb={CUDA_80GB_MB:.0f} (the automatic budget of an 80 GB GPU); the peak and time "
            f"of that counted call:\n\n"
            + table(["mode", "batch", "forward ops", "forward syncs", "backward ops", "backward syncs", "groups", "peak MiB"], counts)
            + f"\n\nForward+backward at B = {BATCH}, with and without a budget; ResNet-18 forward+backward on the same "
            f"{BATCH} x {VIEWS} images: {res['resnet_ms']:.1f} ms per shape:\n\n"
            + table(["mode", "memory_budget_mb", "groups", "peak MiB", "ms per shape", "vs ResNet-18"], per_shape)
            + "\n\n### Paper-scale targets\n\n" + table(["target", "measured", "limit", "status"], rows))


def main(argv=None) -> None:
    """``python -m mvtn_exp.bench.paper_scale [--budget MB|null] KIND:B ...``: the counted rows alone
    (kernel ops and syncs, forward and backward, peak and seconds of that call) for renders of KIND
    (hard | soft | points) at batch B, as a Markdown table."""
    import argparse

    p = argparse.ArgumentParser(description=main.__doc__)
    p.add_argument("rows", nargs="+", help="KIND:B, e.g. hard:32 soft:8 points:32")
    p.add_argument("--budget", default=str(CUDA_80GB_MB), help="renderer.memory_budget_mb (null: the default)")
    a = p.parse_args(argv)
    limit = None if a.budget == "null" else float(a.budget)
    print("| mode | batch | memory_budget_mb | forward ops | forward syncs | backward ops | backward syncs | groups | peak MiB | s |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for spec in a.rows:
        kind, B = spec.split(":")
        r = call(kind, int(B), limit, torch.device("cpu"), count=True)
        print(f"| {kind} | {B} | {a.budget} | {r['fwd_ops']:,} | {r['fwd_syncs']} | {r['bwd_ops']:,} | {r['bwd_syncs']} | "
              f"{r['groups']} | {r['peak_mib']:.0f} | {r['seconds']:.1f} |", flush=True)


if __name__ == "__main__":
    main()
