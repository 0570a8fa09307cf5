"""ModelNet40 point clouds in the two real layouts of the PointNet / PointNet++ releases: labels and
class order, counts, held-out val, orientation, normalisation, fixed points, collate, bad input."""
from __future__ import annotations

import logging
import warnings

import h5py
import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from mvtn_exp.data.collate import collate_shapes
from mvtn_exp.data.mesh_io import DatasetNotFound, ShapeFileError, normalize_unit_sphere
from mvtn_exp.data.modelnet import CountWarning
from mvtn_exp.data.modelnet_points import ModelNetPoints, h5_point_indices

CLASSES = ["night_stand", "airplane", "flower_pot"]  # not sorted: labels must follow the names file
NR_IDS = {"train": {"night_stand": [1, 2, 3], "airplane": [1, 2, 3], "flower_pot": [1, 2, 3]},
          "test": {"night_stand": [201], "airplane": [627, 628], "flower_pot": [150]}}
NR_POINTS = 48  # lines per normal_resampled fixture file (10,000 in the real data)
H5_PREFIX = "data/modelnet40_ply_hdf5_2048/"  # as the real list files write their entries
H5_LABELS = {"ply_data_train0.h5": [0, 1, 2, 0], "ply_data_train1.h5": [1, 2, 0, 1, 2], "ply_data_test0.h5": [2, 0, 1]}
FORMATS = ("normal_resampled", "ply_hdf5_2048")


def cone(n: int, up: int, seed: int, scale: float = 1.0, offset=(0.0, 0.0, 0.0)) -> np.ndarray:
    """``n`` points on a cone 3 long along axis ``up`` (apex towards +up), at most 0.6 wide."""
    r = np.random.default_rng(seed)
    t, ang = r.random(n), r.random(n) * 2 * np.pi
    a, b = [ax for ax in range(3) if ax != up]
    p = np.zeros((n, 3))
    p[:, up], p[:, a], p[:, b] = 3.0 * t, 0.3 * (1 - t) * np.cos(ang), 0.3 * (1 - t) * np.sin(ang)
    return p * scale + np.asarray(offset)


def _txt(pts: np.ndarray) -> str:
    return "".join(f"{x:.6f},{y:.6f},{z:.6f},0.000000,1.000000,0.000000\n" for x, y, z in pts)


def make_normal_resampled(root, up: int = 1):
    """The modelnet40_normal_resampled layout: names file, id lists, <class>/<id>.txt (x,y,z,nx,ny,nz)."""
    root.mkdir(parents=True)
    (root / "modelnet40_shape_names.txt").write_text("\n".join(CLASSES) + "\n")
    for split, ids in NR_IDS.items():
        listed = []
        for c, cls in enumerate(CLASSES):
            (root / cls).mkdir(exist_ok=True)
            for k in ids[cls]:
                sid = f"{cls}_{k:04d}"
                pts = cone(NR_POINTS, up, seed=100 * c + k, scale=1 + k % 3, offset=(5.0, -2.0, 1.0))
                (root / cls / f"{sid}.txt").write_text(_txt(pts))
                listed.append(sid)
        (root / f"modelnet40_{split}.txt").write_text("\n".join(sorted(listed)) + "\n")
    return root


def make_h5(root, up: int = 1):
    """The modelnet40_ply_hdf5_2048 layout: shape_names.txt, {train,test}_files.txt with the data/ prefix,
    h5 files with data [N, 2048, 3] float32, label [N, 1] uint8 and normal."""
    root.mkdir(parents=True)
    (root / "shape_names.txt").write_text("\n".join(CLASSES) + "\n")
    for f, (name, labels) in enumerate(H5_LABELS.items()):
        data = np.stack([cone(2048, up, seed=10 * f + i, scale=1 + i, offset=(i, 0.5, -i))
                         for i in range(len(labels))]).astype(np.float32)
        with h5py.File(root / name, "w") as fh:
            fh["data"] = data
            fh["label"] = np.asarray(labels, np.uint8).reshape(-1, 1)
            fh["normal"] = np.zeros_like(data)
    (root / "train_files.txt").write_text(f"{H5_PREFIX}ply_data_train0.h5\n{H5_PREFIX}ply_data_train1.h5\n")
    (root / "test_files.txt").write_text(f"{H5_PREFIX}ply_data_test0.h5\n")
    return root


