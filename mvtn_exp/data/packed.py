"""Packed shape arrays on disk: one ``.npz`` per dataset split, written atomically, validated on load.

Layout (``PACKED_ARRAYS``): ``verts [sum V, 3] float32``, ``faces [sum F, 3] int32`` (indices local
to each shape), ``verts_per_shape [N]``, ``faces_per_shape [N]``, ``points [N, P, 3] float32``,
``labels [N]``, ``names [N] str``, plus a JSON ``settings`` string: a cache written with other
settings (or by another version) is never misread, it is rebuilt.
"""
from __future__ import annotations

import hashlib
import json
from contextlib import contextmanager
import os
import tempfile
import warnings
from pathlib import Path
from typing import Optional

import numpy as np
import torch
from torch.utils.data import Dataset

PACKED_ARRAYS = ("verts", "faces", "verts_per_shape", "faces_per_shape", "points", "labels", "names")


def files_fingerprint(paths, root) -> str:
    """What a cache built from ``paths`` (files under ``root``) was built from: a SHA-1 of the
    resolved root and, per file, its path under the root, size and modification time (ns). A cache
    keyed by it is rebuilt for another root (same file names, other contents) or a changed file."""
    root = Path(root)
    h = hashlib.sha1(str(root.resolve()).encode())
    for p in paths:
        st = Path(p).stat()
        h.update(f"\n{Path(p).relative_to(root).as_posix()}\t{st.st_size}\t{st.st_mtime_ns}".encode())
    return h.hexdigest()


class CacheWarning(UserWarning):
    """A cache file was there but unusable (stale settings, truncated, inconsistent); it is rebuilt."""


def triangle_areas(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    t = v[f]
    return 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)


def sample_surface(v: np.ndarray, f: np.ndarray, n: int, r: np.random.Generator) -> np.ndarray:
    """``n`` area-weighted uniform samples on the triangles: ``[n, 3]``."""
    area = triangle_areas(v, f)
    t = v[f[r.choice(len(f), size=n, p=area / area.sum())]]
    u, w = r.random(n), r.random(n)
    flip = u + w > 1  # fold the unit square onto the triangle
    u, w = np.where(flip, 1 - u, u), np.where(flip, 1 - w, w)
    return t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + w[:, None] * (t[:, 2] - t[:, 0])


def pack(shapes: list[dict], num_points: int, extra: tuple[str, ...] = ()) -> dict[str, np.ndarray]:
    """Shapes (dicts with verts, faces, points, label, name and the ``extra`` keys) -> packed arrays."""
    out = {
        "verts": np.concatenate([s["verts"] for s in shapes]).astype(np.float32).reshape(-1, 3)
        if shapes else np.zeros((0, 3), np.float32),
        "faces": np.concatenate([s["faces"] for s in shapes]).astype(np.int32).reshape(-1, 3)
        if shapes else np.zeros((0, 3), np.int32),
        "verts_per_shape": np.asarray([len(s["verts"]) for s in shapes], np.int64),
        "faces_per_shape": np.asarray([len(s["faces"]) for s in shapes], np.int64),
        "points": np.asarray([s["points"] for s in shapes], np.float32).reshape(-1, num_points, 3),
        "labels": np.asarray([s["label"] for s in shapes], np.int64),
        "names": np.asarray([s["name"] for s in shapes], dtype=str),
    }
    for key in extra:
        out[key] = np.asarray([s[key] for s in shapes], np.float32)
    return out


def validate(a: dict[str, np.ndarray], n: Optional[int], num_points: int, num_classes: int) -> None:
    """Raise ValueError unless the arrays form ``n`` (None: any number of) well-formed shapes."""
    nv, nf = a["verts_per_shape"], a["faces_per_shape"]
    count = len(a["labels"])
    ok = ((n is None or count == n) and len(nv) == len(nf) == len(a["names"]) == count
          and a["points"].shape == (count, num_points, 3) and a["verts"].shape == (int(nv.sum()), 3)
          and a["faces"].shape == (int(nf.sum()), 3) and bool((nv > 0).all()) and bool((nf > 0).all())
          and bool(np.isfinite(a["verts"]).all()) and bool(np.isfinite(a["points"]).all())
          and bool(((a["labels"] >= 0) & (a["labels"] < num_classes)).all()))
    if ok and len(nf):
        hi = np.repeat(nv, nf)[:, None]
        ok = bool(((a["faces"] >= 0) & (a["faces"] < hi)).all())
    if not ok:
        raise ValueError("inconsistent arrays")


