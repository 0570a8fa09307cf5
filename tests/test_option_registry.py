"""One registry per option kind (``config/options.py``): every option's config class validates with
its defaults, builds its component (the kinds cheap to build on CPU) and states what the rest of the
config reads before anything is built; ``mvtn-train --list KIND`` names every option."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import torch

from mvtn_exp.config.compose import check_overrides
from mvtn_exp.config.help_text import list_experiments, list_kinds
from mvtn_exp.config.options import OPTIONS, list_options, load
from mvtn_exp.config.schema import TrainConfig
from mvtn_exp.config.store import register_configs
from mvtn_exp.models.point_encoders import PointNetConfig

ROOT = Path(__file__).resolve().parents[1]
register_configs()
load()
EVERY_OPTION = [(kind, name) for kind in OPTIONS for name in sorted(OPTIONS[kind])]
BUILT_HERE = ("small_cnn", "resnet18")  # built here; every backbone: tests/test_model_zoo.py


def _run(argv, capsys) -> tuple[int, list[str], list[str]]:
    """``check_overrides`` as ``mvtn-train`` calls it: (exit code, stdout lines, stderr lines)."""
    with pytest.raises(SystemExit) as e:
        check_overrides("mvtn-train", "train", TrainConfig, argv, validate=TrainConfig.validate)
    out, err = capsys.readouterr()
    return e.value.code, out.splitlines(), err.strip().splitlines()


@pytest.mark.parametrize("kind,name", EVERY_OPTION, ids=[f"{k}={n}" for k, n in EVERY_OPTION])
def test_every_option_validates_with_its_defaults_and_builds_when_cheap(kind, name):
    cfg = OPTIONS[kind][name]()
    assert cfg.name == name and cfg.validate() is cfg
    torch.manual_seed(0)
    if kind == "backbone":
        assert cfg.feature_dim > 0
        if name in BUILT_HERE:
            net = cfg.build(3)
            assert net.feature_dim == cfg.feature_dim
            assert net.features(torch.rand(2, 3, 32, 32)).shape == (2, cfg.feature_dim)
    elif kind == "point_encoder":
        enc = cfg.build().eval()
        assert enc(torch.randn(2, 32, 3)).shape == (2, cfg.features)
        assert cfg.build(out_features=5).eval()(torch.randn(2, 32, 3)).shape == (2, 5)
    elif kind == "mvnet":
        net = cfg.build("small_cnn", 4, point_encoder=PointNetConfig()).eval()
        assert isinstance(net, cfg.network)
        points = {"points": torch.randn(2, 32, 3)} if getattr(net, "reads_points", False) else {}
        views = (torch.rand(2, 4) * 360, torch.rand(2, 4) * 60 - 30, torch.full((2, 4), 2.2))
        with torch.no_grad():
            logits, feats = net(torch.rand(2, 4, 3, 32, 32), views, **points)
        assert logits.shape == (2, 4) and feats.shape == (2, net.feature_dim)


@pytest.mark.parametrize("kind", list(OPTIONS))
def test_list_names_every_registered_option_with_a_sentence(kind, capsys):
    code, out, err = _run(["--list", kind], capsys)
    assert code == 0 and err == []
    assert [ln.split()[0] for ln in out] == sorted(OPTIONS[kind])
    for line, (name, text) in zip(out, list_options(kind)):
        assert text and line.split(None, 1)[1] == text and "\n" not in text, (name, text)
        assert not text.startswith(OPTIONS[kind][name].__name__ + "("), text  # not dataclass's signature


def test_list_experiment_names_every_file_with_its_first_comment(capsys):
    code, out, _ = _run(["--list=experiment"], capsys)
    files = sorted(p.stem for p in (ROOT / "mvtn_exp" / "conf" / "experiment").glob("*.yaml"))
    assert code == 0 and [ln.split()[0] for ln in out] == files
    assert all(text and "@package" not in text for _, text in list_experiments())


@pytest.mark.parametrize("argv", [["--list", "selectors"], ["--list"]], ids=["unknown", "missing"])
def test_list_of_an_unknown_kind_is_one_line_naming_the_kinds(argv, capsys):
    code, out, err = _run(argv, capsys)
    assert code == 2 and out == [] and len(err) == 1
    assert all(kind in err[0] for kind in list_kinds()) and "experiment" in err[0]
    with pytest.raises(ValueError, match="expected one of selector"):
        list_options("selectors")


@pytest.mark.slow  # (longer than 5 s on 2 cores and covered in part elsewhere: make test-all)
def test_list_and_help_from_the_command_line():
    """The installed entry point: ``--list mvnet`` exits 0 before Hydra; ``--help`` mentions ``--list``."""
    r = subprocess.run([sys.executable, "-m", "mvtn_exp.cli.train", "--list", "mvnet"], cwd=ROOT,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and r.stderr == "", r.stderr[-800:]
    assert [ln.split()[0] for ln in r.stdout.splitlines()] == sorted(OPTIONS["mvnet"])
    h = subprocess.run([sys.executable, "-m", "mvtn_exp.cli.train", "--help"], cwd=ROOT,
                       capture_output=True, text=True, timeout=120)
    assert h.returncode == 0 and "--list KIND" in h.stdout


def test_build_by_name_goes_through_the_registry_with_one_line_for_an_unknown_name():
    from mvtn_exp.models.backbones import build_backbone
    from mvtn_exp.models.multiview import build_multiview
    from mvtn_exp.models.point_encoders import build_point_encoder

    for build, noun, kind in ((build_backbone, "backbone", "backbone"),
                              (build_multiview, "multi-view network", "mvnet"),
                              (build_point_encoder, "point encoder", "point_encoder")):
        args = ("nope", "small_cnn", 3) if kind == "mvnet" else ("nope", 3)
        with pytest.raises(ValueError) as err:
            build(*args)
        assert str(err.value) == f"unknown {noun} 'nope'; allowed: {', '.join(sorted(OPTIONS[kind]))}"


@pytest.mark.parametrize("pool", ["max", "mean"])
def test_late_fusion_pools_are_checked_with_the_config_and_build(pool, capsys):
    """``mvnet=late_fusion``: max (the paper's) and mean pass the config check and build; any other
    pool is refused by the check, in one line naming ``mvnet.pool``, before a model is built."""
    check_overrides("mvtn-train", "train", TrainConfig, ["mvnet=late_fusion", f"mvnet.pool={pool}",
                                                         "selector=circular"], validate=TrainConfig.validate)
    net = OPTIONS["mvnet"]["late_fusion"](pool=pool).validate().build("small_cnn", 3, point_encoder=PointNetConfig())
    assert net.pool == pool
    code, _, err = _run(["mvnet=late_fusion", "mvnet.pool=sum", "selector=circular"], capsys)
    assert code == 2 and len(err) == 1 and "mvnet.pool" in err[0] and "max" in err[0], err
