"""ShapeNet Parts in the official layout of the PointNet++ release, written here (3 categories, a few
tiny point files): counts, category labels, part labels that follow their points, normalisation,
fixed samples, the cache, collate, each bad input in one line (missing files, a part outside the
category with file:line, malformed lines skipped or refused), and ``dataset=shapenet_parts``."""
from __future__ import annotations

import json
import logging
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf

from mvtn_exp.config.schema import as_config
from mvtn_exp.config.store import register_configs
from mvtn_exp.data import shapenet_parts
from mvtn_exp.data.collate import collate_shapes
from mvtn_exp.data.datasets import build_dataset
from mvtn_exp.data.mesh_io import DatasetNotFound, ShapeFileError, normalize_unit_sphere
from mvtn_exp.data.shapenet_parts import CATEGORIES, PARTS_OF, PartLabelError, ShapeNetParts

register_configs()
SYNSETS = {"Airplane": "02691156", "Bag": "02773838", "Table": "04379243"}
LABEL = {"Airplane": 0, "Bag": 1, "Table": 15}  # index among the 16 sorted categories
# (split, category, id, points in the file)
SHAPES = [("train", "Airplane", "a1", 12), ("train", "Airplane", "a2", 20), ("train", "Bag", "b1", 9),
          ("train", "Table", "t1", 15), ("val", "Airplane", "a3", 10), ("test", "Bag", "b2", 11),
          ("test", "Table", "t2", 8)]
NUM_POINTS = 16  # more than some files hold (drawn with replacement there), fewer than others


def _raw(category: str, sid: str, n: int) -> np.ndarray:
    """``[n, 7]`` rows of a file: distinct points far from the unit sphere (offset, scaled), random
    normals and the category's parts in turn."""
    rng = np.random.default_rng(sum(map(ord, sid)))
    xyz = rng.normal(size=(n, 3)) * 4.0 + [10.0, -3.0, 7.0]
    parts = np.resize(PARTS_OF[LABEL[category]], n)
    return np.column_stack([xyz, rng.normal(size=(n, 3)), parts])


def _write_points(path, rows: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(" ".join(f"{v:.6f}" for v in r) + "\n" for r in rows))


def _tree(root):
    (root / "train_test_split").mkdir(parents=True)
    (root / "synsetoffset2category.txt").write_text("".join(f"{c}\t{s}\n" for c, s in SYNSETS.items()))
    for split in ("train", "val", "test"):
        entries = [f"shape_data/{SYNSETS[c]}/{sid}" for sp, c, sid, _ in SHAPES if sp == split]
        (root / "train_test_split" / f"shuffled_{split}_file_list.json").write_text(json.dumps(entries))
    for _, c, sid, n in SHAPES:
        _write_points(root / SYNSETS[c] / f"{sid}.txt", _raw(c, sid, n))
    return root


@pytest.fixture()
def tree(tmp_path):
    return _tree(tmp_path / "shapenetcore_partanno_segmentation_benchmark_v0_normal")


def _load(tree, tmp_path, split, **kw):
    kw = {"cache_dir": tmp_path / "cache", "num_points": NUM_POINTS, "progress": False, **kw}
    return ShapeNetParts(tree, split, **kw)


def _file(tree, category, sid):
    return tree / SYNSETS[category] / f"{sid}.txt"


def _set_line(path, lineno: int, text: str) -> None:
    lines = path.read_text().splitlines()
    lines[lineno - 1] = text
    path.write_text("\n".join(lines) + "\n")


# ------------------------------------------------------------------------------ what a split holds
def test_counts_classes_labels_and_names(tree, tmp_path):
    train, val, test = (_load(tree, tmp_path, s) for s in ("train", "val", "test"))
    assert (len(train), len(val), len(test)) == (4, 1, 2)
    assert train.classes == sorted(train.classes) == list(CATEGORIES) and len(train.classes) == 16
    assert train.parts_of[0] == [0, 1, 2, 3] and train.parts_of[15] == [47, 48, 49] and train.num_parts == 50
    assert sum(len(p) for p in train.parts_of.values()) == 50
    assert train.names == ["02691156/a1", "02691156/a2", "02773838/b1", "04379243/t1"]  # split-file order
    assert [train[i]["label"] for i in range(4)] == [0, 0, 1, 15] and test[1]["label"] == 15
    item = val[0]
    assert set(item) == {"points", "part_labels", "label", "name"} and item["name"] == "02691156/a3"
    assert item["points"].dtype == torch.float32 and item["points"].shape == (NUM_POINTS, 3)
    assert item["part_labels"].dtype == torch.int64 and item["part_labels"].shape == (NUM_POINTS,)
    assert train.skipped == [] and isinstance(item["label"], int)


