"""ScanObjectNN point clouds (15 classes) from the official ``h5_files.zip`` of the ScanObjectNN authors.

Layout (as unpacked from ``h5_files.zip``; ``root`` is the folder holding ``main_split``)::

    obj_bg    <root>/main_split/training_objectdataset.h5, test_objectdataset.h5
    obj_only  <root>/main_split_nobg/training_objectdataset.h5, test_objectdataset.h5
    pb_t50_rs <root>/main_split/training_objectdataset_augmentedrot_scale75.h5,
              test_objectdataset_augmentedrot_scale75.h5

Each file holds ``data [N, 2048, 3]`` float32, ``label [N]`` (or ``[N, 1]``) integers in 0..14 and
``mask [N, 2048]`` (-1 on background points, else the object's instance id). The whole file is read
into memory once (at most ~100 MB).

Orientation (an assumption: no real file could be inspected when this was written): the clouds are
used as stored, with no rotation, like the MVTN reference loader and the PointNet++/PointNeXt ones.
Those treat the file's Y axis as the vertical (gravity) axis (PointNeXt: ``gravity_dim: 1``, rotation
augmentation about Y), which matches this project's Y-up convention, so no ``zup_to_yup`` is applied
(unlike ModelNet). The sign of up (+Y or -Y) has not been checked on real files.

Each cloud is centred (bounding box) and scaled into the unit sphere (``normalize_unit_sphere``)
after choosing its points: with ``num_points < 2048`` a fixed subset per cloud (seeded by ``seed`` and
the cloud's row in the file), the same on every epoch and every run.

ScanObjectNN has no validation split: ``val_fraction`` of each class's official training clouds
(``modelnet.val_mask``, chosen with ``seed``) form ``val`` and are left out of ``train``; ``test`` is
the official test file. A cloud with NaN/Inf points is skipped with one log line naming the file and
the row (counted in ``skipped``; ``packed.skip``), or, with ``strict=True``, raises ShapeFileError
with that reason.
"""
from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from .h5io import read_labelled_clouds
from .mesh_io import DatasetNotFound, ShapeFileError, normalize_unit_sphere
from .modelnet import CountWarning, val_mask
from .packed import log_skipped, skip, wrap_index

CLASSES = ["bag", "bin", "box", "cabinet", "chair", "desk", "display", "door", "shelf", "table", "bed", "pillow",
           "sink", "sofa", "toilet"]
POINTS = 2048  # points per cloud in the official files
SPLITS = ("train", "val", "test")
# variant -> (folder, training file, test file)
FILES = {
    "obj_bg": ("main_split", "training_objectdataset.h5", "test_objectdataset.h5"),
    "obj_only": ("main_split_nobg", "training_objectdataset.h5", "test_objectdataset.h5"),
    "pb_t50_rs": ("main_split", "training_objectdataset_augmentedrot_scale75.h5",
                  "test_objectdataset_augmentedrot_scale75.h5"),
}
VARIANTS = tuple(FILES)
EXPECTED = {"obj_bg": {"train": 2309, "test": 581}, "obj_only": {"train": 2309, "test": 581},
            "pb_t50_rs": {"train": 11416, "test": 2882}}
LAYOUT = ("obj_bg: <root>/main_split/{training,test}_objectdataset.h5; obj_only: "
          "<root>/main_split_nobg/{training,test}_objectdataset.h5; pb_t50_rs: "
          "<root>/main_split/{training,test}_objectdataset_augmentedrot_scale75.h5 (h5_files.zip from the "
          "ScanObjectNN authors, https://hkust-vgd.github.io/scanobjectnn/, unpacked; root is the folder "
          "holding main_split)")


def h5_path(root, variant: str, official: str) -> Path:
    """The file of ``variant``'s official ``"train"`` or ``"test"`` split under ``root``."""
    folder, train, test = FILES[variant]
    return Path(root) / folder / (train if official == "train" else test)


