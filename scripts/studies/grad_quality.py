"""Camera-gradient quality: autograd's d(loss)/d(azim, elev, dist) against central finite differences.

The loss of view (b, m) is a fixed random linear functional of its whole image,
``L_bm = sum(W_bm * images_bm)`` (and, separately, of the coverage ``alpha``), with ``W`` drawn
once from a seeded generator (uniform in [0, 1) by default). A view's image depends on its own
camera only, so one render with *every* camera moved by +h (and one by -h) gives the central
difference of every view at once: 2 forward passes per parameter and step, whatever B and M.

Per renderer setting (hard/soft x flat/smooth, soft silhouette; the renderer in ``eval()`` mode, so
light and colour are deterministic) it reports, over all B x M views:

* the cosine between the autograd and FD vectors, per parameter and for (azim, elev) together,
  and the median over shapes of the per-shape (azim, elev) cosine,
* ``|autograd| / |FD|`` (vector norms), and the cosine between FD at step h and FD at the first step
  (FD's own stability: hard rasterisation is piecewise constant in the camera),
* forward+backward milliseconds in float32 (the training dtype: median after one warm-up) and of
  the float64 autograd pass.

Angles are perturbed by h degrees; distance by ``dist * radians(h)`` world units (the camera moves
as far along its ray as sideways for an angle step h). Derivatives are per degree / per world unit.

A second table probes the pole: |dL/d elev| and |dL/d azim| at elevation 90, 89.9999, -90, 0, 45
(azimuth fixed) for hard and soft smooth shading, autograd (float64 and float32) against FD with
several steps, with the number of shapes where FD agrees with autograd to 5% (a jump in the image
within +-h shows up as an FD value that grows like 1/h, not as a derivative). At elevation exactly
+-90 a change of azimuth rotates the image about the view axis, so a large azimuth derivative there
is real.

Run: ``python scripts/studies/grad_quality.py`` (Markdown on stdout, JSON under
``outputs/bench/grad_quality/``); ``--help`` lists the options.
"""
from __future__ import annotations

import argparse
import json
import math
import platform
import statistics
import sys
import time
from dataclasses import asdict, dataclass, field
from datetime import datetime
from pathlib import Path

import numpy as np
import torch

from mvtn_exp.data.mesh_io import normalize_unit_sphere
from mvtn_exp.data.shapes import Meshes
from mvtn_exp.render.cameras import Cameras
from mvtn_exp.render.renderer import MultiViewRenderer
from mvtn_exp.bench.render_report import _jsonable, md_table

SETTINGS = {
    "hard_flat": dict(mode="hard", shading="flat"),
    "hard_smooth": dict(mode="hard", shading="smooth"),
    "soft_flat": dict(mode="soft", shading="flat"),
    "soft_smooth": dict(mode="soft", shading="smooth"),
    "soft_silhouette": dict(mode="soft", shading="silhouette"),
}
PARAMS = ("azim", "elev", "dist")
LOSSES = ("images", "alpha")
DTYPES = {"float64": torch.float64, "float32": torch.float32}
# pole table: FD "agrees" with autograd for a shape when |autograd - FD| <= AGREE_REL |autograd| + AGREE_ABS
AGREE_REL, AGREE_ABS = 0.05, 1e-3


@dataclass
class GradOptions:
    """What to measure. ``big``: also the 224 px / 20k-face torus scene (``big_h``: its steps)."""

    size: int = 64
    views: int = 4
    shapes: int = 8
    h: tuple[float, ...] = (0.5, 0.1)
    modes: tuple[str, ...] = tuple(SETTINGS)
    dist: float = 2.2
    dtype: str = "float64"
    weights: str = "uniform"
    seed: int = 0
    big: bool = True
    big_size: int = 224
    big_views: int = 4
    big_h: tuple[float, ...] = (0.5,)
    pole: bool = True
    pole_modes: tuple[str, ...] = ("hard_smooth", "soft_smooth")
    pole_elevs: tuple[float, ...] = (90.0, 89.9999, -90.0, 0.0, 45.0)
    pole_h: tuple[float, ...] = (0.001, 0.01, 0.1, 1.0)
    pole_azim: float = 30.0
    repeats: int = 3
    time_budget_s: float = 2.0
    cache_dir: str = "outputs/cache/synthetic"
    progress: bool = True

    def validate(self) -> "GradOptions":
        bad = [m for m in (*self.modes, *self.pole_modes) if m not in SETTINGS]
        if bad:
            raise ValueError(f"grad_quality: unknown mode(s) {bad}; expected some of {list(SETTINGS)}")
        if self.dtype not in DTYPES:
            raise ValueError(f"grad_quality: dtype={self.dtype!r}; expected one of {list(DTYPES)}")
        if self.weights not in ("uniform", "normal"):
            raise ValueError(f"grad_quality: weights={self.weights!r}; expected uniform or normal")
        if min(self.size, self.views, self.shapes, self.repeats) < 1 or not self.h or min(self.h) <= 0:
            raise ValueError("grad_quality: size, views, shapes, repeats must be >= 1 and every h > 0")
        return self


