"""Part labels as colours: the views' label images (predicted above true) and a point cloud
coloured by part, as uint8 RGB arrays for ``images.write_png`` and TensorBoard."""
from __future__ import annotations

import colorsys

import numpy as np
import torch

from .images import view_grid

BACKGROUND = (1.0, 1.0, 1.0)  # a pixel that shows no primitive (label -1)


def palette(n: int) -> np.ndarray:
    """``[n, 3]`` float32 colours in [0, 1], one per part id: hues a golden-ratio step apart, in
    three bands of saturation and value, so neighbouring ids (one category's parts) differ most."""
    hue = (np.arange(n) * 0.618033988749895) % 1.0
    band = np.arange(n) % 3
    sat, val = np.array([0.85, 0.55, 0.95])[band], np.array([0.9, 0.75, 0.6])[band]
    return np.array([colorsys.hsv_to_rgb(h, s, v) for h, s, v in zip(hue, sat, val)], np.float32).reshape(n, 3)


def part_colors(labels, n: int) -> np.ndarray:
    """Labels ``[...]`` (part ids ``< n``; -1: background) -> ``[..., 3]`` float32 colours."""
    labels = labels.detach().cpu().numpy() if isinstance(labels, torch.Tensor) else np.asarray(labels)
    table = np.concatenate([palette(n), np.asarray([BACKGROUND], np.float32)])
    return table[np.where(labels < 0, n, labels)]


def label_views(pred, true, n: int, pad: int = 2) -> np.ndarray:
    """The M views' label images, ``pred`` and ``true`` ``[M, H, W]`` -> one uint8 grid: the
    predicted labels in the first row, the true ones below, a view per column."""
    M = pred.shape[0]
    both = np.concatenate([part_colors(pred, n), part_colors(true, n)]).transpose(0, 3, 1, 2)
    return view_grid(torch.from_numpy(both), cols=M, pad=pad)


def points_image(points, labels, n: int, size: int = 256, azim: float = 45.0, elev: float = 30.0,
                 radius: int = 1) -> np.ndarray:
    """Points ``[P, 3]`` coloured by part ``[P]`` seen orthographically from (azim, elev) degrees
    -> ``[size, size, 3]`` uint8 with a depth test (a nearer point hides a farther one); each point
    a square of ``2 * radius + 1`` pixels, the cloud scaled to fill the image."""
    p = points.detach().cpu().numpy() if isinstance(points, torch.Tensor) else np.asarray(points, np.float64)
    a, e = np.radians(azim), np.radians(elev)
    right = np.array([np.cos(a), 0.0, -np.sin(a)])
    toward = np.array([np.sin(a) * np.cos(e), np.sin(e), np.cos(a) * np.cos(e)])  # to the camera
    up = np.cross(toward, right)
    x, y, depth = p @ right, p @ up, -(p @ toward)  # depth: larger is farther
    scale = (size - 2 * radius - 1) / max(float(np.ptp(x)), float(np.ptp(y)), 1e-12)
    col = np.round((x - x.min()) * scale).astype(int) + radius
    row = np.round((y.max() - y) * scale).astype(int) + radius
    colors = part_colors(labels, n)
    image = np.tile(np.asarray(BACKGROUND, np.float32), (size, size, 1))
    nearest = np.full((size, size), np.inf)
    for k in np.argsort(-depth):  # far to near: nearer points paint over
        r0, c0 = row[k] - radius, col[k] - radius
        window = nearest[r0:r0 + 2 * radius + 1, c0:c0 + 2 * radius + 1]
        keep = depth[k] <= window
        window[keep] = depth[k]
        image[r0:r0 + 2 * radius + 1, c0:c0 + 2 * radius + 1][keep] = colors[k]
    return (image * 255 + 0.5).astype(np.uint8)
