"""ScanObjectNN from the per-object files (``dataset.format=object_dataset``): OBJ_BG and OBJ_ONLY with
as many points as asked (the paper's 5,000, L251), where the h5 release holds 2,048.

Layout (``object_dataset.zip`` of the ScanObjectNN authors, unpacked; ``root`` is the folder holding
``object_dataset``)::

    <root>/object_dataset/split_new.txt            obj_id <TAB> label <TAB> split ("t": test, else train)
    <root>/object_dataset/<class>/<obj_id>.bin     one scanned object with its background

A ``.bin`` file is float32: the point count, then per point ``x, y, z, nx, ny, nz, r, g, b, label,
nyu_label`` (11 values). Files whose name holds ``part`` or ``indices`` are not objects and are
skipped. ``obj_bg`` reads every point; ``obj_only`` keeps the object's: the points of the most common
``nyu_label`` among those that are not 0, 1 or 2 (unlabelled, wall, floor), as the authors' and
MVTN's loaders do. PB_T50_RS exists only in the h5 release (``format=h5``).

``num_points`` points per object, a fixed choice per object (seeded by ``seed`` and the object's id:
the same on every epoch and run; without replacement when the object has enough points, else with
replacement). The official loaders draw afresh with replacement at every access; the fixed choice
keeps evaluation repeatable. Each cloud is then centred and scaled into the unit sphere, and its
``mask`` marks the object's points (all of them for ``obj_only``). Files are read when an item is
asked for (an object with its background can hold tens of thousands of points). ``val_fraction``
of each class's training objects form ``val`` (``modelnet.val_mask``).
"""
from __future__ import annotations

import zlib
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from .mesh_io import DatasetNotFound, ShapeFileError, normalize_unit_sphere
from .modelnet import val_mask
from .packed import log_skipped, skip, wrap_index
from .scanobjectnn import CLASSES, SPLITS

FOLDER = "object_dataset"
SPLIT_FILE = "split_new.txt"
VARIANTS = ("obj_bg", "obj_only")
VALUES = 11  # per point: x, y, z, nx, ny, nz, r, g, b, label, nyu_label
BACKGROUND = (0.0, 1.0, 2.0)  # nyu labels that are never the object: unlabelled, wall, floor
LAYOUT = (f"<root>/{FOLDER}/{SPLIT_FILE} (obj_id, label, split: 't' for test) and <root>/{FOLDER}/<class>/<obj_id>.bin "
          "(object_dataset.zip from the ScanObjectNN authors, https://hkust-vgd.github.io/scanobjectnn/, unpacked; "
          f"root is the folder holding {FOLDER})")


def read_split(path: Path) -> list[tuple[str, int, bool]]:
    """``split_new.txt`` -> ``(obj_id, label, is_test)`` per line; a malformed line is one ShapeFileError."""
    out = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        parts = line.split("\t")
        if len(parts) != 3 or not parts[1].strip().lstrip("-").isdigit():
            raise ShapeFileError(f"{path}:{n}: expected 'obj_id<TAB>label<TAB>split', got {line!r}")
        label = int(parts[1])
        if not 0 <= label < len(CLASSES):
            raise ShapeFileError(f"{path}:{n}: label {label} is not a ScanObjectNN class (0..{len(CLASSES) - 1})")
        out.append((parts[0].strip(), label, parts[2].strip() == "t"))
    return out


def check_size(path: Path) -> str | None:
    """Why an object file cannot be read (its size disagrees with the count in its header), else None;
    reads 4 bytes."""
    head = np.fromfile(path, dtype=np.float32, count=1)
    count = int(head[0]) if len(head) and np.isfinite(head[0]) else -1
    size = path.stat().st_size
    if count < 1 or size != 4 * (1 + VALUES * count):
        return f"{path}: {size} bytes; expected 4 x (1 + {VALUES} x the count in its first value, {head[0] if len(head) else 'none'})"
    return None


def read_bin(path: Path) -> np.ndarray:
    """``[N, 11]`` float32 of one object file; a file whose size disagrees with its count, or with a
    NaN/Inf coordinate, is one ShapeFileError naming it."""
    raw = np.fromfile(path, dtype=np.float32)
    count = int(raw[0]) if len(raw) and np.isfinite(raw[0]) else -1
    if count < 1 or len(raw) != 1 + VALUES * count:
        raise ShapeFileError(f"{path}: {len(raw)} float32 values; expected 1 + {VALUES} x the count in its first value "
                             f"({raw[0] if len(raw) else 'none'})")
    pts = raw[1:].reshape(count, VALUES)
    if not np.isfinite(pts[:, :3]).all():
        raise ShapeFileError(f"{path}: {int((~np.isfinite(pts[:, :3])).any(1).sum())} points are NaN or Inf")
    return pts


