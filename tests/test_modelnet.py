"""ModelNet meshes in the real layout: labels, counts, orientation, normalisation, fixed points,
broken files skipped and reported (or refused in strict mode), cache reuse, rebuild and resume."""
from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from mvtn_exp.data import modelnet
from mvtn_exp.data.mesh_io import DatasetNotFound, ShapeFileError
from mvtn_exp.data.modelnet import CountWarning, ModelNetMeshes
from mvtn_exp.data.packed import CacheWarning

# A tall box in the file's Z-up frame: 0.2 x 0.4 x 2.0 (x, y, z).
BOX_V = np.array([[x, y, z] for x in (-0.1, 0.1) for y in (-0.2, 0.2) for z in (0.0, 2.0)])
BOX_F = [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
         [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]


def _off(verts, faces, glued=False, comment=False) -> str:
    head = f"OFF{len(verts)} {len(faces)} 0\n" if glued else f"OFF\n{len(verts)} {len(faces)} 0\n"
    body = "".join(" ".join(f"{c:.6f}" for c in v) + "\n" for v in verts)
    body += "".join(f"{len(f)} " + " ".join(map(str, f)) + "\n" for f in faces)
    return ("# made by a test\n\n" if comment else "") + head + body


def _tree(root, broken=True):
    """2 classes x (3 train, 2 test) good boxes (scaled per file), plus broken files in chair/train."""
    for c, cls in enumerate(("chair", "airplane")):
        for split, n in (("train", 3), ("test", 2)):
            d = root / cls / split
            d.mkdir(parents=True)
            for k in range(n):
                v = BOX_V * (1 + k + c) + [5.0, 0, 0]  # off-centre and of any size: preprocessing normalises
                (d / f"{cls}_{k + 1:04d}.off").write_text(_off(v, BOX_F, glued=k == 0, comment=k == 1))
    if broken:
        d = root / "chair" / "train"
        (d / "chair_0100.off").write_text("")  # empty
        nan = BOX_V.copy()
        nan[3, 1] = np.nan
        (d / "chair_0101.off").write_text(_off(nan, BOX_F))
        (d / "chair_0102.off").write_text(_off(BOX_V, [[0, 1, 99]]))  # index out of range
        (d / "chair_0103.off").write_text(_off(np.zeros((3, 3)), [[0, 1, 2]]))  # zero area only
    return root


@pytest.fixture()
def tree(tmp_path):
    return _tree(tmp_path / "ModelNet")


def _load(tree, tmp_path, split, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return ModelNetMeshes(tree, split, cache_dir=tmp_path / "cache", num_points=64, progress=False, **kw)


def test_labels_counts_orientation_normalisation(tree, tmp_path):
    test = _load(tree, tmp_path, "test")
    assert test.classes == ["airplane", "chair"] and len(test) == 4
    assert sorted(test.names) == ["airplane_0001", "airplane_0002", "chair_0001", "chair_0002"]
    assert [int(test[i]["label"]) for i in range(4)] == [0, 0, 1, 1]
    for i in range(len(test)):
        item = test[i]
        v, pts = item["verts"].numpy(), item["points"].numpy()
        assert v.dtype == np.float32 and item["faces"].dtype == torch.int64
        assert abs(np.linalg.norm(v, axis=1).max() - 1) < 1e-5  # unit sphere
        assert np.allclose((v.max(0) + v.min(0)) / 2, 0, atol=1e-5)  # centred
        ext = v.max(0) - v.min(0)
        assert ext[1] > 4 * ext[0] and ext[1] > 4 * ext[2]  # the file's Z (tall) is our Y
        assert pts.shape == (64, 3) and np.linalg.norm(pts, axis=1).max() <= 1 + 1e-5


def test_broken_files_are_skipped_and_named(tree, tmp_path, caplog):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # reported in log lines, not warnings
        train = ModelNetMeshes(tree, "train", cache_dir=tmp_path / "cache", num_points=64, val_fraction=0.0,
                               progress=False)
    assert len(train) == 6 and len(train.skipped) == 4
    lines = [r.getMessage() for r in caplog.records]
    assert any(line.endswith(": skipped 4 of 10 shapes") for line in lines)
    for name in ("chair_0100.off", "chair_0101.off", "chair_0102.off", "chair_0103.off"):
        assert any(name in reason for reason in train.skipped), name
        assert sum(name in line for line in lines) == 1, name  # each named once
    assert all(not n.startswith("chair_01") for n in train.names)


def test_strict_mode_refuses_a_broken_file(tree, tmp_path):
    with pytest.raises(ShapeFileError, match="chair_0100.off"):
        ModelNetMeshes(tree, "train", cache_dir=tmp_path / "cache", num_points=64, strict=True, progress=False)


def test_val_is_held_out_of_train_per_class(tree, tmp_path):
    train = _load(tree, tmp_path, "train", val_fraction=0.34)
    val = _load(tree, tmp_path, "val", val_fraction=0.34)
    assert len(train) + len(val) == 6 and not set(train.names) & set(val.names)
    assert sorted(int(val[i]["label"]) for i in range(len(val))) == [0, 1]  # one of each class
    again = _load(tree, tmp_path, "val", val_fraction=0.34)
    assert again.names == val.names  # deterministic from seed


def test_points_fixed_and_cache_reused(tree, tmp_path, monkeypatch):
    a = _load(tree, tmp_path, "test")
    calls = []
    monkeypatch.setattr(modelnet, "preprocess", lambda *x, **k: calls.append(x) or (_ for _ in ()).throw(AssertionError))
    b = _load(tree, tmp_path, "test")  # from the cache: nothing preprocessed again
    assert not calls
    for i in range(len(a)):
        assert np.array_equal(a[i]["points"].numpy(), b[i]["points"].numpy())


def test_changed_setting_or_corrupt_cache_rebuilds(tree, tmp_path):
    a = _load(tree, tmp_path, "test")
    other = ModelNetMeshes(tree, "test", cache_dir=tmp_path / "cache", num_points=32, progress=False)
    assert other.cache_path != a.cache_path and other[0]["points"].shape == (32, 3)
    a.cache_path.write_bytes(b"not a zip file")
    with pytest.warns(CacheWarning, match="rebuilding"):
        c = ModelNetMeshes(tree, "test", cache_dir=tmp_path / "cache", num_points=64, progress=False)
    assert len(c) == 4


def test_interrupted_preprocessing_resumes(tree, tmp_path, monkeypatch):
    real = modelnet.preprocess
    done = []

    def flaky(path, *a, **k):
        if len(done) == 2:
            raise KeyboardInterrupt
        done.append(path.name)
        return real(path, *a, **k)

    monkeypatch.setattr(modelnet, "preprocess", flaky)
    with pytest.raises(KeyboardInterrupt):
        ModelNetMeshes(tree, "test", cache_dir=tmp_path / "cache", num_points=64, progress=False)
    assert not list((tmp_path / "cache").glob("*.npz"))  # no packed cache from a cut-short run
    redone = []

    def counting(path, *a, **k):
        redone.append(path.name)
        return real(path, *a, **k)

    monkeypatch.setattr(modelnet, "preprocess", counting)
    ds = ModelNetMeshes(tree, "test", cache_dir=tmp_path / "cache", num_points=64, progress=False)
    assert len(ds) == 4 and len(redone) == 2 and not set(redone) & set(done)  # finished shapes not redone
    assert not list((tmp_path / "cache").glob("*.parts"))


def test_missing_root_and_count_warning(tmp_path, monkeypatch, tree):
    with pytest.raises(DatasetNotFound, match="expected layout"):
        ModelNetMeshes(tmp_path / "nowhere", "test", cache_dir=tmp_path / "cache")
    monkeypatch.setitem(modelnet.EXPECTED, 2, {"train": 9843, "test": 2468})
    with pytest.warns(CountWarning, match="4 test files, the official dataset has 2468"):
        modelnet.scan(tree)


def test_real_samples_load(real_samples, tmp_path):
    for name in ("ModelNet40", "ModelNet10"):
        root = real_samples / name
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            test = ModelNetMeshes(root, "test", cache_dir=tmp_path / name, num_points=256, progress=False)
            train = ModelNetMeshes(root, "train", cache_dir=tmp_path / name, num_points=256, val_fraction=0.0,
                                   progress=False)
        assert len(test) == 2 and len(train) == 2 and not test.skipped and not train.skipped
        for ds in (test, train):
            for i in range(len(ds)):
                v = ds[i]["verts"].numpy()
                assert np.isfinite(v).all() and abs(np.linalg.norm(v, axis=1).max() - 1) < 1e-4
                assert len(ds[i]["faces"]) > 0


def test_trains_end_to_end_on_the_modelnet_layout(tree, tmp_path):
    """dataset=modelnet40 through the one trainer: preprocessing on first use, held-out val, test metrics."""
    from mvtn_exp.engine import train

    cfg = {"views": 2, "image_size": 32, "epochs": 1, "batch_size": 4,
           "dataset": {"name": "modelnet40", "root": str(tree), "cache_dir": str(tmp_path / "cache"),
                       "num_points": 128, "val_fraction": 0.34},
           "selector": {"name": "mvtn_circular"}, "logger": {"progress": False, "tensorboard": False}}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        m = train(cfg, tmp_path / "run")
    assert m["classes"] == ["airplane", "chair"] and m["test_size"] == 4
    assert (tmp_path / "run" / "metrics.json").is_file()


def test_prepare_cli_builds_the_cache_and_reports_skips(tree, tmp_path):
    import json
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "mvtn_exp.cli.prepare", "dataset=modelnet40", f"dataset.root={tree}",
                        f"dataset.cache_dir={tmp_path / 'cache'}", "dataset.num_points=64", "logger.progress=false",
                        f"hydra.run.dir={tmp_path / 'run'}"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    summary = json.loads((tmp_path / "run" / "prepare.json").read_text())
    assert r.stdout.strip().splitlines()[-1] == str(tmp_path / "run" / "prepare.json")
    splits = summary["splits"]
    assert splits["test"]["shapes"] == 4 and splits["train"]["shapes"] + splits["val"]["shapes"] == 6
    assert len(splits["train"]["skipped"]) == 4 and list((tmp_path / "cache" / "modelnet").glob("*.npz"))
    missing = subprocess.run([sys.executable, "-m", "mvtn_exp.cli.prepare", "dataset=modelnet40",
                              f"dataset.root={tmp_path / 'nowhere'}", f"hydra.run.dir={tmp_path / 'run2'}"],
                             capture_output=True, text=True, timeout=300)
    assert missing.returncode == 2 and "expected layout" in missing.stderr


def test_retrieval_database_is_the_whole_official_train_split(tree, tmp_path):
    """Retrieval ranks against every official train shape: the val shapes carved out of train for
    model selection go back into the database (ModelNet40: 9,843, not 90% of them)."""
    from mvtn_exp.evaluation.modes import retrieval_database
    from mvtn_exp.engine.trainer import as_config

    cfg = as_config({"dataset": {"name": "modelnet40", "root": str(tree), "cache_dir": str(tmp_path / "cache"),
                                 "num_points": 64, "val_fraction": 0.34}, "logger": {"progress": False}})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        db = retrieval_database(cfg, progress=False)
        train, val = _load(tree, tmp_path, "train", val_fraction=0.34), _load(tree, tmp_path, "val", val_fraction=0.34)
    assert len(val) > 0 and len(db) == len(train) + len(val) == 6  # the 6 readable train files
    assert sorted(db[i]["name"] for i in range(len(db))) == sorted([train[i]["name"] for i in range(len(train))]
                                                                  + [val[i]["name"] for i in range(len(val))])
    assert list(db.classes) == list(train.classes)


def test_cache_is_keyed_by_root_and_contents_not_file_names(tmp_path):
    """Same file names, other contents under another root: another cache, other data; a changed
    file rebuilds too (the key holds the root and every file's bytes)."""
    a = _tree(tmp_path / "A", broken=False)
    b = tmp_path / "B"
    for f in a.rglob("*.off"):  # B: the same names, every shape twice as long along x
        v, faces = _read_off(f)
        dst = b / f.relative_to(a)
        dst.parent.mkdir(parents=True, exist_ok=True)
        dst.write_text(_off(v * [2.0, 1.0, 1.0], faces))
    test_a, test_b = _load(a, tmp_path, "test"), _load(a, tmp_path, "test")
    assert test_a.cache_path == test_b.cache_path  # same root, unchanged files: the cache is reused
    test_b = _load(b, tmp_path, "test")
    assert test_b.cache_path != test_a.cache_path
    extent = lambda ds: float(np.ptp(ds[0]["verts"].numpy()[:, 0]) / np.ptp(ds[0]["verts"].numpy()[:, 1]))
    assert extent(test_b) == pytest.approx(2 * extent(test_a), rel=1e-4)
    one = sorted((a / "airplane" / "test").glob("*.off"))[0]  # a file changed in place
    v, faces = _read_off(one)
    one.write_text(_off(v * [1.0, 3.0, 1.0], faces) + "\n")
    assert _load(a, tmp_path, "test").cache_path != test_a.cache_path


def _read_off(path):
    lines = [ln for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    head = lines[0][3:].split() or lines[1].split()
    start = 1 if lines[0][3:].split() else 2
    nv, nf = int(head[0]), int(head[1])
    v = np.array([[float(x) for x in ln.split()] for ln in lines[start:start + nv]])
    faces = [[int(x) for x in ln.split()[1:]] for ln in lines[start + nv:start + nv + nf]]
    return v, faces
