"""The renderer benchmark behind ``mvtn-bench``: speed and extra peak memory, Markdown + JSON.

Scenes: tori (``trimesh.creation.torus(0.7, 0.3, n, n)``, n = 32 / 100 / 224 -> 2,048 / 20,000 /
100,352 faces) and 2,048 / 5,000 points sampled (seeded) from the 20k torus surface. For every
scene, image size, number of views M (spherical layout, B = 1) and K (mesh: K=1 is ``mode=hard``,
K=8 ``mode=soft, faces_per_pixel=8``; points: ``points_per_pixel``) it measures

* the extra peak memory of one forward+backward,
* forward time under ``no_grad``,
* forward+backward time (azim and elev require grad, loss = images.sum()).

Two phases. Phase 1 measures every memory figure, in the allocator state the process started with
(``mvtn-bench`` pins glibc's mmap threshold at 64 KiB so RSS follows live memory; see
``memory.py``). Phase 2 switches glibc to the thresholds its dynamic rule reaches on its own
(``set_malloc_mode("speed")``: the pinned threshold made CPU timings up to ~2.5x slower) and times:
one warm-up, then the median of up to ``repeats`` runs; a config whose first timed run takes t
seconds runs ``max(1, min(repeats, floor(time_budget_s / t)))`` times, which keeps the full grid to a
few minutes on two CPU cores. Further sections: ResNet-18 forward+backward on the same number of
224 px images (the yardstick of the targets), a dense brute-force K=1 face search against
``search_faces`` where it fits, level of detail (LOD) at 224 px / 12 views, the extra peak memory of a
batch of 8 shapes x 12 views x 224 px, and the targets with PASS/MISS, whose time ratios come from
both sides timed again in alternation (``paired_times``).
"""
from __future__ import annotations

import gc
import json
import math
import os
import platform
import statistics
import sys
import time
from dataclasses import asdict, dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from ..data.shapes import Meshes, PointClouds
from ..models.backbones import resnet18
from ..render import accel, layouts, lod, mesh_raster
from ..render.renderer import MultiViewRenderer
from . import edge_error
from .dense import dense_pairs, dense_search
from ..runtime.memory import PeakMemory, malloc_threshold_note, set_malloc_mode

TORUS_SECTIONS = {"torus-2k": 32, "torus-20k": 100, "torus-100k": 224}
POINT_SOURCE = "torus-20k"  # the surface point clouds are sampled from
LIMIT_MIB = 512.0
SOFT_SHADINGS = ("flat", "smooth")  # soft rows: training uses smooth


@dataclass
class BenchOptions:
    """What to run. ``quick``: 64 px, M in {1, 4}, the 2k torus and 2,048 points, no LOD, no batch of 8."""

    quick: bool = False
    repeats: int = 5
    device: str = "cpu"
    time_budget_s: float = 2.0
    dense_max_pairs: float = 2.0e8
    seed: int = 0
    progress: bool = True
    modules: bool = True  # the paper's module table (bench/modules.py)
    scaling: bool = True  # time and memory against faces, pixels, views, batch (bench/scaling.py)
    compiled: bool = True  # the soft targets again with renderer.compile=true (where torch.compile runs)
    paper_scale: bool = False  # B = 32 x 12 x 224 px: kernel ops, syncs, memory budget (bench/paper_scale.py)


@dataclass
class Grid:
    sizes: tuple[int, ...]
    views: tuple[int, ...]
    meshes: tuple[str, ...]
    points: tuple[int, ...]
    ks: tuple[int, ...] = (1, 8)
    resnet_size: int = 224
    lod_meshes: tuple[str, ...] = ()
    batch8: bool = True
    # the configuration the targets refer to
    target_size: int = 224
    target_views: int = 12


def grid_for(opts: BenchOptions) -> Grid:
    if opts.quick:
        return Grid(sizes=(64,), views=(1, 4), meshes=("torus-2k",), points=(2048,), resnet_size=64, batch8=False)
    return Grid(sizes=(64, 128, 224), views=(1, 4, 12), meshes=("torus-2k", "torus-20k", "torus-100k"),
                points=(2048, 5000), lod_meshes=("torus-20k", "torus-100k"))


# ---------------------------------------------------------------------------- scenes
def torus_of(sections: int, device, name: str) -> Meshes:
    """The benchmark torus (radii 0.7 / 0.3) with ``sections`` x ``sections`` quads: 2 sections^2 faces."""
    import trimesh

    t = trimesh.creation.torus(major_radius=0.7, minor_radius=0.3, major_sections=sections, minor_sections=sections)
    return Meshes.from_list([torch.tensor(np.asarray(t.vertices), dtype=torch.float32, device=device)],
                            [torch.tensor(np.asarray(t.faces), dtype=torch.long, device=device)], names=[name])


def torus(name: str, device) -> Meshes:
    return torus_of(TORUS_SECTIONS[name], device, name)