def read_h5(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """``data [N, 2048, 3] float32``, ``label [N] int64`` and ``mask [N, 2048] bool`` (True on object
    points; None when the file has no ``mask``), checked; raises ShapeFileError naming file and key."""
    data, label, extra = read_labelled_clouds(
        path, len(CLASSES), POINTS, optional=("mask",),
        expected=f"'data' [N, {POINTS}, 3], 'label' [N] and 'mask' [N, {POINTS}]")
    mask = extra.get("mask")
    if mask is not None:
        if mask.shape != (len(data), POINTS):
            raise ShapeFileError(f"{path}: key 'mask' has shape {mask.shape}; expected [{len(data)}, {POINTS}]")
        mask = mask != -1
    return data.astype(np.float32), label, mask


class ScanObjectNN(Dataset):
    """One split ("train" | "val" | "test") of a ScanObjectNN variant; see the module doc.

    ``ds[i]`` -> ``points [num_points, 3] float32`` (unit sphere, as stored otherwise), ``label``,
    ``name`` (``"pb_t50_rs_train_00012"``: variant, split and the cloud's row in its h5 file) and
    ``mask [num_points] bool`` (True on object points) when the file has one. No mesh.
    Attributes: ``classes``, ``labels``, ``names``, ``path`` (the h5 file), ``skipped`` (one reason
    per cloud of the whole official file left out for NaN/Inf points).
    """

    val_from_train = True  # the val split is carved out of the official train split (retrieval reunites them)

    def __init__(self, root, split: str = "train", variant: str = "pb_t50_rs", num_points: int = POINTS,
                 val_fraction: float = 0.1, seed: int = 0, strict: bool = False):
        if split not in SPLITS:
            raise ValueError(f"scanobjectnn: split={split!r}; expected one of {list(SPLITS)}")
        if variant not in FILES:
            raise ValueError(f"scanobjectnn: variant={variant!r}; expected one of {list(VARIANTS)}")
        if not 1 <= int(num_points) <= POINTS:
            raise ValueError(f"scanobjectnn: num_points={num_points}; ScanObjectNN clouds have {POINTS} points, "
                             f"so num_points must be in 1..{POINTS}")
        root = Path(root)
        official = "test" if split == "test" else "train"
        path = h5_path(root, variant, official)
        if not root.is_dir():
            raise DatasetNotFound(f"ScanObjectNN not found: no folder {root.resolve()} (variant {variant}, file "
                                  f"{path}); expected layout: {LAYOUT}")
        if not path.is_file():
            raise DatasetNotFound(f"ScanObjectNN variant {variant}: no file {path.resolve()}; expected layout: "
                                  f"{LAYOUT}")
        data, labels, mask = read_h5(path)
        expected = EXPECTED[variant][official]
        if len(data) != expected:
            warnings.warn(f"ScanObjectNN {variant} {path}: {len(data)} {official} clouds, the official dataset has "
                          f"{expected}", CountWarning, stacklevel=2)
        finite = np.isfinite(data).all(axis=(1, 2))
        self.skipped: list[str] = []
        for i in np.flatnonzero(~finite):
            skip(f"{path}: key 'data' row {i}: {int((~np.isfinite(data[i])).any(1).sum())} points are NaN or Inf",
                 self.skipped, strict)
        log_skipped(f"ScanObjectNN {variant} {official}", self.skipped, len(data), "clouds")
        rows = np.flatnonzero(finite)
        if official == "train":
            is_val = val_mask(labels[rows], val_fraction, seed)
            rows = rows[is_val if split == "val" else ~is_val]
        self.root, self.path, self.split, self.variant = root, path, split, variant
        self.num_points, self.seed, self.classes = int(num_points), int(seed), list(CLASSES)
        self._data, self._mask, self._rows = data, mask, rows
        self.labels = labels[rows]
        self.names = [f"{variant}_{split}_{r:05d}" for r in rows]

    def __len__(self) -> int:
        return len(self._rows)

    def point_indices(self, row: int) -> np.ndarray:
        """The fixed points (sorted indices into the stored 2048) of the cloud in file row ``row``."""
        if self.num_points == POINTS:
            return np.arange(POINTS)
        rng = np.random.default_rng([self.seed, int(row), 11])
        return np.sort(rng.choice(POINTS, size=self.num_points, replace=False))

    def __getitem__(self, i: int) -> dict:
        i = wrap_index(i, len(self), f"ScanObjectNN {self.variant} {self.split}")
        row = int(self._rows[i])
        idx = self.point_indices(row)
        pts = normalize_unit_sphere(self._data[row][idx].astype(np.float64)).astype(np.float32)
        item = {"points": torch.from_numpy(pts), "label": int(self.labels[i]), "name": self.names[i]}
        if self._mask is not None:
            item["mask"] = torch.from_numpy(self._mask[row][idx].copy())
        return item
