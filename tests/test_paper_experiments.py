"""Every paper experiment file runs on fixture data (issue 30): composed as a user types it, built,
trained (an epoch of a few shapes, both ViewGCN stages) and evaluated, so none can rot.

Only the size changes: 16 px images, 4 shapes a batch, 128 points, 1 epoch (ViewGCN: one per
stage), 2 view-optimisation steps instead of 10; the dataset is a tiny tree in the real layout (the
readers' own test fixtures). Views, selectors, networks, backbones, renderers and schedules are the
files' own.
"""
from __future__ import annotations

import warnings
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf

from mvtn_exp.engine import train
from mvtn_exp.evaluation.evaluate import evaluate_checkpoint
from mvtn_exp.engine.trainer import config_dict
from mvtn_exp.config.store import register_configs
from mvtn_exp.config.eval_schema import EvalConfig, OcclusionEvalConfig, RetrievalEvalConfig, RotationEvalConfig

register_configs()
CONF = Path(__file__).resolve().parents[1] / "mvtn_exp" / "conf" / "experiment"
PAPER = sorted(p.stem for p in CONF.glob("paper_*.yaml")) + ["modelnet_spherical"]


@pytest.fixture(scope="module")
def trees(tmp_path_factory) -> dict:
    from test_modelnet import _tree as modelnet_tree
    from test_modelnet_points import make_h5
    from test_scanobjectnn import VARIANTS, _write
    from test_shapenet import _tree as shapenet_tree
    from test_shapenet_parts import _tree as shapenet_parts_tree

    root = tmp_path_factory.mktemp("datasets")
    folder, train_file, test_file, _, _ = VARIANTS["pb_t50_rs"]  # the variant the files default to
    _write(root / "ScanObjectNN" / folder / train_file, 10, 0)
    _write(root / "ScanObjectNN" / folder / test_file, 5, 1)
    return {"modelnet40": modelnet_tree(root / "ModelNet40", broken=False), "scanobjectnn": root / "ScanObjectNN",
            "modelnet40_h5": make_h5(root / "modelnet40_ply_hdf5_2048"),
            "shapenet": shapenet_tree(root / "ShapeNetCore.v2"), "cache": root / "cache",
            "shapenet_parts": shapenet_parts_tree(root / "shapenetcore_partanno_segmentation_benchmark_v0_normal")}


@pytest.fixture(scope="module", autouse=True)
def published_weights(tmp_path_factory):
    """``backbone.weights=imagenet`` without the network: a random-init file per backbone stands in
    for the publisher's (``test_pretrained`` covers fetching and the hash check)."""
    from mvtn_exp.models import backbones, pretrained

    real = pretrained.resolve
    folder = tmp_path_factory.mktemp("published")

    def resolve(backbone, weights, progress=None):
        if not pretrained.is_source(weights):
            return real(backbone, weights, progress)
        path = folder / f"{backbone}-{weights}.pth"
        if not path.is_file():
            torch.save(backbones.build_backbone(backbone, 1000).state_dict(), path)
        return str(path)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(pretrained, "resolve", resolve)
        yield


def test_the_paper_files_start_resnets_from_imagenet_and_g_on_the_papers_pointnet():
    """"a ResNet-18 network, pretrained on ImageNet" (paper L344): every paper file on a ResNet;
    G's PointNet has both T-nets (3.47 M parameters, L736) in every paper file that learns views."""
    for name in PAPER:
        with initialize_config_module(version_base="1.3", config_module="mvtn_exp.conf"):
            cfg = compose("train", overrides=[f"+experiment={name}"])
        if name.startswith("paper_") and cfg.backbone.name.startswith("resnet") and cfg.mvnet.name != "point_classifier":
            assert cfg.backbone.weights == "imagenet", name
        # G's PointNet as the paper's (L736; view transfer takes G from the MVCNN run it names)
        if name.startswith("paper_") and cfg.selector.name.startswith("mvtn") and name != "paper_view_transfer":
            assert cfg.point_encoder.name == "pointnet_paper", name


def _small(name: str, trees: dict, extra=()) -> dict:
    """The experiment as composed from its file, shrunk (see the module docstring)."""
    with initialize_config_module(version_base="1.3", config_module="mvtn_exp.conf"):
        base = OmegaConf.to_object(compose("train", overrides=[f"+experiment={name}", *extra]))
    ds = base.dataset.name
    tree = trees["modelnet40_h5" if getattr(base.dataset, "format", None) == "ply_hdf5_2048" else ds]
    over = [f"+experiment={name}", "image_size=16", "batch_size=4", f"dataset.root={tree}",
            "dataset.num_points=128", "logger.progress=false", "logger.tensorboard=false", *extra]
    if hasattr(base.dataset, "cache_dir"):  # the datasets that preprocess into a cache (not scanobjectnn)
        over.append(f"dataset.cache_dir={trees['cache']}")
    if hasattr(base.dataset, "val_fraction"):  # the datasets without a val split of their own
        over.append("dataset.val_fraction=0.34")
    if base.selector.name == "optimized":
        over.append("selector.steps=2")
    if base.mvnet.name == "viewgcn":
        over += ["epochs=2", "mvnet.stages=[1,1]"]
    else:
        over.append("epochs=1")
    with initialize_config_module(version_base="1.3", config_module="mvtn_exp.conf"):
        cfg = OmegaConf.to_object(compose("train", overrides=over)).validate()
    assert (cfg.views, cfg.selector.name, cfg.mvnet.name, cfg.backbone.name) == \
        (base.views, base.selector.name, base.mvnet.name, base.backbone.name)
    return config_dict(cfg)