def torus_points(count: int, seed: int, device) -> PointClouds:
    import trimesh

    n = TORUS_SECTIONS[POINT_SOURCE]
    t = trimesh.creation.torus(major_radius=0.7, minor_radius=0.3, major_sections=n, minor_sections=n)
    pts, _ = trimesh.sample.sample_surface(t, count, seed=np.random.default_rng(seed))
    return PointClouds.from_list([torch.tensor(np.asarray(pts), dtype=torch.float32, device=device)], names=[f"points-{count}"])


def rotated_copies_y(verts: torch.Tensor, copies: int) -> list[torch.Tensor]:
    """``copies`` versions of ``[V, 3]`` vertices, copy k rotated by ``40 k`` degrees about Y."""
    out = []
    for k in range(copies):
        a = math.radians(40.0 * k)
        R = torch.tensor([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]],
                         dtype=verts.dtype, device=verts.device)
        out.append(verts @ R.T)
    return out


def shape_label(shape) -> str:
    return shape.names[0] if len(shape.names) else type(shape).__name__


def prims_of(shape) -> int:
    return int(shape.faces_per_shape[0]) if isinstance(shape, Meshes) else int(shape.points_per_shape[0])


# the time targets' renderer sides, timed against ResNet-18 in alternation: (shape, K, shading)
PAIRED_TARGETS = {"hard": ("torus-20k", 1), "smooth": ("torus-20k", 8, "smooth"), "flat": ("torus-20k", 8, "flat"),
                  "points": ("points-2048", 8)}

# LOD budgets measured: None is the renderer's default rule (faces per pixel row, silhouette-checked),
# the others the former rule (faces per image pixel)
LOD_FACES_PER_PIXEL = (None, 0.5, 0.25, 0.125)


def renderer_for(shape, size: int, K: int, shading: str = "flat", **extra) -> MultiViewRenderer:
    """The grid's renderer: eager unless ``compile=True`` is passed (the compiled rows are their own)."""
    extra.setdefault("compile", False)
    if isinstance(shape, Meshes):
        mode = dict(mode="hard") if K == 1 else dict(mode="soft", faces_per_pixel=K, shading=shading)
        return MultiViewRenderer(image_size=size, **mode, **extra).eval()
    return MultiViewRenderer(image_size=size, points_per_pixel=K, **extra).eval()


# ---------------------------------------------------------------------------- timing
def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def timed(fn: Callable[[], object], device: torch.device) -> float:
    _sync(device)
    t0 = time.perf_counter()
    fn()
    _sync(device)
    return time.perf_counter() - t0


def paired_times(a: Callable[[], object], b: Callable[[], object], device: torch.device, repeats: int,
                 budget_s: float) -> tuple[list[float], list[float]]:
    """Seconds of ``a`` and ``b`` timed in alternation (one warm-up each; the side that goes first
    alternates), at least 5 rounds and up to ``repeats`` within ``budget_s`` a round: a load change
    hits both sides alike, and ``paired_ratio`` takes the median of the rounds' ratios."""
    a(), b()
    ta, tb = [timed(a, device)], [timed(b, device)]
    n = max(5, min(int(repeats), int(budget_s / max(ta[0] + tb[0], 1e-9))))
    while len(ta) < n:
        first, second = ((a, ta), (b, tb)) if len(ta) % 2 == 0 else ((b, tb), (a, ta))
        for fn, out in (first, second):
            out.append(timed(fn, device))
    return ta, tb


def time_runs(fn: Callable[[], object], device: torch.device, repeats: int, budget_s: float) -> list[float]:
    """Seconds of up to ``repeats`` runs (the caller has warmed ``fn`` up); slow functions run fewer times."""
    times = [timed(fn, device)]
    n = max(1, min(int(repeats), int(budget_s / max(times[0], 1e-9))))
    while len(times) < n:
        times.append(timed(fn, device))
    return times


def paired_ratio(times: tuple[list[float], list[float]]) -> float:
    """Ratio of side a to side b: the median of the per-round ratios when both were timed in
    alternation (``paired_times``: equal lengths), else the ratio of the medians. Each round times
    both sides within a moment, so a load that changes between rounds cancels in its ratio; the
    ratio of medians can pair one side's quiet rounds with the other's loaded ones."""
    a, b = times
    if len(a) == len(b) and len(a) > 1:
        return statistics.median(x / y for x, y in zip(a, b))
    return statistics.median(a) / statistics.median(b)


def med_ms(times_s: list[float] | None) -> float:
    return float("nan") if not times_s else 1000.0 * statistics.median(times_s)


def peak_of(fn: Callable[[], object], device: torch.device) -> tuple[float, float]:
    """(extra peak MiB, seconds) of one run of ``fn``."""
    gc.collect()
    with PeakMemory(device) as pm:
        t = timed(fn, device)
    return pm.peak_mib, t


class Views:
    """Spherical views ``[B, M]``; ``grad`` copies of azim/elev are leaves that require grad."""

    def __init__(self, M: int, B: int, device):
        self.azim, self.elev, self.dist = layouts.spherical(M, batch=B, distance=2.2, device=device, sphere="fibonacci")
        self.azim_g = self.azim.clone().requires_grad_(True)
        self.elev_g = self.elev.clone().requires_grad_(True)


