"""Scaling curves in ``mvtn-bench``: renderer time and peak memory against faces, pixels, views and batch.

Each curve varies one quantity and holds the others at the base scene (a torus of ``BASE_FACES``,
``BASE_SIZE`` px, ``BASE_VIEWS`` spherical views, one shape), hard (K=1) and soft (K=8, smooth
shading, the training setting); forward+backward with camera gradients. Per curve: the exponent
``a`` of a least-squares fit ``time ~ n^a`` (and ``memory ~ n^a``) in log-log, and where the
local exponent between neighbouring points changes most (the bend). The full grid:

- faces 2k, 8k, 20k, 50k, 200k (tori of 32, 64, 100, 158, 316 sections);
- pixels 32, 64, 128, 256, 512 px a side;
- views 1, 2, 4, 8, 12, 20;
- batch 1, 2, 4, 8, 16, 32 shapes (copies of the base torus turned about Y).

``quick``: three points per curve at small sizes (for tests).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from ..data.shapes import Meshes
from .scenes import Views, render_fns, renderer_for, rotated_copies_y, torus_of
from .timing import med_ms, peak_of, time_runs

BASE_FACES, BASE_SIZE, BASE_VIEWS, BASE_BATCH = 8192, 128, 4, 1
MODES = (("hard", 1), ("soft smooth", 8))
AXIS_LABELS = {"faces": "faces", "pixels": "image side (px)", "views": "views M", "batch": "shapes per batch"}


@dataclass(frozen=True)
class Curve:
    name: str  # the quantity varied
    values: tuple[int, ...]


def curves(quick: bool) -> list[Curve]:
    if quick:
        return [Curve("faces", (512, 2048, 8192)), Curve("pixels", (16, 32, 64)), Curve("views", (1, 2, 4)),
                Curve("batch", (1, 2, 4))]
    return [Curve("faces", (2048, 8192, 20000, 49928, 199712)), Curve("pixels", (32, 64, 128, 256, 512)),
            Curve("views", (1, 2, 4, 8, 12, 20)), Curve("batch", (1, 2, 4, 8, 16, 32))]


def base(quick: bool) -> dict:
    return dict(faces=2048, pixels=32, views=2, batch=1) if quick else dict(
        faces=BASE_FACES, pixels=BASE_SIZE, views=BASE_VIEWS, batch=BASE_BATCH)


def torus_faces(faces: int, device) -> Meshes:
    """A torus of about ``faces`` faces (2 n^2 for n sections)."""
    n = max(3, round(math.sqrt(faces / 2)))
    return torus_of(n, device, f"torus-{2 * n * n}")


def scene(point: dict, device) -> Meshes:
    """The shapes of one curve point: ``point["batch"]`` copies of one torus, turned about Y."""
    mesh = torus_faces(point["faces"], device)
    if point["batch"] > 1:
        B = point["batch"]
        mesh = Meshes.from_list(rotated_copies_y(mesh.verts, B), [mesh.faces] * B, names=[f"copy{k}" for k in range(B)])
    return mesh


def fit_exponent(ns, ys) -> float:
    """Least-squares slope of log y against log n."""
    x, y = np.log(np.asarray(ns, float)), np.log(np.asarray(ys, float))
    return float(np.polyfit(x, y, 1)[0])


def bend(ns, ys) -> str:
    """Where the local exponent between neighbouring points changes most: ``"n=X: a1 -> a2"`` ('-' for < 3 points)."""
    if len(ns) < 3:
        return "-"
    local = [math.log(ys[i + 1] / ys[i]) / math.log(ns[i + 1] / ns[i]) for i in range(len(ns) - 1)]
    i = int(np.argmax(np.abs(np.diff(local))))
    return f"n={ns[i + 1]}: {local[i]:.2f} -> {local[i + 1]:.2f}"


class Scaling:
    """Runs the curves in two phases like ``mvtn-bench`` (memory first, then times) and keeps the rows."""

    def __init__(self, quick: bool, device, repeats: int, budget_s: float) -> None:
        self.quick, self.device, self.repeats, self.budget_s = quick, torch.device(device), repeats, budget_s
        self.rows: list[dict] = []
        for c in curves(quick):
            for v in c.values:
                for mode, K in MODES:
                    self.rows.append(dict(curve=c.name, n=v, mode=mode, K=K, point={**base(quick), c.name: v},
                                          peak_mib=None, fwd_bwd_s=[]))
        self._scenes: dict[tuple, object] = {}

    def _fn(self, row):
        p = row["point"]
        key = (p["faces"], p["batch"])
        if key not in self._scenes:
            self._scenes[key] = scene(p, self.device)
        shapes = self._scenes[key]
        r = renderer_for(shapes, p["pixels"], row["K"], "smooth" if row["K"] > 1 else "flat")
        return render_fns(r, shapes, Views(p["views"], p["batch"], self.device))[1]

    def measure_memory(self) -> None:
        for row in self.rows:
            row["peak_mib"], _ = peak_of(self._fn(row), self.device)

    def measure_time(self) -> None:
        for row in self.rows:
            fn = self._fn(row)
            fn()  # warm-up
            row["fwd_bwd_s"] = time_runs(fn, self.device, self.repeats, self.budget_s)

    def fits(self) -> list[dict]:
        out = []
        for c in curves(self.quick):
            for mode, _ in MODES:
                pts = [r for r in self.rows if r["curve"] == c.name and r["mode"] == mode and r["fwd_bwd_s"]]
                if len(pts) < 2:
                    continue
                ns = [r["n"] for r in pts]
                ts = [med_ms(r["fwd_bwd_s"]) for r in pts]
                ms = [max(r["peak_mib"] or 0.0, 1e-3) for r in pts]
                out.append(dict(curve=c.name, mode=mode, values=ns, ms=ts, peak_mib=ms, time_exponent=fit_exponent(ns, ts),
                                memory_exponent=fit_exponent(ns, ms), time_bend=bend(ns, ts)))
        return out


def markdown(fits: list[dict], quick: bool) -> str:
    from .render_report import md_table

    b = base(quick)
    body = [[f["curve"], f["mode"], " / ".join(str(v) for v in f["values"]), " / ".join(f"{t:.1f}" for t in f["ms"]),
             " / ".join(f"{m:.0f}" for m in f["peak_mib"]), f"{f['time_exponent']:.2f}", f"{f['memory_exponent']:.2f}",
             f["time_bend"]] for f in fits]
    return (f"## Scaling curves (base: {b['faces']}-face torus, {b['pixels']} px, {b['views']} views, batch {b['batch']}; "
            "one quantity varied; forward+backward with camera gradients; soft: K=8, smooth)\n\n"
            + md_table(["varied", "mode", "values", "fwd+bwd ms", "extra peak MiB", "time exponent a (t ~ n^a)",
                        "memory exponent", "largest bend of the local time exponent"], body))


def plot(fits: list[dict], path) -> None:
    from ..viz.plots import pyplot, save_figure

    plt = pyplot()
    names = list(dict.fromkeys(f["curve"] for f in fits))
    fig, axes = plt.subplots(2, len(names), figsize=(4.2 * len(names), 7), squeeze=False)
    for j, name in enumerate(names):
        for f in (f for f in fits if f["curve"] == name):
            axes[0, j].loglog(f["values"], f["ms"], "o-", label=f"{f['mode']}: a = {f['time_exponent']:.2f}")
            axes[1, j].loglog(f["values"], f["peak_mib"], "o-", label=f"{f['mode']}: a = {f['memory_exponent']:.2f}")
        for i, what in enumerate(("fwd+bwd ms", "extra peak MiB")):
            axes[i, j].set_xlabel(AXIS_LABELS.get(name, name))
            axes[i, j].xaxis.set_minor_formatter(plt.NullFormatter())  # minor labels overlap
            axes[i, j].set_ylabel(what)
            axes[i, j].grid(alpha=0.3, which="both")
            axes[i, j].legend(fontsize=8)
    save_figure(fig, path)
