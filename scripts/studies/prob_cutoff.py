"""What ``renderer.prob_cutoff`` buys and costs: soft render time against image and camera-gradient error.

A face is searched at a pixel only where its SoftRas probability ``sigmoid(-d^2 / sigma)`` is at
least ``prob_cutoff``; the default 1e-4 puts the blur radius at 3.0 sqrt(sigma), 1e-2 at
2.1 sqrt(sigma) (half the area, so about half the candidates). Against the default, each row
reports, for the training setting (soft, smooth shading, K = 8):

- forward+backward time with camera gradients (median of ``--repeats``; same run, so ratios hold);
- edge pixels (default coverage in [0.001, 0.999]) whose coverage or colour moved by more than
  0.02, and the largest change;
- the cosine between the camera gradient of a fixed random linear loss of the images and the
  default's, and the ratio of their norms.

Run: ``python scripts/studies/prob_cutoff.py`` (Markdown table on stdout).
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch

from mvtn_exp.render import layouts
from mvtn_exp.render.renderer import MultiViewRenderer
from mvtn_exp.bench.edge_error import EDGE_LO, TOL, torus_mesh

DEFAULT = 1e-4


def _render(meshes, cutoff: float, size: int, views: int, weights: torch.Tensor | None = None):
    """Images, coverage and (with ``weights``) the camera gradient of ``sum(weights * images)``."""
    azim, elev, dist = layouts.spherical(views, batch=len(meshes), distance=2.2, sphere="fibonacci")
    azim, elev = azim.clone().requires_grad_(True), elev.clone().requires_grad_(True)
    r = MultiViewRenderer(image_size=size, mode="soft", shading="smooth", faces_per_pixel=8, prob_cutoff=cutoff).eval()
    out = r(meshes, azim, elev, dist)
    grad = None
    if weights is not None:
        (out.images * weights).sum().backward()
        grad = torch.cat([azim.grad.flatten(), elev.grad.flatten()])
    return out.images.detach(), out.alpha.detach()[:, :, 0], grad


def measure(meshes, cutoffs, size: int, views: int, repeats: int) -> list[dict]:
    torch.manual_seed(0)
    weights = torch.randn(len(meshes), views, 3, size, size)
    ref_img, ref_cov, ref_grad = _render(meshes, DEFAULT, size, views, weights)
    edge = (ref_cov >= EDGE_LO) & (ref_cov <= 1 - EDGE_LO)
    rows = []
    for p in cutoffs:
        _render(meshes, p, size, views, weights)  # warm-up
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            img, cov, grad = _render(meshes, p, size, views, weights)
            times.append(time.perf_counter() - t0)
        dc = (cov - ref_cov).abs()[edge]
        drgb = (img - ref_img).abs().amax(2)[edge]
        rows.append({"cutoff": p, "ms": 1000 * statistics.median(times), "edge_pixels": int(edge.sum()),
                     "cov_off": float((dc > TOL).float().mean()), "cov_max": float(dc.max()),
                     "rgb_off": float((drgb > TOL).float().mean()), "rgb_max": float(drgb.max()),
                     "grad_cos": float(torch.nn.functional.cosine_similarity(grad, ref_grad, dim=0)),
                     "grad_ratio": float(grad.norm() / ref_grad.norm())})
    return rows


def to_markdown(rows: list[dict], label: str) -> str:
    base = rows[0]["ms"]
    out = (f"{label}\n\n| prob_cutoff | fwd+bwd ms | x default | edge pixels | coverage off > 0.02 | max coverage change | "
           "colour off > 0.02 | max colour change | camera-gradient cosine | gradient norm ratio |\n"
           "|---|---|---|---|---|---|---|---|---|---|\n")
    return out + "".join(
        f"| {r['cutoff']:g} | {r['ms']:.0f} | {r['ms'] / base:.2f} | {r['edge_pixels']} | {100 * r['cov_off']:.2f}% | "
        f"{r['cov_max']:.3f} | {100 * r['rgb_off']:.2f}% | {r['rgb_max']:.3f} | {r['grad_cos']:.4f} | {r['grad_ratio']:.3f} |\n"
        for r in rows)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cutoffs", type=float, nargs="+", default=[DEFAULT, 1e-3, 1e-2, 5e-2])
    p.add_argument("--repeats", type=int, default=3)
    args = p.parse_args(argv)
    cutoffs = [DEFAULT] + [c for c in args.cutoffs if c != DEFAULT]
    for sections, size, views in ((100, 224, 12), (32, 64, 4)):
        mesh = torus_mesh(sections)
        rows = measure(mesh, cutoffs, size, views, args.repeats)
        print(to_markdown(rows, f"{mesh.names[0]} ({2 * sections * sections} faces), {views} views, {size} px, "
                                f"soft smooth K=8, {torch.get_num_threads()} threads"), flush=True)


if __name__ == "__main__":
    main()
