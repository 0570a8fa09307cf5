"""Data-loading throughput from a packed cache, against the training step it feeds.

``python -m mvtn_exp.bench.loader_bench [shapes] [faces]`` builds a packed split of ``shapes``
meshes of about ``faces`` faces each (icospheres: the size real ModelNet meshes have after
simplification to 20,000 vertices is about 40,000 faces), then times one epoch of the DataLoader
(``collate_shapes`` into packed Meshes, batch 20) with 0 and 2 workers, and prints a Markdown
table with the time per batch and its share of a ResNet-18 MVCNN step on 20 x 12 views of
224 px measured in the same run (forward + backward).
"""
from __future__ import annotations

import sys
import time

import numpy as np
import torch
import trimesh
from torch.utils.data import DataLoader

from ..data.collate import collate_shapes
from ..data.packed import PackedShapes, pack
from ..models.backbones import resnet18


def packed_spheres(shapes: int, faces: int, num_points: int = 2048) -> PackedShapes:
    """``shapes`` icospheres with about ``faces`` faces each (jittered), as a packed split."""
    level = max(0, int(round(np.log(max(faces, 20) / 20) / np.log(4))))
    s = trimesh.creation.icosphere(subdivisions=level)
    rng = np.random.default_rng(0)
    items = []
    for i in range(shapes):
        v = np.asarray(s.vertices) * (1 + 0.05 * rng.standard_normal((len(s.vertices), 1)))
        items.append({"verts": v, "faces": np.asarray(s.faces), "points": v[rng.choice(len(v), num_points)],
                      "label": i % 40, "name": f"sphere_{i:04d}"})
    return PackedShapes(pack(items, num_points), [f"c{k}" for k in range(40)], "train")


def time_loader(ds, batch_size: int, workers: int) -> float:
    """Seconds per batch over one shuffled epoch."""
    loader = DataLoader(ds, batch_size=batch_size, shuffle=True, collate_fn=collate_shapes, num_workers=workers,
                        generator=torch.Generator().manual_seed(0))
    t0 = time.perf_counter()
    n = 0
    for batch in loader:
        n += 1
        assert batch["meshes"] is not None
    return (time.perf_counter() - t0) / max(n, 1)


def time_step(batch: int, views: int, size: int, repeats: int = 2) -> float:
    """Seconds of ResNet-18 forward + backward on ``batch * views`` images of ``size`` px."""
    net = resnet18(num_classes=40)
    x = torch.rand(batch * views, 3, size, size)
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        net(x).sum().backward()
        best = min(best, time.perf_counter() - t0)
    return best


def run(shapes: int = 200, faces: int = 40000, batch: int = 20, views: int = 12, size: int = 224) -> str:
    ds = packed_spheres(shapes, faces)
    faces_each = int(ds._a["faces_per_shape"][0])
    step = time_step(batch, views, size)
    rows = []
    for w in (0, 2):
        t = time_loader(ds, batch, w)
        rows.append(f"| {w} | {t * 1e3:.1f} | {step * 1e3:.0f} | {100 * t / step:.2f}% |")
    head = (f"Packed cache: {shapes} meshes of {faces_each} faces, batch {batch}; step: ResNet-18 fwd+bwd on "
            f"{batch} x {views} views of {size} px\n\n| workers | ms per batch | ms per step | share |\n|---|---|---|---|")
    return head + "\n" + "\n".join(rows)


if __name__ == "__main__":
    args = [int(a) for a in sys.argv[1:3]]
    print(run(*args))
