"""Packed shape arrays on disk: one ``.npz`` per dataset split, written atomically, validated on load.

Layout (``PACKED_ARRAYS``): ``verts [sum V, 3] float32``, ``faces [sum F, 3] int32`` (indices local
to each shape), ``verts_per_shape [N]``, ``faces_per_shape [N]``, ``points [N, P, 3] float32``,
``labels [N]``, ``names [N] str``, plus a JSON ``settings`` string: a cache written with other
settings (or by another version) is never misread, it is rebuilt.

Key contract: the settings (and the cache's file name, a hash of them) hold everything that decides
what a cache holds: the reader's options, its preprocessing version and ``files_fingerprint`` (the
root and every file's bytes). An option that decides only whether a cache may be used is checked
against what it holds instead (``strict``: a reader compares it with its ``skipped`` record).
A file that cannot be used is reported once, in one log line (``skip``). A write that fails (a full
disk) raises an OSError naming the file being written, and leaves no temp file and no lock file.
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
import tempfile
import time
import warnings
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path
from typing import Optional

import numpy as np
import torch
from torch.utils.data import Dataset

from .mesh_io import ShapeFileError

log = logging.getLogger("mvtn_exp.data")

PACKED_ARRAYS = ("verts", "faces", "verts_per_shape", "faces_per_shape", "points", "labels", "names")
RACY_NS = 2 * 10**9  # a file changed this recently is read again at the next start (coarse file-system clocks)
FINGERPRINT_VERSION = "2"  # what files_fingerprint hashes; another value names other caches


def file_digest(path) -> str:
    """SHA-1 (hex) of the bytes of the file at ``path``."""
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_BINARY", 0))
    try:
        h = hashlib.sha1()
        while block := os.read(fd, 1 << 20):
            h.update(block)
        return h.hexdigest()
    finally:
        os.close(fd)


def _digests(paths: list) -> list[str]:
    """``file_digest`` of each path, in order; batches of files on a few threads (reads and SHA-1
    release the GIL; one file per task would cost more in dispatch than small files take to hash)."""
    batches = [paths[i:i + 64] for i in range(0, len(paths), 64)]
    with ThreadPoolExecutor(max_workers=min(8, os.cpu_count() or 1)) as pool:
        return [d for batch in pool.map(lambda b: [file_digest(p) for p in b], batches) for d in batch]


def files_fingerprint(paths, root, memo_dir=None) -> str:
    """What a cache built from ``paths`` (files under ``root``) was built from: a SHA-1 of the
    resolved root and, per file, its path under the root and a SHA-1 of its bytes. A cache keyed by
    it is rebuilt for another root (same file names, other contents) or a file whose bytes changed,
    even one edited in place with its size and modification time put back; a file only touched
    (same bytes, new time) keeps its cache.

    ``memo_dir`` (the cache folder): each file's digest is kept in
    ``<memo_dir>/.digests-<root hash>.json`` beside its size, modification and change times (ns) and
    inode, and a file whose four are unchanged is not read again. The change time cannot be set
    back (``os.utime`` itself moves it), so an in-place edit is always read; a file changed less
    than ``RACY_NS`` before it was hashed is read again next time (file-system clocks tick in
    milliseconds). Without ``memo_dir`` every file is read.

    Cost of reading: batches of files on a few threads overlap the reads; SHA-1 runs at about
    1.8 GB/s per core with the CPU's SHA instructions. Measured on 2 cores, files in the page
    cache: 3,000 files of 170 KB (510 MB; ModelNet40's mean file size) 0.21 s, 5,000 files of 4 KB
    0.09 s, 12,311 files of 170 KB (2.1 GB, ModelNet40's size) 0.8-1.0 s, and 0.18 s for those
    12,311 with the memo on a warm start (their stat and the memo's JSON); from a cold disk the
    disk's read speed bounds the reading."""
    root, paths = Path(root), list(paths)
    digests = _memo_digests(paths, root, Path(memo_dir)) if memo_dir is not None else _digests(paths)
    h = hashlib.sha1(f"{FINGERPRINT_VERSION}\n{root.resolve()}".encode())
    for p, digest in zip(paths, digests):
        h.update(f"\n{Path(p).relative_to(root).as_posix()}\t{digest}".encode())
    return h.hexdigest()


def _memo_digests(paths: list, root: Path, memo_dir: Path) -> list[str]:
    """``file_digest`` of each path, reading only the files whose stat changed since the memo."""
    memo_path = memo_dir / f".digests-{hashlib.sha1(str(root.resolve()).encode()).hexdigest()[:16]}.json"
    try:
        memo = json.loads(memo_path.read_text())
    except (OSError, ValueError):
        memo = {}
    stats = []
    for p in paths:
        st = os.stat(p)
        stats.append([st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino])
    names = [Path(p).relative_to(root).as_posix() for p in paths]
    stale = [i for i, (n, st) in enumerate(zip(names, stats)) if (memo.get(n) or [None])[:4] != st]
    now = time.time_ns()
    for i, digest in zip(stale, _digests([paths[i] for i in stale])):
        racy = now - stats[i][2] < RACY_NS  # changed within the clock's tick: read it again next time
        memo[names[i]] = [*(stats[i] if not racy else [None] * 4), digest]
    if stale:
        try:
            _write_json_atomic(memo_path, memo)
        except OSError:
            pass  # (a read-only or full cache folder: the next start reads the files again)
    return [memo[n][4] for n in names]


def _write_json_atomic(path: Path, value) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name + ".", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(value, f)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


_REPORTED: set[str] = set()  # the skip lines this process logged: each is said once per process


def _report(line: str) -> None:
    if line not in _REPORTED:  # (train and val read from one official file report its bad rows once)
        _REPORTED.add(line)
        log.warning("%s", line)


def skip(reason: str, skipped: list, strict: bool) -> None:
    """A file (or row) that cannot be used: with ``strict`` raise ``ShapeFileError(reason)``; else its
    one log line, ``skipping <reason>`` (once per process), and ``reason`` appended to ``skipped``.
    That line is the only report naming the file (no warning repeats it, nor its source line)."""
    if strict:
        raise ShapeFileError(reason)
    _report(f"skipping {reason}")
    skipped.append(reason)


def log_skipped(who: str, skipped, total: int, unit: str) -> None:
    """After the ``skip`` lines: one line ``<who>: skipped N of M <unit>`` (nothing when none was);
    it counts, it names no file again."""
    if len(skipped):
        _report(f"{who}: skipped {len(skipped)} of {total} {unit}")


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


@contextmanager
def writing(path: Path):
    """An OSError raised inside that names no file (a full disk: ENOSPC from a write) is raised
    again naming ``path``, the file being written: its one line then says which and why."""
    try:
        yield
    except OSError as exc:
        if exc.filename is None:
            raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from exc
        raise


def save_npz_atomic(path: Path, arrays: dict[str, np.ndarray], settings: dict) -> None:
    """Write ``arrays`` + ``settings`` to ``path`` via a temp file and ``os.replace`` (never half a
    file). On failure the temp file is removed; an OSError (a full disk) names ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name + ".", suffix=".tmp")
    try:
        with writing(path), os.fdopen(fd, "wb") as fh:
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


def wrap_index(i: int, n: int, what: str) -> int:
    """``i`` in ``[-n, n)`` as an index in ``[0, n)`` (Python's negative indices); else IndexError
    ``<what>: index i out of range for n``."""
    if not -n <= i < n:
        raise IndexError(f"{what}: index {i} out of range for {n}")
    return i % n


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
        i = wrap_index(i, len(self), f"{type(self).__name__} {self.split}")
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
    the others wait, then load it. The lock file is removed when the holder is done, built or failed
    (a full disk, a strict run's bad file, an interrupt): none is left behind. A waiter whose lock
    file was removed meanwhile locks the new one (``_locked``). POSIX ``flock`` (released by the OS
    if the holder dies); where it is missing (Windows) there is no lock and the atomic writes alone
    keep the cache whole."""
    try:
        import fcntl
    except ImportError:
        yield
        return
    lock = path.with_name(path.name + ".lock")
    lock.parent.mkdir(parents=True, exist_ok=True)
    f = _locked(lock, fcntl)
    try:
        yield
    finally:
        lock.unlink(missing_ok=True)  # (still held: whoever locks next checks it is the file at the path)
        fcntl.flock(f, fcntl.LOCK_UN)
        f.close()


def _locked(lock: Path, fcntl):
    """``lock`` opened and flock-ed, and still the file at that path once the lock is held (a holder
    that finished removed the one this process waited on: then lock the current one)."""
    while True:
        f = open(lock, "a")
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            a, b = os.stat(lock), os.fstat(f.fileno())
            if (a.st_dev, a.st_ino) == (b.st_dev, b.st_ino):
                return f
        except FileNotFoundError:
            pass
        fcntl.flock(f, fcntl.LOCK_UN)
        f.close()


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