def test_part_labels_follow_their_points_and_points_are_normalised(tree, tmp_path):
    train = _load(tree, tmp_path, "train")
    for i, (_, c, sid, n) in enumerate(s for s in SHAPES if s[0] == "train"):
        raw = _raw(c, sid, n)
        expected = normalize_unit_sphere(np.round(raw[:, :3], 6))  # the file's points, centred, max norm 1
        item = train[i]
        pts, parts = item["points"].numpy(), item["part_labels"].numpy()
        match = np.abs(pts[:, None, :] - expected[None]).max(-1) < 1e-5  # [P, n]: which file row each point is
        assert (match.sum(1) == 1).all(), sid
        assert (parts == raw[match.argmax(1), 6]).all() and set(parts) <= set(PARTS_OF[LABEL[c]])
        assert np.linalg.norm(pts, axis=1).max() <= 1 + 1e-6
        if n >= NUM_POINTS:  # without replacement: distinct rows
            assert len(set(match.argmax(1))) == NUM_POINTS


def test_samples_are_fixed_by_seed_and_name(tree, tmp_path):
    a = _load(tree, tmp_path, "train")
    b = _load(tree, tmp_path, "train", cache_dir=tmp_path / "other")
    c = _load(tree, tmp_path, "train", seed=1)
    assert all(torch.equal(a[i]["points"], b[i]["points"]) for i in range(len(a)))
    assert not torch.equal(a[1]["points"], c[1]["points"])


def test_second_load_reads_the_cache(tree, tmp_path, monkeypatch):
    first = _load(tree, tmp_path, "train")
    assert first.cache_path.is_file() and first.cache_path.parent == tmp_path / "cache"

    def fail(*a, **k):
        raise AssertionError("a file was read again")

    monkeypatch.setattr(shapenet_parts, "prepare_shape", fail)
    again = _load(tree, tmp_path, "train")
    assert again.cache_path == first.cache_path and again.names == first.names
    assert all(torch.equal(first[i]["part_labels"], again[i]["part_labels"]) for i in range(len(first)))
    with pytest.raises(AssertionError, match="read again"):
        _load(tree, tmp_path, "train", num_points=NUM_POINTS + 1)  # another setting: another cache


def test_collate_batches_part_labels(tree, tmp_path):
    train = _load(tree, tmp_path, "train")
    batch = collate_shapes([train[0], train[2], train[3]])
    assert batch["points"].shape == (3, NUM_POINTS, 3) and batch["meshes"] is None
    assert batch["part_labels"].dtype == torch.long and batch["part_labels"].shape == (3, NUM_POINTS)
    assert torch.equal(batch["part_labels"][1], train[2]["part_labels"]) and batch["labels"].tolist() == [0, 1, 15]
    assert "part_labels" not in collate_shapes([{"points": torch.zeros(4, 3), "label": 0, "name": "x"}])


# ------------------------------------------------------------------------------ bad input, one line each
def _one_line(exc) -> str:
    line = str(exc.value)
    assert "\n" not in line
    return line


@pytest.mark.parametrize("missing,needle", [
    ("", "no folder"),
    ("synsetoffset2category.txt", "no category file"),
    ("train_test_split/shuffled_val_file_list.json", "no val split file"),
])
def test_missing_root_or_index_files_name_the_path_and_layout(tree, tmp_path, missing, needle):
    root = tmp_path / "absent" if not missing else tree
    if missing:
        (tree / missing).unlink()
    with pytest.raises(DatasetNotFound) as err:
        _load(root, tmp_path, "val")
    line = _one_line(err)
    assert line.startswith(f"ShapeNet Parts: {needle} ") and "expected layout: " in line
    assert str(root / missing if missing else root) in line and "shapenet.cs.stanford.edu" in line


def test_a_part_outside_the_category_names_file_and_line_even_when_lenient(tree, tmp_path):
    path = _file(tree, "Airplane", "a2")
    _set_line(path, 17, "0.1 0.2 0.3 0.0 1.0 0.0 12.000000")
    for strict in (False, True):
        with pytest.raises(PartLabelError) as err:
            _load(tree, tmp_path, "train", strict=strict)
        assert _one_line(err) == f"{path}:17: part 12 is not a part of Airplane (0-3)"
    assert not list((tmp_path / "cache").glob("*.npz"))  # nothing cached


