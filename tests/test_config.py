"""The config tree: every group option and every experiment composes against the schemas and
validates; bad keys, types, options and values are refused at compose time."""
from __future__ import annotations

from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf

from mvtn_exp.config.compose import check_overrides, sweep_variants
from mvtn_exp.config.schema import GROUPS, TrainConfig
from mvtn_exp.config.store import register_configs

CONF = Path(__file__).resolve().parents[1] / "mvtn_exp" / "conf"
register_configs()


def _compose(overrides):
    with initialize_config_module(version_base="1.3", config_module="mvtn_exp.conf"):
        cfg = compose("train", overrides=overrides)
    obj: TrainConfig = OmegaConf.to_object(cfg)
    return obj.validate()


def _options(group):
    return sorted(p.stem for p in (CONF / group).glob("*.yaml"))


def test_required_groups_exist():
    for group in ("dataset", "renderer", "selector", "point_encoder", "backbone", "mvnet", "task", "optim", "logger",
                  "experiment", "hydra", "paths"):
        assert _options(group), group
    assert set(GROUPS) <= {p.name for p in CONF.iterdir() if p.is_dir()}


@pytest.mark.parametrize("group", [g for g in GROUPS if g != "paths"])
def test_every_group_option_composes(group):
    for option in _options(group):
        # (the paper's late fusion and the point classifier take fixed views: not the default learned ones)
        fixed_views = group == "mvnet" and option in ("late_fusion", "point_classifier")
        parts = group == "task" and option == "segmentation"  # (a dataset with part labels)
        cfg = _compose([f"{group}={option}", *(["selector=circular"] if fixed_views else []),
                        *(["dataset=synthetic_parts"] if parts else [])])
        if hasattr(getattr(cfg, group), "name"):
            assert option.startswith(getattr(cfg, group).name), (group, option)


# the paper setups: (dataset, selector, mvnet, views, epochs, C's lr)
_MVCNN, _GCN = ("modelnet40", "mvtn_spherical", "mvcnn", 12, 100, 3e-4), ("mvtn_spherical", "viewgcn", 12, 85, 1e-3)
PAPER = {
    "modelnet_spherical": _MVCNN, "paper_ablation": ("modelnet40", *_GCN), "paper_views_ablation": _MVCNN,
    "paper_ablation_mvcnn": _MVCNN, "modelnet_learned_distance": _MVCNN, "paper_rotation": _MVCNN, "paper_occlusion": _MVCNN,
    "paper_vit_pretraining": ("scanobjectnn", "mvtn_spherical", "mvcnn", 8, 100, 3e-4),  # L629
    "paper_modelnet40_classification": ("modelnet40", *_GCN), "paper_view_transfer": ("modelnet40", *_GCN),
    "paper_scanobjectnn_classification": ("scanobjectnn", *_GCN), "paper_shapenet_retrieval": ("shapenet", *_GCN),
    "paper_noise_baseline": ("scanobjectnn", "noisy", "mvcnn", 8, 100, 1e-3),
    "paper_scene_optimisation": ("scanobjectnn", "optimized", "mvcnn", 8, 100, 1e-3),  # L504
    "paper_resnet50_pretraining": ("scanobjectnn", "mvtn_spherical", "mvcnn", 8, 100, 3e-4),  # L629
    "paper_color": ("modelnet40", *_GCN), "paper_distance": ("modelnet40", "spherical", "viewgcn", 12, 85, 1e-3),  # L1170
    "paper_light": ("modelnet40", "mvtn_circular", "mvcnn", 12, 100, 3e-4),  # L1166
    "paper_mvtn_variants": ("modelnet40", "mvtn_direct", "mvcnn", 12, 100, 3e-4),
    "paper_point_classifiers": ("modelnet40", "circular", "point_classifier", 1, 100, 1e-3),
    "paper_part_segmentation": ("shapenet_parts", "mvtn_spherical", "mvcnn", 12, 100, 3e-4),  # (C: segnet=deeplabv3)
}
# files the user gives on the command line (placeholders in the experiment file)
REQUIRED = {"paper_view_transfer": ["selector.from_ckpt=run/best.pt"]}