def render_fns(r: MultiViewRenderer, shape, v: Views):
    last = {}

    def fwd():
        with torch.no_grad():
            out = r(shape, v.azim, v.elev, v.dist)
        last["stats"] = out.stats

    def fwd_bwd():
        out = r(shape, v.azim_g, v.elev_g, v.dist)
        out.images.sum().backward()
        v.azim_g.grad = None
        v.elev_g.grad = None

    return fwd, fwd_bwd, last


# ---------------------------------------------------------------------------- the benchmark
@dataclass
class Results:
    meta: dict = field(default_factory=dict)
    grid: list = field(default_factory=list)
    resnet: list = field(default_factory=list)
    dense: list = field(default_factory=list)
    lod: list = field(default_factory=list)
    batch8: list = field(default_factory=list)
    paired: dict = field(default_factory=dict)  # target key -> (numerator s, denominator s), timed alternately
    compile_first_s: dict = field(default_factory=dict)  # shading -> seconds of the first compiled call
    edges: list = field(default_factory=list)
    modules: list = field(default_factory=list)
    paper_modules: dict = field(default_factory=dict)
    scaling: list = field(default_factory=list)
    paper_scale: dict = field(default_factory=dict)
    targets: list = field(default_factory=list)


class Bench:
    def __init__(self, opts: BenchOptions):
        if opts.device.startswith("cuda") and not torch.cuda.is_available():
            raise ValueError(f"device={opts.device!r}: CUDA is not available on this machine; use device=cpu")
        if opts.repeats < 1:
            raise ValueError(f"repeats={opts.repeats}: expected >= 1")
        self.opts = opts
        self.dev = torch.device(opts.device)
        self.grid = grid_for(opts)
        self.res = Results()
        self._shapes: dict[str, object] = {}
        self._rows: dict[tuple, dict] = {}

    # scenes are built once and reused
    def shape(self, name: str):
        if name not in self._shapes:
            if name.startswith("torus"):
                self._shapes[name] = torus(name, self.dev)
            else:
                self._shapes[name] = torus_points(int(name.split("-")[1]), self.opts.seed, self.dev)
        return self._shapes[name]

    def times(self, fn) -> list[float]:
        return time_runs(fn, self.dev, self.opts.repeats, self.opts.time_budget_s)

    # ------------------------------------------------------------------ jobs
    def resnet_fn(self, M: int, size: int) -> Callable[[], None]:
        """ResNet-18 forward+backward on ``M`` random images of ``size`` px (seeded)."""
        torch.manual_seed(self.opts.seed)
        net = resnet18(num_classes=40).to(self.dev).train()
        x = torch.rand(M, 3, size, size).to(self.dev)

        def fwd_bwd():
            net.zero_grad(set_to_none=True)
            net(x).sum().backward()

        return fwd_bwd

    def job_resnet(self, M: int, size: int) -> None:
        fwd_bwd = self.resnet_fn(M, size)
        fwd_bwd()  # warm-up
        t = self.times(fwd_bwd)
        self.res.resnet.append(dict(images=M, size=size, fwd_bwd_s=t))

    def grid_row(self, name: str, size: int, M: int, K: int, shading: str) -> dict:
        key = (name, size, M, K, shading)
        if key not in self._rows:
            shape = self.shape(name)
            self._rows[key] = dict(kind="mesh" if isinstance(shape, Meshes) else "points", shape=name, prims=prims_of(shape),
                                   size=size, views=M, K=K, shading=shading, peak_mib=None, memory_run_s=None, fwd_s=[],
                                   fwd_bwd_s=[], stats={})
            self.res.grid.append(self._rows[key])
        return self._rows[key]

    def job_render_memory(self, name: str, size: int, M: int, K: int, shading: str) -> None:
        """Phase 1: extra peak memory of one forward+backward (the config's first call)."""
        shape = self.shape(name)
        _, fwd_bwd, _ = render_fns(renderer_for(shape, size, K, shading), shape, Views(M, 1, self.dev))
        peak, t = peak_of(fwd_bwd, self.dev)
        self.grid_row(name, size, M, K, shading).update(peak_mib=peak, memory_run_s=t)

    def job_render_time(self, name: str, size: int, M: int, K: int, shading: str) -> None:
        """Phase 2: one warm-up forward+backward, then forward (no_grad) and forward+backward times."""
        shape = self.shape(name)
        fwd, fwd_bwd, last = render_fns(renderer_for(shape, size, K, shading), shape, Views(M, 1, self.dev))
        fwd_bwd()
        tf = self.times(fwd)
        tb = self.times(fwd_bwd)
        self.grid_row(name, size, M, K, shading).update(fwd_s=tf, fwd_bwd_s=tb, stats=_jsonable(last.get("stats", {})))

    def job_edge_error(self) -> None:
        """Soft-edge coverage and colour error at K=8 against the every-face reference (``edge_error``)."""
        cases = edge_error.default_cases()[2:3] if self.opts.quick else edge_error.default_cases()
        for meshes, size in cases:
            for shading in SOFT_SHADINGS + ("silhouette",):
                self.res.edges.append(asdict(edge_error.measure(meshes, size=size, shading=shading, K=8)))

    def job_dense(self, name: str, size: int, M: int) -> None:
        mesh = self.shape(name)
        r = renderer_for(mesh, size, 1)
        v = Views(M, 1, self.dev)
        with torch.no_grad():
            pf = r.project_faces(mesh, v.azim, v.elev, v.dist)[0]
        pairs = dense_pairs(pf, size, size)
        row = dict(shape=name, prims=prims_of(mesh), size=size, views=M, pairs=pairs)
        if pairs > self.opts.dense_max_pairs:
            row.update(dense_s=None, search_s=None, identical=None)
            self.res.dense.append(row)
            return
        c = r.cfg

        def search():
            return mesh_raster.search_faces(pf, H=size, W=size, K=1, blur_radius=0.0, tile_size=c.tile_size,
                                            max_candidates=c.max_candidates)

        def dense():
            return dense_search(pf, H=size, W=size)

        a, b = search(), dense()  # warm-ups, also the equality check
        identical = bool(torch.equal(a.pix, b.pix) and torch.equal(a.prim, b.prim))
        del a, b
        row.update(search_s=self.times(search), dense_s=self.times(dense), identical=identical)
        self.res.dense.append(row)

    def job_lod(self, name: str, fpp: float) -> None:
        g = self.grid
        size, M = g.target_size, g.target_views
        mesh = self.shape(name)
        base = renderer_for(mesh, size, 1)
        r = renderer_for(mesh, size, 1, lod=True, lod_faces_per_pixel=fpp)
        v = Views(M, 1, self.dev)
        c = r.cfg
        budget = lod.face_budget(size, c.lod_faces_per_row, c.lod_faces_per_pixel)
        # one-off: the simplification (and its silhouette check) the renderer caches (this call fills the cache)
        t0 = time.perf_counter()
        simple = lod.simplify_meshes(mesh, budget, size, c.lod_min_iou)
        simplify_s = time.perf_counter() - t0
        fwd, fwd_bwd, _ = render_fns(r, mesh, v)
        first_s = timed(fwd_bwd, self.dev)  # first (cached) call: warm-up, not timed
        t_lod = self.times(fwd_bwd)
        ref = self.find_grid(name, size, M, 1)
        if ref is None or not ref["fwd_bwd_s"]:  # not in the grid: measure without LOD here
            _, fb0, _ = render_fns(base, mesh, v)
            fb0()
            t_ref = self.times(fb0)
        else:
            t_ref = ref["fwd_bwd_s"]
        with torch.no_grad():
            a = base(mesh, v.azim, v.elev, v.dist)
            b = r(mesh, v.azim, v.elev, v.dist)
        mae = float((a.images - b.images).abs().mean())
        ma, mb = a.alpha > 0.5, b.alpha > 0.5
        union = int((ma | mb).sum())
        iou = float(int((ma & mb).sum()) / union) if union else 1.0
        faces_after = int(b.stats["lod_faces"][1]) if "lod_faces" in b.stats else int(simple.faces_per_shape.sum())
        self.res.lod.append(dict(shape=name, fpp=fpp, prims=prims_of(mesh), faces_after=faces_after, budget=budget, size=size,
                                 views=M, K=1, no_lod_fwd_bwd_s=t_ref, lod_fwd_bwd_s=t_lod, simplify_s=simplify_s,
                                 first_call_s=first_s, image_mae=mae, silhouette_iou=iou))

    def job_paired_targets(self) -> None:
        """Each time target's two sides (the renderer and ResNet-18, or the 100k and the 2k mesh)
        timed again in alternation (``paired_times``): the Targets table's ratios are same-run ratios."""
        g = self.grid
        S, M = g.target_size, g.target_views
        resnet_fwd_bwd = self.resnet_fn(M, S)

        def render(name, K, shading="flat", **extra):
            shape = self.shape(name)
            return render_fns(renderer_for(shape, S, K, shading, **extra), shape, Views(M, 1, self.dev))[1]

        sides = {key: (lambda k=key: render(*PAIRED_TARGETS[k]), resnet_fwd_bwd) for key in ("hard", "smooth", "flat", "points")}
        small = render("torus-2k", 1)
        sides["100k"] = (lambda: render("torus-100k", 1), small)
        sides["100k_lod"] = (lambda: render("torus-100k", 1, lod=True), small)
        for key, (make, den) in sides.items():
            self.res.paired[key] = paired_times(make(), den, self.dev, self.opts.repeats, 2 * self.opts.time_budget_s)
        if self.opts.compiled and accel.unavailable(self.dev.type) is None:
            for shading in ("smooth", "flat"):
                fn = render(*PAIRED_TARGETS[shading], compile=True)
                t0 = time.perf_counter()
                fn()  # compiles (or loads torch's on-disk compile cache)
                self.res.compile_first_s[shading] = time.perf_counter() - t0
                self.res.paired[f"{shading}_compiled"] = paired_times(fn, resnet_fwd_bwd, self.dev, self.opts.repeats,
                                                                      2 * self.opts.time_budget_s)

    def job_batch8(self, kind: str) -> None:
        g = self.grid
        size, M, B = g.target_size, g.target_views, 8
        if kind == "mesh":
            src, K = self.shape("torus-20k"), 1
            shapes = Meshes.from_list(rotated_copies_y(src.verts, B), [src.faces] * B, names=[f"torus-20k/{k}" for k in range(B)])
        else:
            src, K = self.shape("points-2048"), 8
            shapes = PointClouds.from_list(rotated_copies_y(src.points, B), names=[f"points-2048/{k}" for k in range(B)])
        r = renderer_for(shapes, size, K)
        v = Views(M, B, self.dev)
        _, fwd_bwd, _ = render_fns(r, shapes, v)
        peak, t = peak_of(fwd_bwd, self.dev)
        self.res.batch8.append(dict(kind=kind, shape=shape_label(src), prims=prims_of(src), batch=B, size=size, views=M,
                                    K=K, peak_mib=peak, time_s=t))

    # ------------------------------------------------------------------ plan
    def jobs(self) -> list[tuple[str, Callable[[], None]]]:
        """Phase 1 (memory, allocator pinned as the process started) then phase 2 (times, allocator in speed mode)."""
        g = self.grid
        configs = [(name, size, M, K, sh) for name in list(g.meshes) + [f"points-{n}" for n in g.points]
                   for size in g.sizes for M in g.views for K in g.ks
                   for sh in (SOFT_SHADINGS if K > 1 and name in g.meshes else ("flat",))]
        out = [(f"memory {n} {s}px M={m} K={k} {sh}", lambda a=(n, s, m, k, sh): self.job_render_memory(*a))
               for n, s, m, k, sh in configs]
        if g.batch8:
            out += [(f"memory batch8 {k}", lambda k=k: self.job_batch8(k)) for k in ("mesh", "points")]
        if self.opts.scaling:
            out.append(("scaling curves: memory", self.job_scaling_memory))
        if self.opts.paper_scale:  # (peaks read with the allocator pinned; its time ratios are same-mode ratios)
            out.append(("paper scale: B = 32 x 12 x 224 px", self.job_paper_scale))
        out.append(("switch allocator to speed mode", self.job_speed_mode))
        out += [(f"resnet18 {M}x{g.resnet_size}px", lambda M=M: self.job_resnet(M, g.resnet_size)) for M in g.views]
        out += [(f"time {n} {s}px M={m} K={k} {sh}", lambda a=(n, s, m, k, sh): self.job_render_time(*a))
                for n, s, m, k, sh in configs]
        out += [(f"dense {name} {size}px M={M}", lambda a=(name, size, M): self.job_dense(*a))
                for name in g.meshes for size in g.sizes for M in g.views]
        out += [(f"lod {name} {'default' if fpp is None else f'{fpp} faces/px'}", lambda n=name, f=fpp: self.job_lod(n, f))
                for name in g.lod_meshes for fpp in LOD_FACES_PER_PIXEL]
        if not self.opts.quick:  # (the quick grid has no target configuration)
            out.append(("targets: both sides timed in alternation", self.job_paired_targets))
        out.append(("soft edge error", self.job_edge_error))
        if self.opts.modules:
            out.append(("module table", self.job_modules))
            out.append(("the paper's time and memory tables", self.job_paper_modules))
        if self.opts.scaling:
            out.append(("scaling curves: time", self.job_scaling_time))
        return out

    def job_paper_scale(self) -> None:
        from . import paper_scale

        self.res.paper_scale = paper_scale.measure(self.dev)

    def job_scaling_memory(self) -> None:
        from .scaling import Scaling

        self._scaling = Scaling(self.opts.quick, self.dev, self.opts.repeats, self.opts.time_budget_s)
        self._scaling.measure_memory()

    def job_scaling_time(self) -> None:
        self._scaling.measure_time()
        self.res.scaling = self._scaling.fits()

    def job_modules(self) -> None:
        from .modules import module_rows  # modules.py builds on this file's helpers

        self.res.modules = module_rows(self.opts.quick, self.dev, self.opts.repeats, self.opts.time_budget_s, self.opts.seed)

    def job_paper_modules(self) -> None:
        from .paper_modules import paper_module_rows  # paper_modules.py builds on this file's helpers

        self.res.paper_modules = paper_module_rows(self.opts.quick, self.dev, self.opts.repeats, self.opts.time_budget_s,
                                                   self.opts.seed)

    def job_speed_mode(self) -> None:
        self.res.meta["timing_malloc"] = ("glibc mmap threshold 32 MiB, trim 64 MiB (set with mallopt)"
                                          if set_malloc_mode("speed") else "unchanged (mallopt unavailable)")

    def find_grid(self, shape: str, size: int, M: int, K: int, shading: str = "flat"):
        for row in self.res.grid:
            if (row["shape"], row["size"], row["views"], row["K"], row["shading"]) == (shape, size, M, K, shading):
                return row
        return None

    def run(self) -> Results:
        from tqdm import tqdm

        t0 = time.perf_counter()
        self.res.meta = environment(self.opts, self.dev)
        jobs = self.jobs()
        bar = tqdm(jobs, desc="mvtn-bench", unit="cfg", file=sys.stderr, disable=None if self.opts.progress else True, dynamic_ncols=True)
        for label, job in bar:
            bar.set_postfix_str(label, refresh=True)
            job()
        bar.close()
        self.res.targets = targets(self)
        self.res.meta["elapsed_s"] = time.perf_counter() - t0
        return self.res


