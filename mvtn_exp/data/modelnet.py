"""ModelNet40 / ModelNet10 meshes: ``<root>/<class>/{train,test}/<class>_NNNN.off``, preprocessed once.

Preprocessing (as the paper): rotate -90 degrees about X (the files are Z-up; we are Y-up), centre
the bounding box, scale into the unit sphere, simplify with fast-simplification to at most
``max_vertices`` vertices (the paper used 20,000), and sample ``num_points`` surface points fixed
per shape (seeded by the file name), so evaluation is deterministic. A shape that cannot be used
(unreadable file, NaN coordinates, indices out of range, no faces, only zero-area faces) is reported
in one log line with its path and the reason and skipped (counted; listed in the cache's ``skipped``
record, in file order), or raises ShapeFileError with that reason with ``strict``.

Cache: ``<cache_dir>/<dataset>_<split>_<key>.npz`` (packed arrays, ``packed.py``), ``key`` hashing
every setting that decides what it holds: the classes, the split, ``num_points``, ``max_vertices``,
``seed``, the preprocessing version and the files (``packed.files_fingerprint``: the root and every
file's bytes). ``strict`` decides no content: a cache holds what a lenient read gives (the usable
shapes, and one reason per file left out in ``skipped``), and ``strict`` is checked against it: a
strict read of a cache that skipped files raises the first reason, the very line a strict read of a
cold cache raises; a cache that skipped nothing serves strict and lenient runs alike.

One process at a time builds a given cache: runs that start together on a cold cache (a parallel
sweep, DDP ranks) wait on ``<cache>.lock`` while the first builds it, then load it
(``packed.cache_lock``; the lock file goes when the build ends, done or failed). Shapes are first
written one by one into a ``.parts`` folder beside it, so an interrupted run resumes without redoing
finished shapes; the packed file is written atomically at the end and the parts removed.

ModelNet has no validation split: ``val_fraction`` of each class's official train shapes (chosen
with ``seed``) form ``val`` and are left out of ``train``; ``test`` is the official test split.
"""
from __future__ import annotations

import hashlib
import json
import warnings
import zlib
from pathlib import Path

import numpy as np

from .mesh_io import DatasetNotFound, ShapeFileError, check_mesh, normalize_unit_sphere, read_off, zup_to_yup
from .packed import (PACKED_ARRAYS, PackedShapes, cache_lock, files_fingerprint, load_npz, log_skipped, pack,
                     sample_surface, save_npz_atomic, skip, triangle_areas, validate, writing)

PREP_VERSION = "2"  # bump when preprocessing or the skip reasons change: old caches then miss
EXPECTED = {40: {"train": 9843, "test": 2468}, 10: {"train": 3991, "test": 908}}
LAYOUT = ("<root>/<class>/{train,test}/<class>_NNNN.off for every class (ModelNet40: 40 classes, 9843 train / "
          "2468 test shapes; the Princeton ModelNet40.zip, unpacked)")
SPLITS = ("train", "val", "test")


class CountWarning(UserWarning):
    """A split holds another number of shapes than the official dataset."""


def scan(root) -> tuple[list[str], dict[str, list[tuple[Path, int]]]]:
    """Sorted class names and, for "train" / "test", the sorted ``(file, label)`` pairs."""
    root = Path(root)
    if not root.is_dir():
        raise DatasetNotFound(f"ModelNet not found at {root.resolve()}; expected layout: {LAYOUT}")
    classes = sorted(p.name for p in root.iterdir() if p.is_dir() and (p / "train").is_dir() and (p / "test").is_dir())
    if not classes:
        raise DatasetNotFound(f"ModelNet at {root.resolve()} has no <class>/train and <class>/test folders; "
                                 f"expected layout: {LAYOUT}")
    files = {split: [(f, label) for label, c in enumerate(classes) for f in sorted((root / c / split).glob("*.off"))]
             for split in ("train", "test")}
    expected = EXPECTED.get(len(classes))
    for split in ("train", "test"):
        if expected and len(files[split]) != expected[split]:
            warnings.warn(f"ModelNet{len(classes)} at {root}: {len(files[split])} {split} files, the official "
                          f"dataset has {expected[split]}", CountWarning, stacklevel=2)
    return classes, files


