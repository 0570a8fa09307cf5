"""The report of ``mvtn-bench``: the targets with PASS/MISS, the Markdown tables of bench.md and the
raw JSON of bench.json.

The time targets' ratios come from both sides timed in alternation (``Results.paired``) where the
benchmark measured them so, else from the grid's and ResNet-18's own rows.
"""
from __future__ import annotations

import json
import math
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from ..render import accel
from . import edge_error
from .scenes import LOD_FACES_PER_PIXEL
from .timing import med_ms, paired_ratio

if TYPE_CHECKING:
    from .render_bench import Bench, Results

LIMIT_MIB = 512.0


# ---------------------------------------------------------------------------- targets
def _target(name, value_txt, limit_txt, ok, reason=None, value=None, limit=None):
    status = f"n/a ({reason})" if ok is None else ("PASS" if ok else "MISS")
    return dict(target=name, value=value_txt, limit=limit_txt, status=status, measured=value, threshold=limit)


def targets(bench: Bench) -> list[dict]:
    """The Targets table's rows: the renderer against ResNet-18, 100k against 2k faces, the batch of
    8's memory, and the paper-scale rows where they were measured."""
    quick = "not in this grid (quick=true)" if bench.opts.quick else "not measured"
    out = _resnet_targets(bench, quick) + _lod_targets(bench, quick) + _batch8_targets(bench, quick)
    if bench.res.paper_scale:
        from . import paper_scale

        out += [_target(*row) for row in paper_scale.targets(bench.res.paper_scale, bench.dev.type == "cuda")]
    return out


def _pair(res: Results, key, num_row, den_s):
    """(numerator s, denominator s): timed in alternation when measured so, else from their own rows."""
    if key in res.paired:
        return res.paired[key]
    return (num_row["fwd_bwd_s"], den_s) if num_row is not None and den_s is not None else None


def _vs_resnet(bench: Bench, quick: str, title, key, row, factor):
    """One time target against ResNet-18 fwd+bwd on the target's images: at most ``factor`` x it."""
    g = bench.grid
    net = next((r for r in bench.res.resnet if r["images"] == g.target_views and r["size"] == g.target_size), None)
    times = _pair(bench.res, key, row, net["fwd_bwd_s"] if net else None)
    if times is None:
        return _target(title, "-", f"<= {factor:g} x ResNet-18", None, quick)
    ms, net_ms = med_ms(times[0]), med_ms(times[1])
    ratio = paired_ratio(times)
    return _target(title, f"{ms:.1f} ms vs ResNet-18 {net_ms:.1f} ms: {ratio:.3f} x",
                   f"<= {factor:g} x ({factor * net_ms:.1f} ms)", ratio <= factor, value=ratio, limit=factor)


def _resnet_targets(bench: Bench, quick: str) -> list[dict]:
    """The renderer's fwd+bwd against ResNet-18's: hard, soft eager and compiled, points."""
    g = bench.grid
    S, M = g.target_size, g.target_views
    out = [_vs_resnet(bench, quick, f"20k-face mesh, {M} views, {S} px, K=1: fwd+bwd vs ResNet-18 fwd+bwd on {M} images",
                      "hard", bench.find_grid("torus-20k", S, M, 1), 0.15)]
    default_compiles = accel.auto_compiles(bench.dev.type, True, S)  # what renderer.compile=null runs for these rows
    for shading, factor in (("smooth", 1.0), ("flat", 1.0)):
        out.append(_vs_resnet(bench, quick, f"20k-face mesh, {M} views, {S} px, soft K=8 {shading}, eager (renderer.compile=false"
                              + ("" if default_compiles else "; the default here") + f"): fwd+bwd vs ResNet-18 fwd+bwd on {M} images",
                              shading, bench.find_grid("torus-20k", S, M, 8, shading), factor))
    out += [_compiled_target(bench, quick, shading, default_compiles) for shading in ("smooth", "flat")]
    out.append(_vs_resnet(bench, quick, f"2048 points, {M} views, {S} px, K=8: fwd+bwd vs ResNet-18 fwd+bwd on {M} images",
                          "points", bench.find_grid("points-2048", S, M, 8), 0.1))
    return out


def _compiled_target(bench: Bench, quick: str, shading: str, default_compiles: bool) -> dict:
    """Soft K=8 with renderer.compile=true against ResNet-18 (n/a where torch.compile does not run)."""
    S, M, res = bench.grid.target_size, bench.grid.target_views, bench.res
    key = f"{shading}_compiled"
    first = res.compile_first_s.get(shading)
    title = (f"20k-face mesh, {M} views, {S} px, soft K=8 {shading}, renderer.compile=true"
             + ("; the default here (null)" if default_compiles else "")
             + (f" (first call {first:.1f} s{', after the smooth row compiled the shared parts' if shading == 'flat' else ''})"
                if first is not None else "") + f": fwd+bwd vs ResNet-18 fwd+bwd on {M} images")
    if key in res.paired:
        return _vs_resnet(bench, quick, title, key, None, 1.0)
    unavailable = accel.unavailable(bench.dev.type)
    why = quick if bench.opts.quick else (unavailable or ("compiled=false" if not bench.opts.compiled else "not measured"))
    return _target(title, "-", "<= 1 x ResNet-18", None, why)


