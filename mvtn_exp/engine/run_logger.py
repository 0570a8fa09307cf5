"""TensorBoard logging of a run (``<run_dir>/tb``); every call is a no-op when it is switched off."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ..config.schema import LoggerConfig
from ..viz.images import view_grid


class RunLogger:
    """Scalars, images and histograms for TensorBoard. ``enabled`` is False when
    ``logger.tensorboard=false``; the methods then do nothing."""

    def __init__(self, run_dir, cfg: LoggerConfig) -> None:
        self.cfg = cfg
        self.writer = None
        if cfg.tensorboard:
            from torch.utils.tensorboard import SummaryWriter

            self.writer = SummaryWriter(log_dir=str(Path(run_dir) / "tb"))

    @property
    def enabled(self) -> bool:
        return self.writer is not None

    def scalars(self, values: dict[str, float], step: int) -> None:
        if self.writer is not None:
            for tag, value in values.items():
                self.writer.add_scalar(tag, float(value), step)

    def views(self, tag: str, images: torch.Tensor, step: int, shapes: int = 4) -> None:
        """A grid of the rendered views of the first ``shapes`` shapes (``images [B, M, 3, H, W]``),
        one row per shape."""
        if self.writer is None or not self.cfg.images or images.numel() == 0:  # (a point classifier renders none)
            return
        imgs = images[:shapes].detach().float().cpu().clamp(0, 1)
        grid = view_grid(imgs.reshape(-1, *imgs.shape[2:]), cols=imgs.shape[1])  # [H', W', 3] uint8
        self.writer.add_image(tag, np.ascontiguousarray(grid), step, dataformats="HWC")

    def image(self, tag: str, image, step: int) -> None:
        """One uint8 ``[H, W, 3]`` picture (with ``logger.images``)."""
        if self.writer is not None and self.cfg.images:
            self.writer.add_image(tag, np.ascontiguousarray(image), step, dataformats="HWC")

    def histogram(self, tag: str, values: torch.Tensor, step: int) -> None:
        if self.writer is not None and values.numel() > 0:
            self.writer.add_histogram(tag, values.detach().float().cpu().reshape(-1), step)

    def close(self) -> None:
        if self.writer is not None:
            self.writer.flush()
            self.writer.close()
            self.writer = None
