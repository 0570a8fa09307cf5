"""G's training strategies: every registered one declares its keys, its multi-process support and
its training keys, no key is declared twice, and a new strategy is one file plus one YAML (here:
a toy strategy defined in this file, composed into a selector and trained)."""
from __future__ import annotations

from dataclasses import dataclass, fields

import pytest
import torch

from conftest import tiny_config as tiny
from mvtn_exp.engine.trainer import as_config, train
from mvtn_exp.selectors import REGISTRY
from mvtn_exp.selectors.config import LearnedKeys, LearnedSelectorConfig, SelectorConfig, compose_selector
from mvtn_exp.selectors.mvtn import MVTNSphericalConfig
from mvtn_exp.selectors.strategies import (STRATEGIES, StepContext, Strategy, StrategyKeys, declaration_problems,
                                           key_names, register_strategy)


def test_every_strategy_declares_keys_multi_process_and_training_keys():
    REGISTRY.schema("poi")  # every selector module loaded
    assert {"smoothed", "flips", "race", "search"} <= set(STRATEGIES)
    for name, strategy in STRATEGIES.items():
        assert strategy.name == name and not declaration_problems(strategy), (name, declaration_problems(strategy))
        assert issubclass(strategy.keys, StrategyKeys) and key_names(strategy.keys)
        assert set(strategy.training_keys) <= set(key_names(strategy.keys))
        assert isinstance(strategy.multi_process, bool)
    assert not STRATEGIES["flips"].multi_process and not STRATEGIES["race"].multi_process
    assert STRATEGIES["smoothed"].multi_process and STRATEGIES["search"].multi_process


def test_no_key_is_declared_by_two_strategies_or_a_strategy_and_a_base_config():
    owners: dict[str, str] = {}
    for owner, cls in [("SelectorConfig", SelectorConfig), ("LearnedKeys", LearnedKeys),
                       *((s.name, s.keys) for s in STRATEGIES.values())]:
        for key in key_names(cls):
            assert key not in owners or (owner, owners[key]) == ("LearnedKeys", "SelectorConfig") and key == "name", \
                f"selector.{key}: declared by {owners[key]} and {owner}"
            owners.setdefault(key, owner)


def test_every_option_has_its_strategies_keys_and_frees_their_training_keys():
    REGISTRY.schema("poi")
    for name, option in REGISTRY.items():
        for strategy in option.strategies:
            assert issubclass(option, strategy.keys), (name, strategy.name)
            assert {f"selector.{k}" for k in strategy.training_keys} <= set(option.free_keys()), (name, strategy.name)
    assert [s.name for s in REGISTRY["poi"].strategies] == ["smoothed", "flips", "race", "search"]
    assert [s.name for s in REGISTRY["mvtn_spherical"].strategies] == ["smoothed", "flips", "search"]
    assert REGISTRY["spherical"].strategies == ()
    assert "selector.race_z" in REGISTRY["poi"].free_keys() and "selector.race_z" not in REGISTRY["mvtn_spherical"].free_keys()


def test_each_strategy_says_whether_it_trains_in_several_processes():
    poi = REGISTRY.schema("poi")().validate()
    assert set(poi.modules(1)) == {"hypotheses"}
    line = poi.multi_process_problem(1, 2)
    assert line.startswith("selector.hypotheses=8 with 2 processes: selector=poi's per-shape statistics (hypotheses)")
    assert poi.multi_process_problem(1, 1) is None
    flips = REGISTRY.schema("mvtn_spherical")(flip_explore=0.25).validate()
    assert set(flips.modules(4)) == {"polarity"} and "selector.flip_explore=0.25 with 2" in flips.multi_process_problem(4, 2)
    smoothed = REGISTRY.schema("mvtn_spherical")(grad="smoothed", probe_pairs=4).validate()
    assert smoothed.modules(4) == {} and smoothed.multi_process_problem(4, 2) is None
    assert [s.name for s in smoothed.enabled_strategies()] == ["smoothed"]