def _lod_targets(bench: Bench, quick: str) -> list[dict]:
    """The 100k-face mesh against the 2k-face one (K=1 fwd+bwd), without and with LOD: at most 2 x."""
    S, M, res = bench.grid.target_size, bench.grid.target_views, bench.res
    small, big = bench.find_grid("torus-2k", S, M, 1), bench.find_grid("torus-100k", S, M, 1)
    lod_big = next((r for r in res.lod if r["shape"] == "torus-100k" and r["fpp"] == LOD_FACES_PER_PIXEL[0]), None)
    lod_row = dict(fwd_bwd_s=lod_big["lod_fwd_bwd_s"]) if lod_big else None
    out = []
    for key, label, row in (("100k", "without LOD", big), ("100k_lod", "with LOD (the renderer's default)", lod_row)):
        title = f"100k-face vs 2k-face mesh, {S} px, {M} views, K=1 fwd+bwd, {label}"
        times = _pair(res, key, row, small["fwd_bwd_s"] if small else None)
        if times is None:
            out.append(_target(title, "-", "<= 2 x", None, quick))
            continue
        a, b, ratio = med_ms(times[0]), med_ms(times[1]), paired_ratio(times)
        note = " (2k is under the LOD budget: unchanged)" if label.startswith("with LOD") else ""
        out.append(_target(title, f"{a:.1f} ms / {b:.1f} ms: {ratio:.2f} x{note}", "<= 2 x", ratio <= 2.0, value=ratio, limit=2.0))
    return out


def _batch8_targets(bench: Bench, quick: str) -> list[dict]:
    """The extra peak memory of a batch of 8 shapes: at most ``LIMIT_MIB``."""
    S, M = bench.grid.target_size, bench.grid.target_views
    out = []
    for kind, desc in (("mesh", "20k-face mesh, K=1"), ("points", "2048 points, K=8")):
        title = f"batch of 8 x {M} views x {S} px, fwd+bwd extra peak memory: {desc}"
        row = next((r for r in bench.res.batch8 if r["kind"] == kind), None)
        if row is None:
            out.append(_target(title, "-", f"<= {LIMIT_MIB:.0f} MiB", None, quick))
            continue
        out.append(_target(title, f"{row['peak_mib']:.0f} MiB", f"<= {LIMIT_MIB:.0f} MiB", row["peak_mib"] <= LIMIT_MIB,
                           value=row["peak_mib"], limit=LIMIT_MIB))
    return out


# ---------------------------------------------------------------------------- Markdown and JSON
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
    """bench.md: the run's header, then one section per table, the Targets last."""
    parts = [_md_head(res), _md_grid(res), _md_resnet(res), _md_dense(res), _md_lod(res), _md_batch8(res), _md_edges(res)]
    parts += _md_other_modules(res)
    parts.append(_md_targets(res))
    return "\n\n".join(parts) + "\n"


def _md_head(res: Results) -> str:
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
    return "\n".join(head)


def _md_grid(res: Results) -> str:
    rows = [[r["shape"], r["prims"], r["size"], r["views"], r["K"], r["shading"] if r["kind"] == "mesh" else "-",
             f_ms(r["fwd_s"]), f_ms(r["fwd_bwd_s"]), _f1(r["peak_mib"]), r["stats"].get("active_pixels", "-"),
             r["stats"].get("slots", "-"), r["stats"].get("rest_faces", "-"), f"{len(r['fwd_s'])}/{len(r['fwd_bwd_s'])}"]
            for r in res.grid]
    return ("## Renderer grid (B=1, spherical views; mesh K=1: hard flat, K=8: soft, flat and smooth; points K: points per pixel)\n\n"
            + md_table(["shape", "faces/points", "px", "M", "K", "shading", "fwd ms", "fwd+bwd ms", "extra peak MiB (fwd+bwd)",
                        "active px", "soft slots", "soft rest faces", "runs fwd/fb"], rows))


def _md_resnet(res: Results) -> str:
    rows = [[r["images"], r["size"], f_ms(r["fwd_bwd_s"]), len(r["fwd_bwd_s"])] for r in res.resnet]
    return ("## ResNet-18 reference (40 classes, train mode, forward+backward)\n\n"
            + md_table(["images", "px", "fwd+bwd ms", "runs"], rows))


