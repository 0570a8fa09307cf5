"""Fixed view layouts (plain functions; the training pipeline's selectors wrap them).

Each returns ``(azim, elev, dist)``, each ``[B, M]``, degrees / degrees / world units.
``spherical`` is one of two constructions of M views spread over the sphere (``SPHERES``):
``equal_area`` (the rings the paper uses, its default) and ``fibonacci``.
"""
from __future__ import annotations

import math

import torch


def _check_m(M: int) -> None:
    if int(M) != M or M < 1:
        raise ValueError(f"views: expected an integer number of views M >= 1, got {M!r}")


def circular(M: int, batch: int = 1, elevation: float = 30.0, distance: float = 2.2, device=None, dtype=torch.float32,
             azim_start: float = 0.0):
    """M views at one elevation, azimuths ``azim_start + 360 k / M`` (k = 0..M-1) in [0, 360)."""
    _check_m(M)
    azim = torch.remainder(float(azim_start) + torch.arange(M, dtype=torch.float64) * (360.0 / M), 360.0)
    azim = azim.to(device=device, dtype=dtype)
    elev = torch.full((M,), float(elevation), device=device, dtype=dtype)
    return _batch(azim, elev, distance, batch)


def spherical(M: int, batch: int = 1, distance: float = 2.2, device=None, dtype=torch.float32,
              sphere: str = "equal_area"):
    """Exactly M views spread over the sphere, by the construction ``sphere`` (``SPHERES``)."""
    if sphere not in SPHERES:
        raise ValueError(f"sphere={sphere!r}: expected one of {', '.join(SPHERES)}")
    return SPHERES[sphere](M, batch, distance, device, dtype)


def equal_area_rings(M: int) -> list[tuple[float, int]]:
    """``[(elevation in degrees, views on that ring), ...]`` from the south pole up, summing to M.

    The equal-area construction the paper uses (Deserno's: cells of area ``a = 4 pi / M``, side
    ``d = sqrt(a)``; ``round(pi / d)`` rings at polar angles ``pi (m + 1/2) / rings``, ring m
    holding ``round(2 pi sin(theta_m) / d_phi)`` views with ``d_phi = a / (pi / rings)``). Its
    rounding gives M - 1 or M + 1 views for some M (and none for others); here the total is then
    corrected to exactly M, deterministically: a missing view goes to the ring whose count was
    rounded down the most (ideal count minus rounded count largest), a view too many leaves the
    ring rounded up the most (ties: the lower ring), one view at a time; a ring left with no
    view disappears. M = 12 gives rings at -60 / 0 / +60 with 3 / 6 / 3 views, as in the paper.
    """
    _check_m(M)
    a = 4.0 * math.pi / M
    rings = max(1, round(math.pi / math.sqrt(a)))
    d_theta = math.pi / rings
    d_phi = a / d_theta
    thetas = [math.pi * (m + 0.5) / rings for m in range(rings)]
    ideal = [2.0 * math.pi * math.sin(t) / d_phi for t in thetas]
    counts = [int(round(x)) for x in ideal]
    while sum(counts) != M:
        short = sum(counts) < M
        residual = [(x - c) if short else (c - x) for x, c in zip(ideal, counts)]
        eligible = [i for i in range(rings) if short or counts[i] > 0]
        i = max(eligible, key=lambda j: (residual[j], -j))
        counts[i] += 1 if short else -1
    return [(math.degrees(t) - 90.0, c) for t, c in zip(thetas, counts) if c > 0]


def equal_area(M: int, batch: int = 1, distance: float = 2.2, device=None, dtype=torch.float32):
    """Exactly M views on the paper's equal-area rings (``equal_area_rings``): ring by ring from
    the south pole up, azimuths ``360 n / (views on the ring)`` starting at 0 (as the official
    code). M = 1: the view (0, 0)."""
    azim, elev = [], []
    for e, n in equal_area_rings(M):
        azim += [360.0 * k / n for k in range(n)]
        elev += [e] * n
    return _batch(torch.tensor(azim, dtype=torch.float64).to(device=device, dtype=dtype),
                  torch.tensor(elev, dtype=torch.float64).to(device=device, dtype=dtype), distance, batch)


def fibonacci(M: int, batch: int = 1, distance: float = 2.2, device=None, dtype=torch.float32):
    """Exactly M near-uniform views on the sphere (Fibonacci lattice).

    ``y_k = 1 - 2 (k + 1/2) / M``, elevation ``asin(y_k)``, azimuth ``k * 137.508`` degrees mod 360.
    M = 1 gives the equator view (0, 0); M = 2 gives two views at +-30 degrees elevation.
    """
    _check_m(M)
    k = torch.arange(M, dtype=torch.float64)
    y = 1.0 - 2.0 * (k + 0.5) / M
    elev = torch.rad2deg(torch.asin(y))
    golden = 180.0 * (3.0 - math.sqrt(5.0))
    azim = torch.remainder(k * golden, 360.0)
    return _batch(azim.to(device=device, dtype=dtype), elev.to(device=device, dtype=dtype), distance, batch)


def _batch(azim, elev, distance, batch):
    B = int(batch)
    return (azim.expand(B, -1).clone(), elev.expand(B, -1).clone(), torch.full((B, len(azim)), float(distance), dtype=azim.dtype, device=azim.device))


SPHERES = {"equal_area": equal_area, "fibonacci": fibonacci}