# ----------------------------------------------------------------------------- a new strategy, here only
@dataclass
class PullKeys(StrategyKeys):
    """``elevation_pull``: weight of a penalty pulling G's elevations towards 0 (0: off)."""

    elevation_pull: float = 0.0

    def validate(self):
        super().validate()
        if self.elevation_pull < 0:
            raise ValueError(f"selector.elevation_pull={self.elevation_pull}: expected >= 0")
        return self


class ElevationPull(Strategy):
    """Adds ``elevation_pull x mean(elev^2) / 100`` to the objective while G learns; records the
    mean |elevation| of each epoch's views."""

    name = "toy_elevation_pull"
    keys = PullKeys
    training_keys = ("elevation_pull",)

    @classmethod
    def enabled(cls, s) -> bool:
        return s.elevation_pull > 0

    def start_epoch(self, model, epoch: int, ctx: StepContext) -> None:
        self.learning, self.terms, self.elevations = ctx.learning, 0, []

    def after_forward(self, ctx: StepContext) -> None:
        self.elevations.append(float(ctx.views[1].detach().abs().mean()))

    def g_term(self, ctx: StepContext):
        if not self.learning:
            return None
        self.terms += 1
        return self.s.elevation_pull * ctx.views[1].pow(2).mean() / 100.0

    def end_epoch(self, model, epoch: int) -> list[str]:
        return [f"epoch {epoch + 1}: elevation pull on {self.terms} steps"]

    def history(self, model) -> dict:
        return {"pull_mean_elevation": sum(self.elevations) / len(self.elevations)}


@pytest.fixture
def toy_pull():
    """The strategy registered as a user would, and selector ``toy_pull`` = mvtn_spherical + it."""
    register_strategy(ElevationPull)
    option = compose_selector("toy_pull", MVTNSphericalConfig, ElevationPull)
    try:
        yield option
    finally:
        REGISTRY.pop("toy_pull", None)
        STRATEGIES.pop(ElevationPull.name, None)


