"""Checkpoints: atomic writes (temp file + ``os.replace``), loading, and the config compatibility check."""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

import torch

# keys whose change makes a checkpoint's weights meaningless for the new config
MODEL_KEYS = ("views", "selector", "backbone", "shape", "image_size")


class CheckpointMismatch(ValueError):
    """A checkpoint was written with a different model-defining config."""


def save_atomic(path, payload: dict) -> Path:
    """``torch.save`` into a temp file beside ``path`` then ``os.replace``: readers never see half a file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save(payload, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def load(path, map_location="cpu") -> dict:
    """Read a checkpoint written by ``save_atomic`` (a clear error for a missing file)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"ckpt_path={str(path)!r}: no such checkpoint file")
    return torch.load(path, map_location=map_location, weights_only=False)


def check_compatible(saved: dict, current: dict, keys=MODEL_KEYS) -> None:
    """Raise ``CheckpointMismatch`` naming every model-defining key that differs."""
    diff = [k for k in keys if saved.get(k) != current.get(k)]
    if diff:
        detail = ", ".join(f"{k}: checkpoint={saved.get(k)!r} vs config={current.get(k)!r}" for k in diff)
        raise CheckpointMismatch(f"checkpoint config differs in model-defining key(s) {diff} ({detail})")