def test_a_part_error_wins_over_an_earlier_malformed_line(tree, tmp_path):
    path = _file(tree, "Table", "t1")
    _set_line(path, 2, "0.1 0.2 oops 0 1 0 47")
    _set_line(path, 5, "0.1 0.2 0.3 0 1 0 3.000000")
    with pytest.raises(PartLabelError, match=rf"t1\.txt:5: part 3 is not a part of Table \(47-49\)"):
        _load(tree, tmp_path, "train")


@pytest.mark.parametrize("text,reason", [
    ("0.1 0.2 oops 0 1 0 1", "expected 7 numbers 'x y z nx ny nz part'"),
    ("0.1 0.2 0.3 0 1 0", "expected 7 numbers 'x y z nx ny nz part'"),
    ("nan 0.2 0.3 0 1 0 1", "NaN or Inf coordinate"),
    ("0.1 0.2 0.3 0 1 0 1.5", "part label 1.5 is not a whole number"),
])
def test_a_malformed_line_is_skipped_with_one_log_line_or_refused_when_strict(tree, tmp_path, caplog, text, reason):
    path = _file(tree, "Airplane", "a1")
    _set_line(path, 4, text)
    with pytest.raises(ShapeFileError) as err:
        _load(tree, tmp_path, "train", strict=True)
    line = _one_line(err)
    assert line.startswith(f"{path}:4: {reason}")
    caplog.set_level(logging.WARNING, logger="mvtn_exp.data")
    train = _load(tree, tmp_path, "train")
    assert len(train) == 3 and "02691156/a1" not in train.names and train.skipped == [line]
    assert [r.getMessage() for r in caplog.records if str(path) in r.getMessage()] == [f"skipping {line}"]
    with pytest.raises(ShapeFileError, match=f"{path}:4: "):  # strict against the lenient cache
        _load(tree, tmp_path, "train", strict=True)


def test_a_missing_or_empty_point_file_is_skipped_or_refused(tree, tmp_path):
    _file(tree, "Bag", "b1").unlink()
    _file(tree, "Table", "t1").write_text("\n")
    with pytest.raises(ShapeFileError, match=r"b1\.txt: no such file \(listed in .*shuffled_train_file_list\.json\)"):
        _load(tree, tmp_path, "train", strict=True)
    train = _load(tree, tmp_path, "train")
    assert train.names == ["02691156/a1", "02691156/a2"] and len(train.skipped) == 2
    assert train.skipped[1] == f"{_file(tree, 'Table', 't1')}: no points (expected lines 'x y z nx ny nz part')"


@pytest.mark.parametrize("file,text,message", [
    ("train_test_split/shuffled_test_file_list.json", '["shape_data/02691156/a3", "shape_data/09999999/x"]',
     r"shuffled_test_file_list\.json: entry 1 'shape_data/09999999/x': synset 09999999 is not in .*"
     r"synsetoffset2category\.txt"),
    ("train_test_split/shuffled_test_file_list.json", '["02691156/a3"]', r"entry 0 '02691156/a3' is not 'shape_data/"),
    ("train_test_split/shuffled_test_file_list.json", "[", r"shuffled_test_file_list\.json: not valid JSON"),
    ("synsetoffset2category.txt", "Airplane\t02691156\nPlane\t1\n", r"category\.txt:2: 'Plane' is not a ShapeNet Parts"),
    ("synsetoffset2category.txt", "Airplane 02691156 x\n", r"category\.txt:1: expected '<Category><TAB><synset>'"),
])
def test_malformed_index_files_name_the_file_and_entry(tree, tmp_path, file, text, message):
    (tree / file).write_text(text)
    with pytest.raises(ShapeFileError, match=message) as err:
        _load(tree, tmp_path, "test")
    _one_line(err)


# ------------------------------------------------------------------------------ the dataset option
def test_dataset_shapenet_parts_composes_and_builds(tree, tmp_path):
    with initialize_config_module(version_base="1.3", config_module="mvtn_exp.conf"):
        cfg = compose("train", overrides=["dataset=shapenet_parts", f"dataset.root={tree}", "dataset.num_points=16",
                                          f"dataset.cache_dir={tmp_path / 'cache'}"])
    typed = OmegaConf.to_object(cfg).validate()
    d = typed.dataset
    assert (d.name, d.shape, d.strict, type(d).__name__) == ("shapenet_parts", "points", False, "ShapeNetPartsConfig")
    assert d.root == str(tree) and d.num_points == 16
    test = build_dataset(d, "test", progress=False)
    assert len(test) == 2 and test.cache_path.parent == tmp_path / "cache" / "shapenet_parts"
    assert collate_shapes([test[0], test[1]])["part_labels"].shape == (2, 16)