def object_points(pts: np.ndarray, variant: str, path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(xyz ``[n, 3]``, object mask ``[n]``) of an object file's points for ``variant``."""
    nyu = pts[:, -1]
    candidates = nyu[~np.isin(nyu, BACKGROUND)]
    if len(candidates) == 0:
        raise ShapeFileError(f"{path}: no point carries an object label (every nyu_label is 0, 1 or 2)")
    values, counts = np.unique(candidates, return_counts=True)
    mask = nyu == values[np.argmax(counts)]
    if variant == "obj_only":
        return pts[mask, :3], np.ones(int(mask.sum()), bool)
    return pts[:, :3], mask


class ScanObjectNNObjects(Dataset):
    """One split ("train" | "val" | "test") of OBJ_BG or OBJ_ONLY from the per-object files (module doc).

    ``ds[i]`` -> ``points [num_points, 3] float32`` (unit sphere), ``label``, ``name`` (the object id)
    and ``mask [num_points] bool`` (object points). Attributes: ``classes``, ``labels``, ``names``,
    ``paths``, ``skipped`` (one reason per object file left out: its size disagrees with its count;
    ``strict=True`` raises instead).
    """

    val_from_train = True

    def __init__(self, root, split: str = "train", variant: str = "obj_bg", num_points: int = 5000,
                 val_fraction: float = 0.1, seed: int = 0, strict: bool = False):
        if split not in SPLITS:
            raise ValueError(f"scanobjectnn: split={split!r}; expected one of {list(SPLITS)}")
        if variant not in VARIANTS:
            raise ValueError(f"dataset.variant={variant}: the per-object files (dataset.format=object_dataset) hold "
                             f"{' and '.join(VARIANTS)}; pb_t50_rs exists only in the h5 release (dataset.format=h5)")
        folder = Path(root) / FOLDER
        split_file = folder / SPLIT_FILE
        if not split_file.is_file():
            raise DatasetNotFound(f"ScanObjectNN per-object files not found: no file {split_file.resolve()}; "
                                  f"expected layout: {LAYOUT}")
        entries = read_split(split_file)
        files = {p.name: p for p in folder.glob("*/*.bin") if "part" not in p.name and "indices" not in p.name}
        missing = [e[0] for e in entries if e[0] not in files]
        if missing:
            raise DatasetNotFound(f"{split_file}: {len(missing)} listed objects have no file under {folder}/<class>/, "
                                  f"e.g. {missing[0]}")
        official = [e for e in entries if e[2] == (split == "test")]
        bad = {e[0]: why for e in official if (why := check_size(files[e[0]])) is not None}
        self.skipped: list[str] = []
        for why in bad.values():
            skip(why, self.skipped, strict)
        log_skipped(f"ScanObjectNN {variant} {'test' if split == 'test' else 'train'}", self.skipped, len(official),
                    "object files")
        official = [e for e in official if e[0] not in bad]
        labels = np.array([e[1] for e in official], dtype=np.int64)
        keep = np.ones(len(official), bool)
        if split != "test":
            is_val = val_mask(labels, val_fraction, seed)
            keep = is_val if split == "val" else ~is_val
        self.variant, self.split, self.num_points, self.seed = variant, split, int(num_points), int(seed)
        self.classes = list(CLASSES)
        self.names = [e[0] for e, k in zip(official, keep) if k]
        self.labels = labels[keep]
        self.paths = [files[n] for n in self.names]

    def __len__(self) -> int:
        return len(self.names)

    def point_indices(self, name: str, available: int) -> np.ndarray:
        """The fixed choice of ``num_points`` of ``available`` points for object ``name``."""
        rng = np.random.default_rng([self.seed, zlib.crc32(name.encode()), 13])
        return np.sort(rng.choice(available, size=self.num_points, replace=available < self.num_points))

    def __getitem__(self, i: int) -> dict:
        i = wrap_index(i, len(self), f"ScanObjectNN {self.variant} {self.split}")
        path = self.paths[i]
        xyz, mask = object_points(read_bin(path), self.variant, path)
        idx = self.point_indices(self.names[i], len(xyz))
        pts = normalize_unit_sphere(xyz[idx].astype(np.float64)).astype(np.float32)
        return {"points": torch.from_numpy(pts), "label": int(self.labels[i]), "name": self.names[i],
                "mask": torch.from_numpy(mask[idx].copy())}
