"""The working directory's configs/ (or MVTN_CONFIGS) is searched before the packaged configs."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf

from mvtn_exp.config.schema import TrainConfig
from mvtn_exp.config.store import register_configs

ROOT = Path(__file__).resolve().parents[1]
register_configs()


def _compose(overrides):
    with initialize_config_module(version_base="1.3", config_module="mvtn_exp.conf"):
        cfg = compose("train", overrides=overrides)
    return OmegaConf.to_object(cfg).validate()


@pytest.fixture
def user_configs(tmp_path, monkeypatch):
    folder = tmp_path / "configs"
    (folder / "experiment").mkdir(parents=True)
    (folder / "mvnet").mkdir()
    (folder / "experiment" / "mine.yaml").write_text("# @package _global_\nviews: 3\nepochs: 5\n")
    (folder / "mvnet" / "mvcnn.yaml").write_text(  # replaces the packaged one
        "defaults:\n  - /schema/mvnet/mvcnn@_here_\n  - _self_\npool: mean\ndropout: 0.3\n")
    monkeypatch.setenv("MVTN_CONFIGS", str(folder))
    return folder


def test_a_user_experiment_is_found_and_a_same_named_file_replaces_the_packaged_one(user_configs):
    cfg = _compose(["+experiment=mine"])
    assert (cfg.views, cfg.epochs) == (3, 5)
    assert (cfg.mvnet.pool, cfg.mvnet.dropout) == ("mean", 0.3)


def test_without_the_folder_the_packaged_configs_alone(tmp_path, monkeypatch):
    monkeypatch.setenv("MVTN_CONFIGS", str(tmp_path / "absent"))
    cfg = _compose([])
    assert (cfg.mvnet.pool, cfg.mvnet.dropout) == ("max", 0.0)
    with pytest.raises(Exception, match="experiment/mine"):
        _compose(["+experiment=mine"])


def test_the_repositorys_example_composes_and_a_bad_key_is_one_line(tmp_path):
    """From the repository root, configs/experiment/example_small_views.yaml composes through the
    CLI's own checks; a user file with an unknown key is one line, exit 2."""
    import os

    os.environ["MVTN_CONFIGS"] = str(ROOT / "configs")
    try:
        cfg = _compose(["+experiment=example_small_views"])
    finally:
        del os.environ["MVTN_CONFIGS"]
    assert (cfg.views, cfg.image_size, cfg.epochs) == (2, 32, 4)
    bad = tmp_path / "configs" / "experiment"
    bad.mkdir(parents=True)
    (bad / "typo.yaml").write_text("# @package _global_\nviewz: 3\n")
    r = subprocess.run([sys.executable, "-m", "mvtn_exp.cli.train", "+experiment=typo",
                        f"hydra.run.dir={tmp_path / 'run'}"], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "viewz" in r.stderr, r.stderr[-1500:]
    assert not (tmp_path / "run").exists()


def test_a_user_option_file_without_its_schema_is_one_line_naming_the_fix(tmp_path, monkeypatch, capsys):
    """A file in a one-schema-per-option group must say which option it sets; if it does not, the
    error names the defaults line to add (not Hydra's trace), exit 2."""
    from mvtn_exp.config.compose import check_overrides

    (tmp_path / "mvnet").mkdir()
    (tmp_path / "mvnet" / "mine.yaml").write_text("name: mvcnn\npool: mean\n")
    monkeypatch.setenv("MVTN_CONFIGS", str(tmp_path))
    with pytest.raises(SystemExit) as e:
        check_overrides("mvtn-train", "train", TrainConfig, ["mvnet=mine"], validate=TrainConfig.validate)
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 1
    assert "mvnet.pool" in err[0] and "/schema/mvnet/NAME@_here_" in err[0] and "viewgcn" in err[0], err


@pytest.mark.parametrize("text, where, needle", [
    ("# @package _global_\nviews: 2\nviewz: 3\n", "mine.yaml:3", "Key 'viewz' not in 'TrainConfig'"),
    ("# @package _global_\nepochs: 2\nselector:\n  distance: far\n", "mine.yaml:4", "key 'selector.distance'"),
    ("# @package _global_\nviews: [\n", "mine.yaml:3", "while parsing a flow node"),
])
def test_a_bad_user_file_is_named_with_its_line(tmp_path, monkeypatch, capsys, text, where, needle):
    from mvtn_exp.config.compose import check_overrides

    (tmp_path / "experiment").mkdir()
    (tmp_path / "experiment" / "mine.yaml").write_text(text)
    monkeypatch.setenv("MVTN_CONFIGS", str(tmp_path))
    with pytest.raises(SystemExit) as e:
        check_overrides("mvtn-train", "train", TrainConfig, ["+experiment=mine"], validate=TrainConfig.validate)
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 1, err
    assert err[0].startswith(f"mvtn-train: config error in {tmp_path / 'experiment' / where}: ") and needle in err[0], err


def test_a_user_file_named_like_the_main_config_is_refused(tmp_path, monkeypatch, capsys):
    from mvtn_exp.config.compose import check_overrides

    (tmp_path / "train.yaml").write_text("views: 3\n")
    monkeypatch.setenv("MVTN_CONFIGS", str(tmp_path))
    with pytest.raises(SystemExit) as e:
        check_overrides("mvtn-train", "train", TrainConfig, [], validate=TrainConfig.validate)
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 1 and f"{tmp_path / 'train.yaml'}: a file named like mvtn-train's main" in err[0]