def make(tmp_path, fmt: str, up: int = 1):
    return (make_normal_resampled if fmt == "normal_resampled" else make_h5)(tmp_path / fmt, up)


def load(root, split, fmt, **kw):
    """The dataset, tiny fixtures' CountWarnings silenced (other warnings pass)."""
    if fmt == "normal_resampled":
        kw.setdefault("num_points", NR_POINTS)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", CountWarning)
        return ModelNetPoints(root, split, format=fmt, **kw)


def recorded(fn):
    """``fn()``'s result and the messages of every warning (``"CountWarning: ..."``) and every data
    log line (``"log: ..."``, where skipped clouds are reported) it gave."""
    logger, lines = logging.getLogger("mvtn_exp.data"), []
    handler = logging.Handler(logging.WARNING)
    handler.emit = lambda record: lines.append(f"log: {record.getMessage()}")
    logger.addHandler(handler)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            out = fn()
    finally:
        logger.removeHandler(handler)
    return out, [f"{w.category.__name__}: {w.message}" for w in caught] + lines


def items(ds):
    return [ds[i] for i in range(len(ds))]


# ---------------------------------------------------------------- labels, classes, counts
def test_normal_resampled_labels_follow_names_file_and_ids_with_underscores(tmp_path):
    root = make(tmp_path, "normal_resampled")
    test = load(root, "test", "normal_resampled")
    assert test.classes == CLASSES and not test.skipped
    assert sorted(test.names) == ["airplane_0627", "airplane_0628", "flower_pot_0150", "night_stand_0201"]
    for it in items(test):
        assert it["label"] == CLASSES.index(it["name"].rsplit("_", 1)[0]) and isinstance(it["label"], int)
    assert {it["name"]: it["label"] for it in items(test)}["night_stand_0201"] == 0  # class "night_stand", not "night"
    train = load(root, "train", "normal_resampled", val_fraction=0.0)
    assert len(train) == 9 and sorted(np.bincount(train.labels).tolist()) == [3, 3, 3]


def test_h5_labels_names_and_both_listed_files(tmp_path):
    root = make(tmp_path, "ply_hdf5_2048")
    test = load(root, "test", "ply_hdf5_2048")
    assert test.classes == CLASSES and not test.skipped
    assert test.names == ["ply_data_test0_0000", "ply_data_test0_0001", "ply_data_test0_0002"]
    assert [it["label"] for it in items(test)] == [2, 0, 1]  # the file's uint8 labels, as ints
    train = load(root, "train", "ply_hdf5_2048", val_fraction=0.0)
    assert len(train) == 9 and train.names[4] == "ply_data_train1_0000"  # entries resolved by file name
    assert train.labels.tolist() == H5_LABELS["ply_data_train0.h5"] + H5_LABELS["ply_data_train1.h5"]


@pytest.mark.parametrize("fmt,n_test,train,test", [("normal_resampled", 4, 9843, 2468), ("ply_hdf5_2048", 3, 9840, 2468)])
def test_counts_other_than_official_warn_with_both_numbers(tmp_path, fmt, n_test, train, test):
    root = make(tmp_path, fmt)
    _, val_msgs = recorded(lambda: ModelNetPoints(root, "val", format=fmt, num_points=32))
    _, test_msgs = recorded(lambda: ModelNetPoints(root, "test", format=fmt, num_points=32))
    assert any(f"CountWarning: ModelNet40 {fmt} at {root}: 9 train clouds listed, the official dataset has {train}"
               == m for m in val_msgs), val_msgs
    assert any(f"{n_test} test clouds listed, the official dataset has {test}" in m for m in test_msgs), test_msgs
    assert any(m.startswith("CountWarning") and "lists 3 classes, the official dataset has 40" in m
               for m in test_msgs), test_msgs


# ---------------------------------------------------------------- val split
@pytest.mark.parametrize("fmt", FORMATS)
def test_val_is_a_stratified_deterministic_part_of_official_train(tmp_path, fmt):
    root = make(tmp_path, fmt)
    full = load(root, "train", fmt, val_fraction=0.0)
    train = load(root, "train", fmt, val_fraction=0.34)
    val = load(root, "val", fmt, val_fraction=0.34)
    assert len(val) == 3 and sorted(val.labels.tolist()) == [0, 1, 2]  # one per class
    assert not set(train.names) & set(val.names) and sorted(train.names + val.names) == sorted(full.names)
    assert load(root, "val", fmt, val_fraction=0.34).names == val.names  # fixed by seed
    test = load(root, "test", fmt, val_fraction=0.34)
    assert not set(test.names) & set(full.names)  # test is the official test split, untouched


