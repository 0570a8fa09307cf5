"""Checkpoints: atomic writes (temp file + ``os.replace``), loading, and the config compatibility check."""
from __future__ import annotations

import io
import os
import pickle
import tempfile
from pathlib import Path

import numpy as np
import torch

from .dotted import lookup


# config keys (dotted) whose change makes a checkpoint's weights meaningless for the new config
MODEL_KEYS = ("views", "image_size", "selector", "point_encoder", "backbone.name", "mvnet", "dataset.name",
              "dataset.shape", "dataset.variant", "task.name")


# numpy arrays of plain numbers, which older checkpoints hold (numpy's RNG state): rebuilding one runs
# no code of the file's choosing (an object array would need further globals, still refused)
NUMPY_ARRAYS = [(getattr(np, "_core", None) or np.core).multiarray._reconstruct, np.ndarray, np.dtype, type(np.dtype(np.uint32))]


# what ``save_atomic``'s payload holds; another format is refused (docs/training.md#checkpoint-formats)
FORMAT = 4


class CheckpointMismatch(ValueError):
    """A checkpoint was written with a different model-defining config."""


def save_atomic(path, payload: dict) -> Path:
    """``torch.save`` into a temp file beside ``path`` then ``os.replace``: readers never see half a file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    buffer = io.BytesIO()  # serialised in memory first: a full disk then fails in write() with ENOSPC,
    torch.save(payload, buffer)  # not in torch's zip writer as "unexpected pos"
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(buffer.getbuffer())
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        if os.path.exists(tmp):
            os.unlink(tmp)
        if isinstance(exc, OSError) and exc.filename is None:  # name the file (a full disk says no more)
            raise OSError(exc.errno, exc.strerror, str(path)) from exc
        raise
    return path


def describe_non_checkpoint(path: Path) -> str | None:
    """What ``path`` is when it cannot be a ``torch.save`` file (a zip holding ``data.pkl``, or a
    legacy pickle), e.g. "a JSON or other text file (starts with '{"a')"; None when it may be one."""
    import zipfile

    with open(path, "rb") as f:
        head = f.read(64)
    if not head:
        return "an empty file"
    if head.startswith(b"PK\x03\x04"):
        try:
            with zipfile.ZipFile(path) as z:
                names = z.namelist()
        except (zipfile.BadZipFile, OSError):
            return "a damaged zip archive"
        if any(n.endswith("data.pkl") for n in names):
            return None
        kind = "a NumPy .npz archive" if any(n.endswith(".npy") for n in names) else "a zip archive"
        return f"{kind} ({len(names)} entries, e.g. {names[0]!r})" if names else f"{kind} (empty)"
    if head[:1] == b"\x80":  # a pickle (torch.save's legacy format)
        return None
    if head.startswith(b"\x93NUMPY"):
        return "a NumPy .npy array"
    if head.startswith(b"\x89HDF"):
        return "an HDF5 file"
    if head.startswith(b"\x89PNG"):
        return "a PNG image"
    try:
        text = head.decode("utf-8")
    except UnicodeDecodeError:
        return f"binary data of {path.stat().st_size} bytes (starts with {head[:8].hex(' ')})"
    kind = "a JSON or other text file" if text.lstrip()[:1] in ("{", "[") else "a text file"
    return f"{kind} (starts with {text.strip()[:20]!r})"


def load(path, map_location="cpu") -> dict:
    """Read a checkpoint written by ``save_atomic`` (a clear error for a missing or unreadable file).

    Always ``torch.load(weights_only=True)``: only tensors and plain Python containers are
    unpickled, so a file carrying code (any other pickled object) is refused, never run."""
    path = Path(path)
    if path.is_dir():
        found = [name for name in ("best.pt", "last.pt") if (path / name).is_file()]
        hint = f"pass {path / found[0]}" if found else "it holds no best.pt or last.pt"
        raise FileNotFoundError(f"checkpoint {str(path)!r} is a folder, not a checkpoint file: {hint}")
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint {str(path)!r}: no such file")
    what = describe_non_checkpoint(path)
    if what is not None:
        raise CheckpointMismatch(f"checkpoint {str(path)!r} is {what}, not a checkpoint (mvtn-train writes "
                                 "last.pt / best.pt with torch.save)")
    try:
        with torch.serialization.safe_globals(NUMPY_ARRAYS):  # older checkpoints hold numpy RNG keys
            payload = torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as exc:
        what = str(exc).splitlines()
        culprit = next((line.strip() for line in what if "GLOBAL" in line or "Unsupported" in line), what[0] if what else "")
        raise CheckpointMismatch(f"checkpoint {str(path)!r} holds objects other than tensors and plain data, refused "
                                 f"unread (only mvtn-train checkpoints of this version load safely): {culprit}") from exc
    except Exception as exc:
        first = (str(exc).splitlines() or [""])[0]
        raise CheckpointMismatch(f"checkpoint {str(path)!r} cannot be read ({type(exc).__name__}: {first})") from exc
    if not isinstance(payload, dict) or "model" not in payload or "config" not in payload:
        raise CheckpointMismatch(f"checkpoint {str(path)!r} was not written by mvtn-train (no model/config)")
    written = int(payload.get("format", 1))
    if written != FORMAT:
        raise CheckpointMismatch(f"checkpoint {str(path)!r} is in format {written}; this mvtn-exp reads format {FORMAT} "
                                 f"only (docs/training.md#checkpoint-formats names the release that reads format {written})")
    return payload


def _get(cfg: dict, dotted: str):
    return lookup(cfg, dotted)


def _leaves(value, prefix: str) -> dict:
    if isinstance(value, dict):
        out = {}
        for k, v in value.items():
            out.update(_leaves(v, f"{prefix}.{k}"))
        return out
    return {prefix: value}


def check_compatible(saved: dict, current: dict, keys=MODEL_KEYS, free=()) -> None:
    """Raise ``CheckpointMismatch`` naming every model-defining setting (dotted key) that differs;
    ``free``: dotted keys that say how a part trains, not what the model is (may differ)."""
    diff = []
    free = set(free)
    for key in keys:
        old, new = _leaves(_get(saved, key), key), _leaves(_get(current, key), key)
        for leaf in sorted(set(old) | set(new)):
            if leaf in free:  # how G trains, not what the model is
                continue
            if old.get(leaf) != new.get(leaf):
                diff.append(f"{leaf}: checkpoint={old.get(leaf)!r} vs config={new.get(leaf)!r}")
    if diff:
        raise CheckpointMismatch("checkpoint config differs in model-defining settings: " + "; ".join(diff))
