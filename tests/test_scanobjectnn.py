"""ScanObjectNN h5 files in the real layout of h5_files.zip (all three variants): classes, counts,
held-out val, normalisation, fixed point subsets, masks, batching, and every refused input."""
from __future__ import annotations

import warnings

import h5py
import numpy as np
import pytest
import torch

from mvtn_exp.data import scanobjectnn
from mvtn_exp.data.collate import collate_shapes
from mvtn_exp.data.mesh_io import DatasetNotFound, ShapeFileError
from mvtn_exp.data.modelnet import CountWarning
from mvtn_exp.data.scanobjectnn import ScanObjectNN

OFFICIAL_CLASSES = ["bag", "bin", "box", "cabinet", "chair", "desk", "display", "door", "shelf", "table", "bed",
                    "pillow", "sink", "sofa", "toilet"]
USED = [0, 4, 9, 14, 7]  # classes present in the fixtures
BG = 500  # the first BG points of every cloud are background (mask -1)
# variant -> (folder, train file, test file, train count, test count): counts differ per variant so a
# variant reading another variant's file is caught
VARIANTS = {
    "obj_bg": ("main_split", "training_objectdataset.h5", "test_objectdataset.h5", 30, 15),
    "obj_only": ("main_split_nobg", "training_objectdataset.h5", "test_objectdataset.h5", 25, 10),
    "pb_t50_rs": ("main_split", "training_objectdataset_augmentedrot_scale75.h5",
                  "test_objectdataset_augmentedrot_scale75.h5", 35, 20),
}


def _clouds(n: int, seed: int) -> np.ndarray:
    """n clouds of 2048 points, off-centre and of different sizes and (anisotropic) shapes."""
    r = np.random.default_rng(seed)
    pts = r.normal(size=(n, 2048, 3)) * r.uniform(0.2, 3.0, size=(n, 1, 3))
    return (pts + r.uniform(-5, 5, size=(n, 1, 3))).astype(np.float32)


def _write(path, n, seed, label_col=False, data=None, labels=None, mask=True, drop=()):
    path.parent.mkdir(parents=True, exist_ok=True)
    data = _clouds(n, seed) if data is None else data
    labels = np.asarray([USED[k % len(USED)] for k in range(n)], np.int64) if labels is None else labels
    arrays = {"data": data, "label": labels[:, None] if label_col else labels}
    if mask:
        m = np.full((n, 2048), 3, np.int32)
        m[:, :BG] = -1
        arrays["mask"] = m
    with h5py.File(path, "w") as fh:
        for k, v in arrays.items():
            if k not in drop:
                fh.create_dataset(k, data=v)
    return data, labels


def _tree(root, variants=tuple(VARIANTS)):
    """The h5_files.zip layout; obj_only's training labels are stored [N, 1] as some releases do."""
    raw = {}
    for s, v in enumerate(variants):
        folder, train, test, n_train, n_test = VARIANTS[v]
        raw[v, "train"] = _write(root / folder / train, n_train, 10 * s, label_col=v == "obj_only")
        raw[v, "test"] = _write(root / folder / test, n_test, 10 * s + 1)
    return raw


@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    root = tmp_path_factory.mktemp("h5") / "ScanObjectNN"
    return root, _tree(root)