# ---------------------------------------------------------------- orientation, normalisation
def _assert_up_is_plus_y(pts: np.ndarray):
    ext = pts.max(0) - pts.min(0)
    assert ext[1] > 3 * ext[0] and ext[1] > 3 * ext[2], ext  # elongated along our Y
    y = pts[:, 1]
    radial = np.linalg.norm(pts[:, [0, 2]] - np.median(pts[:, [0, 2]], 0), axis=1)
    top, bottom = radial[y > np.quantile(y, 0.8)].mean(), radial[y < np.quantile(y, 0.2)].mean()
    assert top < bottom  # the narrow apex (file's +up) is at our +Y, not -Y


@pytest.mark.parametrize("fmt", FORMATS)
def test_default_keeps_the_files_y_up(tmp_path, fmt):
    """Both releases are Y-up already (module doc): a cloud elongated along the file's Y stays along +Y."""
    ds = load(make(tmp_path, fmt, up=1), "test", fmt)
    assert ds.zup is False
    for it in items(ds):
        _assert_up_is_plus_y(it["points"].numpy())


@pytest.mark.parametrize("fmt", FORMATS)
def test_zup_true_turns_the_files_z_into_plus_y(tmp_path, fmt):
    root = make(tmp_path, fmt, up=2)
    for it in items(load(root, "test", fmt, zup=True)):
        _assert_up_is_plus_y(it["points"].numpy())
    pts = load(root, "test", fmt)[0]["points"].numpy()  # default: not rotated, still along Z
    ext = pts.max(0) - pts.min(0)
    assert ext[2] > 3 * ext[1]


@pytest.mark.parametrize("fmt,num_points", [("normal_resampled", 32), ("ply_hdf5_2048", 2048),
                                            ("ply_hdf5_2048", 100)])
def test_items_are_unit_sphere_float32_clouds(tmp_path, fmt, num_points):
    ds = load(make(tmp_path, fmt), "train", fmt, num_points=num_points, val_fraction=0.0)
    for it in items(ds):
        p = it["points"]
        assert p.dtype == torch.float32 and p.shape == (num_points, 3) and set(it) == {"points", "label", "name"}
        p = p.numpy()
        assert abs(np.linalg.norm(p, axis=1).max() - 1) < 1e-5  # farthest point on the unit sphere
        assert np.allclose((p.max(0) + p.min(0)) / 2, 0, atol=1e-5)  # bounding box centred


# ---------------------------------------------------------------- fixed points
def test_normal_resampled_takes_the_first_points_of_the_file(tmp_path):
    root = make(tmp_path, "normal_resampled")
    ds = load(root, "test", "normal_resampled", num_points=32)
    for it in items(ds):
        cls = it["name"].rsplit("_", 1)[0]
        rows = np.loadtxt(root / cls / f"{it['name']}.txt", delimiter=",")
        assert np.allclose(it["points"].numpy(), normalize_unit_sphere(rows[:32, :3]), atol=1e-6)
    again = load(root, "test", "normal_resampled", num_points=32)
    assert all(torch.equal(a["points"], b["points"]) for a, b in zip(items(ds), items(again)))


def test_normal_resampled_reads_only_the_lines_it_uses(tmp_path):
    root = make(tmp_path, "normal_resampled")
    f = root / "airplane" / "airplane_0627.txt"
    lines = f.read_text().splitlines()
    lines[39] = "oops"  # line 40: beyond 32 points, within 48
    f.write_text("\n".join(lines) + "\n")
    assert not load(root, "test", "normal_resampled", num_points=32).skipped
    ds, msgs = recorded(lambda: load(root, "test", "normal_resampled", num_points=48))
    assert "log: ModelNet40 normal_resampled test: skipped 1 of 4 clouds" in msgs
    assert len(ds.skipped) == 1 and "airplane_0627.txt: line 40" in ds.skipped[0]


