"""ShapeNetCore.v2 (55 synsets) with the SHREC'17 split, preprocessed once into a packed cache.

Layout: ``<root>/<synsetId>/<modelId>/models/model_normalized.obj`` (ShapeNetCore.v2, unpacked),
the split CSV (default ``<root>/all.csv``; header ``id,synsetId,subSynsetId,modelId,split``,
``split`` one of train / val / test) and the synset dictionary (default
``<root>/shapenet_synset_dict_v2.json``: ``{"02691156": "airplane", ...}``, as in PyTorch3D).

Every CSV column is read as text: SHREC ids keep their leading zeros (``"000772"``) and so do
synsets (``"02691156"``). ``classes`` are the sorted dictionary names of the synsets the CSV uses
(all splits, so labels agree across splits); label = index in that list. Items carry ``name``
(the SHREC id), ``synset``, ``sub_synset`` and ``model_id`` (strings) for SHREC-style metrics.

Preprocessing (OBJ geometry only, materials ignored): ShapeNet v2 is Y-up already, so no
rotation; unreferenced vertices dropped, bounding box centred, scaled into the unit sphere,
simplified to at most ``max_vertices`` vertices, ``num_points`` surface points sampled, fixed per
shape (seeded by ``seed`` and the model id: every file is called ``model_normalized.obj``). As in
the paper, ShapeNet is rendered as point clouds: items carry only ``points`` unless
``as_points=False``. Caching (resumable, versioned, atomic) is ``modelnet.prepare_split``'s.

A CSV row whose OBJ is missing is skipped with the path in the reason and counted (``strict``:
raises ShapeFileError); so are unreadable or degenerate meshes. Each skipped row is reported once,
in one log line (``packed.skip``); when shapes were skipped a CountWarning gives the number loaded
and the number of rows the CSV lists for the split. The cache's key is ``modelnet.prepare_split``'s
(every setting, and the files' bytes); ``strict`` is checked against what it holds, as there.
"""
from __future__ import annotations

import csv
import hashlib
import json
import warnings
import zlib
from pathlib import Path
from typing import NamedTuple

import numpy as np

from . import modelnet
from .mesh_io import DatasetNotFound, normalize_unit_sphere, read_mesh
from .modelnet import CountWarning
from .packed import PackedShapes, sample_surface, skip, triangle_areas

PREP_VERSION = "1"  # bump when preprocessing changes: old caches then miss
HEADER = ("id", "synsetId", "subSynsetId", "modelId", "split")
SPLITS = ("train", "val", "test")
MESH_PATH = "models/model_normalized.obj"
DICT_NAME = "shapenet_synset_dict_v2.json"
LAYOUT = (f"<root>/<synsetId>/<modelId>/{MESH_PATH} for every row of the split CSV (default <root>/all.csv, "
          f"header {','.join(HEADER)}) and the synset dictionary (default <root>/{DICT_NAME}, "
          '{"02691156": "airplane", ...})')
SOURCES = ("ShapeNetCore.v2 comes from https://shapenet.org (ShapeNetCore.v2.zip, unpacked); the SHREC'17 split "
           "all.csv (35,765 train / 5,159 val / 10,266 test) from the SHREC'17 track 'Large-scale 3D shape "
           "retrieval from ShapeNet Core55' (https://shapenet.cs.stanford.edu/shrec17/); "
           f"{DICT_NAME} from PyTorch3D (pytorch3d/datasets/shapenet/{DICT_NAME})")


class SplitRow(NamedTuple):
    """One row of the split CSV; every field is text. ``line``: its line number in the file."""

    id: str
    synset: str
    sub_synset: str
    model_id: str
    split: str
    line: int


def _not_found(what: str, path: Path) -> DatasetNotFound:
    return DatasetNotFound(f"ShapeNet {what} not found at {Path(path).resolve()}; expected layout: {LAYOUT}. "
                           f"{SOURCES}")


