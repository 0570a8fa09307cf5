"""ShapeNetCore.v2 + SHREC'17 split in the real layout: text ids, labels by sorted synset names,
counts per split, metadata per item, normalisation without rotation, fixed points and cache reuse,
missing OBJs skipped and counted (or refused in strict mode), missing files named; and the real
split CSV and synset dictionary when ../shared is there."""
from __future__ import annotations

import json
import warnings
from collections import Counter

import numpy as np
import pytest
import torch

from mvtn_exp.data import shapenet
from mvtn_exp.data.collate import collate_shapes
from mvtn_exp.data.mesh_io import DatasetNotFound, ShapeFileError
from mvtn_exp.data.modelnet import CountWarning
from mvtn_exp.data.shapenet import ShapeNetCore, read_split_csv

# Synset ids sort airplane < trash bin < bag; their names sort airplane < bag < trash bin.
SYNSETS = {"02691156": "airplane", "02747177": "trash bin", "02773838": "bag", "03001627": "chair"}
HEADER = "id,synsetId,subSynsetId,modelId,split\n"
# (id, synset, sub-synset, model id, split, scale); "00012345" looks like a number, so does every id.
ROWS = [
    ("000772", "02691156", "02690373", "521eab9363fdc2a07209009cfb89d4bd", "train", 1.0),
    ("001119", "02691156", "02690373", "00012345", "train", 2.0),
    ("000003", "02773838", "02773838", "1b84dededd445058e44a5473032f38f", "train", 3.0),
    ("000004", "02747177", "02747177", "2a20ec86e1aaf196cb9b19b1f6bbf9e", "train", 1.5),
    ("000005", "02773838", "02774630", "ffffffffffffffffffffffffffffffff", "train", 1.0),  # OBJ missing
    ("000006", "02691156", "02691156", "0a2b3c4d", "val", 1.0),
    ("000007", "02773838", "02773838", "0e5f6a7b", "val", 2.5),
    ("000008", "02747177", "02747177", "0c9d8e7f", "test", 1.0),
    ("000009", "02691156", "02690373", "0d1e2f3a", "test", 0.5),
]
MISSING = "ffffffffffffffffffffffffffffffff"
# A box tall along Y (the file's and our up axis): 0.2 x 2.0 x 0.4 around (5, 1, 0), off-centre.
BOX_V = np.array([[x, y, z] for x in (4.9, 5.1) for y in (0.0, 2.0) for z in (-0.2, 0.2)])
BOX_F = [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
         [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]


def _obj(scale: float) -> str:
    """ShapeNet-like OBJ text: an mtllib whose .mtl is missing, texture coordinates, v/vt faces,
    and a far vertex no face uses."""
    out = ["# exported by a test", "mtllib model_normalized.mtl", "o mesh1"]
    out += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in BOX_V * scale]
    out += ["v 100 100 100", "vt 0 0", "vt 1 0", "vt 0 1", "usemtl material_0_1_8", "s off"]
    out += [f"f {a + 1}/1 {b + 1}/2 {c + 1}/3" for a, b, c in BOX_F]
    return "\n".join(out) + "\n"


def _tree(root):
    root.mkdir(parents=True)
    for rid, syn, sub, mid, split, scale in ROWS:
        if mid != MISSING:
            d = root / syn / mid / "models"
            d.mkdir(parents=True)
            (d / "model_normalized.obj").write_text(_obj(scale))
    (root / "all.csv").write_text(HEADER + "".join(f"{r[0]},{r[1]},{r[2]},{r[3]},{r[4]}\n" for r in ROWS))
    (root / "shapenet_synset_dict_v2.json").write_text(json.dumps(SYNSETS))
    return root


@pytest.fixture()
def tree(tmp_path):
    return _tree(tmp_path / "ShapeNetCore.v2")


