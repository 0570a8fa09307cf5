"""ModelNet40 point clouds as released by the PointNet / PointNet++ authors (no meshes).

Two formats, each read from its folder as unpacked (``root`` is that folder):

``normal_resampled`` (``modelnet40_normal_resampled.zip``, PointNet++): ``<root>/modelnet40_shape_names.txt``
    (or ``shape_names.txt``), ``<root>/modelnet40_{train,test}.txt`` listing ids (``night_stand_0001``)
    and ``<root>/<class>/<id>.txt`` per id: 10,000 lines ``x,y,z,nx,ny,nz``. The class of an id is the id
    without its trailing ``_NNNN`` (class names have underscores: ``flower_pot``). A cloud is the first
    ``num_points`` lines of its file (the files are uniformly resampled already; the authors' loader
    does the same), so only those lines are read and checked; normals are dropped.
``ply_hdf5_2048`` (``modelnet40_ply_hdf5_2048.zip``, PointNet): ``<root>/shape_names.txt``,
    ``<root>/{train,test}_files.txt`` listing h5 files (as ``data/modelnet40_ply_hdf5_2048/ply_data_train0.h5``:
    each entry is resolved by its file name inside ``root``), each with ``data [N, 2048, 3]``,
    ``label [N, 1]`` (uint8; index into the names file) and ``normal``. Names: ``<h5 stem>_<row:04d>``
    (``ply_data_train0_0007``). With ``num_points < 2048`` a cloud is a fixed subset of its points, seeded
    by ``seed`` and its name (sorted indices; the same every epoch and run).

``classes``: the names file, in its order (label = index). Labels are never re-sorted.

Orientation. Decision: neither format is rotated (``zup=None`` means False for both); ``zup=True``
applies ``zup_to_yup`` (rotate -90 degrees about X: the file's +Z becomes our +Y) for data that is
Z-up. Evidence: the Princeton OFF meshes are Z-up, but both releases were re-sampled and written by
the PointNet authors, whose own code treats Y as up in both: PointNet's ``provider.rotate_point_cloud``
("rotation is per shape based along up direction") rotates about Y on the h5 files, and PointNet++
(charlesq34/pointnet2) trains on *both* releases (``modelnet_dataset.py`` for normal_resampled,
``modelnet_h5_dataset.py`` for the h5 files) with that same about-Y augmentation. Were either release
Z-up like the OFF files, that "up direction" augmentation would tumble its shapes end over end. Caveat:
no real file of either release could be inspected when this was written (none in shared/data), and
the sign of up (+Y or -Y) is not established by that evidence; pass ``zup=True`` if real files show
the OFF files' Z-up.

After choosing the points (and rotating, if asked), each cloud is centred (bounding box) and scaled
into the unit sphere (``normalize_unit_sphere``), as the mesh reader does.

Splits: ModelNet has no validation split: ``val_fraction`` of each class of the official train split
(``modelnet.val_mask``, chosen with ``seed`` among all the shapes the split lists, before any is
skipped, so a broken file never moves other shapes between train and val) form ``val`` and are left
out of ``train``; ``test`` is the official test split.

Bad input: a missing root, names file, list file or listed data file raises ``DatasetNotFound`` naming
the path, the format, the expected layout and where the data comes from. A cloud that cannot be used
(a non-numeric line, NaN/Inf coordinates, fewer lines than ``num_points``; an unknown id in the list)
is skipped with one log line giving its reason (file and line; ``packed.skip``), kept in ``skipped``
(list ids that name no class are in ``train``'s and ``val``'s alike: they belong to neither; the
line is logged once), or raises
``ShapeFileError`` with ``strict=True``. A malformed h5 file (missing key, wrong shapes, labels outside
the names file) always raises. Splits or names files of another size than the official release give a
``CountWarning`` with both numbers. Everything is read at construction (the official train split of
normal_resampled is ~8,900 small text reads for ``train``; ``val`` reads only its own files).
"""
from __future__ import annotations

import re
import warnings
import zlib
from pathlib import Path, PurePosixPath
from typing import Optional

import numpy as np
import torch
from torch.utils.data import Dataset

from .h5io import read_labelled_clouds
from .mesh_io import DatasetNotFound, ShapeFileError, normalize_unit_sphere, zup_to_yup
from .modelnet import CountWarning, val_mask
from .packed import log_skipped, skip, wrap_index

