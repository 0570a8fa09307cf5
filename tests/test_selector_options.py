"""One schema per selector option: a key of another option is refused naming the option and the
key, moved keys name their new place, "learned" is a property of the option, the recipe is one
name, and a new selector touches only its own code (here: this file)."""
from dataclasses import dataclass

import pytest
import torch
from torch import nn

from conftest import tiny_config as tiny
from mvtn_exp.config.compose import check_overrides
from mvtn_exp.engine.trainer import as_config, train
from mvtn_exp.config.schema import TrainConfig
from mvtn_exp.config.store import register_configs
from mvtn_exp.selectors import REGISTRY, ViewSelector
from mvtn_exp.selectors.config import LearnedSelectorConfig, register

register_configs()


def _refused(argv, capsys) -> str:
    with pytest.raises(SystemExit) as e:
        check_overrides("mvtn-train", "train", TrainConfig, argv, validate=TrainConfig.validate)
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


def test_a_key_of_another_option_is_refused_naming_option_and_key(capsys):
    line = _refused(["selector=circular", "selector.poi_gain=3"], capsys)
    assert "selector=circular has no key 'poi_gain'" in line and "keys of selector=circular" in line
    line = _refused(["selector=spherical", "selector.elevation=10"], capsys)
    assert "selector=spherical has no key 'elevation'" in line and "circular" in line


@pytest.mark.parametrize("old", ["optim.selector_grad=smoothed", "optim.lr_selector=0.01"])
def test_a_key_of_no_schema_is_refused_naming_the_allowed_keys(old, capsys):
    line = _refused([old], capsys)
    assert old.split("=")[0].split(".")[1] in line and "allowed keys here: " in line and "lr," in line


def test_learned_is_a_property_of_the_option_not_its_name():
    learned = {name for name, option in REGISTRY.items() if option.learned}
    assert learned == {"mvtn_direct", "mvtn_direct_offset", "mvtn_circular", "mvtn_spherical", "mvtn_poi", "poi"}
    assert not REGISTRY["optimized"].learned and not REGISTRY["noisy"].learned


def test_the_recipe_is_one_name_with_its_renderer(tmp_path):
    from hydra import compose, initialize_config_module

    with initialize_config_module(version_base="1.3", config_module="mvtn_exp.conf"):
        cfg = as_config(compose("train", overrides=["selector=poi", "views=1"]))
        soft = as_config(compose("train", overrides=["selector=poi", "renderer=soft"]))
    s = cfg.selector
    assert (s.gain, s.hypotheses, s.race_epochs, s.race_mode, s.antipodes, s.lr) == (32.0, 8, 8, "pooled", True, 1e-2)
    assert (s.grad, s.loss, s.bn_recalibrate) == ("smoothed", "centered_logit", 24)
    assert (cfg.renderer.mode, cfg.renderer.train_light, cfg.renderer.train_color) == ("hard", "camera", "white")
    assert soft.renderer.mode == "soft"  # the command line's renderer wins


def test_the_recipe_with_one_set_of_views_is_one_line_away():
    """The recipe races eight hypotheses; one set of views is three keys, and a half-way line is
    refused with the whole line to write."""
    from hydra import compose, initialize_config_module

    lean = "selector.hypotheses=1 selector.race_epochs=0 selector.antipodes=false"
    with initialize_config_module(version_base="1.3", config_module="mvtn_exp.conf"):
        cfg = as_config(compose("train", overrides=["selector=poi", *lean.split()]))
        assert (cfg.selector.hypotheses, cfg.selector.race_epochs, cfg.selector.antipodes) == (1, 0, False)
        assert cfg.selector.modules(cfg.views) == {}  # no race: nothing per shape to keep
        with pytest.raises(ValueError, match=lean):
            as_config(compose("train", overrides=["selector=poi", "selector.hypotheses=1"]))
        with pytest.raises(ValueError, match=lean):
            as_config(compose("train", overrides=["selector=poi", "selector.grad=search"]))


# ----------------------------------------------------------------------------- a new selector, here only
class ToySelector(ViewSelector):
    """M views at one learned elevation (a single parameter), azimuths 360 k / M."""

    learned = True

    def __init__(self, views: int, distance: float) -> None:
        super().__init__(views)
        self.distance = distance
        self.elevation = nn.Parameter(torch.tensor(10.0))

    def initial_views(self, batch: int = 1):
        return self.forward(torch.zeros(batch, 1, 3))

    def forward(self, points):
        B, M = points.shape[0], self.views
        azim = (torch.arange(M, dtype=torch.float32) * 360.0 / M).expand(B, M).to(points.device)
        elev = self.elevation.expand(B, M)
        return azim, elev, torch.full_like(azim, self.distance)


@dataclass
class ToyConfig(LearnedSelectorConfig):
    name: str = "toy_test_selector"

    def build(self, views, seed, point_encoder=None):
        return ToySelector(views, self.distance)


def test_a_toy_selector_defined_here_registers_and_trains_one_step(tmp_path):
    register("toy_test_selector")(ToyConfig)
    try:
        cfg = as_config(tiny(str(tmp_path / "cache"), epochs=1, **{"selector.name": "toy_test_selector",
                                                                   "selector.lr": 0.5}))
        assert type(cfg.selector) is ToyConfig and cfg.selector.learned
        with pytest.raises(ValueError, match="selector=toy_test_selector has no key 'gain'"):
            as_config(tiny(str(tmp_path / "cache"), **{"selector.name": "toy_test_selector", "selector.gain": 3}))
        run = train(cfg, tmp_path / "run")
        state = torch.load(tmp_path / "run" / "last.pt", weights_only=True)
        assert run["steps"] >= 1 and float(state["model"]["selector.elevation"]) != 10.0  # G took its step
        assert run["history"][0]["grad_norm_selector"] > 0
    finally:
        REGISTRY.pop("toy_test_selector", None)


def test_warmup_views_are_the_ones_asked_for(tmp_path):
    """``selector.warmup_views``: random gives new directions per shape, spherical the layout for
    every shape, u0 G's initial views."""
    from types import SimpleNamespace

    from mvtn_exp.render import layouts
    from mvtn_exp.selectors import MVTNSelector
    from mvtn_exp.selectors.training import LearnedTraining

    batch = {"points": torch.zeros(4, 10, 3)}
    model = SimpleNamespace(device=torch.device("cpu"), selector=MVTNSelector(3, "spherical"))
    got = {}
    for kind in ("random", "spherical", "u0"):
        cfg = as_config(tiny(str(tmp_path), views=3, **{"selector.name": "mvtn_spherical", "selector.warmup_epochs": 1,
                                                        "selector.warmup_views": kind}))
        torch.manual_seed(0)
        got[kind] = LearnedTraining(cfg).warmup_views(model, batch)
    lay = layouts.spherical(3, 4, 2.2)
    assert torch.allclose(got["spherical"][0], lay[0]) and torch.allclose(got["spherical"][1], lay[1])
    assert not torch.equal(got["random"][0][0], got["random"][0][1])  # per shape
    assert not torch.allclose(got["random"][0], lay[0])
    u0 = model.selector.initial_views(4)
    assert torch.equal(got["u0"][0], u0[0]) and torch.equal(got["u0"][1], u0[1])