def test_h5_subset_is_fixed_per_cloud_and_seeded(tmp_path):
    root = make(tmp_path, "ply_hdf5_2048")
    with h5py.File(root / "ply_data_test0.h5", "r") as fh:
        src = fh["data"][()].astype(np.float64)
    a = load(root, "test", "ply_hdf5_2048", num_points=256)
    b = load(root, "test", "ply_hdf5_2048", num_points=256)
    for i, (x, y) in enumerate(zip(items(a), items(b))):
        assert torch.equal(x["points"], y["points"])
        idx = h5_point_indices(x["name"], 2048, 256, 0)
        assert len(np.unique(idx)) == 256 and (np.diff(idx) > 0).all()
        assert np.allclose(x["points"].numpy(), normalize_unit_sphere(src[i][idx]), atol=1e-6)
    c = load(root, "test", "ply_hdf5_2048", num_points=256, seed=1)
    assert not torch.equal(a[0]["points"], c[0]["points"])  # another seed, another subset
    full = load(root, "test", "ply_hdf5_2048")  # all 2048, in the file's order
    assert np.allclose(full[0]["points"].numpy(), normalize_unit_sphere(src[0]), atol=1e-6)


# ---------------------------------------------------------------- collate
@pytest.mark.parametrize("fmt", FORMATS)
def test_collate_shapes_batches_items(tmp_path, fmt):
    ds = load(make(tmp_path, fmt), "train", fmt, num_points=32, val_fraction=0.0)
    batch = next(iter(DataLoader(ds, batch_size=4, collate_fn=collate_shapes)))
    assert batch["points"].shape == (4, 32, 3) and batch["points"].dtype == torch.float32
    assert batch["labels"].dtype == torch.long and batch["labels"].tolist() == ds.labels[:4].tolist()
    assert batch["names"] == ds.names[:4] and batch["meshes"] is None


# ---------------------------------------------------------------- bad input
@pytest.mark.parametrize("fmt,source", [("normal_resampled", "PointNet\\+\\+ authors"),
                                        ("ply_hdf5_2048", "PointNet authors")])
def test_missing_root_names_path_format_layout_and_source(tmp_path, fmt, source):
    with pytest.raises(DatasetNotFound, match=f"(?s){fmt}: no folder .*nowhere.*expected layout.*{source}"):
        ModelNetPoints(tmp_path / "nowhere", "test", format=fmt)


def test_missing_names_file(tmp_path):
    root = make(tmp_path, "normal_resampled")
    (root / "modelnet40_shape_names.txt").rename(root / "shape_names.txt")  # the other name is accepted
    assert load(root, "test", "normal_resampled").classes == CLASSES
    (root / "shape_names.txt").unlink()
    with pytest.raises(DatasetNotFound, match="(?s)modelnet40_shape_names.txt or .*shape_names.txt.*expected layout"):
        load(root, "test", "normal_resampled")
    h5root = make(tmp_path, "ply_hdf5_2048")
    (h5root / "shape_names.txt").unlink()
    with pytest.raises(DatasetNotFound, match="(?s)ply_hdf5_2048: no class names file .*shape_names.txt"):
        load(h5root, "test", "ply_hdf5_2048")


@pytest.mark.parametrize("fmt,name", [("normal_resampled", "modelnet40_test.txt"), ("ply_hdf5_2048", "test_files.txt")])
def test_missing_list_file(tmp_path, fmt, name):
    root = make(tmp_path, fmt)
    (root / name).unlink()
    assert len(load(root, "train", fmt)) > 0  # the other split still loads
    with pytest.raises(DatasetNotFound, match=f"(?s){fmt}: no test list file .*{name}.*expected layout"):
        load(root, "test", fmt)


@pytest.mark.parametrize("fmt,rel", [("normal_resampled", "airplane/airplane_0002.txt"),
                                     ("ply_hdf5_2048", "ply_data_train1.h5")])
def test_missing_listed_data_file(tmp_path, fmt, rel):
    root = make(tmp_path, fmt)
    (root / rel).unlink()
    with pytest.raises(DatasetNotFound, match=f"(?s){fmt}: no file .*{rel}.*listed.*expected layout"):
        load(root, "val", fmt)


