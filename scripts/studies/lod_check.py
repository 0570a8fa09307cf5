"""What level of detail keeps: faces, image error and silhouette IoU of ``renderer.lod=true``.

For each mesh (the 100k-face benchmark torus and the real ModelNet samples under
``../shared/data/real_samples``, each centred and scaled into the unit sphere) and image size, the
mesh is rendered hard with and without LOD from 12 spherical views; a row gives the budget, the
faces LOD kept, the one-off time of the simplification and its silhouette check, the mean absolute
image difference and the silhouette IoU. ``--min-iou 0`` shows what simplification alone does
(the former behaviour).

Run: ``python scripts/studies/lod_check.py [--sizes 224 64] [--min-iou 0.99]`` (Markdown on stdout).
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from mvtn_exp.bench.scenes import Views, renderer_for, torus_of
from mvtn_exp.data import mesh_io
from mvtn_exp.data.shapes import Meshes
from mvtn_exp.render import lod

SAMPLES = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "real_samples"


def unit_mesh(verts: np.ndarray, faces: np.ndarray) -> Meshes:
    v = verts - (verts.max(0) + verts.min(0)) / 2
    v = v / (np.linalg.norm(v, axis=1).max() or 1.0)
    return Meshes.from_list([torch.tensor(v, dtype=torch.float32)], [torch.tensor(faces, dtype=torch.long)])


def meshes(samples: Path = SAMPLES) -> dict:
    out = {"torus-100k": torus_of(224, "cpu", "torus-100k")}
    for path in sorted(samples.glob("*/*/*/*.off")) if samples.is_dir() else []:
        out[path.stem] = unit_mesh(*mesh_io.read_mesh(path))
    return out


def rows(shapes: dict, sizes, min_iou: float, views: int = 12) -> list[dict]:
    v = Views(views, 1, torch.device("cpu"))
    out = []
    for name, m in shapes.items():
        for size in sizes:
            with torch.no_grad():
                a = renderer_for(m, size, 1)(m, v.azim, v.elev, v.dist)
                t0 = time.perf_counter()
                b = renderer_for(m, size, 1, lod=True, lod_min_iou=min_iou)(m, v.azim, v.elev, v.dist)
                seconds = time.perf_counter() - t0
            ma, mb = a.alpha > 0.5, b.alpha > 0.5
            out.append(dict(mesh=name, faces=int(m.faces_per_shape.sum()), size=size, budget=lod.face_budget(size),
                            kept=int(b.stats["lod_faces"][1]), seconds=seconds,
                            mae=float((a.images - b.images).abs().mean()),
                            iou=float((ma & mb).sum() / (ma | mb).sum())))
    return out


def to_markdown(table: list[dict], min_iou: float) -> str:
    lines = [f"renderer.lod=true, lod_min_iou={min_iou:g}, 12 spherical views, hard", "",
             "| mesh | faces | px | budget | faces kept | simplify + check s (once) | image MAE | silhouette IoU (12 views) |",
             "|---|---|---|---|---|---|---|---|"]
    lines += [f"| {r['mesh']} | {r['faces']} | {r['size']} | {r['budget']} | {r['kept']} | {r['seconds']:.2f} | "
              f"{r['mae']:.4f} | {r['iou']:.4f} |" for r in table]
    return "\n".join(lines)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[224, 64])
    p.add_argument("--min-iou", type=float, default=0.99)
    args = p.parse_args(argv)
    torch.manual_seed(0)
    print(to_markdown(rows(meshes(), args.sizes, args.min_iou), args.min_iou))


if __name__ == "__main__":
    main()