def read_split_csv(path) -> list[SplitRow]:
    """The rows of a SHREC'17 split CSV, every column as text; errors name the file and the line."""
    path = Path(path)
    if not path.is_file():
        raise _not_found("split CSV", path)
    rows, seen = [], {}
    with open(path, newline="", encoding="utf-8-sig") as fh:
        reader = csv.reader(fh)
        header = next(reader, None)
        if header is None or tuple(h.strip() for h in header) != HEADER:
            raise ValueError(f"{path}:1: expected the header {','.join(HEADER)}, got "
                             f"{','.join(header) if header else 'an empty file'}")
        for fields in reader:
            line = reader.line_num
            if not fields or (len(fields) == 1 and not fields[0].strip()):
                continue  # blank line
            if len(fields) != len(HEADER):
                raise ValueError(f"{path}:{line}: expected {len(HEADER)} columns ({','.join(HEADER)}), "
                                 f"got {len(fields)}: {','.join(fields)}")
            fields = [f.strip() for f in fields]
            empty = [h for h, f in zip(HEADER, fields) if not f]
            if empty:
                raise ValueError(f"{path}:{line}: empty {', '.join(empty)}")
            if fields[4] not in SPLITS:
                raise ValueError(f"{path}:{line}: split {fields[4]!r}; expected one of {', '.join(SPLITS)}")
            if fields[0] in seen:
                raise ValueError(f"{path}:{line}: id {fields[0]} already on line {seen[fields[0]]}")
            seen[fields[0]] = line
            rows.append(SplitRow(*fields, line))
    return rows


def read_synset_dict(path) -> dict[str, str]:
    """``{synsetId: name}`` from a JSON object of strings; names must be distinct (they are the classes)."""
    path = Path(path)
    if not path.is_file():
        raise _not_found("synset dictionary", path)
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from None
    if not isinstance(d, dict) or not all(isinstance(k, str) and isinstance(v, str) and v for k, v in d.items()):
        raise ValueError(f"{path}: expected a JSON object of synset id -> name strings, "
                         '{"02691156": "airplane", ...}')
    by_name: dict[str, str] = {}
    for k, v in d.items():
        if v in by_name:
            raise ValueError(f"{path}: synsets {by_name[v]} and {k} share the name {v!r}; class names must differ")
        by_name[v] = k
    return d


def preprocess(path: Path, label: int, num_points: int, max_vertices: int, seed: int, name: str) -> dict:
    """One ``model_normalized.obj`` -> ``{verts, faces, points, label, name}`` (no rotation, unit sphere)."""
    v, f = read_mesh(path)  # OBJ geometry only; raises ShapeFileError (missing, unreadable, degenerate)
    used, f = np.unique(f, return_inverse=True)  # drop unreferenced vertices: they would skew the normalisation
    v, f = v[used], f.reshape(-1, 3)
    v = normalize_unit_sphere(v)
    v, f = modelnet._simplify(v, f, max_vertices)
    f = f[triangle_areas(v, f) > 0]  # check_mesh guarantees one face is left
    model_id = path.parent.parent.name  # every file is model_normalized.obj: seed by the model
    rng = np.random.default_rng([seed, zlib.crc32(model_id.encode())])
    pts = sample_surface(v, f, num_points, rng)
    return {"verts": v.astype(np.float32), "faces": f.astype(np.int32), "points": pts.astype(np.float32),
            "label": label, "name": name}


