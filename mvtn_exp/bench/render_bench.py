"""The renderer benchmark behind ``mvtn-bench``: the grid it measures for speed and extra peak memory.

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
batch of 8 shapes x 12 views x 224 px, and both sides of every time target timed again in
alternation (``timing.paired_times``). The scenes are ``scenes.py``'s; ``render_report.py`` makes the
targets (PASS/MISS), bench.md and bench.json of the results.
"""
from __future__ import annotations

import os
import platform
import sys
import time
from dataclasses import asdict, dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Callable

import torch

from ..data.shapes import Meshes, PointClouds
from ..models.backbones import resnet18
from ..render import accel, lod, mesh_raster
from ..runtime.memory import malloc_threshold_note, set_malloc_mode
from . import edge_error
from .dense import dense_pairs, dense_search
from .render_report import _jsonable, targets, write_outputs
from .scenes import (LOD_FACES_PER_PIXEL, PAIRED_TARGETS, Views, prims_of, render_fns, renderer_for, rotated_copies_y,
                     shape_label, torus, torus_points)
from .timing import paired_times, peak_of, time_runs, timed

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
        from .modules import module_rows  # (imported when the job runs)

        self.res.modules = module_rows(self.opts.quick, self.dev, self.opts.repeats, self.opts.time_budget_s, self.opts.seed)

    def job_paper_modules(self) -> None:
        from .paper_modules import paper_module_rows  # (imported when the job runs)

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


# ---------------------------------------------------------------------------- the run
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


def run_bench(opts: BenchOptions, out_dir: Path) -> Path:
    """Run the benchmark, print the Markdown to stdout, write bench.md / bench.json; returns bench.md's path."""
    res = Bench(opts).run()
    md_path, _, md = write_outputs(res, out_dir)
    print(md, flush=True)
    print(md_path.resolve(), flush=True)
    return md_path