def _simplify(v: np.ndarray, f: np.ndarray, max_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """At most about ``max_vertices`` vertices (a request: what fast-simplification reaches is kept
    as long as it is a valid mesh; on failure the input is kept)."""
    if max_vertices <= 0 or len(v) <= max_vertices:
        return v, f
    import fast_simplification

    try:
        v2, f2 = fast_simplification.simplify(np.ascontiguousarray(v, np.float32), np.ascontiguousarray(f, np.int32),
                                              target_reduction=1.0 - max_vertices / len(v))
        check_mesh("simplified", v2, f2)
        return v2.astype(np.float64), f2.astype(np.int64)
    except Exception:  # keep the original: simplification must never lose a shape
        return v, f


def preprocess(path: Path, label: int, num_points: int, max_vertices: int, seed: int) -> dict:
    """One OFF file -> ``{verts, faces, points, label, name}`` (Y-up, unit sphere); raises ShapeFileError."""
    v, f = read_off(path)
    check_mesh(path, v, f)
    v = normalize_unit_sphere(zup_to_yup(v))
    v, f = _simplify(v, f, max_vertices)
    keep = triangle_areas(v, f) > 0  # zero-area faces render nothing; check_mesh guarantees one is left
    f = f[keep]
    rng = np.random.default_rng([seed, zlib.crc32(path.name.encode())])
    pts = sample_surface(v, f, num_points, rng)
    return {"verts": v.astype(np.float32), "faces": f.astype(np.int32), "points": pts.astype(np.float32),
            "label": label, "name": path.stem}


def _part_path(parts: Path, path: Path) -> Path:
    return parts / f"{path.parent.parent.name}__{path.stem}.npz"


def prepare_split(files: list[tuple[Path, int]], cache_path: Path, settings: dict, num_classes: int,
                  strict: bool = False, progress: bool = True, preprocess_fn=None) -> dict[str, np.ndarray]:
    """Preprocess ``files`` into the packed cache at ``cache_path`` (resumable; see the module doc)
    -> its arrays and ``skipped`` (one reason per file left out, in file order).

    ``strict``: the first file that cannot be used raises ShapeFileError with its reason, cached or
    not (a cache built leniently that skipped files raises its first reason). A cache write that
    fails (a full disk) raises an OSError naming the file being written; the lock file and the
    temp file are removed, the finished per-shape parts kept for the next run.

    ``preprocess_fn(path, label, num_points, max_vertices, seed) -> {verts, faces, points, label, name}``
    (raising ShapeFileError for an unusable file) lets other readers reuse this caching; default: this
    module's ``preprocess``, looked up at call time."""
    if preprocess_fn is None:
        preprocess_fn = preprocess

    def cached():
        return load_npz(cache_path, settings, (*PACKED_ARRAYS, "skipped"),
                        lambda a: validate(a, None, settings["num_points"], num_classes))

    arrays = cached()
    if arrays is None:
        with cache_lock(cache_path):  # one process builds, others wait for it (packed.cache_lock)
            arrays = cached()
            if arrays is None:
                arrays = _build_split(files, cache_path, settings, num_classes, strict, progress, preprocess_fn)
    if strict and len(arrays["skipped"]):
        raise ShapeFileError(str(arrays["skipped"][0]))  # the line a cold strict read gives
    return arrays


def _build_split(files, cache_path: Path, settings: dict, num_classes: int, strict: bool, progress: bool,
                 preprocess_fn) -> dict[str, np.ndarray]:
    """``prepare_split``'s work, under its lock: per-shape parts (resumable), then the packed file."""
    from tqdm.auto import tqdm

    parts = cache_path.with_suffix(".parts")
    parts.mkdir(parents=True, exist_ok=True)
    with writing(parts / "settings.json"):
        (parts / "settings.json").write_text(json.dumps(settings, sort_keys=True))
    shapes, skipped = [], []
    for path, label in tqdm(files, desc=f"prepare {cache_path.stem}", unit="shape", disable=None if progress else True, leave=False):
        part = _part_path(parts, path)
        shape = _read_part(part)
        if shape is None:
            try:
                shape = preprocess_fn(path, label, settings["num_points"], settings["max_vertices"], settings["seed"])
            except ShapeFileError as exc:
                skip(str(exc), skipped, strict)
                continue
            _write_part(part, shape)
        shapes.append(shape)
    arrays = pack(shapes, settings["num_points"])
    arrays["skipped"] = np.asarray(skipped, dtype=str)
    validate(arrays, len(shapes), settings["num_points"], num_classes)
    save_npz_atomic(cache_path, arrays, settings)
    for p in parts.iterdir():
        p.unlink()
    parts.rmdir()
    log_skipped(cache_path.stem, skipped, len(files), "shapes")
    return arrays


def _read_part(part: Path):
    """The shape a finished earlier run left in ``part``, or None (none there, or cut short by a
    crash: then removed, and the shape is done again)."""
    if not part.exists():
        return None
    try:
        with np.load(part, allow_pickle=False) as z:
            return {"verts": z["verts"], "faces": z["faces"], "points": z["points"], "label": int(z["label"]),
                    "name": str(z["name"])}
    except Exception:
        part.unlink()
        return None


def _write_part(part: Path, shape: dict) -> None:
    """``shape`` into ``part`` via a temp file (removed if the write fails; an OSError names ``part``)."""
    tmp = part.with_suffix(".tmp.npz")
    try:
        with writing(part):
            np.savez(tmp, **{k: np.asarray(v) for k, v in shape.items()})
        tmp.replace(part)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def val_mask(labels: np.ndarray, fraction: float, seed: int) -> np.ndarray:
    """Stratified: ``round(fraction * n_c)`` shapes of each class c (at least 1 when fraction > 0)."""
    rng = np.random.default_rng([seed, 7])
    mask = np.zeros(len(labels), bool)
    for c in np.unique(labels):
        idx = np.flatnonzero(labels == c)
        k = min(len(idx) - 1, max(1, round(fraction * len(idx)))) if fraction > 0 and len(idx) > 1 else 0
        mask[rng.choice(idx, size=k, replace=False)] = True
    return mask


def subset(a: dict[str, np.ndarray], keep: np.ndarray) -> dict[str, np.ndarray]:
    vo = np.concatenate([[0], np.cumsum(a["verts_per_shape"])])
    fo = np.concatenate([[0], np.cumsum(a["faces_per_shape"])])
    idx = np.flatnonzero(keep)
    vsel = np.concatenate([np.arange(vo[i], vo[i + 1]) for i in idx]) if len(idx) else np.zeros(0, int)
    fsel = np.concatenate([np.arange(fo[i], fo[i + 1]) for i in idx]) if len(idx) else np.zeros(0, int)
    return {"verts": a["verts"][vsel], "faces": a["faces"][fsel], "verts_per_shape": a["verts_per_shape"][idx],
            "faces_per_shape": a["faces_per_shape"][idx], "points": a["points"][idx], "labels": a["labels"][idx],
            "names": a["names"][idx]}


class ModelNetMeshes(PackedShapes):
    """One split ("train" | "val" | "test") of ModelNet40 (or ModelNet10) meshes; see the module doc.

    ``ds[i]`` -> ``verts [V, 3] float32`` (Y-up, unit sphere), ``faces [F, 3] int64``,
    ``points [num_points, 3] float32``, ``label``, ``name`` (``"desk_0201"``); ``skipped``: the
    reasons of the shapes left out of the whole official split.
    """

    val_from_train = True  # the val split is carved out of the official train split (retrieval reunites them)

    def __init__(self, root, split: str = "train", cache_dir="outputs/cache/modelnet", num_points: int = 2048,
                 max_vertices: int = 20000, val_fraction: float = 0.1, seed: int = 0, strict: bool = False,
                 as_points: bool = False, progress: bool = True):
        if split not in SPLITS:
            raise ValueError(f"modelnet: split={split!r}; expected one of {list(SPLITS)}")
        classes, files = scan(root)
        official = "test" if split == "test" else "train"
        settings = {"version": PREP_VERSION, "classes": classes, "split": official, "num_points": int(num_points),
                    "max_vertices": int(max_vertices), "seed": int(seed),
                    "files": files_fingerprint([p for p, _ in files[official]], root, cache_dir)}
        key = hashlib.sha1(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:16]
        name = f"modelnet{len(classes)}"
        self.cache_path = Path(cache_dir) / f"{name}_{official}_{key}.npz"
        arrays = prepare_split(files[official], self.cache_path, settings, len(classes), strict, progress)
        self.skipped = [str(s) for s in arrays["skipped"]]
        if official == "train":
            is_val = val_mask(arrays["labels"], val_fraction, seed)
            arrays = subset(arrays, is_val if split == "val" else ~is_val)
        super().__init__(arrays, classes, split, as_points)
