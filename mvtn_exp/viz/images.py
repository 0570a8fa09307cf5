"""Image grids and PNG files (standard library zlib encoder: no imaging dependency)."""
from __future__ import annotations

import math
import struct
import zlib
from pathlib import Path

import numpy as np
import torch


def view_grid(images: torch.Tensor, cols: int | None = None, pad: int = 2, pad_value: float = 0.5) -> np.ndarray:
    """``[M, 3, H, W]`` in [0, 1] -> ``[rows*(H+pad)-pad, cols*(W+pad)-pad, 3]`` uint8 grid."""
    imgs = images.detach().float().clamp(0, 1).cpu().numpy()
    M, _, H, W = imgs.shape
    cols = cols or math.ceil(math.sqrt(M))
    rows = math.ceil(M / cols)
    grid = np.full((rows * (H + pad) - pad, cols * (W + pad) - pad, 3), pad_value, dtype=np.float32)
    for k in range(M):
        r, c = divmod(k, cols)
        grid[r * (H + pad): r * (H + pad) + H, c * (W + pad): c * (W + pad) + W] = imgs[k].transpose(1, 2, 0)
    return (grid * 255 + 0.5).astype(np.uint8)


def write_png(path: str | Path, rgb: np.ndarray) -> Path:
    """Write an ``[H, W, 3]`` uint8 array as an 8-bit RGB PNG."""
    rgb = np.ascontiguousarray(rgb, dtype=np.uint8)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"write_png: expected [H, W, 3] uint8, got {rgb.shape}")
    H, W, _ = rgb.shape
    raw = b"".join(b"\x00" + rgb[i].tobytes() for i in range(H))

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    png = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", W, H, 8, 2, 0, 0, 0))
    png += chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b"")
    path = Path(path)
    path.write_bytes(png)
    return path