@pytest.mark.parametrize("name", _options("experiment"))
def test_every_experiment_composes(name):
    cfg = _compose([f"+experiment={name}", *REQUIRED.get(name, [])])
    assert cfg.renderer.image_size == cfg.image_size
    if name.startswith("synthetic_views"):  # the README's view-dependent comparison: same setup both sides
        assert cfg.dataset.name == "synthetic_views" and cfg.augment.rotate == "so3" and cfg.renderer.mode == "hard"
        assert cfg.renderer.train_light == "camera" and cfg.renderer.train_color == "white" and cfg.views == 1
        learned = "learned" in name
        assert cfg.selector.name == ("poi" if learned else "spherical")
        if learned:  # the recipe, from the selector's own defaults
            assert cfg.selector.grad == "smoothed" and cfg.selector.loss == "centered_logit"
            assert cfg.selector.gain == 32.0 and cfg.selector.hypotheses == 8 and cfg.selector.race_epochs == 8
            assert cfg.selector.antipodes and cfg.selector.race_mode == "pooled"
    elif name == "tradeoff_synthetic_views":  # the study's view-dependent half: the learned recipe, swept
        assert cfg.dataset.name == "synthetic_views" and cfg.selector.name == "poi" and cfg.epochs == 20
    elif name.startswith("synthetic_parts"):  # the embedded part segmentation: same setup, fixed or learned views
        assert (cfg.dataset.name, cfg.task.name, cfg.segnet.name, cfg.views, cfg.epochs) == \
            ("synthetic_parts", "segmentation", "fcn_small", 4, 60)
        assert cfg.selector.name == ("mvtn_spherical" if "learned" in name else "spherical")
        lit = "lit" in name  # the third recipe: the second, lit from above in world space and white, train as test
        balanced = "balanced" in name or lit  # the second: batch 2, the inverse-sqrt class weights
        assert (cfg.batch_size, cfg.task.balance) == ((2, "inverse_sqrt") if balanced else (8, "none"))
        r = cfg.renderer
        paper_lights = ("camera", "random", [0.0, 1.0, 0.0], "white", "random")
        want = ("fixed", "fixed", [0.0, 1.0, 0.0], "white", "white") if lit else paper_lights
        assert (r.light, r.train_light, list(r.light_direction), r.color, r.train_color) == want, name
        if "learned" in name:  # G waits for C only in the lit recipe
            assert (cfg.selector.warmup_epochs, cfg.selector.warmup_views) == ((20, "u0") if lit else (0, "u0"))
    elif name.startswith(("synthetic", "tradeoff")):
        assert cfg.dataset.name == "synthetic" and cfg.epochs <= 10
    else:  # the paper setups: dataset, G, C, M, epochs, C's learning rate
        want = PAPER[name]
        got = (cfg.dataset.name, cfg.selector.name, cfg.mvnet.name, cfg.views, cfg.epochs, cfg.optim.lr)
        assert got == want, name
        assert cfg.image_size == 224 and cfg.batch_size == 20 and cfg.optim.schedule == "step"
        assert not cfg.optim.decay_selector  # the official code decays C only
        if cfg.selector.learned:  # the paper's text for G (1e-3), the official code's G
            assert cfg.selector.lr == 1e-3 and cfg.selector.clip == 30 and cfg.selector.regressor == "official"
        if cfg.mvnet.name == "viewgcn":  # the supplement: 50 single-view epochs, then 35
            assert cfg.mvnet.stages == [50, 35] and cfg.mvnet.fps_start == "random" and cfg.mvnet.level_views is None
        if name == "paper_noise_baseline":  # 8 spherical views plus noise, black background
            assert cfg.selector.base_layout == "spherical" and (cfg.selector.noise_azim, cfg.selector.noise_elev) == (18.0, 9.0)
            assert cfg.renderer.background == [0.0, 0.0, 0.0]
    text = (CONF / "experiment" / f"{name}.yaml").read_text()
    assert text.startswith("# @package _global_")


@pytest.mark.parametrize("name", [n for n in _options("experiment")
                                  if "sweeper" in (CONF / "experiment" / f"{n}.yaml").read_text()
                                  and "/hydra/sweeper: optuna" not in (CONF / "experiment" / f"{n}.yaml").read_text()
                                  and "/hydra/sweeper: mvtn_optuna" not in (CONF / "experiment" / f"{n}.yaml").read_text()])