FORMATS = ("normal_resampled", "ply_hdf5_2048")
SPLITS = ("train", "val", "test")
NUM_CLASSES = 40
EXPECTED = {"normal_resampled": {"train": 9843, "test": 2468}, "ply_hdf5_2048": {"train": 9840, "test": 2468}}
MAX_POINTS = {"normal_resampled": 10000, "ply_hdf5_2048": 2048}  # points per cloud in the releases
ZUP_DEFAULT = {"normal_resampled": False, "ply_hdf5_2048": False}  # both are Y-up already (module doc)
LAYOUTS = {
    "normal_resampled": "<root>/modelnet40_shape_names.txt (or shape_names.txt), <root>/modelnet40_train.txt and "
                        "<root>/modelnet40_test.txt (one id per line, e.g. night_stand_0001) and <root>/<class>/<id>.txt "
                        "for every listed id (10,000 lines 'x,y,z,nx,ny,nz'); root is the unpacked "
                        "modelnet40_normal_resampled folder (9843 train / 2468 test shapes)",
    "ply_hdf5_2048": "<root>/shape_names.txt, <root>/train_files.txt and <root>/test_files.txt (one h5 path per "
                     "line, found by its file name inside root) and the listed <root>/ply_data_{train0..4,test0..1}.h5 "
                     "(keys data [N, 2048, 3], label [N, 1]); root is the unpacked modelnet40_ply_hdf5_2048 folder "
                     "(9840 train / 2468 test clouds)",
}
SOURCES = {
    "normal_resampled": "modelnet40_normal_resampled.zip from the PointNet++ authors (Qi et al., "
                        "https://github.com/charlesq34/pointnet2, data/README.md: "
                        "https://shapenet.cs.stanford.edu/media/modelnet40_normal_resampled.zip)",
    "ply_hdf5_2048": "modelnet40_ply_hdf5_2048.zip from the PointNet authors (Qi et al., "
                     "https://github.com/charlesq34/pointnet: "
                     "https://shapenet.cs.stanford.edu/media/modelnet40_ply_hdf5_2048.zip)",
}
NAMES_FILES = {"normal_resampled": ("modelnet40_shape_names.txt", "shape_names.txt"),
               "ply_hdf5_2048": ("shape_names.txt",)}
LIST_FILES = {"normal_resampled": "modelnet40_{}.txt", "ply_hdf5_2048": "{}_files.txt"}
ID_RE = re.compile(r"(.+)_(\d+)")


def _not_found(fmt: str, what: str) -> DatasetNotFound:
    return DatasetNotFound(f"ModelNet40 {fmt}: {what}; expected layout: {LAYOUTS[fmt]}. The data is "
                           f"{SOURCES[fmt]}.")


def read_shape_names(root: Path, fmt: str) -> tuple[Path, list[str]]:
    """The names file of ``fmt`` under ``root`` and its class names, in file order."""
    for name in NAMES_FILES[fmt]:
        path = root / name
        if path.is_file():
            break
    else:
        raise _not_found(fmt, f"no class names file {' or '.join(str(root / n) for n in NAMES_FILES[fmt])}")
    classes = [line.strip() for line in path.read_text(errors="replace").splitlines() if line.strip()]
    if not classes:
        raise ShapeFileError(f"{path}: no class names (expected one ModelNet40 class per line)")
    dup = sorted({c for c in classes if classes.count(c) > 1})
    if dup:
        raise ShapeFileError(f"{path}: class names listed twice: {dup}")
    if len(classes) != NUM_CLASSES:
        warnings.warn(f"ModelNet40 {fmt}: {path} lists {len(classes)} classes, the official dataset has "
                      f"{NUM_CLASSES}", CountWarning, stacklevel=3)
    return path, classes


def _parse_txt(path: Path, num_points: int) -> np.ndarray:
    """Line by line (slow, exact): the first ``num_points`` rows ``[n, 3]``, or ShapeFileError naming the line."""
    rows, ncols = [], None
    with open(path, errors="replace") as fh:
        for lineno, line in enumerate(fh, 1):
            s = line.strip()
            if not s:
                continue
            try:
                vals = [float(t) for t in s.split(",")]
            except ValueError:
                raise ShapeFileError(f"{path}: line {lineno}: not comma-separated numbers x,y,z,nx,ny,nz: "
                                     f"{s[:60]!r}") from None
            if len(vals) < 3 or (ncols is not None and len(vals) != ncols):
                raise ShapeFileError(f"{path}: line {lineno}: {len(vals)} values, expected "
                                     f"{ncols or 'at least 3'} (x,y,z,nx,ny,nz)")
            ncols = len(vals)
            if not np.isfinite(vals[:3]).all():
                raise ShapeFileError(f"{path}: line {lineno}: NaN or Inf coordinate: {s[:60]!r}")
            rows.append(vals[:3])
            if len(rows) == num_points:
                break
    return np.asarray(rows, np.float64).reshape(-1, 3)


