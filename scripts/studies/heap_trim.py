"""How much of the renderer's CPU time is the allocator's? The bench's targets under two heap settings.

``python scripts/studies/heap_trim.py --trim-mib 64 2048`` times, in one process per setting, the
renderer targets of ``mvtn-bench`` (2,048 points K = 8, the 20k-face torus hard and soft smooth; 12
views, 224 px, forward+backward) against ResNet-18 forward+backward on the same 12 images, the two
in alternation (``paired_times``), with glibc's mmap threshold at 32 MiB and its trim threshold at
each ``--trim-mib``: 64 MiB is where glibc's dynamic rule settles after large frees (what
``mvtn-bench`` times with); a large one keeps freed heap memory for the next call instead of
returning it to the kernel and faulting it in again. Each setting runs in a fresh process started
with ``MALLOC_MMAP_THRESHOLD_=65536`` (as ``mvtn-bench``), then switched with ``mallopt``.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys

CASES = ("points", "hard", "smooth")


def measure(trim_mib: int, cases=CASES, repeats: int = 5, size: int = 224, views: int = 12) -> list[dict]:
    """In this process: set the heap thresholds, then time each case against ResNet-18 in alternation."""
    import torch

    from mvtn_exp.runtime import memory
    from mvtn_exp.bench.render_bench import Bench, BenchOptions
    from mvtn_exp.bench.scenes import Views, render_fns, renderer_for, torus_of, torus_points
    from mvtn_exp.bench.timing import paired_ratio, paired_times

    if memory._LIBC is None:
        raise SystemExit("heap_trim: needs glibc (mallopt)")
    memory._LIBC.mallopt(memory._M_MMAP_THRESHOLD, 32 << 20)
    memory._LIBC.mallopt(memory._M_TRIM_THRESHOLD, int(trim_mib) << 20)
    dev = torch.device("cpu")
    v = Views(views, 1, dev)
    resnet = Bench(BenchOptions()).resnet_fn(views, size)
    shapes = {"points": (torus_points(2048, 0, dev), 8, "flat"), "hard": (torus_of(100, dev, "torus-20k"), 1, "flat"),
              "smooth": (torus_of(100, dev, "torus-20k"), 8, "smooth")}
    rows = []
    for case in cases:
        shape, K, shading = shapes[case]
        fn = render_fns(renderer_for(shape, size, K, shading), shape, v)[1]
        t = paired_times(fn, resnet, dev, repeats, 10.0)
        rows.append(dict(trim_mib=trim_mib, case=case, render_ms=1e3 * sorted(t[0])[len(t[0]) // 2],
                         resnet_ms=1e3 * sorted(t[1])[len(t[1]) // 2], ratio=paired_ratio(t)))
    return rows


def row_line(r: dict) -> str:
    return f"| {r['trim_mib']} | {r['case']} | {r['render_ms']:.1f} | {r['resnet_ms']:.1f} | {r['ratio']:.3f} |"


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--trim-mib", type=int, nargs="+", default=[64, 2048])
    ap.add_argument("--size", type=int, default=224, help="image side (px)")
    ap.add_argument("--views", type=int, default=12)
    ap.add_argument("--one", type=int, default=None, help=argparse.SUPPRESS)  # the child process of one setting
    a = ap.parse_args(argv)
    if a.one is not None:
        for r in measure(a.one, size=a.size, views=a.views):
            print(row_line(r), flush=True)
        return
    print("| trim threshold MiB | target | render ms | ResNet-18 ms | render / ResNet-18 (paired) |")
    print("|---|---|---|---|---|")
    env = {**os.environ, "MALLOC_MMAP_THRESHOLD_": "65536"}
    for mib in a.trim_mib:
        subprocess.run([sys.executable, __file__, "--one", str(mib), "--size", str(a.size), "--views", str(a.views)],
                       env=env, check=True)


if __name__ == "__main__":
    main()