def _load(tree, tmp_path, split, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return ShapeNetCore(tree, split, cache_dir=tmp_path / "cache", num_points=32, progress=False, **kw)


def test_read_split_csv_keeps_text(tree):
    rows = read_split_csv(tree / "all.csv")
    assert [r.id for r in rows] == [r[0] for r in ROWS]  # "000772", not 772
    assert rows[1].model_id == "00012345" and rows[1].synset == "02691156" and rows[1].sub_synset == "02690373"
    assert rows[4].sub_synset == "02774630" and rows[0].line == 2
    assert Counter(r.split for r in rows) == {"train": 5, "val": 2, "test": 2}


@pytest.mark.parametrize("text, match", [
    ("id,synset,subSynsetId,modelId,split\n000001,02691156,02691156,a,train\n", r"bad\.csv:1: expected the header"),
    (HEADER + "000001,02691156,02691156,a,train\n000002,02691156,02691156,b,training\n",
     r"bad\.csv:3: split 'training'"),
    (HEADER + "000001,02691156,02691156,a,train\n000002,02691156,b,test\n", r"bad\.csv:3: expected 5 columns"),
    (HEADER + "000001,02691156,02691156,a,train\n000001,02691156,02691156,b,test\n",
     r"bad\.csv:3: id 000001 already on line 2"),
    (HEADER + "000001,,02691156,a,train\n", r"bad\.csv:2: empty synsetId"),
])
def test_read_split_csv_refuses_bad_files(tmp_path, text, match):
    (tmp_path / "bad.csv").write_text(text)
    with pytest.raises(ValueError, match=match):
        read_split_csv(tmp_path / "bad.csv")


def test_labels_counts_and_metadata(tree, tmp_path):
    train, val, test = (_load(tree, tmp_path, s) for s in ("train", "val", "test"))
    assert train.classes == val.classes == test.classes == ["airplane", "bag", "trash bin"]  # chair: not in CSV
    assert (len(train), len(val), len(test)) == (4, 2, 2) and train.expected == 5
    expect = {r[0]: r for r in ROWS if r[3] != MISSING}
    label = {"02691156": 0, "02773838": 1, "02747177": 2}
    for ds in (train, val, test):
        for i in range(len(ds)):
            item = ds[i]
            _, syn, sub, mid, split, _ = expect[item["name"]]
            assert split == ds.split and item["label"] == label[syn]
            assert (item["synset"], item["sub_synset"], item["model_id"]) == (syn, sub, mid)
            assert "verts" not in item and item["points"].shape == (32, 3)  # rendered as point clouds
    assert sorted(train.names) == ["000003", "000004", "000772", "001119"]
    assert dict(zip(train.names, train.sub_synsets))["001119"] == "02690373"
    batch = collate_shapes([test[0], test[1]])
    assert batch["meshes"] is None and batch["points"].shape == (2, 32, 3)
    assert sorted(batch["labels"].tolist()) == [0, 2]


def test_normalised_without_rotation(tree, tmp_path):
    test = _load(tree, tmp_path, "test", as_points=False)
    for i in range(len(test)):
        item = test[i]
        v, pts = item["verts"].numpy(), item["points"].numpy()
        assert item["faces"].dtype == torch.int64 and len(item["faces"]) == 12
        assert abs(np.linalg.norm(v, axis=1).max() - 1) < 1e-5  # unit sphere (the unused far vertex ignored)
        assert np.allclose((v.max(0) + v.min(0)) / 2, 0, atol=1e-5)
        ext = v.max(0) - v.min(0)
        assert ext[1] > 4 * ext[2] > 4 * ext[0]  # Y stays up: no rotation
        assert np.linalg.norm(pts, axis=1).max() <= 1 + 1e-5
        assert np.abs(pts).max(0)[1] > 0.5  # points lie on the normalised surface


def test_points_fixed_per_model_and_cache_reused(tree, tmp_path, monkeypatch):
    a = _load(tree, tmp_path, "train")
    calls = []
    monkeypatch.setattr(shapenet, "preprocess", lambda *x, **k: calls.append(x) or (_ for _ in ()).throw(AssertionError))
    b = _load(tree, tmp_path, "train")  # from the cache: nothing preprocessed again
    assert not calls and b.cache_path == a.cache_path and b.names == a.names
    for i in range(len(a)):
        assert np.array_equal(a[i]["points"].numpy(), b[i]["points"].numpy())
    # every file is model_normalized.obj: the samples must still differ between two same-scale models
    by = {a.names[i]: a[i]["points"].numpy() for i in range(len(a))}
    assert not np.allclose(by["000772"], by["000004"] * 1.0)
    monkeypatch.undo()
    c = _load(tree, tmp_path, "train", seed=1)
    assert c.cache_path != a.cache_path and not np.allclose(c[0]["points"].numpy(), a[0]["points"].numpy())


def test_missing_obj_skipped_counted_or_refused(tree, tmp_path, caplog):
    with pytest.warns(CountWarning, match=r"train: 4 shapes loaded, the split CSV .* lists 5 \(1 skipped") as rec:
        train = ShapeNetCore(tree, "train", cache_dir=tmp_path / "cache", num_points=32, progress=False)
    assert not any(MISSING in str(w.message) for w in rec)  # the file is named once, in its log line
    assert [r.getMessage() for r in caplog.records if MISSING in r.getMessage()] == [f"skipping {train.skipped[0]}"]
    assert len(train) == 4 and len(train.skipped) == 1 and train.expected == 5
    assert str(tree / "02773838" / MISSING / "models" / "model_normalized.obj") in train.skipped[0]
    assert "000005" not in train.names
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a complete split warns nothing
        ShapeNetCore(tree, "val", cache_dir=tmp_path / "cache", num_points=32, progress=False)
    with pytest.raises(ShapeFileError, match=f"{MISSING}/models/model_normalized.obj: no such file"):
        ShapeNetCore(tree, "train", cache_dir=tmp_path / "cache2", num_points=32, strict=True, progress=False)
    # the file appears later: the cache (keyed by the rows on disk) is rebuilt with it
    d = tree / "02773838" / MISSING / "models"
    d.mkdir(parents=True)
    (d / "model_normalized.obj").write_text(_obj(1.0))
    again = _load(tree, tmp_path, "train")
    assert len(again) == 5 and not again.skipped and again.cache_path != train.cache_path


def test_broken_obj_is_skipped(tree, tmp_path):
    (tree / "02747177" / "0c9d8e7f" / "models" / "model_normalized.obj").write_text("v 0 0 0\nv 1 0 0\nf 1 2 1\n")
    with pytest.warns(CountWarning, match="1 shapes loaded, the split CSV .* lists 2"):
        test = ShapeNetCore(tree, "test", cache_dir=tmp_path / "cache", num_points=32, progress=False)
    assert test.names == ["000009"] and "0c9d8e7f" in test.skipped[0]


def test_missing_files_and_unknown_synset(tree, tmp_path):
    for path, kw in [(tmp_path / "nowhere", {}),
                     (tree / "all.csv", {"split_csv": None}),
                     (tree / "shapenet_synset_dict_v2.json", {})]:
        root = path if path.name == "nowhere" else tree
        if path.name != "nowhere":
            path.rename(path.with_suffix(".gone"))
        with pytest.raises(DatasetNotFound, match="expected layout") as exc:
            ShapeNetCore(root, "test", cache_dir=tmp_path / "cache", **kw)
        msg = str(exc.value)
        assert str(path.resolve()) in msg and "model_normalized.obj" in msg
        assert "ShapeNetCore.v2" in msg and "SHREC'17" in msg and "shapenet.org" in msg
        if path.name != "nowhere":
            path.with_suffix(".gone").rename(path)
    with pytest.raises(DatasetNotFound, match="other.csv"):
        ShapeNetCore(tree, "test", split_csv=tree / "other.csv", cache_dir=tmp_path / "cache")
    small = {k: v for k, v in SYNSETS.items() if k != "02773838"}
    (tmp_path / "small.json").write_text(json.dumps(small))
    with pytest.raises(ValueError, match=r"synset 02773838 \(line 4\) not in the synset dictionary .*small\.json"):
        ShapeNetCore(tree, "test", synset_dict=tmp_path / "small.json", cache_dir=tmp_path / "cache")
    with pytest.raises(ValueError, match="split='training'"):
        ShapeNetCore(tree, "training", cache_dir=tmp_path / "cache")


def test_real_split_csv_and_synset_dict(real_samples):
    rows = read_split_csv(real_samples / "shapenet_split.csv")
    assert len(rows) == 51190
    assert Counter(r.split for r in rows) == {"train": 35765, "val": 5159, "test": 10266}
    assert all(len(r.id) == 6 and r.id.isdigit() for r in rows)
    assert rows[0].id == "000772" and rows[0].synset == "02691156" and rows[0].sub_synset == "02690373"
    names = shapenet.read_synset_dict(real_samples / "shapenet_synset_dict_v2.json")
    synsets = {r.synset for r in rows}
    assert len(synsets) == 55 and synsets <= set(names)
    assert len({names[s] for s in synsets}) == 55 and names["02691156"] == "airplane"


def test_unused_vertices_do_not_skew_normalisation(tmp_path, monkeypatch):
    """trimesh drops them for OBJ today; preprocess must not rely on that."""
    far = np.vstack([BOX_V, [[100.0, 100.0, 100.0]]])
    monkeypatch.setattr(shapenet, "read_mesh", lambda path: (far, np.asarray(BOX_F)))
    path = tmp_path / "02691156" / "abc" / "models" / "model_normalized.obj"
    shape = shapenet.preprocess(path, 0, 16, 20000, 0, name="000001")
    v = shape["verts"]
    assert len(v) == 8 and abs(np.linalg.norm(v, axis=1).max() - 1) < 1e-5 and shape["name"] == "000001"
    assert shape["faces"].max() == 7 and shape["points"].shape == (16, 3)
