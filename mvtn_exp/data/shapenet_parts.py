"""ShapeNet Parts (the part segmentation benchmark, 16 categories, 50 parts) from the PointNet++
release ``shapenetcore_partanno_segmentation_benchmark_v0_normal``, preprocessed once into a cache.

Layout (``root`` is the unpacked release folder)::

    <root>/synsetoffset2category.txt                                  "Airplane<TAB>02691156" per line
    <root>/train_test_split/shuffled_{train,val,test}_file_list.json  ["shape_data/<synset>/<id>", ...]
    <root>/<synset>/<id>.txt                                          "x y z nx ny nz part" per point

``part`` (written as a float, ``2.000000``) is the GLOBAL part id, 0..49. ``classes`` are always the
benchmark's 16 categories, sorted (``CATEGORIES``; label = index), whatever the category file lists,
so labels and part ids agree with the benchmark's; ``parts_of`` maps a category index to its sorted
global part ids (``PARTS_OF``: Airplane 0-3, Bag 4-5, ..., Table 47-49). The official split files
list 12,137 train / 1,870 val / 2,874 test shapes.

Preprocessing: the points of a file (normals dropped) are centred (bounding box) and scaled into
the unit sphere (``normalize_unit_sphere``, as every reader here), then ``num_points`` of them are
drawn, fixed per shape (seeded by ``seed`` and the shape's name ``<synset>/<id>``; without
replacement when the file holds enough, else with replacement), each with its part label.

Cache: ``<cache_dir>/shapenet_parts_<split>_<key>.npz`` (``packed.cached_arrays``: atomic, locked,
validated on load), ``key`` hashing every setting that decides what it holds: the split, ``num_points``,
``seed``, the preprocessing version and ``files_fingerprint`` of the category file, the split file and
every listed point file found (the root and their bytes). As in ``modelnet``, a cache holds what a
lenient read gives (``skipped``: one reason per shape left out) and ``strict`` is checked against it.

Bad input, one line each: a missing root, category file or split file is ``DatasetNotFound`` naming
it, the expected layout and the source. A malformed category or split file, or a split entry whose
synset the category file lacks, is ``ShapeFileError`` naming the file (and line or entry). A point
file that cannot be used (missing, unreadable, empty, a malformed line: named with its line number)
is skipped with one log line (``packed.skip``) or, with ``strict``, raises ``ShapeFileError``. A part
label outside the shape's category (``<file>:<line>: part 12 is not a part of Airplane (0-3)``) is
a corrupt benchmark: always ``PartLabelError`` (a ``ShapeFileError``), never skipped.
"""
from __future__ import annotations

import hashlib
import json
import re
import warnings
import zlib
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from .mesh_io import DatasetNotFound, ShapeFileError, normalize_unit_sphere
from .packed import cached_arrays, files_fingerprint, log_skipped, skip, wrap_index

PREP_VERSION = "1"  # bump when preprocessing or the skip reasons change: old caches then miss
SPLITS = ("train", "val", "test")
EXPECTED = {"train": 12137, "val": 1870, "test": 2874}  # shapes the official split files list
CATEGORIES = ("Airplane", "Bag", "Cap", "Car", "Chair", "Earphone", "Guitar", "Knife", "Lamp", "Laptop",
              "Motorbike", "Mug", "Pistol", "Rocket", "Skateboard", "Table")
PART_COUNTS = (4, 2, 2, 4, 4, 3, 3, 2, 4, 2, 6, 2, 3, 3, 3, 3)  # per category, in CATEGORIES order
PARTS_OF = {c: list(range(sum(PART_COUNTS[:c]), sum(PART_COUNTS[:c + 1]))) for c in range(len(CATEGORIES))}
NUM_PARTS = sum(PART_COUNTS)  # 50
CATEGORY_FILE = "synsetoffset2category.txt"
SPLIT_FILE = "train_test_split/shuffled_{}_file_list.json"
VALUES = 7  # per point: x, y, z, nx, ny, nz, part
ARRAYS = ("points", "part_labels", "labels", "names", "skipped")
ENTRY_RE = re.compile(r"shape_data/([^/]+)/([^/]+)")
LAYOUT = (f"<root>/{CATEGORY_FILE} ('<Category><TAB><synset>' per line), "
          f"<root>/{SPLIT_FILE.format('{train,val,test}')} (JSON lists of 'shape_data/<synset>/<id>') and "
          "<root>/<synset>/<id>.txt ('x y z nx ny nz part' per point, part the global part id 0..49); root is the "
          "unpacked shapenetcore_partanno_segmentation_benchmark_v0_normal folder (12,137 train / 1,870 val / "
          "2,874 test shapes)")