def _train(cfg: dict, run: Path) -> dict:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # tiny fixtures never have the official counts
        return train(cfg, run)


@pytest.fixture(scope="module")
def mvcnn_run(trees, tmp_path_factory, published_weights) -> Path:
    """modelnet_spherical trained: the base setup, and the G that view transfer reads."""
    run = tmp_path_factory.mktemp("modelnet_spherical")
    m = _train(_small("modelnet_spherical", trees), run)
    assert 0.0 <= m["test_acc"] <= 1.0 and m["epochs"] == 1
    return run


SLOW = {"paper_vit_pretraining",  # ViT-B/16 (86 M parameters): ~17 s on 2 cores
        "paper_color", "paper_resnet50_pretraining", "paper_view_transfer"}  # (~5 s each; MVCNN as paper_modelnet40_classification)


@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.slow) if n in SLOW else n
                                  for n in PAPER if n not in ("modelnet_spherical",)])
def test_paper_experiment_trains_and_evaluates(name, trees, mvcnn_run, tmp_path):
    extra = []
    if name == "paper_view_transfer":
        extra = [f"selector.from_ckpt={mvcnn_run / 'best.pt'}"]
    if name == "paper_ablation_mvcnn":  # its late-fusion half (the MVTN half is the other files' setup)
        extra = ["+fusion=late_spherical"]
    if name == "paper_vit_pretraining":
        from mvtn_exp.models.backbones import build_backbone

        weights = tmp_path / "dino_vitbase16_pretrain.pth"  # a DINO-style file: no classifier
        torch.save({k: v for k, v in build_backbone("vit_base", 1000).state_dict().items() if not k.startswith("head.")},
                   weights)
        extra = [f"backbone.weights={weights}"]
    cfg = _small(name, trees, extra)
    m = _train(cfg, tmp_path / "run")
    assert 0.0 <= m["test_acc"] <= 1.0 and m["test_size"] > 0
    assert len(m["history"]) == cfg["epochs"]
    if cfg["mvnet"]["name"] == "viewgcn":  # stage 2 trained and the best checkpoint is the whole graph
        assert int(torch.load(tmp_path / "run" / "best.pt", weights_only=False)["model"]["mvnet.stage"]) == 2
    if name == "paper_modelnet40_classification":
        # G as metrics.json records it: the paper's PointNet (3.47-3.49 M, L736) plus its regressor
        # (9.09 K, Table 12, L742), within 1%
        assert abs(m["cost"]["params_selector"] / (3.47e6 + 9.09e3) - 1) < 0.01, m["cost"]["params_selector"]
    if name == "paper_modelnet40_classification":  # the rotation table's evaluation of its best.pt
        ev = evaluate_checkpoint(EvalConfig(ckpt=str(tmp_path / "run" / "best.pt"), robustness="rotation", progress=False,
                                            rotation=RotationEvalConfig(thetas=[90.0], repeats=1)), tmp_path / "eval")
        assert 0.0 <= ev["rotation"]["90"]["mean_acc"] <= 1.0
    if name == "paper_point_classifiers":  # the occlusion table's point baselines: cut points, classified
        ev = evaluate_checkpoint(EvalConfig(ckpt=str(tmp_path / "run" / "best.pt"), robustness="occlusion", progress=False,
                                            occlusion=OcclusionEvalConfig(ratios=[0.0, 0.5])), tmp_path / "eval")
        assert 0.0 <= ev["occlusion"]["0.5"]["mean_acc"] <= 1.0
        assert m["cost"]["params_mvnet"] > 0 and m["cost"]["render_ms_per_shape"] < 1.0  # nothing rendered
    if name == "paper_shapenet_retrieval":  # the retrieval table's evaluation
        ev = evaluate_checkpoint(EvalConfig(ckpt=str(tmp_path / "run" / "best.pt"), task="retrieval", progress=False,
                                            retrieval=RetrievalEvalConfig(dim=4, list_length=3)), tmp_path / "eval")
        assert 0.0 <= ev["retrieval"]["shrec17"]["micro"]["mAP"] <= 1.0


def test_every_paper_experiment_is_in_the_paper_tables():
    """Each paper experiment file is a table of ``mvtn-report`` (docs/paper.md lists them all)."""
    from mvtn_exp.runs.report import load_tables

    named = {t.experiment for t in load_tables()} | {r.experiment for t in load_tables() for r in t.rows}
    assert {n for n in PAPER if n.startswith("paper_")} <= named
    doc = (CONF.parents[2] / "docs" / "paper.md").read_text()
    for n in PAPER:
        assert f"+experiment={n}" in doc, n