def _md_dense(res: Results) -> str:
    rows = []
    for r in res.dense:
        if r["dense_s"] is None:
            rows.append([r["shape"], r["prims"], r["size"], r["views"], f"{r['pairs']:.3g}",
                         f"n/a (too large: {r['pairs']} pairs)", "-", "-", "-"])
        else:
            rows.append([r["shape"], r["prims"], r["size"], r["views"], f"{r['pairs']:.3g}", f_ms(r["dense_s"]), f_ms(r["search_s"]),
                         f"{med_ms(r['dense_s']) / med_ms(r['search_s']):.1f} x", "yes" if r["identical"] else "NO"])
    o_pairs = f"{res.meta['options']['dense_max_pairs']:.3g}"
    return (f"## Dense reference vs search_faces (hard K=1 search only, same projected faces; dense only where pairs <= {o_pairs})\n\n"
            + md_table(["mesh", "faces", "px", "M", "pixel x face pairs", "dense ms", "search_faces ms", "speed-up", "identical"], rows))


def _md_lod(res: Results) -> str:
    if not res.lod:
        return "## Level of detail\n\nnot run (quick=true)"
    rows = []
    for r in res.lod:
        a, b = med_ms(r["no_lod_fwd_bwd_s"]), med_ms(r["lod_fwd_bwd_s"])
        after = f"{r['faces_after']}" + (" (kept whole)" if r["faces_after"] == r["prims"] else "")
        rule = "default: 32 per row, checked" if r["fpp"] is None else f"{r['fpp']:g} per pixel"
        rows.append([r["shape"], r["prims"], rule, after, r["budget"], f"{a:.1f}", f"{b:.1f}", f"{a / b:.2f} x", f"{r['simplify_s']:.2f}",
                     f"{r['first_call_s']:.2f}", f"{r['image_mae']:.4f}", f"{r['silhouette_iou']:.4f}"])
    S, M = res.lod[0]["size"], res.lod[0]["views"]
    return (f"## Level of detail ({S} px, {M} views, K=1, forward+backward)\n\n"
            + md_table(["mesh", "faces", "budget rule", "faces after LOD", "budget", "no LOD ms", "LOD ms", "speed-up", "simplify s (one-off)",
                        "first LOD call s", "image MAE", "silhouette IoU"], rows)
            + "\n\nLOD times exclude the first call; the simplification is timed once on its own (it is cached afterwards). "
            "The default rule keeps a simplification only if its silhouettes keep IoU >= renderer.lod_min_iou.")


def _md_batch8(res: Results) -> str:
    if not res.batch8:
        return "## Batch of 8 shapes\n\nnot run (quick=true)"
    rows = [[r["kind"], r["shape"], r["prims"], r["batch"], r["views"], r["size"], r["K"], f"{r['peak_mib']:.1f}", f"{r['time_s']:.2f}"]
            for r in res.batch8]
    return ("## Batch of 8 shapes (copies rotated about Y), forward+backward memory\n\n"
            + md_table(["kind", "shape", "faces/points", "B", "M", "px", "K", "extra peak MiB", "time s (memory run)"], rows))


def _md_edges(res: Results) -> str:
    rows = [[r["shape"], r["size"], r["shading"], r["edge_pixels"], f"{100 * r['cov_off']:.2f}%", f"{r['cov_max']:.1e}",
             f"{100 * r['rgb_off']:.2f}%", f"{r['rgb_max']:.1e}", r["faces"]] for r in res.edges]
    return (f"## Soft edges: K=8 against every face within the blur radius (edge pixels: reference coverage in "
            f"[{edge_error.EDGE_LO:g}, 1 - {edge_error.EDGE_LO:g}]; 4 spherical views)\n\n"
            + md_table(["mesh", "px", "shading", "edge pixels", f"coverage off > {edge_error.TOL:g}", "max coverage error",
                        f"colour off > {edge_error.TOL:g}", "max colour error", "most faces in a pixel"], rows))


def _md_other_modules(res: Results) -> list[str]:
    """The sections the other bench modules write: modules, the paper's tables, paper scale, scaling."""
    m, parts = res.meta, []
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

        parts.append(scaling_markdown(res.scaling, m["options"]["quick"]) + "\n\nPlotted in `scaling.png` beside this file.")
    return parts


def _md_targets(res: Results) -> str:
    rows = [[t["target"], t["value"], t["limit"], t["status"]] for t in res.targets]
    times = (f"Times: each target's two sides timed in alternation in one job ({min(len(t[0]) for t in res.paired.values())}+ "
             "rounds); the times are each side's median, the ratio the median of the rounds' ratios, so a "
             "load change between rounds cancels."
             if res.paired else "Times: from the grid and ResNet-18 rows above.")
    return "## Targets\n\n" + md_table(["target", "measured", "limit", "status"], rows) + "\n\n" + times


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