def test_the_option_refuses_meshes_and_a_missing_root_in_one_line(tmp_path):
    default = as_config({"dataset": {"name": "shapenet_parts"}}).dataset
    assert default.root.endswith("/shapenetcore_partanno_segmentation_benchmark_v0_normal")
    assert (default.shape, default.num_points) == ("points", 2048)
    with pytest.raises(ValueError, match="ShapeNet Parts holds point clouds only") as err:
        as_config({"dataset": {"name": "shapenet_parts", "shape": "mesh"}})
    _one_line(err)
    cfg = as_config({"dataset": {"name": "shapenet_parts", "root": str(tmp_path / "none")}}).dataset
    with pytest.raises(DatasetNotFound, match="expected layout: .*synsetoffset2category.txt") as err:
        build_dataset(cfg, "train")
    _one_line(err)


def test_prepare_stops_at_a_wrong_part_with_an_error_the_cli_prints_with_exit_2(tree, tmp_path, capsys):
    from mvtn_exp.cli.prepare import prepare

    _set_line(_file(tree, "Bag", "b1"), 3, "0.1 0.2 0.3 0 1 0 7.000000")
    cfg = as_config({"dataset": {"name": "shapenet_parts", "root": str(tree), "cache_dir": str(tmp_path / "cache"),
                                 "num_points": 16}, "logger": {"progress": False}})
    with pytest.raises(ValueError, match=r"b1\.txt:3: part 7 is not a part of Bag \(4-5\)"):  # exit 2 in mvtn-prepare
        prepare(cfg)
    assert issubclass(DatasetNotFound, FileNotFoundError)  # also exit 2 there


@pytest.mark.slow
def test_prepare_cli_prints_a_wrong_part_in_one_line_with_exit_2(tree, tmp_path):
    path = _file(tree, "Bag", "b2")
    _set_line(path, 3, "0.1 0.2 0.3 0 1 0 7.000000")
    r = subprocess.run([sys.executable, "-m", "mvtn_exp.cli.prepare", "dataset=shapenet_parts", f"dataset.root={tree}",
                        f"dataset.cache_dir={tmp_path / 'cache'}", "dataset.num_points=16", "logger.progress=false",
                        f"hydra.run.dir={tmp_path / 'run'}"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr[-2000:]
    assert r.stderr.strip().splitlines() == [f"mvtn-prepare: error: {path}:3: part 7 is not a part of Bag (4-5)"]


def test_verify_dataset_counts_the_split_lists_and_names_each_problem(tree, capsys):
    import importlib.util

    spec = importlib.util.spec_from_file_location("verify_dataset", Path(__file__).parents[1] / "scripts" / "verify_dataset.py")
    verify = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(verify)
    _file(tree, "Bag", "b2").unlink()
    assert verify.main(["shapenet_parts", str(tree)]) == 1
    out = capsys.readouterr().out.strip().splitlines()
    assert f"{tree / 'synsetoffset2category.txt'}: 3 categories, expected 16" in out
    assert f"{tree / 'train_test_split' / 'shuffled_train_file_list.json'}: 4 shapes, expected 12137" in out
    assert f"{tree}: 1 of 2 point files of shuffled_test_file_list.json missing (<root>/<synset>/<id>.txt)" in out
    assert out[-1] == f"shapenet_parts at {tree}: 10 files, 5 problem(s)"  # (the category file, 3 lists, 6 point files)


def test_the_papers_experiment_composes_and_trains_a_step_on_the_official_layout(tree, tmp_path):
    """``+experiment=paper_part_segmentation`` as composed (DeepLabV3 with its auxiliary head on
    ResNet-101, mode fusion, the 2D loss), made small: one epoch of 64 px fixed views from scratch
    (its learned views: tests/test_paper_experiments.py)."""
    selector = "spherical"
    from mvtn_exp.config.compose import compose_train_config
    from mvtn_exp.engine import train

    cfg = compose_train_config(["+experiment=paper_part_segmentation", f"dataset.root={tree}", f"selector={selector}",
                                f"dataset.cache_dir={tmp_path / 'cache'}", f"dataset.num_points={NUM_POINTS}",
                                "views=1", "image_size=64", "epochs=1", "batch_size=2", "backbone.weights=null",
                                "logger.progress=false", "logger.tensorboard=false"])
    assert (cfg.task.name, cfg.task.fuse, cfg.segnet.name, cfg.segnet.aux, cfg.backbone.name) == \
        ("segmentation", "mode", "deeplabv3", True, "resnet101")
    m = train(cfg, tmp_path / "run")
    assert m["steps"] == 2 and 0.0 <= m["test_instance_miou"] <= 1.0
    assert set(m["test_per_category_miou"]) == {"Bag", "Table"} and m["test_size"] == 2