SOURCE = ("shapenetcore_partanno_segmentation_benchmark_v0_normal.zip from the PointNet++ authors (Qi et al., "
          "https://shapenet.cs.stanford.edu/media/shapenetcore_partanno_segmentation_benchmark_v0_normal.zip)")


class PartLabelError(ShapeFileError):
    """A point labelled with a part outside its shape's category: a corrupt benchmark, never skipped."""


def _not_found(what: str) -> DatasetNotFound:
    return DatasetNotFound(f"ShapeNet Parts: {what}; expected layout: {LAYOUT}. The data is {SOURCE}.")


def part_range(parts) -> str:
    """``0-3`` for consecutive part ids, else ``0, 2, 5``."""
    parts = list(parts)
    if parts == list(range(parts[0], parts[-1] + 1)) and len(parts) > 1:
        return f"{parts[0]}-{parts[-1]}"
    return ", ".join(str(p) for p in parts)


def read_categories(path: Path) -> dict[str, int]:
    """``synsetoffset2category.txt`` -> ``{synset: category index}`` (index into ``CATEGORIES``);
    a malformed line, an unknown category or a repeated synset is one ShapeFileError naming the line."""
    out: dict[str, int] = {}
    for lineno, line in enumerate(Path(path).read_text(errors="replace").splitlines(), 1):
        if not line.strip():
            continue
        fields = line.split()
        if len(fields) != 2:
            raise ShapeFileError(f"{path}:{lineno}: expected '<Category><TAB><synset>', got {line.strip()[:60]!r}")
        name, synset = fields
        if name not in CATEGORIES:
            raise ShapeFileError(f"{path}:{lineno}: {name!r} is not a ShapeNet Parts category "
                                 f"({', '.join(CATEGORIES)})")
        if synset in out:
            raise ShapeFileError(f"{path}:{lineno}: synset {synset} listed twice")
        out[synset] = CATEGORIES.index(name)
    return out


def read_split(path: Path, synsets: dict[str, int], category_path: Path) -> list[tuple[str, str]]:
    """A ``shuffled_<split>_file_list.json`` -> ``(synset, id)`` per entry, in file order; one
    ShapeFileError naming the file and the entry when it is not a list of ``shape_data/<synset>/<id>``
    strings with synsets of ``category_path``."""
    try:
        entries = json.loads(Path(path).read_text(errors="replace"))
    except ValueError as exc:
        raise ShapeFileError(f"{path}: not valid JSON ({exc})") from None
    if not isinstance(entries, list):
        raise ShapeFileError(f"{path}: expected a JSON list of 'shape_data/<synset>/<id>' strings")
    out = []
    for i, entry in enumerate(entries):
        m = ENTRY_RE.fullmatch(entry) if isinstance(entry, str) else None
        if m is None:
            raise ShapeFileError(f"{path}: entry {i} {entry!r} is not 'shape_data/<synset>/<id>'")
        if m.group(1) not in synsets:
            raise ShapeFileError(f"{path}: entry {i} {entry!r}: synset {m.group(1)} is not in {category_path}")
        out.append((m.group(1), m.group(2)))
    return out


def _line_problem(vals) -> str | None:
    """Why one parsed line (its floats, or None when a field is not a number) is not a point."""
    if vals is None or len(vals) != VALUES:
        return f"expected {VALUES} numbers 'x y z nx ny nz part'"
    if not np.isfinite(vals[:3]).all():
        return "NaN or Inf coordinate"
    if not np.isfinite(vals[6]) or vals[6] != round(vals[6]):
        return f"part label {vals[6]} is not a whole number"
    return None


