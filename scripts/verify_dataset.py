"""Check a downloaded dataset's layout and counts before training, and fingerprint the copy.

    python scripts/verify_dataset.py modelnet40 data/ModelNet40
    python scripts/verify_dataset.py scanobjectnn data/h5_files --manifest scanobjectnn.sha256
    python scripts/verify_dataset.py shapenet_parts data/shapenetcore_partanno_segmentation_benchmark_v0_normal
    python scripts/verify_dataset.py modelnet40 data/ModelNet40 --check scanobjectnn.sha256

Exit 0 when the layout and the official counts match, 1 when something differs (each problem one
line), 2 for a bad command line. ``--manifest FILE`` writes SHA-256 of every file read (sorted
paths): commit it beside your results, and ``--check FILE`` on another machine proves it reads the
same bytes. Nothing is downloaded (see scripts/datasets/<name>.md for where to get each dataset).
"""
from __future__ import annotations

import argparse
import hashlib
import sys
from pathlib import Path

MODELNET = {"modelnet40": (40, 9843, 2468), "modelnet10": (10, 3991, 908)}
SCANOBJECTNN = ["main_split/training_objectdataset.h5", "main_split/test_objectdataset.h5",
                "main_split_nobg/training_objectdataset.h5", "main_split_nobg/test_objectdataset.h5",
                "main_split/training_objectdataset_augmentedrot_scale75.h5",
                "main_split/test_objectdataset_augmentedrot_scale75.h5"]
SHAPENET_ROWS = 51190  # SHREC17 all.csv


def modelnet(root: Path, name: str) -> tuple[list[Path], list[str]]:
    classes, train, test = MODELNET[name]
    found = sorted(d for d in root.iterdir() if d.is_dir()) if root.is_dir() else []
    problems = [] if len(found) == classes else [f"{root}: {len(found)} class folders, expected {classes}"]
    files = []
    for split, expected in (("train", train), ("test", test)):
        split_files = sorted(f for d in found for f in (d / split).glob("*.off"))
        if len(split_files) != expected:
            problems.append(f"{root}/<class>/{split}: {len(split_files)} .off files, expected {expected}")
        files += split_files
    return files, problems


def scanobjectnn(root: Path) -> tuple[list[Path], list[str]]:
    files = [root / f for f in SCANOBJECTNN]
    return [f for f in files if f.is_file()], [f"{f}: missing" for f in files if not f.is_file()]


def shapenet(root: Path, split_csv: Path) -> tuple[list[Path], list[str]]:
    import csv

    with open(split_csv, newline="") as f:
        rows = list(csv.DictReader(f))
    problems = [] if len(rows) == SHAPENET_ROWS else [f"{split_csv}: {len(rows)} rows, expected {SHAPENET_ROWS}"]
    files, missing = [], 0
    for r in rows:
        obj = root / r["synsetId"] / r["modelId"] / "models" / "model_normalized.obj"
        if obj.is_file():
            files.append(obj)
        else:
            missing += 1
    if missing:
        problems.append(f"{root}: {missing} of {len(rows)} models of {split_csv.name} missing "
                        "(<root>/<synsetId>/<modelId>/models/model_normalized.obj)")
    return files, problems


def shapenet_parts(root: Path) -> tuple[list[Path], list[str]]:
    """The category file, the three official split lists with their counts, and every listed file."""
    from mvtn_exp.data import shapenet_parts as sp
    from mvtn_exp.data.mesh_io import ShapeFileError

    category_path = root / sp.CATEGORY_FILE
    if not category_path.is_file():
        return [], [f"{category_path}: missing"]
    try:
        synsets = sp.read_categories(category_path)
    except ShapeFileError as exc:
        return [category_path], [str(exc)]
    files, problems = [category_path], []
    if len(synsets) != len(sp.CATEGORIES):
        problems.append(f"{category_path}: {len(synsets)} categories, expected {len(sp.CATEGORIES)}")
    for split, expected in sp.EXPECTED.items():
        path = root / sp.SPLIT_FILE.format(split)
        try:
            entries = sp.read_split(path, synsets, category_path) if path.is_file() else None
        except ShapeFileError as exc:
            problems.append(str(exc))
            continue
        if entries is None:
            problems.append(f"{path}: missing")
            continue
        files.append(path)
        if len(entries) != expected:
            problems.append(f"{path}: {len(entries)} shapes, expected {expected}")
        shapes = [root / synset / f"{name}.txt" for synset, name in entries]
        missing = sum(not f.is_file() for f in shapes)
        if missing:
            problems.append(f"{root}: {missing} of {len(shapes)} point files of {path.name} missing (<root>/<synset>/<id>.txt)")
        files += [f for f in shapes if f.is_file()]
    return files, problems


def sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("dataset", choices=[*MODELNET, "scanobjectnn", "shapenet", "shapenet_parts"])
    p.add_argument("root", type=Path)
    p.add_argument("--split-csv", type=Path, help="shapenet: SHREC17 all.csv")
    p.add_argument("--manifest", type=Path, help="write SHA-256 of every file to this file")
    p.add_argument("--check", type=Path, help="compare with a manifest written before")
    a = p.parse_args(argv)
    if not a.root.is_dir():
        print(f"verify_dataset: {a.root}: no such folder", file=sys.stderr)
        return 2
    if a.dataset == "shapenet":
        if a.split_csv is None or not a.split_csv.is_file():
            print("verify_dataset: shapenet needs --split-csv PATH/all.csv (an existing file)", file=sys.stderr)
            return 2
        files, problems = shapenet(a.root, a.split_csv)
    elif a.dataset == "scanobjectnn":
        files, problems = scanobjectnn(a.root)
    elif a.dataset == "shapenet_parts":
        files, problems = shapenet_parts(a.root)
    else:
        files, problems = modelnet(a.root, a.dataset)
    if a.manifest or a.check:
        lines = [f"{sha256(f)}  {f.relative_to(a.root)}" for f in sorted(files)]
        if a.manifest:
            a.manifest.write_text("\n".join(lines) + "\n")
        if a.check:
            expected = set(a.check.read_text().splitlines())
            differ = sorted(expected.symmetric_difference(lines))
            problems += [f"manifest {a.check}: {len(differ)} entries differ, e.g. {differ[0]}"] if differ else []
    for line in problems:
        print(line)
    print(f"{a.dataset} at {a.root}: {len(files)} files, " + ("OK" if not problems else f"{len(problems)} problem(s)"))
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