class ShapeNetCore(PackedShapes):
    """One split ("train" | "val" | "test") of ShapeNetCore.v2 with the SHREC'17 split; see the module doc.

    ``ds[i]`` -> ``points [num_points, 3] float32``, ``label``, ``name`` (SHREC id, ``"000772"``),
    ``synset``, ``sub_synset``, ``model_id`` and, when ``as_points=False``, ``verts [V, 3] float32`` /
    ``faces [F, 3] int64``. ``skipped``: reasons of the split's rows left out; ``expected``: the
    number of rows the CSV lists for the split.
    """

    def __init__(self, root, split: str = "train", split_csv=None, synset_dict=None,
                 cache_dir="outputs/cache/shapenet", num_points: int = 2048, max_vertices: int = 20000,
                 seed: int = 0, strict: bool = False, as_points: bool = True, progress: bool = True):
        if split not in SPLITS:
            raise ValueError(f"shapenet: split={split!r}; expected one of {list(SPLITS)}")
        root = Path(root)
        if not root.is_dir():
            raise _not_found("root", root)
        csv_path = Path(split_csv) if split_csv is not None else root / "all.csv"
        dict_path = Path(synset_dict) if synset_dict is not None else root / DICT_NAME
        rows = read_split_csv(csv_path)
        names = read_synset_dict(dict_path)
        first_line: dict[str, int] = {}
        for r in rows:
            first_line.setdefault(r.synset, r.line)
        unknown = sorted(s for s in first_line if s not in names)
        if unknown:
            raise ValueError(f"{csv_path}: synset {unknown[0]} (line {first_line[unknown[0]]})"
                             + (f" and {len(unknown) - 1} more ({', '.join(unknown[1:6])})" if len(unknown) > 1 else "")
                             + f" not in the synset dictionary {dict_path}")
        classes = sorted(names[s] for s in first_line)
        label_of = {s: classes.index(names[s]) for s in first_line}

        mine = [r for r in rows if r.split == split]
        dup = _first_duplicate([r.model_id for r in mine])
        if dup is not None:  # the per-shape cache parts are named by model id
            raise ValueError(f"{csv_path}: model {dup} appears twice in the {split} split")
        files, by_path, skipped = [], {}, []
        for r in mine:
            path = root / r.synset / r.model_id / MESH_PATH
            if not path.is_file():
                skip(f"{path}: no such file (row {r.id}, {csv_path}:{r.line})", skipped, strict)
                continue
            files.append((path, label_of[r.synset]))
            by_path[path] = r.id
        settings = {"version": f"{modelnet.PREP_VERSION}.{PREP_VERSION}", "dataset": "shapenet", "classes": classes,
                    "split": split, "num_points": int(num_points), "max_vertices": int(max_vertices),
                    "seed": int(seed),  # the rows present on disk: a file that appears later rebuilds the cache
                    "rows": hashlib.sha1("\n".join(f"{by_path[p]},{p.relative_to(root).as_posix()},{lab}"
                                                   for p, lab in files).encode()).hexdigest(),
                    "files": modelnet.files_fingerprint([p for p, _ in files], root, cache_dir)}  # the root, every file's bytes
        key = hashlib.sha1(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:16]
        self.cache_path = Path(cache_dir) / f"shapenet{len(classes)}_{split}_{key}.npz"

        def prep(path, label, n, max_v, s):  # looks `preprocess` up at call time (tests monkeypatch it)
            return preprocess(path, label, n, max_v, s, name=by_path[path])

        arrays = modelnet.prepare_split(files, self.cache_path, settings, len(classes), strict, progress,
                                        preprocess_fn=prep)
        self.skipped = skipped + [str(s) for s in arrays["skipped"]]
        self.expected = len(mine)
        super().__init__(arrays, classes, split, as_points)
        row_of = {r.id: r for r in mine}
        self.synsets = [row_of[n].synset for n in self.names]
        self.sub_synsets = [row_of[n].sub_synset for n in self.names]
        self.model_ids = [row_of[n].model_id for n in self.names]
        if len(self) != self.expected:
            warnings.warn(f"ShapeNet {split}: {len(self)} shapes loaded, the split CSV {csv_path} lists "
                          f"{self.expected} ({len(self.skipped)} skipped, each named in its own log line)",
                          CountWarning, stacklevel=2)

    def item(self, i: int) -> dict:
        item = super().item(i)
        i = i % len(self)
        item.update(synset=self.synsets[i], sub_synset=self.sub_synsets[i], model_id=self.model_ids[i])
        return item


    def retrieval_report(self, q_z: np.ndarray, q_y: np.ndarray, list_length: int) -> dict:
        """SHREC'17 as the challenge evaluates it: every shape of this split queries the split itself
        (itself included), features ``q_z [N, D]`` in this dataset's order, graded by sub-synset
        (None: labelled only at its synset)."""
        from ..tasks import retrieval

        subs = [None if sub == syn else sub for sub, syn in zip(self.sub_synsets, self.synsets)]
        shrec = retrieval.shrec17_metrics(q_z, q_y, q_z, q_y, n=list_length, query_sublabels=subs, db_sublabels=subs)
        out = {k: v for k, v in shrec.items() if k != "per_query"}
        out["database"] = f"the {self.split} split itself ({len(q_y)} shapes, each query included)"
        return {"shrec17": out}


def _first_duplicate(values) -> str | None:
    seen = set()
    for v in values:
        if v in seen:
            return v
        seen.add(v)
    return None
