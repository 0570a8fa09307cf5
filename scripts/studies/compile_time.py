"""What ``renderer.compile=true`` costs before it pays: the first compiled render against the next.

``python scripts/studies/compile_time.py`` renders ``mvtn-bench``'s soft target rows (the 20k-face
torus, 12 views, 224 px, K = 8, smooth and flat, forward+backward with camera gradients) with the
compiled renderer, each shading in a fresh process per cache state: ``cold`` (an empty torch compile
cache, a new ``TORCHINDUCTOR_CACHE_DIR``: what a new machine pays once) and ``warm`` (a cache of its
own that one earlier process filled with the same render: what every later run pays). It prints the
first call's seconds (compile included) and the second's. ``--sections`` / ``--size`` / ``--views`` shrink the
scene (the test runs it tiny).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile

SHADINGS = ("smooth", "flat")


def measure(shading: str, sections: int = 100, size: int = 224, views: int = 12) -> dict:
    """In this process: the first and second compiled forward+backward of one shading."""
    import time

    import torch

    from mvtn_exp.bench.scenes import Views, render_fns, renderer_for, torus_of

    dev = torch.device("cpu")
    shape = torus_of(sections, dev, f"torus-{2 * sections * sections}")
    fb = render_fns(renderer_for(shape, size, 8, shading, compile=True), shape, Views(views, 1, dev))[1]
    times = []
    for _ in range(2):
        t0 = time.perf_counter()
        fb()
        times.append(time.perf_counter() - t0)
    return dict(shading=shading, faces=2 * sections * sections, first_s=times[0], second_s=times[1])


def _run(cache_dir: str, shading: str, sections: int, size: int, views: int) -> dict:
    env = dict(os.environ, TORCHINDUCTOR_CACHE_DIR=cache_dir)
    code = (f"import json, sys; sys.path.insert(0, {os.path.dirname(os.path.abspath(__file__))!r}); "
            f"import compile_time as c; print(json.dumps(c.measure({shading!r}, {sections}, {size}, {views})))")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def in_fresh_process(cache: str, shading: str, sections: int = 100, size: int = 224, views: int = 12) -> dict:
    """``measure`` in a new process with a compile cache of its own: ``cold`` (empty) or ``warm``
    (filled by one earlier process that rendered the same)."""
    with tempfile.TemporaryDirectory() as tmp:
        if cache == "warm":
            _run(tmp, shading, sections, size, views)
        return dict(_run(tmp, shading, sections, size, views), cache=cache)


def to_markdown(rows: list[dict]) -> str:
    lines = ["| compile cache | shading | faces | first call s (compile included) | second call s |", "|---|---|---|---|---|"]
    lines += [f"| {r['cache']} | {r['shading']} | {r['faces']} | {r['first_s']:.1f} | {r['second_s']:.2f} |" for r in rows]
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sections", type=int, default=100, help="torus sections (2 s^2 faces; 100: the 20k-face torus)")
    ap.add_argument("--size", type=int, default=224)
    ap.add_argument("--views", type=int, default=12)
    ap.add_argument("--cache", nargs="+", default=["cold", "warm"], choices=["cold", "warm"])
    a = ap.parse_args(argv)
    rows = [in_fresh_process(cache, shading, a.sections, a.size, a.views) for cache in a.cache for shading in SHADINGS]
    print(to_markdown(rows))


if __name__ == "__main__":
    main()