# ---------------------------------------------------------------------------- targets
def _target(name, value_txt, limit_txt, ok, reason=None, value=None, limit=None):
    status = f"n/a ({reason})" if ok is None else ("PASS" if ok else "MISS")
    return dict(target=name, value=value_txt, limit=limit_txt, status=status, measured=value, threshold=limit)


def targets(bench: Bench) -> list[dict]:
    g = bench.grid
    S, M = g.target_size, g.target_views
    res = bench.res
    quick = "not in this grid (quick=true)" if bench.opts.quick else "not measured"
    net = next((r for r in res.resnet if r["images"] == M and r["size"] == S), None)
    out = []

    def pair(key, num_row, den_s):
        """(numerator s, denominator s): timed in alternation when measured so, else from their own rows."""
        if key in res.paired:
            return res.paired[key]
        return (num_row["fwd_bwd_s"], den_s) if num_row is not None and den_s is not None else None

    def vs_resnet(title, key, row, factor):
        times = pair(key, row, net["fwd_bwd_s"] if net else None)
        if times is None:
            return _target(title, "-", f"<= {factor:g} x ResNet-18", None, quick)
        ms, net_ms = med_ms(times[0]), med_ms(times[1])
        ratio = paired_ratio(times)
        return _target(title, f"{ms:.1f} ms vs ResNet-18 {net_ms:.1f} ms: {ratio:.3f} x",
                       f"<= {factor:g} x ({factor * net_ms:.1f} ms)", ratio <= factor, value=ratio, limit=factor)

    out.append(vs_resnet(f"20k-face mesh, {M} views, {S} px, K=1: fwd+bwd vs ResNet-18 fwd+bwd on {M} images", "hard",
                         bench.find_grid("torus-20k", S, M, 1), 0.15))
    default_compiles = accel.auto_compiles(bench.dev.type, True, S)  # what renderer.compile=null runs for these rows
    for shading, factor in (("smooth", 1.0), ("flat", 1.0)):
        out.append(vs_resnet(f"20k-face mesh, {M} views, {S} px, soft K=8 {shading}, eager (renderer.compile=false"
                             + ("" if default_compiles else "; the default here") + f"): fwd+bwd vs ResNet-18 fwd+bwd on {M} images",
                             shading, bench.find_grid("torus-20k", S, M, 8, shading), factor))
    unavailable = accel.unavailable(bench.dev.type)
    for shading in ("smooth", "flat"):
        key = f"{shading}_compiled"
        first = res.compile_first_s.get(shading)
        title = (f"20k-face mesh, {M} views, {S} px, soft K=8 {shading}, renderer.compile=true"
                 + ("; the default here (null)" if default_compiles else "")
                 + (f" (first call {first:.1f} s{', after the smooth row compiled the shared parts' if shading == 'flat' else ''})"
                    if first is not None else "") + f": fwd+bwd vs ResNet-18 fwd+bwd on {M} images")
        if key in res.paired:
            out.append(vs_resnet(title, key, None, 1.0))
        else:
            why = quick if bench.opts.quick else (unavailable or ("compiled=false" if not bench.opts.compiled else "not measured"))
            out.append(_target(title, "-", "<= 1 x ResNet-18", None, why))
    out.append(vs_resnet(f"2048 points, {M} views, {S} px, K=8: fwd+bwd vs ResNet-18 fwd+bwd on {M} images", "points",
                         bench.find_grid("points-2048", S, M, 8), 0.1))

    small, big = bench.find_grid("torus-2k", S, M, 1), bench.find_grid("torus-100k", S, M, 1)
    lod_big = next((r for r in res.lod if r["shape"] == "torus-100k" and r["fpp"] == LOD_FACES_PER_PIXEL[0]), None)
    lod_row = dict(fwd_bwd_s=lod_big["lod_fwd_bwd_s"]) if lod_big else None
    for key, label, row in (("100k", "without LOD", big), ("100k_lod", "with LOD (the renderer's default)", lod_row)):
        title = f"100k-face vs 2k-face mesh, {S} px, {M} views, K=1 fwd+bwd, {label}"
        times = pair(key, row, small["fwd_bwd_s"] if small else None)
        if times is None:
            out.append(_target(title, "-", "<= 2 x", None, quick))
            continue
        a, b, ratio = med_ms(times[0]), med_ms(times[1]), paired_ratio(times)
        note = " (2k is under the LOD budget: unchanged)" if label.startswith("with LOD") else ""
        out.append(_target(title, f"{a:.1f} ms / {b:.1f} ms: {ratio:.2f} x{note}", "<= 2 x", ratio <= 2.0, value=ratio, limit=2.0))

    for kind, desc in (("mesh", "20k-face mesh, K=1"), ("points", "2048 points, K=8")):
        title = f"batch of 8 x {M} views x {S} px, fwd+bwd extra peak memory: {desc}"
        row = next((r for r in res.batch8 if r["kind"] == kind), None)
        if row is None:
            out.append(_target(title, "-", f"<= {LIMIT_MIB:.0f} MiB", None, quick))
            continue
        out.append(_target(title, f"{row['peak_mib']:.0f} MiB", f"<= {LIMIT_MIB:.0f} MiB", row["peak_mib"] <= LIMIT_MIB,
                           value=row["peak_mib"], limit=LIMIT_MIB))
    if res.paper_scale:
        from . import paper_scale

        out += [_target(*row) for row in paper_scale.targets(res.paper_scale, bench.dev.type == "cuda")]
    return out