def test_every_job_of_a_sweep_experiment_composes(name):
    """Every combination in an experiment's ``hydra.sweeper.params`` composes and validates (a
    sweep never starts jobs that would be refused), and the grid has the size its comment says."""
    import itertools

    params = OmegaConf.load(CONF / "experiment" / f"{name}.yaml").hydra.sweeper.params
    grid = [[f"{key}={value.strip()}" for value in str(values).split(",")] for key, values in params.items()]
    jobs = list(itertools.product(*grid))
    assert len(jobs) > 1
    # large grids: every value of every key once (linear, as the CLI checks a command-line sweep)
    checked = jobs if len(jobs) <= 30 else [tuple(v) for v in sweep_variants([f"{k}={v}" for k, v in params.items()])]
    seen = set()
    with initialize_config_module(version_base="1.3", config_module="mvtn_exp.conf"):
        composed = [compose("train", overrides=[f"+experiment={name}", *job]) for job in checked]
    for c in composed:
        cfg = OmegaConf.to_object(c).validate()
        seen.add((cfg.views, cfg.selector.name, cfg.mvnet.name, cfg.backbone.name, cfg.point_encoder.name,
                  getattr(cfg.selector, "learn_distance", None), getattr(cfg.dataset, "variant", None), cfg.renderer.mode, cfg.image_size, cfg.seed,
                  getattr(cfg.selector, "objective", None), cfg.backbone.weights, cfg.renderer.train_color,
                  cfg.renderer.train_light, cfg.selector.distance))
    assert len(seen) == len(checked)  # every job is a different setting
    text = (CONF / "experiment" / f"{name}.yaml").read_text()
    assert f"{len(jobs)} jobs" in text


def test_synthetic_experiments_select_their_views():
    assert _compose(["+experiment=synthetic_circular"]).selector.name == "circular"
    assert _compose(["+experiment=synthetic_spherical"]).selector.name == "spherical"
    assert _compose(["+experiment=synthetic_mvtn"]).selector.learned


def test_top_level_keys_reach_the_parts():
    cfg = _compose(["views=7", "image_size=48", "seed=3", "dataset.seed=5"])
    assert cfg.views == 7 and cfg.renderer.image_size == 48 and cfg.seed == 3 and cfg.dataset.seed == 5
    assert cfg.dataset.root.endswith("outputs/cache/synthetic")  # interpolated from paths


@pytest.mark.parametrize("argv, needle", [
    (["viewz=3"], "allowed keys here"),
    (["views=abc"], "views"),
    (["selector=nope"], "available options for selector"),
    (["dataset.rotate=sideways"], "dataset.rotate"),
    (["optim.schedule=linear"], "optim.schedule"),
    (["augment.rotate=sideways"], "augment.rotate"),
    (["+optim.lr_selectr=1"], "adds key 'optim.lr_selectr', which is not in the schema"),
    (["++viewz=3"], "adds key 'viewz'"),
    (["+renderer.sigmaa=1"], "allowed keys here"),
    (["device=gpu"], "expected auto, cpu, cuda or cuda:N"),
    pytest.param(["device=cuda"], "CUDA is not available on this machine",
                 marks=pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")),
    (["renderer.mode=wire"], "renderer.mode"),
    (["selector.regressor=mlp"], "selector.regressor"),
    (["selector.grad=finite"], "selector.grad"),
    (["selector.probe_pairs=0"], "selector.probe_pairs"),
    (["selector.probe_sigma=0"], "selector.probe_sigma"),
    (["selector.probe_every=0"], "selector.probe_every"),
    (["selector.warmup_num_views=12"], "there is no warm-up"),
    (["selector.warmup_epochs=1", "selector.warmup_num_views=12"], "use warmup_views=spherical or random"),
    (["selector.warmup_epochs=1", "selector.warmup_views=ring"], "selector.warmup_views"),
    (["selector.beta1=1.0"], "selector.beta1=1.0: must be in [0, 1)"),
    (["selector.grad=smoothed", "selector.learn_distance=true"], "needs selector.grad=autograd"),
    (["selector.loss=entropy"], "selector.loss"),
    (["selector.loss=centered_logit"], "needs selector.grad=smoothed"),
    (["selector.flip_explore=1.0"], "expected a probability in [0, 1)"),
    (["selector.flip_explore=0.5", "selector.flip_epochs=0"], "selector.flip_epochs"),
    (["selector=spherical", "selector.flip_explore=0.5"], "selector=spherical has no key 'flip_explore'"),
    (["selector=mvtn_poi", "selector.hypotheses=2"], "set both"),
    (["selector=mvtn_spherical", "selector.hypotheses=2", "selector.race_epochs=2"], "selector=mvtn_spherical has no key 'hypotheses'"),
    (["selector.bn_recalibrate=-1"], "selector.bn_recalibrate"),
    (["selector.bn_recalibrate_scope=test"], "selector.bn_recalibrate_scope"),
    (["-m", "views=1,0"], "views=0"),
    (["renderer.memory_budget_mb=1"], "renderer.memory_budget_mb >= "),
    (["renderer.memory_budget_mb=0"], "renderer.memory_budget_mb must be > 0"),
    (["-m", "backbone=small_cnn,vgg"], "available options for backbone"),
])
def test_check_overrides_refuses(argv, needle, capsys):
    with pytest.raises(SystemExit) as e:
        check_overrides("mvtn-train", "train", TrainConfig, argv, validate=TrainConfig.validate)
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0] and err[0].startswith("mvtn-train: config error in mvtn_exp/conf/")