def _g_elevations(run_dir, cfg) -> torch.Tensor:
    from mvtn_exp.model import build_mvtn
    from mvtn_exp.runtime import checkpoint

    model = build_mvtn(cfg, num_classes=12)
    model.load_state_dict(checkpoint.load(run_dir / "last.pt")["model"])
    points = torch.randn(8, 256, 3, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        return model.eval().select({"points": points})[1]


def test_a_toy_strategy_composed_through_a_yaml_trains_and_pulls_g(toy_pull, tmp_path, monkeypatch):
    from hydra import compose as hydra_compose
    from hydra import initialize_config_module

    from mvtn_exp.config.store import register_configs

    (tmp_path / "configs" / "selector").mkdir(parents=True)
    (tmp_path / "configs" / "selector" / "toy_pull.yaml").write_text(
        "defaults:\n  - /schema/selector/toy_pull@_here_\n  - _self_\nelevation_pull: 50.0\nlr: 0.05\n")
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("MVTN_CONFIGS", raising=False)
    register_configs()
    cache = str(tmp_path / "cache")
    overrides = ["selector=toy_pull", "views=4", "image_size=16", "epochs=2", "batch_size=8", "backbone=small_cnn",
                 f"dataset.root={cache}", "dataset.num_per_class=[4,2,2]", "logger.progress=false",
                 "logger.tensorboard=false"]
    with initialize_config_module(version_base="1.3", config_module="mvtn_exp.conf"):
        cfg = as_config(hydra_compose("train", overrides=overrides))
        off = as_config(hydra_compose("train", overrides=overrides + ["selector.elevation_pull=0"]))
    assert type(cfg.selector).__name__ == "ToyPullConfig" and cfg.selector.elevation_pull == 50.0
    assert "selector.elevation_pull" in cfg.selector.free_keys()
    assert [s.name for s in cfg.selector.enabled_strategies()] == ["toy_elevation_pull"]
    assert off.selector.enabled_strategies() == []
    pulled = train(cfg, tmp_path / "pulled")
    plain = train(off, tmp_path / "plain")
    log = (tmp_path / "pulled" / "train.log").read_text()
    assert "epoch 1: elevation pull on 6 steps" in log and "epoch 2: elevation pull on 6 steps" in log
    assert [h["pull_mean_elevation"] > 0 for h in pulled["history"]] == [True, True]
    assert "pull_mean_elevation" not in plain["history"][0]
    assert pulled["history"][1]["pull_mean_elevation"] < pulled["history"][0]["pull_mean_elevation"]
    near, far = _g_elevations(tmp_path / "pulled", cfg), _g_elevations(tmp_path / "plain", off)
    assert float(near.abs().mean()) < float(far.abs().mean()) - 1.0, (near, far)


def test_a_disabled_strategy_changes_nothing(toy_pull, tmp_path):
    """``toy_pull`` with its strategy off trains exactly as ``mvtn_spherical``."""
    cache = str(tmp_path / "cache")
    runs = {}
    for name in ("mvtn_spherical", "toy_pull"):
        runs[name] = train(as_config(tiny(cache, epochs=1, **{"selector.name": name})), tmp_path / name)
    a, b = (torch.load(tmp_path / n / "last.pt", weights_only=True)["model"] for n in runs)
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_a_strategy_is_checked_when_registered_and_when_offered():
    @dataclass
    class Clash(StrategyKeys):
        probe_pairs: int = 3

    class Clashing(Strategy):
        name, keys = "toy_clashing", Clash

    with pytest.raises(ValueError, match="selector.probe_pairs: a key of strategy 'smoothed'"):
        register_strategy(Clashing)

    @dataclass
    class Base(StrategyKeys):
        lr: float = 1.0

    class Shadowing(Strategy):
        name, keys = "toy_shadowing", Base

    with pytest.raises(ValueError, match="selector.lr: a key of LearnedKeys"):
        register_strategy(Shadowing)

    class Undeclared(Strategy):
        name, keys, multi_process = "toy_undeclared", PullKeys, False

    with pytest.raises(ValueError, match="names its switch key"):
        register_strategy(Undeclared)
    assert not {"toy_clashing", "toy_shadowing", "toy_undeclared"} & set(STRATEGIES)
    with pytest.raises(TypeError, match="without their keys"):
        @dataclass
        class Missing(LearnedSelectorConfig):
            name: str = "toy_missing"
            strategies = LearnedSelectorConfig.strategies + (ElevationPull,)

    @dataclass
    class OwnPull(MVTNSphericalConfig):  # declares the strategy's key itself
        elevation_pull: float = 1.0

    with pytest.raises(TypeError, match="selector.elevation_pull is a key of strategy 'toy_elevation_pull' and of OwnPull"):
        @dataclass
        class Shadowed(PullKeys, OwnPull):
            strategies = MVTNSphericalConfig.strategies + (ElevationPull,)


def test_a_strategy_mixed_in_by_hand_keeps_flat_keys_and_validates_them():
    @dataclass
    class HandMade(PullKeys, MVTNSphericalConfig):
        name: str = "toy_hand_made"
        strategies = MVTNSphericalConfig.strategies + (ElevationPull,)

    keys = [f.name for f in fields(HandMade)]
    assert keys.count("elevation_pull") == 1 and keys.index("probe_pairs") < keys.index("elevation_pull")
    REGISTRY.register("toy_hand_made")(HandMade)
    try:
        assert HandMade(elevation_pull=0.5).validate().elevation_pull == 0.5
        with pytest.raises(ValueError, match="selector.elevation_pull=-1.0"):
            HandMade(elevation_pull=-1.0).validate()
        with pytest.raises(ValueError, match="selector.probe_pairs"):  # the base keys are still checked
            HandMade(probe_pairs=0).validate()
    finally:
        REGISTRY.pop("toy_hand_made", None)