def read_points_txt(path, num_points: int) -> np.ndarray:
    """The first ``num_points`` points ``[num_points, 3]`` float64 of a normal_resampled file (normals
    dropped); ShapeFileError naming the file (and the line) when they are not all there and finite."""
    path = Path(path)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # numpy: empty file / blank lines and max_rows
            a = np.loadtxt(path, delimiter=",", comments=None, max_rows=num_points, ndmin=2, dtype=np.float64)
        ok = a.shape[1] >= 3 and bool(np.isfinite(a[:, :3]).all())
    except ValueError:  # non-numeric, ragged or undecodable: the slow parser names the line
        ok = False
    except OSError as exc:
        raise ShapeFileError(f"{path}: unreadable ({exc})") from None
    pts = a[:, :3] if ok else _parse_txt(path, num_points)
    if len(pts) < num_points:
        raise ShapeFileError(f"{path}: {len(pts)} points, fewer than num_points={num_points}")
    return pts


def read_h5(path: Path, num_classes: int) -> tuple[np.ndarray, np.ndarray]:
    """``data [N, P, 3]`` float and ``label [N]`` int64 (checked against ``num_classes``, the names
    file's classes) of one ply_hdf5_2048 file; ShapeFileError naming the file and the key otherwise."""
    data, label, _ = read_labelled_clouds(path, num_classes, expected="'data' [N, 2048, 3] and 'label' [N, 1]")
    return data, label


def h5_point_indices(name: str, available: int, num_points: int, seed: int) -> np.ndarray:
    """The fixed points (sorted indices into its ``available``) of the h5 cloud called ``name``."""
    if num_points == available:
        return np.arange(available)
    rng = np.random.default_rng([int(seed), zlib.crc32(name.encode()), 13])
    return np.sort(rng.choice(available, size=num_points, replace=False))