# ---------------------------------------------------------------------------- scenes
@dataclass
class Scene:
    """B meshes with M views each: azim, elev, dist ``[B, M]`` (float64)."""

    name: str
    meshes: Meshes
    azim: torch.Tensor
    elev: torch.Tensor
    dist: torch.Tensor
    size: int

    @property
    def faces(self) -> list[int]:
        return [int(f) for f in self.meshes.faces_per_shape]


def synthetic_meshes(count: int, cache_dir: str | Path, dtype=torch.float64) -> Meshes:
    """The first ``count`` shapes of the synthetic test split with one shape per class (12 classes;
    ``count`` > 12 takes more per class), in the unit sphere, at most 2000 faces each."""
    from mvtn_exp.data.synthetic import CLASSES, SyntheticShapes

    per_class = max(1, math.ceil(count / len(CLASSES)))
    ds = SyntheticShapes(cache_dir, "test", num_per_class=(0, 0, per_class), seed=0, max_faces=2000, progress=False)
    # dataset order is class-major: take shape k of every class before shape k + 1 of any
    order = [c * per_class + k for k in range(per_class) for c in range(len(CLASSES))][:count]
    items = [ds[i] for i in order]
    return Meshes.from_list([torch.as_tensor(it["verts"]).to(dtype) for it in items],
                            [torch.as_tensor(it["faces"], dtype=torch.long) for it in items], names=[it["name"] for it in items])


def torus_20k(dtype=torch.float64) -> Meshes:
    """``trimesh.creation.torus(0.7, 0.3, 100, 100)``: 20,000 faces, normalised into the unit sphere."""
    import trimesh

    t = trimesh.creation.torus(major_radius=0.7, minor_radius=0.3, major_sections=100, minor_sections=100)
    v = normalize_unit_sphere(np.asarray(t.vertices, np.float64))
    return Meshes.from_list([torch.tensor(v, dtype=dtype)], [torch.tensor(np.asarray(t.faces), dtype=torch.long)], names=["torus-20k"])