def _parse_lines(path: Path, category: int) -> np.ndarray:
    """Line by line (slow, exact): ``[n, 7]`` float64, or the error naming the line. A part outside
    the category raises PartLabelError at once; else the first malformed line is ShapeFileError."""
    rows, bad = [], None
    parts = PARTS_OF[category]
    with open(path, errors="replace") as fh:
        for lineno, line in enumerate(fh, 1):
            s = line.strip()
            if not s:
                continue
            try:
                vals = [float(t) for t in s.split()]
            except ValueError:
                vals = None
            problem = _line_problem(vals)
            if problem is not None:
                bad = bad or f"{path}:{lineno}: {problem}: {s[:60]!r}"
                continue
            if int(vals[6]) not in parts:
                raise PartLabelError(f"{path}:{lineno}: part {int(vals[6])} is not a part of {CATEGORIES[category]} "
                                     f"({part_range(parts)})")
            rows.append(vals)
    if bad is not None:
        raise ShapeFileError(bad)
    if not rows:
        raise ShapeFileError(f"{path}: no points (expected lines 'x y z nx ny nz part')")
    return np.asarray(rows, np.float64)


def read_part_file(path, category: int) -> tuple[np.ndarray, np.ndarray]:
    """The points ``[n, 3]`` float64 and global part ids ``[n]`` int64 of one ``<id>.txt`` of a shape
    of ``category``; see the module doc for the errors (each names the file and the line)."""
    path = Path(path)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # numpy: an empty file
            a = np.loadtxt(path, comments=None, ndmin=2, dtype=np.float64)
        parts = PARTS_OF[category]
        ok = (a.shape[1] == VALUES and len(a) > 0 and bool(np.isfinite(a[:, :3]).all())
              and bool(((a[:, 6] >= parts[0]) & (a[:, 6] <= parts[-1]) & (a[:, 6] == np.round(a[:, 6]))).all()))
    except ValueError:  # non-numeric or ragged: the slow parser names the line
        ok = False
    except OSError as exc:
        raise ShapeFileError(f"{path}: unreadable ({exc})") from None
    if not ok:  # (PARTS_OF's parts are consecutive: the range check above is the membership check)
        a = _parse_lines(path, category)
    return a[:, :3], a[:, 6].astype(np.int64)


