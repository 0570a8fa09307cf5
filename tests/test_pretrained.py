"""Published backbone weights by name (``backbone.weights=imagenet``): fetched once into torch's hub
cache from a ``file://`` fixture (never the network), hash-checked, loaded into C; offline, a
file of another hash and an unknown pairing are one line each, and the CLI writes nothing then."""
from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from mvtn_exp.models import pretrained
from mvtn_exp.models.backbones import small_cnn

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def hub(tmp_path, monkeypatch):
    """An empty torch hub cache, and published small_cnn weights served from a ``file://`` folder."""
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    monkeypatch.delenv(pretrained.MIRROR_ENV, raising=False)  # (conftest's no-network mirror: the fixture serves)
    torch.manual_seed(0)
    served = tmp_path / "served"
    served.mkdir()
    state = small_cnn(num_classes=10).state_dict()
    tmp = served / "tmp.pth"
    torch.save(state, tmp)
    digest = hashlib.sha256(tmp.read_bytes()).hexdigest()[:8]
    name = f"small-{digest}.pth"
    tmp.rename(served / name)
    pub = pretrained.Published(f"file://{served}/{name}", digest, "a fixture")
    monkeypatch.setitem(pretrained.PUBLISHED, ("small_cnn", "imagenet"), pub)
    pretrained._verified.cache_clear()
    return dict(served=served, pub=pub, state=state, cache=tmp_path / "torch" / "hub" / "checkpoints" / name)


def test_imagenet_is_fetched_once_into_the_hub_cache_and_loads_into_the_backbone(hub, monkeypatch):
    path = pretrained.resolve("small_cnn", "imagenet", progress=False)
    assert Path(path) == hub["cache"] and hub["cache"].is_file()
    (hub["served"] / hub["pub"].file_name).unlink()  # the publisher is gone: the cache serves
    assert pretrained.resolve("small_cnn", "imagenet", progress=False) == path
    model = small_cnn(num_classes=40, weights=path)  # (the 10-class head stays fresh)
    assert torch.equal(model.state_dict()["body.0.weight"], hub["state"]["body.0.weight"])
    assert pretrained.resolve("small_cnn", None) is None and pretrained.resolve("small_cnn", "/x/w.pth") == "/x/w.pth"


def test_the_mirror_serves_the_file_under_its_publishers_name(hub, tmp_path, monkeypatch):
    mirror = tmp_path / "mirror"
    mirror.mkdir()
    (hub["served"] / hub["pub"].file_name).rename(mirror / hub["pub"].file_name)
    monkeypatch.setenv(pretrained.MIRROR_ENV, f"file://{mirror}/")
    assert Path(pretrained.resolve("small_cnn", "imagenet", progress=False)).is_file()


def test_offline_another_hash_and_an_unknown_pairing_are_one_line_each(hub, monkeypatch):
    monkeypatch.setenv(pretrained.MIRROR_ENV, f"file://{hub['served']}/nowhere")
    with pytest.raises(pretrained.PretrainedError) as info:
        pretrained.resolve("small_cnn", "imagenet", progress=False)
    msg = str(info.value)
    assert "\n" not in msg and "cannot download file://" in msg and "backbone.weights=/path/to/small-" in msg
    monkeypatch.delenv(pretrained.MIRROR_ENV)
    bad = pretrained.Published(hub["pub"].url, "00000000", "a fixture")
    monkeypatch.setitem(pretrained.PUBLISHED, ("small_cnn", "imagenet"), bad)
    with pytest.raises(pretrained.PretrainedError, match="is not the pinned file"):
        pretrained.resolve("small_cnn", "imagenet", progress=False)
    assert not hub["cache"].parent.exists() or not any(hub["cache"].parent.iterdir())  # nothing cached, no .partial
    with pytest.raises(pretrained.PretrainedError, match=r"no published imagenet weights for backbone=dgcnn .*resnet18"):
        pretrained.resolve("dgcnn", "imagenet")


def test_a_cached_file_that_lost_its_hash_is_removed_not_loaded(hub):
    path = Path(pretrained.resolve("small_cnn", "imagenet", progress=False))
    path.write_bytes(path.read_bytes()[:-10])
    with pytest.raises(pretrained.PretrainedError, match="does not have the pinned SHA-256"):
        pretrained.resolve("small_cnn", "imagenet", progress=False)
    assert not path.exists()


def test_every_published_file_is_pinned_by_the_hash_in_its_name():
    for (backbone, source), pub in pretrained.PUBLISHED.items():
        assert pub.url.startswith("https://") and f"-{pub.sha256}." in pub.file_name, (backbone, source)
        assert len(pub.sha256) >= 8 and int(pub.sha256, 16) >= 0


def test_training_loads_them_evaluation_builds_c_without_them(hub, tmp_path, monkeypatch):
    from conftest import tiny_config
    from mvtn_exp.engine.trainer import as_config
    from mvtn_exp.model import build_mvtn

    cfg = as_config(tiny_config(str(tmp_path), **{"backbone.weights": "imagenet"}))  # (small_cnn: the fixture's)
    model = build_mvtn(cfg, 3)
    assert torch.equal(model.mvnet.backbone.state_dict()["body.0.weight"], hub["state"]["body.0.weight"])

    def no(*a, **k):
        raise AssertionError("resolved")

    monkeypatch.setattr(pretrained, "resolve", no)
    model = build_mvtn(cfg, 3, pretrained_weights=False)
    assert hasattr(model.mvnet, "input_mean")  # (trained on normalised inputs: evaluated on them too)


@pytest.mark.parametrize("served", ["nothing", "another file"])
def test_the_cli_refuses_unobtainable_weights_in_one_line_and_writes_nothing(tmp_path, served):
    mirror = tmp_path / "mirror"
    mirror.mkdir()
    if served == "another file":
        (mirror / "resnet18-f37072fd.pth").write_bytes(b"not the published weights")
    out = tmp_path / "out"
    env = dict(os.environ, TORCH_HOME=str(tmp_path / "torch"), **{pretrained.MIRROR_ENV: f"file://{mirror}"})
    r = subprocess.run([sys.executable, "-m", "mvtn_exp.cli.train", "backbone=resnet18", "backbone.weights=imagenet",
                        f"hydra.run.dir={out}"], cwd=tmp_path, capture_output=True, text=True, env=env, timeout=300)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1, r.stderr[-2000:]
    assert ("cannot download file://" if served == "nothing" else "is not the pinned file") in lines[0]
    assert not out.exists() and not (tmp_path / "outputs").exists()
    assert not any((tmp_path / "torch").rglob("*.pth*"))


def test_a_backbone_without_published_weights_is_refused_at_compose_time(tmp_path):
    from conftest import tiny_config
    from mvtn_exp.engine.trainer import as_config

    with pytest.raises(ValueError, match=r"backbone.weights=imagenet: no published imagenet weights for backbone=small_cnn"):
        as_config(tiny_config(str(tmp_path), **{"backbone.weights": "imagenet"}))
