"""What ``renderer.compile=true`` costs before it pays: the first compiled render against the next.

``python scripts/studies/compile_time.py`` renders ``mvtn-bench``'s soft target rows (the 20k-face
torus, 12 views, 224 px, K = 8, smooth then flat, forward+backward with camera gradients) with the
compiled renderer in a fresh process per cache state: ``cold`` (an empty torch compile cache: a new
``TORCHINDUCTOR_CACHE_DIR``, what a new machine pays once) and ``warm`` (the user's cache, as a
second run on the same machine finds it). It prints, per state and shading, the first call's
seconds (compile included) and the second's. ``--sections`` / ``--size`` / ``--views`` shrink the
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


def measure(sections: int = 100, size: int = 224, views: int = 12) -> list[dict]:
    """In this process: the first and second compiled forward+backward of each shading."""
    import time

    import torch

    from mvtn_exp.bench.render_bench import Views, render_fns, renderer_for, torus_of

    dev = torch.device("cpu")
    shape = torus_of(sections, dev, f"torus-{2 * sections * sections}")
    rows = []
    for shading in SHADINGS:
        fb = render_fns(renderer_for(shape, size, 8, shading, compile=True), shape, Views(views, 1, dev))[1]
        times = []
        for _ in range(2):
            t0 = time.perf_counter()
            fb()
            times.append(time.perf_counter() - t0)
        rows.append(dict(shading=shading, faces=2 * sections * sections, first_s=times[0], second_s=times[1]))
    return rows


def in_fresh_process(cache: str, sections: int, size: int, views: int) -> list[dict]:
    """``measure`` in a new process; ``cache``: ``cold`` (a new, empty compile cache) or ``warm``."""
    env = dict(os.environ)
    with tempfile.TemporaryDirectory() as tmp:
        if cache == "cold":
            env["TORCHINDUCTOR_CACHE_DIR"] = tmp
        code = (f"import json, sys; sys.path.insert(0, {os.path.dirname(os.path.abspath(__file__))!r}); "
                f"import compile_time as c; print(json.dumps(c.measure({sections}, {size}, {views})))")
        out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout
    return [dict(row, cache=cache) for row in json.loads(out.strip().splitlines()[-1])]


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
    rows = [row for cache in a.cache for row in in_fresh_process(cache, a.sections, a.size, a.views)]
    print(to_markdown(rows))


if __name__ == "__main__":
    main()