def prepare_shape(path, category: int, name: str, num_points: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """One point file -> ``points [num_points, 3]`` float32 (unit sphere) and ``part_labels
    [num_points]`` uint8, a choice fixed by ``seed`` and ``name`` (module doc)."""
    xyz, parts = read_part_file(path, category)
    xyz = normalize_unit_sphere(xyz)
    rng = np.random.default_rng([int(seed), zlib.crc32(name.encode())])
    idx = np.sort(rng.choice(len(xyz), size=num_points, replace=len(xyz) < num_points))
    return xyz[idx].astype(np.float32), parts[idx].astype(np.uint8)


def check_arrays(a: dict[str, np.ndarray], num_points: int) -> None:
    """Raise ValueError unless the arrays are well-formed shapes of ``num_points`` points whose part
    labels belong to their category."""
    n = len(a["labels"])
    ok = (a["points"].shape == (n, num_points, 3) and a["part_labels"].shape == (n, num_points)
          and len(a["names"]) == n and bool(np.isfinite(a["points"]).all())
          and bool(((a["labels"] >= 0) & (a["labels"] < len(CATEGORIES))).all()))
    if ok and n:
        lo = np.asarray([PARTS_OF[c][0] for c in range(len(CATEGORIES))])[a["labels"]][:, None]
        hi = np.asarray([PARTS_OF[c][-1] for c in range(len(CATEGORIES))])[a["labels"]][:, None]
        ok = bool(((a["part_labels"] >= lo) & (a["part_labels"] <= hi)).all())
    if not ok:
        raise ValueError("inconsistent arrays")


class ShapeNetParts(Dataset):
    """One split ("train" | "val" | "test") of ShapeNet Parts; see the module doc.

    ``ds[i]`` -> ``points [num_points, 3] float32`` (unit sphere), ``part_labels [num_points] int64``
    (global part ids), ``label`` (category index into ``classes``) and ``name`` (``"02691156/<id>"``).
    Attributes: ``classes`` (the 16 categories, sorted), ``parts_of`` (category index -> sorted global
    part ids), ``num_parts`` (50), ``labels``, ``names``, ``skipped`` (one reason per listed shape left
    out), ``cache_path``.
    """

    num_parts = NUM_PARTS

    def __init__(self, root, split: str = "train", cache_dir="outputs/cache/shapenet_parts", num_points: int = 2048,
                 seed: int = 0, strict: bool = False, progress: bool = True):
        if split not in SPLITS:
            raise ValueError(f"shapenet_parts: split={split!r}; expected one of {list(SPLITS)}")
        if int(num_points) < 1:
            raise ValueError(f"shapenet_parts: num_points={num_points}; expected at least 1")
        root = Path(root)
        if not root.is_dir():
            raise _not_found(f"no folder {root.resolve()}")
        category_path, split_path = root / CATEGORY_FILE, root / SPLIT_FILE.format(split)
        for what, p in (("category file", category_path), (f"{split} split file", split_path)):
            if not p.is_file():
                raise _not_found(f"no {what} {p}")
        self.root, self.split, self.strict = root, split, bool(strict)
        self.num_points, self.seed = int(num_points), int(seed)
        self.classes, self.parts_of = list(CATEGORIES), {c: list(p) for c, p in PARTS_OF.items()}
        # the release names no parts: "<category>/<k>", k-th of the category's parts (global ids in order)
        self.part_names = [f"{CATEGORIES[c]}/{k}" for c in sorted(PARTS_OF) for k in range(len(PARTS_OF[c]))]
        synsets = read_categories(category_path)
        entries = read_split(split_path, synsets, category_path)
        skipped, files = [], []
        for synset, sid in entries:
            path = root / synset / f"{sid}.txt"
            if not path.is_file():
                skip(f"{path}: no such file (listed in {split_path})", skipped, strict)
                continue
            files.append((path, synsets[synset], f"{synset}/{sid}"))
        listed = [category_path, split_path, *(p for p, _, _ in files)]  # the root and these files' bytes
        settings = {"version": PREP_VERSION, "dataset": "shapenet_parts", "split": split,
                    "num_points": self.num_points, "seed": self.seed,
                    "files": files_fingerprint(listed, root, cache_dir)}
        key = hashlib.sha1(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:16]
        self.cache_path = Path(cache_dir) / f"shapenet_parts_{split}_{key}.npz"
        arrays = cached_arrays(self.cache_path, settings, ARRAYS, lambda a: check_arrays(a, self.num_points),
                               lambda: self._build(files, progress))
        if strict and len(arrays["skipped"]):
            raise ShapeFileError(str(arrays["skipped"][0]))  # the line a cold strict read gives
        self.skipped = skipped + [str(s) for s in arrays["skipped"]]
        log_skipped(f"ShapeNet Parts {split}", self.skipped, len(entries), "shapes")
        self._points, self._parts = arrays["points"], arrays["part_labels"]
        self.labels = arrays["labels"]
        self.names = [str(s) for s in arrays["names"]]

    def _build(self, files: list[tuple[Path, int, str]], progress: bool) -> dict[str, np.ndarray]:
        """Read and sample every file (``prepare_shape``) -> the cache's arrays."""
        from tqdm.auto import tqdm

        points, parts, labels, names, skipped = [], [], [], [], []
        bar = tqdm(files, desc=f"prepare {self.cache_path.stem}", unit="shape", disable=None if progress else True,
                   leave=False)
        for path, category, name in bar:
            try:
                pts, lab = prepare_shape(path, category, name, self.num_points, self.seed)
            except PartLabelError:
                raise
            except ShapeFileError as exc:
                skip(str(exc), skipped, self.strict)
                continue
            points.append(pts)
            parts.append(lab)
            labels.append(category)
            names.append(name)
        return {"points": np.asarray(points, np.float32).reshape(-1, self.num_points, 3),
                "part_labels": np.asarray(parts, np.uint8).reshape(-1, self.num_points),
                "labels": np.asarray(labels, np.int64), "names": np.asarray(names, dtype=str),
                "skipped": np.asarray(skipped, dtype=str)}

    def __len__(self) -> int:
        return len(self.labels)

    def __getitem__(self, i: int) -> dict:
        i = wrap_index(i, len(self), f"ShapeNet Parts {self.split}")
        return {"points": torch.from_numpy(self._points[i].copy()),
                "part_labels": torch.from_numpy(self._parts[i].astype(np.int64)),
                "label": int(self.labels[i]), "name": self.names[i]}