# ---------------------------------------------------------------------------- reporting
def environment(opts: BenchOptions, dev: torch.device) -> dict:
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((l.split(":", 1)[1].strip() for l in f if l.startswith("model name")), cpu)
    except OSError:
        pass
    meta = dict(date=datetime.now().isoformat(timespec="seconds"), options=asdict(opts), grid=asdict(grid_for(opts)),
                torch=torch.__version__, python=platform.python_version(), device=str(dev), threads=torch.get_num_threads(),
                cpu=cpu, cpu_count=os.cpu_count(), malloc=malloc_threshold_note())
    if dev.type == "cuda":
        meta["gpu"] = torch.cuda.get_device_name(dev)
    return meta


def _jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, (bool, int, str)) or obj is None:
        return obj
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if torch.is_tensor(obj):
        return _jsonable(obj.tolist())
    if isinstance(obj, (np.generic,)):
        return _jsonable(obj.item())
    return str(obj)


def md_table(headers: list[str], rows: list[list]) -> str:
    lines = ["| " + " | ".join(headers) + " |", "|" + "|".join("---" for _ in headers) + "|"]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def _f1(x) -> str:
    return "-" if x is None else f"{x:.1f}"


def f_ms(times_s) -> str:
    return "-" if not times_s else f"{med_ms(times_s):.1f}"