def test_bad_lines_are_skipped_and_named_or_refused_when_strict(tmp_path):
    root = make(tmp_path, "normal_resampled")

    def edit(rel, lineno, text):
        f = root / rel
        lines = f.read_text().splitlines()
        lines[lineno - 1] = text
        f.write_text("\n".join(lines) + "\n")

    edit("night_stand/night_stand_0002.txt", 5, "0.1,zero,0.3,0,1,0")
    edit("airplane/airplane_0003.txt", 7, "0.1,nan,0.3,0,1,0")
    edit("flower_pot/flower_pot_0002.txt", 1, "0.1,0.2")
    f = root / "flower_pot" / "flower_pot_0001.txt"
    f.write_text("\n".join(f.read_text().splitlines()[:10]) + "\n")  # 10 points only
    ds, msgs = recorded(lambda: ModelNetPoints(root, "train", format="normal_resampled", num_points=NR_POINTS,
                                               val_fraction=0.0))
    assert "log: ModelNet40 normal_resampled train: skipped 4 of 9 clouds" in msgs
    assert not [m for m in msgs if m.startswith("UserWarning")]  # each cloud named once, in its log line
    assert sorted(m for m in msgs if m.startswith("log: skipping ")) == sorted(f"log: skipping {s}" for s in ds.skipped)
    assert len(ds) == 5 and len(ds.skipped) == 4
    for reason in ("night_stand_0002.txt: line 5: not comma-separated numbers", "airplane_0003.txt: line 7: NaN",
                   "flower_pot_0002.txt: line 1: 2 values", "flower_pot_0001.txt: 10 points, fewer than num_points=48"):
        assert any(reason in s for s in ds.skipped), (reason, ds.skipped)
    assert not {"night_stand_0002", "airplane_0003", "flower_pot_0001", "flower_pot_0002"} & set(ds.names)
    with pytest.raises(ShapeFileError, match="airplane_0003.txt: line 7"):  # the first listed bad file
        load(root, "train", "normal_resampled", val_fraction=0.0, strict=True)


def test_list_ids_without_a_known_class_are_skipped_and_named(tmp_path):
    root = make(tmp_path, "normal_resampled")
    f = root / "modelnet40_test.txt"
    f.write_text(f.read_text() + "chair_0001\nnight_stand\n")
    ds, msgs = recorded(lambda: load(root, "test", "normal_resampled"))
    assert "log: ModelNet40 normal_resampled test: skipped 2 of 6 clouds" in msgs
    assert len(ds) == 4 and len(ds.skipped) == 2
    assert "modelnet40_test.txt: line 5: id 'chair_0001'" in ds.skipped[0] and "line 6" in ds.skipped[1]
    with pytest.raises(ShapeFileError, match="line 5"):
        load(root, "test", "normal_resampled", strict=True)


def test_h5_nan_cloud_is_skipped_or_refused_and_malformed_files_raise(tmp_path):
    root = make(tmp_path, "ply_hdf5_2048")
    with h5py.File(root / "ply_data_test0.h5", "r+") as fh:
        fh["data"][1, 7, 0] = np.nan
    ds, msgs = recorded(lambda: ModelNetPoints(root, "test", format="ply_hdf5_2048"))
    assert "log: ModelNet40 ply_hdf5_2048 test: skipped 1 of 3 clouds" in msgs
    assert ds.names == ["ply_data_test0_0000", "ply_data_test0_0002"]
    assert "ply_data_test0.h5: key 'data' row 1 (ply_data_test0_0001): 1 points are NaN" in ds.skipped[0]
    with pytest.raises(ShapeFileError, match="ply_data_test0.h5: key 'data' row 1"):
        load(root, "test", "ply_hdf5_2048", strict=True)
    with h5py.File(root / "ply_data_test0.h5", "r+") as fh:
        fh["label"][0, 0] = 3  # the names file has 3 classes
    with pytest.raises(ShapeFileError, match="ply_data_test0.h5: key 'label' has 1 values outside 0..2"):
        load(root, "test", "ply_hdf5_2048")
    with h5py.File(root / "ply_data_test0.h5", "r+") as fh:
        del fh["label"]
    with pytest.raises(ShapeFileError, match="ply_data_test0.h5: no key 'label'"):
        load(root, "test", "ply_hdf5_2048")


@pytest.mark.parametrize("fmt,too_many", [("normal_resampled", 10001), ("ply_hdf5_2048", 2049)])
def test_bad_arguments(tmp_path, fmt, too_many):
    root = make(tmp_path, fmt)
    with pytest.raises(ValueError, match=f"num_points={too_many}"):
        ModelNetPoints(root, "test", format=fmt, num_points=too_many)
    with pytest.raises(ValueError, match="num_points=0"):
        ModelNetPoints(root, "test", format=fmt, num_points=0)
    with pytest.raises(ValueError, match="split='valid'"):
        ModelNetPoints(root, "valid", format=fmt)
    with pytest.raises(ValueError, match="format='off'"):
        ModelNetPoints(root, "test", format="off")