class ModelNetPoints(Dataset):
    """One split ("train" | "val" | "test") of ModelNet40 point clouds; see the module doc.

    ``ds[i]`` -> ``points [num_points, 3] float32`` (Y-up, unit sphere), ``label`` (int) and ``name``
    (``"night_stand_0001"`` / ``"ply_data_train0_0007"``); no mesh. Attributes: ``classes`` (names-file
    order), ``labels``, ``names``, ``skipped`` (one reason per cloud of this split left out), ``zup``.
    """

    val_from_train = True  # the val split is carved out of the official train split (retrieval reunites them)

    def __init__(self, root, split: str = "train", format: str = "normal_resampled", num_points: int = 2048,
                 val_fraction: float = 0.1, seed: int = 0, strict: bool = False, zup: Optional[bool] = None):
        if split not in SPLITS:
            raise ValueError(f"modelnet_points: split={split!r}; expected one of {list(SPLITS)}")
        if format not in FORMATS:
            raise ValueError(f"modelnet_points: format={format!r}; expected one of {list(FORMATS)}")
        if not 1 <= int(num_points) <= MAX_POINTS[format]:
            raise ValueError(f"modelnet_points: num_points={num_points}; {format} clouds have "
                             f"{MAX_POINTS[format]} points, so num_points must be in 1..{MAX_POINTS[format]}")
        root = Path(root)
        if not root.is_dir():
            raise _not_found(format, f"no folder {root.resolve()}")
        self.root, self.split, self.format = root, split, format
        self.num_points, self.seed, self.strict = int(num_points), int(seed), bool(strict)
        self.zup = ZUP_DEFAULT[format] if zup is None else bool(zup)
        self.names_path, self.classes = read_shape_names(root, format)
        official = "test" if split == "test" else "train"
        self.list_path = root / LIST_FILES[format].format(official)
        if not self.list_path.is_file():
            raise _not_found(format, f"no {official} list file {self.list_path}")
        self.skipped: list[str] = []
        read = self._read_txt if format == "normal_resampled" else self._read_h5
        clouds, labels, names = read(official, float(val_fraction))
        log_skipped(f"ModelNet40 {format} {split}", self.skipped, len(self.skipped) + len(names), "clouds")
        self._points = np.zeros((len(clouds), self.num_points, 3), np.float32)
        for i, pts in enumerate(clouds):
            self._points[i] = normalize_unit_sphere(zup_to_yup(pts) if self.zup else pts)
        self.labels = np.asarray(labels, np.int64)
        self.names = list(names)

    # ------------------------------------------------------------------ reading
    def _bad(self, reason: str) -> None:
        skip(reason, self.skipped, self.strict)

    def _count(self, official: str, n: int) -> None:
        expected = EXPECTED[self.format][official]
        if n != expected:
            warnings.warn(f"ModelNet40 {self.format} at {self.root}: {n} {official} clouds listed, the official "
                          f"dataset has {expected}", CountWarning, stacklevel=4)

    def _in_split(self, labels: np.ndarray, val_fraction: float) -> np.ndarray:
        if self.split == "test":
            return np.ones(len(labels), bool)
        is_val = val_mask(labels, val_fraction, self.seed)
        return is_val if self.split == "val" else ~is_val

    def _read_txt(self, official: str, val_fraction: float):
        index = {c: i for i, c in enumerate(self.classes)}
        entries = []  # (id, label)
        n_listed = 0
        for lineno, line in enumerate(self.list_path.read_text(errors="replace").splitlines(), 1):
            sid = line.strip()
            if not sid:
                continue
            n_listed += 1
            m = ID_RE.fullmatch(sid)
            if m is None or m.group(1) not in index:
                self._bad(f"{self.list_path}: line {lineno}: id {sid!r} is not <class>_NNNN with a class of "
                          f"{self.names_path.name}")
                continue
            entries.append((sid, index[m.group(1)]))
        self._count(official, n_listed)
        paths = [self.root / sid[:sid.rindex("_")] / f"{sid}.txt" for sid, _ in entries]
        missing = [p for p in paths if not p.is_file()]
        if missing:
            raise _not_found(self.format, f"no file {missing[0]} (listed in {self.list_path}; {len(missing)} of "
                                          f"{len(paths)} listed files missing)")
        keep = self._in_split(np.asarray([lab for _, lab in entries], np.int64), val_fraction)
        clouds, labels, names = [], [], []
        for (sid, lab), path, k in zip(entries, paths, keep):
            if not k:
                continue
            try:
                clouds.append(read_points_txt(path, self.num_points))
            except ShapeFileError as exc:
                self._bad(str(exc))
                continue
            labels.append(lab)
            names.append(sid)
        return clouds, labels, names

    def _read_h5(self, official: str, val_fraction: float):
        entries = [line.strip() for line in self.list_path.read_text(errors="replace").splitlines() if line.strip()]
        paths = [self.root / PurePosixPath(e.replace("\\", "/")).name for e in entries]
        for e, p in zip(entries, paths):
            if not p.is_file():
                raise _not_found(self.format, f"no file {p} (listed as {e!r} in {self.list_path}; list entries "
                                              "are found by their file name inside root)")
        datas, labels, names = [], [], []
        for p in paths:
            data, label = read_h5(p, len(self.classes))
            if data.shape[1] < self.num_points:
                raise ValueError(f"modelnet_points: num_points={self.num_points} but {p} has clouds of "
                                 f"{data.shape[1]} points")
            datas.append(data)
            labels.append(label)
            names += [(p, f"{p.stem}_{i:04d}", i) for i in range(len(data))]
        labels = np.concatenate(labels) if labels else np.zeros(0, np.int64)
        self._count(official, len(labels))
        keep = self._in_split(labels, val_fraction)
        clouds, out_labels, out_names = [], [], []
        offsets = np.cumsum([0] + [len(d) for d in datas])
        for j in np.flatnonzero(keep):
            f = int(np.searchsorted(offsets, j, side="right") - 1)
            path, name, row = names[j]
            cloud = datas[f][row]
            finite = np.isfinite(cloud).all(1)
            if not finite.all():
                self._bad(f"{path}: key 'data' row {row} ({name}): {int((~finite).sum())} points are NaN or Inf")
                continue
            idx = h5_point_indices(name, len(cloud), self.num_points, self.seed)
            clouds.append(cloud[idx].astype(np.float64))
            out_labels.append(int(labels[j]))
            out_names.append(name)
        return clouds, out_labels, out_names

    # ------------------------------------------------------------------ access
    def __len__(self) -> int:
        return len(self.labels)

    def __getitem__(self, i: int) -> dict:
        i = wrap_index(i, len(self), f"ModelNet40 {self.format} {self.split}")
        return {"points": torch.from_numpy(self._points[i].copy()), "label": int(self.labels[i]),
                "name": self.names[i]}
