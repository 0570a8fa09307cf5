"""Mixed precision (``precision=fp32|bf16|fp16``): autocast for the multi-view network C only.

G (a small network whose outputs are camera angles) and the renderer R (its candidate search,
depth tests and soft blending compare small differences of large numbers) always run in float32;
C's convolutions and matmuls run in the chosen half type and its logits come back as float32, so
the loss is computed in float32. ``fp16`` scales the loss (``torch.amp.GradScaler``) so small
gradients do not flush to zero; it is refused on CPU, where float16 kernels are missing or slow
(``bf16`` is CPU autocast's type).
"""
from __future__ import annotations

from contextlib import nullcontext

import torch

from ..config.checks import one_of

PRECISIONS = ("fp32", "bf16", "fp16")


def check_precision(precision: str, device: str) -> None:
    """One-line errors naming the keys, for a precision the device cannot run (``models/precision.py``)."""
    one_of("precision", precision, PRECISIONS)
    if precision == "fp16" and not str(device).startswith("cuda"):
        raise ValueError(f"precision=fp16 with device={device}: float16 autocast needs CUDA; on CPU use "
                         "precision=bf16 or fp32")

DTYPES = {"bf16": torch.bfloat16, "fp16": torch.float16}


def autocast(precision: str, device: torch.device):
    """The autocast context of C's forward (a no-op for fp32)."""
    if precision == "fp32":
        return nullcontext()
    return torch.autocast(device_type=torch.device(device).type, dtype=DTYPES[precision])


def grad_scaler(precision: str, device: torch.device) -> torch.amp.GradScaler:
    """A loss scaler, enabled for fp16 only (a pass-through otherwise)."""
    return torch.amp.GradScaler(torch.device(device).type, enabled=precision == "fp16")
