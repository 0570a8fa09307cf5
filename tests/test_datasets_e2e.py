"""Every real dataset option through the one trainer (``dataset=...``), on tiny fixture trees in the
real layouts built by each reader's own tests."""
from __future__ import annotations

import warnings

import pytest

from mvtn_exp.engine import train


def _run(dataset: dict, tmp_path, **kw) -> dict:
    cfg = {"views": 2, "image_size": 32, "epochs": 1, "batch_size": 4, "dataset": dataset,
           "selector": {"name": "mvtn_spherical"}, "logger": {"progress": False, "tensorboard": False}, **kw}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return train(cfg, tmp_path / "run")


def test_scanobjectnn_points(tmp_path):
    from test_scanobjectnn import _tree

    root = tmp_path / "ScanObjectNN"
    _tree(root)
    m = _run({"name": "scanobjectnn", "root": str(root), "shape": "points", "variant": "obj_only",
              "num_points": 256, "val_fraction": 0.2}, tmp_path)
    assert len(m["classes"]) == 15 and m["test_size"] > 0 and 0 <= m["test_acc"] <= 1


def test_scanobjectnn_refuses_meshes_and_unknown_variants(tmp_path):
    with pytest.raises(ValueError, match="point clouds only"):
        _run({"name": "scanobjectnn", "root": str(tmp_path), "shape": "mesh", "variant": "obj_bg"}, tmp_path)
    with pytest.raises(ValueError, match="dataset.variant"):
        _run({"name": "scanobjectnn", "root": str(tmp_path), "shape": "points", "variant": "hardest"}, tmp_path)


def test_shapenet_points(tmp_path):
    from test_shapenet import _tree

    root = _tree(tmp_path / "ShapeNetCore.v2")
    m = _run({"name": "shapenet", "root": str(root), "shape": "points", "num_points": 128,
              "cache_dir": str(tmp_path / "cache")}, tmp_path, batch_size=2)
    assert m["test_size"] > 0 and len(m["classes"]) >= 2


def test_missing_real_dataset_names_layout(tmp_path):
    from mvtn_exp.data.mesh_io import DatasetNotFound

    for name in ("modelnet40", "scanobjectnn", "shapenet"):
        shape = "mesh" if name == "modelnet40" else "points"
        variant = {"variant": "obj_bg"} if name == "scanobjectnn" else {}  # (a key of scanobjectnn only)
        with pytest.raises(DatasetNotFound, match="expected layout"):
            _run({"name": name, "root": str(tmp_path / "none"), "shape": shape, **variant}, tmp_path)


@pytest.mark.parametrize("fmt", ["normal_resampled", "ply_hdf5_2048"])
def test_modelnet40_point_formats(tmp_path, fmt):
    from test_modelnet_points import make

    root = make(tmp_path, fmt)
    m = _run({"name": "modelnet40", "format": fmt, "root": str(root), "shape": "points", "num_points": 32,
              "val_fraction": 0.3}, tmp_path, batch_size=2)
    assert m["test_size"] > 0
    with pytest.raises(ValueError, match="point clouds only"):
        _run({"name": "modelnet40", "format": fmt, "root": str(root), "shape": "mesh"}, tmp_path)


def test_shapenet_retrieval_reports_shrec17_metrics(tmp_path):
    from test_shapenet import _tree

    from mvtn_exp.evaluation.evaluate import evaluate_checkpoint
    from mvtn_exp.config.eval_schema import EvalConfig, RetrievalEvalConfig

    root = _tree(tmp_path / "ShapeNetCore.v2")
    _run({"name": "shapenet", "root": str(root), "shape": "points", "num_points": 128,
          "cache_dir": str(tmp_path / "cache")}, tmp_path, batch_size=2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        m = evaluate_checkpoint(EvalConfig(ckpt=str(tmp_path / "run" / "best.pt"), task="retrieval", progress=False,
                                           retrieval=RetrievalEvalConfig(dim=4, list_length=3)), tmp_path / "eval")
    shrec = m["retrieval"]["shrec17"]
    assert shrec["N"] <= 3 and {"micro", "macro"} <= set(shrec)
    assert shrec["database"].startswith("the test split itself")  # the challenge's protocol
    assert all(0 <= shrec["micro"][k] <= 1 for k in shrec["micro"])
