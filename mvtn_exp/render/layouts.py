"""Fixed view layouts (plain functions; the training pipeline's selectors wrap them).

Each returns ``(azim, elev, dist)``, each ``[B, M]``, degrees / degrees / world units.
"""
from __future__ import annotations

import math

import torch


def _check_m(M: int) -> None:
    if int(M) != M or M < 1:
        raise ValueError(f"views: expected an integer number of views M >= 1, got {M!r}")


def circular(M: int, batch: int = 1, elevation: float = 30.0, distance: float = 2.2, device=None, dtype=torch.float32):
    """M views at one elevation, azimuths ``360 k / M`` (k = 0..M-1)."""
    _check_m(M)
    azim = torch.arange(M, device=device, dtype=dtype) * (360.0 / M)
    elev = torch.full((M,), float(elevation), device=device, dtype=dtype)
    return _batch(azim, elev, distance, batch)


def spherical(M: int, batch: int = 1, distance: float = 2.2, device=None, dtype=torch.float32):
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