def test_check_overrides_accepts_good_sweeps():
    check_overrides("mvtn-train", "train", TrainConfig, ["-m", "selector=circular,spherical", "views=1,4"],
                    validate=TrainConfig.validate)
    check_overrides("mvtn-train", "train", TrainConfig, ["+experiment=synthetic_circular", "++optim.lr=0.01"],
                    validate=TrainConfig.validate)


def test_sweep_variants_are_linear():
    v = sweep_variants(["selector=a,b,c", "views=1,4", "seed=0"])
    assert v[0] == ["selector=a", "views=1", "seed=0"] and len(v) == 1 + 2 + 1
    assert ["selector=c", "views=1", "seed=0"] in v and ["selector=a", "views=4", "seed=0"] in v


def test_schema_defaults_equal_the_default_yaml():
    """``train(dict)`` from Python and ``mvtn-train`` with no overrides run the same experiment."""
    from mvtn_exp.engine.trainer import as_config

    assert _compose([]) == as_config({})


def test_help_lists_this_projects_groups_and_keys():
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "mvtn_exp.cli.train", "--help"], capture_output=True, text=True,
                       timeout=120, cwd=CONF.parents[1])
    assert r.returncode == 0, r.stderr
    out = r.stdout
    assert out.startswith("mvtn-train (mvtn-exp ") and "powered by Hydra" not in out
    groups = {ln.split()[0]: ln for ln in out.splitlines() if ln.startswith("  ") and not ln.strip().startswith(("views=", "ckpt"))}
    assert "mvtn_spherical*" in groups["selector"] and "mvtn_direct" in groups["selector"]
    assert "evaluate" not in groups and "hydra" not in groups  # not choosable from mvtn-train
    assert "augment.{rotate}" in out and "views=4" in out
    assert "selector.{name,distance" in out and "gain" not in out.split("selector.{", 1)[1].split("}")[0]
    v = subprocess.run([sys.executable, "-m", "mvtn_exp.cli.eval", "--version"], capture_output=True, text=True, timeout=60)
    assert v.returncode == 0 and v.stdout.startswith("mvtn-eval (mvtn-exp) ")


def test_help_lists_the_keys_of_the_options_chosen_on_the_command_line(capsys):
    """``selector=poi mvnet=viewgcn --help``: the keys of those options, not of the defaults."""
    with pytest.raises(SystemExit) as e:
        check_overrides("mvtn-train", "train", TrainConfig, ["selector=poi", "mvnet=viewgcn", "--help"])
    out = capsys.readouterr().out
    assert e.value.code == 0
    sel = out.split("selector.{", 1)[1].split("}")[0].split(",")
    assert "gain" in sel and "race_epochs" in sel and "regressor" not in sel
    assert "mvnet.{name,dropout,k,fps_start,level_views,stages}" in out and "poi*" in out