def random_views(B: int, M: int, seed: int, dist: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Seeded generic views ``[B, M]``: azimuth uniform in [0, 360), elevation in [-60, 60] degrees."""
    g = torch.Generator().manual_seed(seed)
    azim = torch.rand(B, M, generator=g, dtype=torch.float64) * 360.0
    elev = torch.rand(B, M, generator=g, dtype=torch.float64) * 120.0 - 60.0
    return azim, elev, torch.full((B, M), float(dist), dtype=torch.float64)


def weights(shape, seed: int, kind: str) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    if kind == "normal":
        return torch.randn(shape, generator=g, dtype=torch.float64)
    return torch.rand(shape, generator=g, dtype=torch.float64)


# ---------------------------------------------------------------------------- measurements
class Probe:
    """Per-view losses ``[B, M]`` of one renderer on one scene (images and alpha), with W fixed."""

    def __init__(self, r: MultiViewRenderer, scene: Scene, dtype, seed: int, kind: str):
        self.r, self.scene, self.dtype = r, scene, dtype
        B, M = scene.azim.shape
        S = scene.size
        self.w = {"images": weights((B, M, 3, S, S), seed, kind).to(dtype), "alpha": weights((B, M, 1, S, S), seed + 1, kind).to(dtype)}
        self.meshes = scene.meshes.with_verts(scene.meshes.verts.to(dtype))
        self.out_dtype = None

    def losses(self, azim, elev, dist) -> dict[str, torch.Tensor]:
        out = self.r(self.meshes, azim, elev, dist)
        self.out_dtype = str(out.images.dtype).replace("torch.", "")
        return {"images": (out.images * self.w["images"]).flatten(2).sum(2), "alpha": (out.alpha * self.w["alpha"]).flatten(2).sum(2)}

    def cams(self):
        s = self.scene
        return s.azim.to(self.dtype), s.elev.to(self.dtype), s.dist.to(self.dtype)

    def autograd(self) -> tuple[dict[str, dict[str, torch.Tensor]], float]:
        """{loss: {param: dL_bm/dparam_bm [B, M]}} and the seconds of forward + the images backward."""
        leaves = [t.clone().requires_grad_(True) for t in self.cams()]
        t0 = time.perf_counter()
        L = self.losses(*leaves)
        grads = {}
        for i, name in enumerate(LOSSES):
            total = L[name].sum()
            if total.requires_grad:
                g = torch.autograd.grad(total, leaves, retain_graph=i + 1 < len(LOSSES), allow_unused=True)
            else:  # e.g. hard coverage: a mask, no graph at all
                g = (None,) * 3
            grads[name] = {p: (x if x is not None else torch.zeros_like(leaves[0])).detach().double() for p, x in zip(PARAMS, g)}
            if i == 0:
                seconds = time.perf_counter() - t0
        return grads, seconds

    @torch.no_grad()
    def fd(self, h: float, params=PARAMS) -> dict[str, dict[str, torch.Tensor]]:
        """Central differences {loss: {param: [B, M]}}; angle step h degrees, distance step dist * radians(h)."""
        base = list(self.cams())
        out = {name: {} for name in LOSSES}
        for p in params:
            j = PARAMS.index(p)
            delta = base[j] * math.radians(h) if p == "dist" else torch.full_like(base[j], h)
            plus, minus = list(base), list(base)
            plus[j], minus[j] = base[j] + delta, base[j] - delta
            Lp, Lm = self.losses(*plus), self.losses(*minus)
            for name in LOSSES:
                out[name][p] = ((Lp[name] - Lm[name]) / (plus[j] - minus[j])).double()  # the step as represented
        return out


def cosine(u: torch.Tensor, v: torch.Tensor) -> float | None:
    """Cosine of two flattened vectors; None when either is zero (no direction to compare)."""
    u, v = u.reshape(-1), v.reshape(-1)
    nu, nv = float(u.norm()), float(v.norm())
    return None if nu == 0 or nv == 0 else float(torch.dot(u, v)) / (nu * nv)


def norm_ratio(u: torch.Tensor, v: torch.Tensor) -> float | None:
    nv = float(v.norm())
    return None if nv == 0 else float(u.norm()) / nv


def compare(auto: dict[str, torch.Tensor], fd: dict[str, torch.Tensor], fd_ref: dict[str, torch.Tensor] | None) -> dict:
    """Cosines and norm ratios of autograd vs FD (per parameter, angles together, per shape)."""
    ang_a = torch.stack([auto["azim"], auto["elev"]], -1)  # [B, M, 2]
    ang_f = torch.stack([fd["azim"], fd["elev"]], -1)
    per_shape = [cosine(ang_a[b], ang_f[b]) for b in range(len(ang_a))]
    per_shape = [c for c in per_shape if c is not None]
    row = {f"cos_{p}": cosine(auto[p], fd[p]) for p in PARAMS}
    row.update({f"ratio_{p}": norm_ratio(auto[p], fd[p]) for p in PARAMS})
    row.update(cos_angles=cosine(ang_a, ang_f), ratio_angles=norm_ratio(ang_a, ang_f),
               median_shape_cos=statistics.median(per_shape) if per_shape else None,
               fd_cos_vs_ref=None if fd_ref is None else cosine(ang_f, torch.stack([fd_ref["azim"], fd_ref["elev"]], -1)))
    return row


def time_fwd_bwd(r: MultiViewRenderer, scene: Scene, repeats: int, budget_s: float) -> list[float]:
    """Seconds of float32 forward + backward of sum(images) to (azim, elev, dist): one warm-up, then
    up to ``repeats`` runs (fewer when one run takes more than ``budget_s / repeats``)."""
    meshes = scene.meshes.with_verts(scene.meshes.verts.float())

    def once():
        leaves = [t.float().clone().requires_grad_(True) for t in (scene.azim, scene.elev, scene.dist)]
        t0 = time.perf_counter()
        torch.autograd.grad(r(meshes, *leaves).images.sum(), leaves, allow_unused=True)
        return time.perf_counter() - t0

    once()  # warm-up
    times = [once()]
    n = max(1, min(repeats, int(budget_s / max(times[0], 1e-9))))
    while len(times) < n:
        times.append(once())
    return times


def grad_rows(scene: Scene, opts: GradOptions, steps: tuple[float, ...], log) -> list[dict]:
    dtype = DTYPES[opts.dtype]
    rows = []
    for mode in opts.modes:
        r = MultiViewRenderer(image_size=scene.size, **SETTINGS[mode]).eval()
        probe = Probe(r, scene, dtype, opts.seed + 17, opts.weights)
        t0 = time.perf_counter()
        auto, fb_s = probe.autograd()
        fds = {h: probe.fd(h) for h in steps}
        f32 = time_fwd_bwd(r, scene, opts.repeats, opts.time_budget_s)
        for loss in LOSSES:
            for k, h in enumerate(steps):
                ref = None if k == 0 else fds[steps[0]][loss]
                row = dict(scene=scene.name, setting=mode, loss=loss, h=h, dtype=probe.out_dtype, **compare(auto[loss], fds[h][loss], ref))
                row.update(fwd_bwd_ms_f32=1e3 * statistics.median(f32), fwd_bwd_ms_measured=1e3 * fb_s, runs_f32=len(f32))
                rows.append(row)
        log(f"{scene.name} {mode}: {time.perf_counter() - t0:.1f} s")
    return rows


def pole_rows(meshes: Meshes, opts: GradOptions, log) -> list[dict]:
    """|dL/d elev|, |dL/d azim| per view at the pole elevations, autograd (float64, float32) vs FD."""
    B, E = len(meshes.faces_per_shape), len(opts.pole_elevs)
    elev = torch.tensor(opts.pole_elevs, dtype=torch.float64).expand(B, E).clone()
    scene = Scene("pole", meshes, torch.full((B, E), opts.pole_azim, dtype=torch.float64), elev,
                  torch.full((B, E), opts.dist, dtype=torch.float64), opts.size)
    rows = []
    for mode in opts.pole_modes:
        t0 = time.perf_counter()
        r = MultiViewRenderer(image_size=opts.size, **SETTINGS[mode]).eval()
        probe = Probe(r, scene, DTYPES[opts.dtype], opts.seed + 29, opts.weights)
        auto, _ = probe.autograd()
        auto32, _ = Probe(r, scene, torch.float32, opts.seed + 29, opts.weights).autograd()
        fds = {h: probe.fd(h, params=("azim", "elev")) for h in opts.pole_h}
        for j, e in enumerate(opts.pole_elevs):
            for p in ("elev", "azim"):
                a = auto["images"][p][:, j]
                row = dict(setting=mode, elev=e, param=p, auto_median=float(a.abs().median()), auto_max=float(a.abs().max()),
                           auto_f32_median=float(auto32["images"][p][:, j].abs().median()), dtype=probe.out_dtype)
                for h in opts.pole_h:
                    f = fds[h]["images"][p][:, j]
                    row[f"fd_median_{h:g}"] = float(f.abs().median())
                    row[f"cos_{h:g}"] = cosine(a, f)
                    row[f"agree_{h:g}"] = int(((a - f).abs() <= AGREE_REL * a.abs() + AGREE_ABS).sum())
                row["shapes"] = len(a)
                rows.append(row)
        log(f"pole {mode}: {time.perf_counter() - t0:.1f} s")
    return rows


def frame_derivatives(elevs, azim: float) -> list[dict]:
    """Frobenius norm of dR/d elev and dR/d azim (per degree) of the analytic camera frame."""
    out = []
    for e in elevs:
        a = torch.tensor([[azim]], dtype=torch.float64, requires_grad=True)
        el = torch.tensor([[float(e)]], dtype=torch.float64, requires_grad=True)
        jac = torch.autograd.functional.jacobian(lambda x, y: Cameras(x, y, torch.full_like(x, 2.2)).frames()[0], (a, el))
        out.append(dict(elev=e, dR_dazim=float(jac[0].norm()), dR_delev=float(jac[1].norm())))
    return out


# ---------------------------------------------------------------------------- run + report
def run(opts: GradOptions, log=None) -> dict:
    """Measure everything ``opts`` asks for; returns ``{"meta", "scenes", "rows", "pole", "frame"}``."""
    opts.validate()
    log = log or (lambda msg: print(msg, file=sys.stderr, flush=True) if opts.progress else None)
    t0 = time.perf_counter()
    res = dict(meta=dict(date=datetime.now().isoformat(timespec="seconds"), options=asdict(opts), torch=torch.__version__,
                         python=platform.python_version(), threads=torch.get_num_threads()),
               scenes=[], rows=[], pole=[], frame=[])
    res["meta"]["renderers"] = {m: asdict(MultiViewRenderer(**SETTINGS[m]).cfg) for m in dict.fromkeys((*opts.modes, *opts.pole_modes))}
    meshes = synthetic_meshes(opts.shapes, opts.cache_dir)
    scenes = [(Scene(f"synthetic {opts.shapes}x{opts.views} @ {opts.size} px", meshes,
                     *random_views(opts.shapes, opts.views, opts.seed, opts.dist), opts.size), tuple(opts.h))]
    if opts.big:
        scenes.append((Scene(f"torus-20k 1x{opts.big_views} @ {opts.big_size} px", torus_20k(),
                             *random_views(1, opts.big_views, opts.seed + 1, opts.dist), opts.big_size), tuple(opts.big_h)))
    for scene, steps in scenes:
        res["scenes"].append(dict(name=scene.name, shapes=list(scene.meshes.names), faces=scene.faces,
                                  verts_abs_sum=float(scene.meshes.verts.double().abs().sum()),
                                  azim=scene.azim.tolist(), elev=scene.elev.tolist(), dist=opts.dist, size=scene.size, h=list(steps)))
        res["rows"] += grad_rows(scene, opts, steps, log)
    if opts.pole:
        res["pole"] = pole_rows(meshes, opts, log)
        res["frame"] = frame_derivatives(opts.pole_elevs, opts.pole_azim)
    res["meta"]["elapsed_s"] = time.perf_counter() - t0
    return res


def _f(x, fmt="{:.3f}") -> str:
    return "n/a" if x is None or (isinstance(x, float) and not math.isfinite(x)) else fmt.format(x)


def to_markdown(res: dict) -> str:
    o = res["meta"]["options"]
    dtype = res["rows"][0]["dtype"] if res["rows"] else o["dtype"]
    parts = [
        "# Camera-gradient quality: autograd vs central finite differences",
        "",
        f"- date: {res['meta']['date']}; torch {res['meta']['torch']}, {res['meta']['threads']} threads; "
        f"total {res['meta'].get('elapsed_s', float('nan')):.0f} s",
        f"- loss per view: sum(W * images) (and sum(W * alpha)), W seeded {o['weights']} in "
        f"{'[0, 1)' if o['weights'] == 'uniform' else 'N(0, 1)'}; renderer in eval() (camera light, white), "
        "defaults otherwise (sigma = gamma = 1e-4, faces_per_pixel = 8)",
        f"- rendered in {dtype} for the gradients and FD; fwd+bwd f32: median of float32 runs after a warm-up; "
        f"{dtype} ms: the measured autograd pass (forward + images backward)",
        "- FD: angle step h degrees, distance step dist * radians(h); all views of all shapes are moved at once "
        "(a view's image depends on its own camera only)",
        "- cos az+el: over the (azim, elev) derivatives of all shapes x views; median shape cos: median over shapes of "
        "the per-shape (azim, elev) cosine; ratio: |autograd| / |FD| (vector norms); FD vs FD h0: cosine between FD "
        "at this h and at the first h; n/a: a zero vector (e.g. hard coverage has no gradient)",
    ]
    for sc in res["scenes"]:
        rows = []
        for r in (r for r in res["rows"] if r["scene"] == sc["name"]):
            rows.append([r["setting"], r["loss"], f"{r['h']:g}", _f(r["cos_azim"]), _f(r["cos_elev"]), _f(r["cos_dist"]),
                         _f(r["cos_angles"]), _f(r["median_shape_cos"]), _f(r["ratio_angles"]), _f(r["ratio_dist"]),
                         _f(r["fd_cos_vs_ref"]), _f(r["fwd_bwd_ms_f32"], "{:.0f}"), _f(r["fwd_bwd_ms_measured"], "{:.0f}")])
        faces = sc["faces"]
        parts.append(f"\n## Gradient quality: {sc['name']} (faces {min(faces)}-{max(faces)}; views: azim U[0, 360), "
                     f"elev U[-60, 60], dist {sc['dist']:g})\n\n"
                     + md_table(["setting", "loss on", "h deg", "cos azim", "cos elev", "cos dist", "cos az+el", "median shape cos",
                                 "ratio az+el", "ratio dist", "FD vs FD h0", "fwd+bwd ms f32", f"fwd+bwd ms {dtype}"], rows))
    if res["pole"]:
        hs = o["pole_h"]
        rows = []
        for r in res["pole"]:
            rows.append([r["setting"], f"{r['elev']:g}", f"d/d {r['param']}", f"{r['auto_median']:.4g} ({r['auto_max']:.4g})",
                         f"{r['auto_f32_median']:.4g}", *[f"{r[f'fd_median_{h:g}']:.4g}" for h in hs],
                         " / ".join(_f(r[f"cos_{h:g}"]) for h in hs),
                         " / ".join(f"{r[f'agree_{h:g}']}/{r['shapes']}" for h in hs)])
        n = res["scenes"][0]["faces"]
        parts.append(f"\n## Near the pole: |dL/d angle| per degree ({len(n)} synthetic shapes, azim {o['pole_azim']:g}, "
                     f"{o['size']} px, loss sum(W * images) of one view)\n\n"
                     + md_table(["setting", "elev", "derivative", f"autograd {dtype}: median (max) over shapes", "autograd f32 median",
                                 *[f"FD h={h:g} median" for h in hs], "cos(autograd, FD) over shapes, h = " + " / ".join(f"{h:g}" for h in hs),
                                 f"shapes where FD agrees (within {AGREE_REL:.0%} + {AGREE_ABS:g}), h = " + " / ".join(f"{h:g}" for h in hs)],
                                rows))
        frame = ", ".join(f"elev {f['elev']:g}: {f['dR_delev']:.4g} / {f['dR_dazim']:.4g}" for f in res["frame"])
        parts.append(f"\nCamera frame |dR/d elev| / |dR/d azim| (Frobenius, per degree): {frame}.")
    return "\n".join(parts) + "\n"


def write_outputs(res: dict, out_dir: Path) -> tuple[Path, Path, str]:
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    md = to_markdown(res)
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    md_path, js_path = out_dir / f"grad_quality-{stamp}.md", out_dir / f"grad_quality-{stamp}.json"
    md_path.write_text(md)
    js_path.write_text(json.dumps(_jsonable(res), indent=1))
    return md_path, js_path, md


def _floats(text: str) -> tuple[float, ...]:
    return tuple(float(x) for x in text.split(",") if x.strip())


def parse_args(argv=None) -> tuple[GradOptions, Path]:
    d = GradOptions()
    p = argparse.ArgumentParser(prog="python scripts/studies/grad_quality.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--size", type=int, default=d.size, help="image size of the synthetic scene and the pole table")
    p.add_argument("--views", type=int, default=d.views, help="views per shape")
    p.add_argument("--shapes", type=int, default=d.shapes, help="synthetic shapes (one per class first)")
    p.add_argument("--h", type=_floats, default=d.h, help="FD steps in degrees, comma separated (first = reference)")
    p.add_argument("--modes", type=lambda s: tuple(x for x in s.split(",") if x), default=d.modes,
                   help=f"comma separated subset of {','.join(SETTINGS)}")
    p.add_argument("--dtype", choices=list(DTYPES), default=d.dtype, help="dtype of the autograd and FD renders")
    p.add_argument("--weights", choices=["uniform", "normal"], default=d.weights, help="distribution of W")
    p.add_argument("--seed", type=int, default=d.seed)
    p.add_argument("--no-big", dest="big", action="store_false", help="skip the 224 px / 20k-face torus scene")
    p.add_argument("--big-size", type=int, default=d.big_size)
    p.add_argument("--big-views", type=int, default=d.big_views)
    p.add_argument("--big-h", type=_floats, default=d.big_h, help="FD steps of the torus scene")
    p.add_argument("--no-pole", dest="pole", action="store_false", help="skip the pole table")
    p.add_argument("--pole-modes", type=lambda s: tuple(x for x in s.split(",") if x), default=d.pole_modes)
    p.add_argument("--pole-h", type=_floats, default=d.pole_h)
    p.add_argument("--repeats", type=int, default=d.repeats, help="most float32 timing runs (median)")
    p.add_argument("--cache-dir", default=d.cache_dir, help="synthetic dataset cache")
    p.add_argument("--out", default="outputs/bench/grad_quality", help="folder of the .md and .json files")
    p.add_argument("--quiet", dest="progress", action="store_false", help="no progress lines on stderr")
    a = vars(p.parse_args(argv))
    out = Path(a.pop("out"))
    return GradOptions(**a).validate(), out


def main(argv=None) -> None:
    opts, out = parse_args(argv)
    res = run(opts)
    md_path, js_path, md = write_outputs(res, out)
    print(md, flush=True)
    print(md_path.resolve(), flush=True)
    print(js_path.resolve(), flush=True)


if __name__ == "__main__":
    main()