def to_markdown(res: Results) -> str:
    m = res.meta
    o = m["options"]
    dev = m["device"] + (f" ({m['gpu']})" if "gpu" in m else f" ({m['cpu']}, {m['cpu_count']} cores)")
    head = [
        "# mvtn-bench: renderer speed and memory",
        "",
        f"- date: {m['date']}; device: {dev}; torch {m['torch']}, {m['threads']} threads; python {m['python']}",
        f"- grid: {'quick' if o['quick'] else 'full'}; {m['malloc']}",
        f"- times: median of up to {o['repeats']} runs after one warm-up; a config whose first run takes t s runs "
        f"max(1, min({o['repeats']}, floor({o['time_budget_s']:g} / t))) times; allocator while timing: {m.get('timing_malloc', '-')}",
        "- memory (measured first, each config's first call): extra peak over the memory at the start of one forward+backward "
        + ("(CUDA max_memory_allocated)" if m["device"].startswith("cuda") else "(process RSS: sampled every 0.5 ms + VmHWM)"),
        f"- total time: {m.get('elapsed_s', float('nan')):.0f} s",
    ]
    parts = ["\n".join(head)]

    rows = [[r["shape"], r["prims"], r["size"], r["views"], r["K"], r["shading"] if r["kind"] == "mesh" else "-",
             f_ms(r["fwd_s"]), f_ms(r["fwd_bwd_s"]), _f1(r["peak_mib"]), r["stats"].get("active_pixels", "-"),
             r["stats"].get("slots", "-"), r["stats"].get("rest_faces", "-"), f"{len(r['fwd_s'])}/{len(r['fwd_bwd_s'])}"]
            for r in res.grid]
    parts.append("## Renderer grid (B=1, spherical views; mesh K=1: hard flat, K=8: soft, flat and smooth; points K: points per pixel)\n\n"
                 + md_table(["shape", "faces/points", "px", "M", "K", "shading", "fwd ms", "fwd+bwd ms", "extra peak MiB (fwd+bwd)",
                             "active px", "soft slots", "soft rest faces", "runs fwd/fb"], rows))

    rows = [[r["images"], r["size"], f_ms(r["fwd_bwd_s"]), len(r["fwd_bwd_s"])] for r in res.resnet]
    parts.append("## ResNet-18 reference (40 classes, train mode, forward+backward)\n\n"
                 + md_table(["images", "px", "fwd+bwd ms", "runs"], rows))

    rows = []
    for r in res.dense:
        if r["dense_s"] is None:
            rows.append([r["shape"], r["prims"], r["size"], r["views"], f"{r['pairs']:.3g}",
                         f"n/a (too large: {r['pairs']} pairs)", "-", "-", "-"])
        else:
            rows.append([r["shape"], r["prims"], r["size"], r["views"], f"{r['pairs']:.3g}", f_ms(r["dense_s"]), f_ms(r["search_s"]),
                         f"{med_ms(r['dense_s']) / med_ms(r['search_s']):.1f} x", "yes" if r["identical"] else "NO"])
    o_pairs = f"{o['dense_max_pairs']:.3g}"
    parts.append(f"## Dense reference vs search_faces (hard K=1 search only, same projected faces; dense only where pairs <= {o_pairs})\n\n"
                 + md_table(["mesh", "faces", "px", "M", "pixel x face pairs", "dense ms", "search_faces ms", "speed-up", "identical"], rows))

    if res.lod:
        rows = []
        for r in res.lod:
            a, b = med_ms(r["no_lod_fwd_bwd_s"]), med_ms(r["lod_fwd_bwd_s"])
            after = f"{r['faces_after']}" + (" (kept whole)" if r["faces_after"] == r["prims"] else "")
            rule = "default: 32 per row, checked" if r["fpp"] is None else f"{r['fpp']:g} per pixel"
            rows.append([r["shape"], r["prims"], rule, after, r["budget"], f"{a:.1f}", f"{b:.1f}", f"{a / b:.2f} x", f"{r['simplify_s']:.2f}",
                         f"{r['first_call_s']:.2f}", f"{r['image_mae']:.4f}", f"{r['silhouette_iou']:.4f}"])
        S, M = res.lod[0]["size"], res.lod[0]["views"]
        parts.append(f"## Level of detail ({S} px, {M} views, K=1, forward+backward)\n\n"
                     + md_table(["mesh", "faces", "budget rule", "faces after LOD", "budget", "no LOD ms", "LOD ms", "speed-up", "simplify s (one-off)",
                                 "first LOD call s", "image MAE", "silhouette IoU"], rows)
                     + "\n\nLOD times exclude the first call; the simplification is timed once on its own (it is cached afterwards). "
                     "The default rule keeps a simplification only if its silhouettes keep IoU >= renderer.lod_min_iou.")
    else:
        parts.append("## Level of detail\n\nnot run (quick=true)")

    if res.batch8:
        rows = [[r["kind"], r["shape"], r["prims"], r["batch"], r["views"], r["size"], r["K"], f"{r['peak_mib']:.1f}", f"{r['time_s']:.2f}"]
                for r in res.batch8]
        parts.append("## Batch of 8 shapes (copies rotated about Y), forward+backward memory\n\n"
                     + md_table(["kind", "shape", "faces/points", "B", "M", "px", "K", "extra peak MiB", "time s (memory run)"], rows))
    else:
        parts.append("## Batch of 8 shapes\n\nnot run (quick=true)")

    rows = [[r["shape"], r["size"], r["shading"], r["edge_pixels"], f"{100 * r['cov_off']:.2f}%", f"{r['cov_max']:.1e}",
             f"{100 * r['rgb_off']:.2f}%", f"{r['rgb_max']:.1e}", r["faces"]] for r in res.edges]
    parts.append(f"## Soft edges: K=8 against every face within the blur radius (edge pixels: reference coverage in "
                 f"[{edge_error.EDGE_LO:g}, 1 - {edge_error.EDGE_LO:g}]; 4 spherical views)\n\n"
                 + md_table(["mesh", "px", "shading", "edge pixels", f"coverage off > {edge_error.TOL:g}", "max coverage error",
                             f"colour off > {edge_error.TOL:g}", "max colour error", "most faces in a pixel"], rows))

    if res.modules:
        from .modules import markdown as modules_markdown

        parts.append(modules_markdown(res.modules))
    if res.paper_modules:
        from .paper_modules import markdown as paper_modules_markdown

        parts.append(paper_modules_markdown(res.paper_modules, m["device"]))
    if res.paper_scale:
        from . import paper_scale

        parts.append(paper_scale.markdown(res.paper_scale, m["device"].startswith("cuda")))
    if res.scaling:
        from .scaling import markdown as scaling_markdown

        parts.append(scaling_markdown(res.scaling, o["quick"]) + "\n\nPlotted in `scaling.png` beside this file.")
    rows = [[t["target"], t["value"], t["limit"], t["status"]] for t in res.targets]
    times = (f"Times: each target's two sides timed in alternation in one job ({min(len(t[0]) for t in res.paired.values())}+ "
             "rounds); the times are each side's median, the ratio the median of the rounds' ratios, so a "
             "load change between rounds cancels."
             if res.paired else "Times: from the grid and ResNet-18 rows above.")
    parts.append("## Targets\n\n" + md_table(["target", "measured", "limit", "status"], rows) + "\n\n" + times)
    return "\n\n".join(parts) + "\n"


def write_outputs(res: Results, out_dir: Path) -> tuple[Path, Path, str]:
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    md = to_markdown(res)
    md_path = out_dir / "bench.md"
    md_path.write_text(md)
    js = out_dir / "bench.json"
    js.write_text(json.dumps(_jsonable(asdict(res)), indent=1))
    if res.scaling:
        from .scaling import plot

        plot(res.scaling, out_dir / "scaling.png")
    return md_path, js, md


def run_bench(opts: BenchOptions, out_dir: Path) -> Path:
    """Run the benchmark, print the Markdown to stdout, write bench.md / bench.json; returns bench.md's path."""
    res = Bench(opts).run()
    md_path, _, md = write_outputs(res, out_dir)
    print(md, flush=True)
    print(md_path.resolve(), flush=True)
    return md_path