def _load(root, split, variant="pb_t50_rs", **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", CountWarning)  # tiny fixtures never have the official counts
        return ScanObjectNN(root, split, variant=variant, **kw)


def _row(name: str) -> int:
    return int(name.rsplit("_", 1)[1])


def test_classes_and_counts_per_split_for_every_variant(tree):
    root, raw = tree
    for v, (_, _, _, n_train, n_test) in VARIANTS.items():
        test = _load(root, "test", v)
        train, val = _load(root, "train", v, val_fraction=0.2), _load(root, "val", v, val_fraction=0.2)
        assert test.classes == OFFICIAL_CLASSES and train.classes == OFFICIAL_CLASSES
        assert len(test) == n_test and len(train) + len(val) == n_train and len(val) == len(USED), v
        assert test.names[0] == f"{v}_test_00000" and test.path.name == VARIANTS[v][2]
        for ds, official in ((test, "test"), (train, "train"), (val, "train")):
            file_labels = raw[v, official][1]
            for i in range(len(ds)):
                assert ds[i]["label"] == int(file_labels[_row(ds.names[i])]) == int(ds.labels[i])
            assert not ds.skipped


def test_val_is_held_out_per_class_disjoint_and_deterministic(tree):
    root, _ = tree
    train = _load(root, "train", "obj_bg", val_fraction=0.34)
    val = _load(root, "val", "obj_bg", val_fraction=0.34)
    counts = {c: int((val.labels == c).sum()) for c in USED}
    assert counts == {c: 2 for c in USED}  # round(0.34 * 6) of each class's 6 clouds
    assert all(int((train.labels == c).sum()) == 4 for c in USED)
    train_rows, val_rows = {_row(n) for n in train.names}, {_row(n) for n in val.names}
    assert not train_rows & val_rows and train_rows | val_rows == set(range(30))
    assert all(n.startswith("obj_bg_val_") for n in val.names)
    assert _load(root, "val", "obj_bg", val_fraction=0.34).names == val.names
    assert _load(root, "val", "obj_bg", val_fraction=0.34, seed=1).names != val.names
    assert len(_load(root, "train", "obj_bg", val_fraction=0.0)) == 30


def test_points_normalised_as_stored_with_mask(tree):
    root, raw = tree
    ds = _load(root, "test", "obj_only")
    data = raw["obj_only", "test"][0].astype(np.float64)
    for i in range(len(ds)):
        item = ds[i]
        p = item["points"]
        assert isinstance(p, torch.Tensor) and p.dtype == torch.float32 and p.shape == (2048, 3)
        p = p.numpy().astype(np.float64)
        assert abs(np.linalg.norm(p, axis=1).max() - 1) < 1e-5
        assert np.allclose((p.max(0) + p.min(0)) / 2, 0, atol=1e-5)
        raw_pts = data[_row(item["name"])]
        centre = (raw_pts.max(0) + raw_pts.min(0)) / 2
        expect = (raw_pts - centre) / np.linalg.norm(raw_pts - centre, axis=1).max()
        assert np.allclose(p, expect, atol=1e-5)  # same axes as the file: no rotation, no reordering
        assert item["mask"].dtype == torch.bool and item["mask"].shape == (2048,)
        assert not item["mask"][:BG].any() and item["mask"][BG:].all()


def test_fixed_subset_when_fewer_points(tree):
    root, raw = tree
    a, b = _load(root, "test", num_points=1024), _load(root, "test", num_points=1024)
    data = raw["pb_t50_rs", "test"][0].astype(np.float64)
    subsets = []
    for i in range(4):
        x = a[i]
        assert x["points"].shape == (1024, 3) and x["points"].dtype == torch.float32
        assert torch.equal(x["points"], a[i]["points"]) and torch.equal(x["points"], b[i]["points"])  # never resampled
        idx = a.point_indices(_row(x["name"]))
        assert len(np.unique(idx)) == 1024  # without replacement
        expect = scanobjectnn.normalize_unit_sphere(data[_row(x["name"])][idx])
        assert np.allclose(x["points"].numpy(), expect, atol=1e-5)
        assert abs(np.linalg.norm(x["points"].numpy(), axis=1).max() - 1) < 1e-5
        assert torch.equal(x["mask"], torch.from_numpy(idx >= BG))
        subsets.append(tuple(idx))
    assert len(set(subsets)) == 4  # per cloud, not one subset for all
    other = _load(root, "test", num_points=1024, seed=5)
    assert not np.array_equal(other.point_indices(0), a.point_indices(0))
    with pytest.raises(ValueError, match="num_points=4096"):
        ScanObjectNN(root, "test", num_points=4096)


def test_items_batch_with_collate_shapes(tree):
    root, _ = tree
    ds = _load(root, "train", "obj_only", num_points=256)
    batch = collate_shapes([ds[i] for i in range(5)])
    assert batch["points"].shape == (5, 256, 3) and batch["points"].dtype == torch.float32
    assert batch["labels"].tolist() == [int(ds.labels[i]) for i in range(5)] and batch["meshes"] is None
    assert batch["names"] == ds.names[:5]
    loader = torch.utils.data.DataLoader(ds, batch_size=4, collate_fn=collate_shapes)
    assert next(iter(loader))["points"].shape == (4, 256, 3)
    with pytest.raises(IndexError, match="out of range"):
        ds[len(ds)]


def test_missing_root_names_path_variant_and_layout(tmp_path):
    with pytest.raises(DatasetNotFound) as exc:
        ScanObjectNN(tmp_path / "nowhere", "test", variant="obj_bg")
    msg = str(exc.value)
    assert "nowhere" in msg and "obj_bg" in msg and "h5_files.zip" in msg and "ScanObjectNN authors" in msg
    for name in ("main_split/{training,test}_objectdataset.h5", "main_split_nobg/",
                 "_objectdataset_augmentedrot_scale75.h5"):
        assert name in msg


def test_missing_file_of_one_variant(tmp_path):
    root = tmp_path / "ScanObjectNN"
    _tree(root, variants=("obj_bg", "pb_t50_rs"))  # no main_split_nobg
    assert len(_load(root, "test", "obj_bg")) == 15
    with pytest.raises(DatasetNotFound, match=r"obj_only.*main_split_nobg[/\\]training_objectdataset\.h5.*"
                                              r"h5_files\.zip"):
        ScanObjectNN(root, "train", variant="obj_only")
    (root / "main_split" / VARIANTS["pb_t50_rs"][2]).unlink()
    with pytest.raises(DatasetNotFound, match="pb_t50_rs.*test_objectdataset_augmentedrot_scale75.h5"):
        ScanObjectNN(root, "test", variant="pb_t50_rs")


def test_unknown_variant_and_split(tree):
    root, _ = tree
    with pytest.raises(ValueError, match=r"variant='pb_t25'.*'obj_bg', 'obj_only', 'pb_t50_rs'"):
        ScanObjectNN(root, "test", variant="pb_t25")
    with pytest.raises(ValueError, match="split='valid'"):
        ScanObjectNN(root, "valid")


def _one_file(tmp_path, **kw):
    root = tmp_path / "ScanObjectNN"
    _write(root / "main_split" / "test_objectdataset.h5", kw.pop("n", 15), 3, **kw)
    return root


@pytest.mark.parametrize("key", ["data", "label"])
def test_missing_key_is_named(tmp_path, key):
    root = _one_file(tmp_path, drop=(key,))
    with pytest.raises(ShapeFileError, match=rf"test_objectdataset\.h5: no key '{key}'"):
        ScanObjectNN(root, "test", variant="obj_bg")


@pytest.mark.parametrize("kw,key", [
    ({"data": _clouds(15, 0)[:, :1024]}, "data"),  # 1024 points a cloud
    ({"data": np.zeros((15, 2048, 4), np.float32)}, "data"),
    ({"labels": np.zeros(14, np.int64)}, "label"),  # one label short
    ({"labels": np.zeros((15, 2), np.int64)}, "label"),
])
def test_wrong_shapes_are_refused(tmp_path, kw, key):
    root = _one_file(tmp_path, **kw)
    with pytest.raises(ShapeFileError, match=rf"test_objectdataset\.h5: key '{key}' has shape"):
        _load(root, "test", "obj_bg")


@pytest.mark.parametrize("bad", [15, -1])
def test_labels_out_of_range_are_refused(tmp_path, bad):
    labels = np.asarray([USED[k % len(USED)] for k in range(15)], np.int64)
    labels[7] = bad
    root = _one_file(tmp_path, labels=labels)
    with pytest.raises(ShapeFileError, match=rf"test_objectdataset\.h5: key 'label' has 1 values outside 0..14 "
                                             rf"\(e.g. {bad} at row 7\)"):
        _load(root, "test", "obj_bg")


def test_nan_cloud_skipped_and_counted_or_refused_in_strict_mode(tmp_path, monkeypatch, caplog):
    monkeypatch.setitem(scanobjectnn.EXPECTED, "obj_bg", {"train": 2309, "test": 15})  # no count warning
    data = _clouds(15, 0)
    data[4, 100, 1] = np.nan
    data[9, 5] = np.inf
    root = _one_file(tmp_path, data=data)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # each cloud in one log line, no warning
        ds = ScanObjectNN(root, "test", variant="obj_bg")
    lines = [r.getMessage() for r in caplog.records]
    assert lines == [f"skipping {ds.skipped[0]}", f"skipping {ds.skipped[1]}", "ScanObjectNN obj_bg test: skipped 2 of 15 clouds"]
    assert "test_objectdataset.h5: key 'data' row 4" in lines[0]
    assert len(ds) == 13 and len(ds.skipped) == 2
    assert "row 4" in ds.skipped[0] and "row 9" in ds.skipped[1]
    assert {_row(n) for n in ds.names} == set(range(15)) - {4, 9}
    assert all(torch.isfinite(ds[i]["points"]).all() for i in range(len(ds)))
    with pytest.raises(ShapeFileError, match=r"test_objectdataset\.h5: key 'data' row 4: 1 points are NaN"):
        _load(root, "test", "obj_bg", strict=True)


def test_count_warning_gives_both_numbers(tree, monkeypatch):
    root, _ = tree
    monkeypatch.setitem(scanobjectnn.EXPECTED, "obj_bg", {"train": 30, "test": 581})
    with pytest.warns(CountWarning, match="15 test clouds, the official dataset has 581"):
        ScanObjectNN(root, "test", variant="obj_bg")
    with warnings.catch_warnings():
        warnings.simplefilter("error", CountWarning)  # the right count: no warning
        ScanObjectNN(root, "val", variant="obj_bg")