def test_tradeoff_study_grid_composes_and_compares_fixed_with_learned():
    from hydra import compose, initialize_config_module

    with initialize_config_module(version_base="1.3", config_module="mvtn_exp.conf"):
        params = compose("train", overrides=["+experiment=tradeoff_synthetic"], return_hydra_config=True).hydra.sweeper.params
    grid = {k: str(v).split(",") for k, v in params.items()}
    assert grid["seed"] == ["0", "1", "2"] and set(grid["renderer"]) == {"hard", "soft"}
    learned = []
    for key, values in grid.items():
        for value in values:
            cfg = _compose(["+experiment=tradeoff_synthetic", f"{key}={value}"])
            learned.append(cfg.selector.learned)
            assert cfg.dataset.name == "synthetic" and cfg.epochs == 8
    assert any(learned) and not all(learned)


def test_multirun_with_cfg_is_one_line_not_hydras_traceback(capsys):
    with pytest.raises(SystemExit) as e:
        check_overrides("mvtn-train", "train", TrainConfig, ["-m", "views=1,4", "--cfg", "job"],
                        validate=TrainConfig.validate)
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--cfg" in err[0] and "-m/--multirun" in err[0]


@pytest.mark.parametrize("name", _options("preset"))
def test_presets_compose_and_state_their_measured_cost(name):
    cfg = _compose([f"+preset={name}"])
    text = (CONF / "preset" / f"{name}.yaml").read_text()
    assert text.startswith("# @package _global_")
    if name == "paper":
        assert cfg.views == 12 and cfg.image_size == 224 and cfg.selector.regressor == "official"
    else:  # on the measured front: the comment names the study, whose page gives its accuracy and cost
        assert "tradeoff_synthetic" in text and "docs/results/tradeoff.md" in text
        page = (CONF.parents[1] / "docs" / "results" / "tradeoff.md").read_text()
        assert f"`+preset={name}`" in page and "ms per shape" in page
        assert cfg.views == 1 and cfg.image_size == 32
        # the front's ends: fixed views on the hard renderer, learned views on the soft one
        assert cfg.selector.learned == (name == "balanced") and cfg.renderer.mode == ("soft" if name == "balanced" else "hard")


def test_presets_are_the_three_documented():
    assert _options("preset") == ["balanced", "fast", "paper"]


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")
@pytest.mark.parametrize("cli, argv", [("eval", ["ckpt=x.pt"]), ("render", ["input=builtin:sphere"]),
                                       ("bench", ["quick=true"])])  # mvtn-train: test_check_overrides_refuses
def test_every_cli_refuses_cuda_on_a_cpu_build_in_one_line(cli, argv, tmp_path):
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", f"mvtn_exp.cli.{cli}", "device=cuda", *argv], cwd=tmp_path,
                       capture_output=True, text=True, timeout=120)
    err = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(err) == 1, r.stderr[-2000:]
    assert err[0].startswith(f"mvtn-{cli}: config error") and "device='cuda': CUDA is not available" in err[0]
    assert not list(tmp_path.iterdir())  # refused before any output folder was made


def test_device_auto_resolves_to_what_the_machine_has(monkeypatch):
    """device=auto is every CLI's default and never fails: CUDA when torch sees it, else CPU."""
    from mvtn_exp.cli.bench import BenchAppConfig
    from mvtn_exp.cli.render import RenderAppConfig
    from mvtn_exp.config.schema import TrainConfig, check_device, resolve_device
    from mvtn_exp.config.eval_schema import EvalConfig

    assert TrainConfig().device == EvalConfig().device == BenchAppConfig().device == RenderAppConfig().device == "auto"
    check_device("device", "auto")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto") == resolve_device(None) == "cpu" and resolve_device("cuda:1") == "cuda:1"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert resolve_device("auto") == "cuda" and resolve_device("cpu") == "cpu"


@pytest.mark.parametrize("prog", ["train", "eval", "render", "bench", "prepare"])
def test_help_into_a_closed_pipe_ends_quietly(prog):
    """``mvtn-X --help | head -1``: a reader that closed the pipe ends the command with exit 0 and
    no BrokenPipeError traceback."""
    import os
    import subprocess
    import sys

    r, w = os.pipe()
    os.close(r)  # the reader is gone before anything is written
    try:
        done = subprocess.run([sys.executable, "-m", f"mvtn_exp.cli.{prog}", "--help"], stdout=w, stderr=subprocess.PIPE,
                              text=True, timeout=120)
    finally:
        os.close(w)
    assert done.returncode == 0 and "Traceback" not in done.stderr and "BrokenPipe" not in done.stderr, done.stderr
