"""Where a procedural dataset caches its splits: its settings checked, the cache file named by a
hash of every setting, in a root that holds nothing but such caches."""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

SPLITS = ("train", "val", "test")
ROTATIONS = ("none", "y", "so3")


def split_count(split: str, rotate: str, num_per_class, seed: int, num_points: int, max_faces: int,
                who: str = "synthetic") -> int:
    """Check a procedural dataset's settings (ValueError naming the key) -> shapes per class in ``split``."""
    for key, val, allowed in (("split", split, SPLITS), ("rotate", rotate, ROTATIONS)):
        if val not in allowed:
            raise ValueError(f"{who}: {key}={val!r}; expected one of {list(allowed)}")
    counts = tuple(int(c) for c in num_per_class)
    if len(counts) != 3 or min(counts) < 0:
        raise ValueError(f"{who}: num_per_class={num_per_class!r}; expected 3 counts >= 0 (train, val, test)")
    if int(seed) < 0 or int(num_points) < 1 or int(max_faces) < 1:
        raise ValueError(f"{who}: need seed >= 0, num_points >= 1, max_faces >= 1 (got {seed}, {num_points}, {max_faces})")
    return counts[SPLITS.index(split)]


def check_cache_root(root: Path, prefix: str) -> None:
    """A synthetic dataset's root is a cache folder it writes into: refuse one that holds anything
    else (e.g. a real dataset's folder passed by mistake), before writing a byte there."""
    if not root.is_dir():
        return
    for entry in sorted(root.iterdir()):
        if not entry.exists():  # gone since the listing: another run's lock or temp file, released meanwhile
            continue
        if not (entry.is_file() and entry.name.startswith("synthetic") and entry.name.endswith((".npz", ".tmp", ".lock"))):
            raise ValueError(f"dataset {prefix}: root {str(root)!r} holds {entry.name!r}, which is not a synthetic "
                             f"cache file; this root is the folder the dataset caches itself in: point it at an "
                             f"empty or cache-only folder (a real dataset's root belongs to its own dataset=...)")


def cache_file(root, prefix: str, settings: dict) -> Path:
    """``<root>/<prefix>_<split>_<hash>.npz`` (``root`` is created; it must hold nothing but caches:
    ``check_cache_root``); the hash covers every setting."""
    key = hashlib.sha1(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:16]
    root = Path(root)
    check_cache_root(root, prefix)
    root.mkdir(parents=True, exist_ok=True)
    return root / f"{prefix}_{settings['split']}_{key}.npz"
