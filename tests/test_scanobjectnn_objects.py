"""ScanObjectNN from the per-object files (dataset.format=object_dataset): the split file, OBJ_BG and
OBJ_ONLY points, 5,000 points per object (the paper's, L251), fixed choices, and every refused input."""
from __future__ import annotations

import numpy as np
import pytest

from mvtn_exp.data.mesh_io import DatasetNotFound, ShapeFileError
from mvtn_exp.data.scanobjectnn import CLASSES
from mvtn_exp.data.scanobjectnn_objects import ScanObjectNNObjects

WALL, OBJECT = 1.0, 7.0  # nyu labels: a wall (background) and the object's


def _object(path, n_object: int, n_background: int, seed: int) -> np.ndarray:
    """An object file: n_object points far from the origin labelled OBJECT, n_background labelled WALL
    (and a few of another object label, fewer than the object's)."""
    r = np.random.default_rng(seed)
    obj = np.zeros((n_object, 11), np.float32)
    obj[:, :3] = r.normal(size=(n_object, 3)) + 10.0
    obj[:, -1] = OBJECT
    bg = np.zeros((n_background, 11), np.float32)
    bg[:, :3] = r.normal(size=(n_background, 3)) * 5
    bg[:, -1] = WALL
    other = np.zeros((3, 11), np.float32)
    other[:, :3], other[:, -1] = -20.0, 9.0
    pts = np.concatenate([obj, bg, other])
    path.parent.mkdir(parents=True, exist_ok=True)
    np.concatenate([[np.float32(len(pts))], pts.reshape(-1)]).astype(np.float32).tofile(path)
    return pts


def _tree(root, objects: dict) -> None:
    """objects: obj_id -> (label, is_test, n_object, n_background)."""
    folder = root / "object_dataset"
    lines = []
    for k, (obj_id, (label, test, n_obj, n_bg)) in enumerate(objects.items()):
        _object(folder / CLASSES[label] / obj_id, n_obj, n_bg, k)
        lines.append(f"{obj_id}\t{label}\t{'t' if test else 'n'}")
    (folder / "split_new.txt").write_text("\n".join(lines) + "\n")
    (folder / CLASSES[0] / "005_00001_part.bin").write_bytes(b"\x00" * 8)  # not an object: never read


OBJECTS = {f"{k:03d}_000{k:02d}.bin": (k % 3, k >= 9, 3000 + 200 * k, 4000) for k in range(12)}


def test_split_file_counts_and_labels(tmp_path):
    _tree(tmp_path, OBJECTS)
    train, val, test = (ScanObjectNNObjects(tmp_path, s, "obj_bg", 5000, val_fraction=0.34) for s in ("train", "val", "test"))
    assert len(test) == 3 and len(train) + len(val) == 9 and len(val) >= 1
    assert set(train.names) | set(val.names) | set(test.names) == set(OBJECTS)
    assert not set(train.names) & set(val.names)
    for ds in (train, val, test):
        for name, label in zip(ds.names, ds.labels):
            assert label == OBJECTS[name][0]


@pytest.mark.parametrize("variant", ["obj_bg", "obj_only"])
def test_points_background_and_a_fixed_choice(tmp_path, variant):
    _tree(tmp_path, OBJECTS)
    ds = ScanObjectNNObjects(tmp_path, "test", variant, num_points=5000, seed=3)
    item = ds[0]
    pts, mask = item["points"].numpy(), item["mask"].numpy()
    assert pts.shape == (5000, 3) and mask.shape == (5000,) and item["label"] == OBJECTS[item["name"]][0]
    assert np.linalg.norm(pts, axis=1).max() == pytest.approx(1.0, abs=1e-5)  # the unit sphere
    if variant == "obj_only":  # the most common object label only: no wall, not the smaller other object
        assert mask.all()
        n_obj = OBJECTS[item["name"]][2]
        assert len(np.unique(pts, axis=0)) <= n_obj  # drawn from the object's points (with replacement)
    else:  # the background is kept, and the mask says which points are the object's
        assert 0.2 < mask.mean() < 0.8
    again = ScanObjectNNObjects(tmp_path, "test", variant, num_points=5000, seed=3)[0]["points"]
    other = ScanObjectNNObjects(tmp_path, "test", variant, num_points=5000, seed=4)[0]["points"]
    assert np.array_equal(again.numpy(), pts) and not np.array_equal(other.numpy(), pts)


def test_refused_inputs_name_the_file(tmp_path, caplog):
    with pytest.raises(DatasetNotFound, match="split_new.txt"):
        ScanObjectNNObjects(tmp_path, "train", "obj_bg")
    _tree(tmp_path, OBJECTS)
    with pytest.raises(ValueError, match="pb_t50_rs exists only in the h5 release"):
        ScanObjectNNObjects(tmp_path, "train", "pb_t50_rs")
    bad = tmp_path / "object_dataset" / CLASSES[0] / "000_00000.bin"
    bad.write_bytes(bad.read_bytes()[:-4])  # a truncated file
    ds = ScanObjectNNObjects(tmp_path, "train", "obj_bg", val_fraction=0.0)
    assert "000_00000.bin" not in ds.names and "000_00000.bin" in ds.skipped[0]
    assert [r.getMessage() for r in caplog.records if "000_00000.bin" in r.getMessage()] == [f"skipping {ds.skipped[0]}"]
    assert any(r.getMessage().startswith("ScanObjectNN obj_bg train: skipped 1 of") for r in caplog.records)
    with pytest.raises(ShapeFileError, match="000_00000.bin: .* bytes; expected"):
        ScanObjectNNObjects(tmp_path, "train", "obj_bg", strict=True)
    (tmp_path / "object_dataset" / "split_new.txt").write_text("001_00001.bin\t99\tt\n")
    with pytest.raises(ShapeFileError, match="split_new.txt:1: label 99"):
        ScanObjectNNObjects(tmp_path, "test", "obj_bg")
    (tmp_path / "object_dataset" / "split_new.txt").write_text("nope_00001.bin\t1\tt\n")
    with pytest.raises(DatasetNotFound, match="1 listed objects have no file"):
        ScanObjectNNObjects(tmp_path, "test", "obj_bg")


def test_config_refuses_pb_t50_rs_from_the_object_files_and_formats_of_other_datasets():
    from mvtn_exp.data.config import ScanObjectNNConfig

    with pytest.raises(ValueError, match="pb_t50_rs exists only in the h5 release"):
        ScanObjectNNConfig(variant="pb_t50_rs", format="object_dataset").validate()
    for other in ("ply_hdf5_2048", "off"):  # ModelNet40's formats
        with pytest.raises(ValueError, match="dataset.format"):
            ScanObjectNNConfig(variant="obj_bg", format=other).validate()
    assert ScanObjectNNConfig().validate().format == "h5"  # the h5 release unless asked