def save_npz_atomic(path: Path, arrays: dict[str, np.ndarray], settings: dict) -> None:
    """Write ``arrays`` + ``settings`` to ``path`` via a temp file and ``os.replace`` (never half a file)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name + ".", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            np.savez_compressed(fh, **arrays, settings=np.asarray(json.dumps(settings, sort_keys=True)))
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes it private; give it the usual permissions
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def load_npz(path: Path, settings: dict, keys, check) -> Optional[dict[str, np.ndarray]]:
    """The arrays of ``path`` if it exists, was written with ``settings`` and passes ``check(arrays)``;
    else None (with a CacheWarning when a file was there but unusable)."""
    if not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            stored = json.loads(str(z["settings"]))
            if stored != json.loads(json.dumps(settings, sort_keys=True)):
                raise ValueError(f"written with other settings {stored}")
            arrays = {k: z[k] for k in keys}
        check(arrays)
        return arrays
    except Exception as exc:  # truncated zip, bad CRC, missing key, stale settings, ...
        warnings.warn(f"cache {path} is unusable ({type(exc).__name__}: {exc}); rebuilding it", CacheWarning,
                      stacklevel=3)
        return None


class PackedShapes(Dataset):
    """A dataset split held as packed arrays. ``ds[i]`` -> dict: ``points [P, 3] float32``,
    ``label int``, ``name str`` and, unless ``as_points``, ``verts [V, 3] float32`` and
    ``faces [F, 3] int64`` (what ``collate_shapes`` batches)."""

    def __init__(self, arrays: dict[str, np.ndarray], classes: list[str], split: str, as_points: bool = False):
        self._a, self.classes, self.split, self.as_points = arrays, list(classes), split, bool(as_points)
        self.labels = arrays["labels"]
        self.names = [str(s) for s in arrays["names"]]
        self._vo = np.concatenate([[0], np.cumsum(arrays["verts_per_shape"])])
        self._fo = np.concatenate([[0], np.cumsum(arrays["faces_per_shape"])])

    def __len__(self) -> int:
        return len(self.labels)

    def item(self, i: int) -> dict:
        if not -len(self) <= i < len(self):
            raise IndexError(f"{type(self).__name__} {self.split}: index {i} out of range for {len(self)} shapes")
        i = i % len(self)
        a = self._a
        item = {"points": torch.from_numpy(a["points"][i].copy()), "label": int(a["labels"][i]),
                "name": self.names[i]}
        if not self.as_points:
            item["verts"] = torch.from_numpy(a["verts"][self._vo[i]:self._vo[i + 1]].copy())
            item["faces"] = torch.from_numpy(a["faces"][self._fo[i]:self._fo[i + 1]].astype(np.int64))
        return item

    def __getitem__(self, i: int) -> dict:
        return self.item(i)



@contextmanager
def cache_lock(path: Path):
    """Hold an exclusive lock on ``<path>.lock`` while the cache at ``path`` is looked up and built:
    processes that start together on a cold cache (a parallel sweep, several ranks) build it once;
    the others wait, then load it. POSIX ``flock`` (released by the OS if the holder dies); where
    it is missing (Windows) there is no lock and the atomic writes alone keep the cache whole."""
    try:
        import fcntl
    except ImportError:
        yield
        return
    lock = path.with_name(path.name + ".lock")
    lock.parent.mkdir(parents=True, exist_ok=True)
    with open(lock, "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
            # the cache is written: drop the lock file (a process still waiting on it finds the
            # cache when it gets the lock; one arriving later finds the cache before locking)
            lock.unlink(missing_ok=True)
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def cached_arrays(path: Path, settings: dict, keys, check, build) -> dict[str, np.ndarray]:
    """The arrays cached at ``path`` (see ``load_npz``), or ``build()``'s, checked and then cached
    atomically; built by one process at a time (``cache_lock``)."""
    arrays = load_npz(path, settings, keys, check)
    if arrays is not None:
        return arrays
    with cache_lock(path):
        arrays = load_npz(path, settings, keys, check)  # another process may have built it meanwhile
        if arrays is None:
            arrays = build()
            check(arrays)
            save_npz_atomic(path, arrays, settings)
    return arrays