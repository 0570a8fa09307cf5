"""The paper's alternatives and newer components (issue 12): each trains, evaluates and round-trips
a checkpoint from its config option; component-specific behaviour below."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import torch

from mvtn_exp.runtime import checkpoint
from mvtn_exp.engine import train
from mvtn_exp.evaluation.evaluate import evaluate_checkpoint
from mvtn_exp.engine.trainer import as_config
from mvtn_exp.model import build_mvtn
from mvtn_exp.config.options import OPTIONS, load
from mvtn_exp.models.backbones import build_backbone
from mvtn_exp.models.multiview import build_multiview
from mvtn_exp.models.point_encoders import build_point_encoder
from mvtn_exp.models.view_transformer import ViewTransformer
from mvtn_exp.config.eval_schema import EvalConfig
from mvtn_exp.selectors import NoisySelector, build_selector

from conftest import tiny_config

ROOT = Path(__file__).resolve().parents[1]
load()
IMAGE_NETS = sorted(n for n, c in OPTIONS["mvnet"].items() if getattr(c.network, "reads_images", True))


@pytest.fixture(scope="module")
def cache(tmp_path_factory) -> str:
    return str(tmp_path_factory.mktemp("synthetic_cache"))


def _tiny(cache, **groups) -> dict:
    """``tiny_config`` at M = 3, one epoch; ``groups``: ``group={key: value}`` or ``key=value``."""
    flat = {f"{g}.{k}": v for g, d in groups.items() if isinstance(d, dict) for k, v in d.items()}
    flat.update({k: v for k, v in groups.items() if not isinstance(v, dict)})
    return tiny_config(cache, **{"views": 3, "epochs": 1, **flat})


@pytest.mark.parametrize("groups", [
    {"mvnet": {"name": "view_transformer", "blocks": 1, "heads": 2, "width": 32}},
    {"selector": {"name": "noisy", "base_layout": "spherical"}},
    {"point_encoder": {"name": "dgcnn", "k": 8, "emb_dims": 64}},
    {"backbone": {"name": "vit_tiny"}},
    {"selector": {"name": "optimized", "steps": 1, "step_size": 25.0, "objective": "margin"}},
    {"mvnet": {"name": "viewgcn", "stages": [1, 1], "k": 2}, "epochs": 2},
    {"mvnet": {"name": "late_fusion", "num_points": 64}, "selector": {"name": "circular"}},
], ids=["view_transformer", "noisy", "dgcnn", "vit_tiny", "optimized", "viewgcn", "late_fusion"])
def test_component_trains_evaluates_and_round_trips_a_checkpoint(cache, tmp_path, groups):
    """Train one epoch, then rebuild the model from best.pt's config alone and evaluate it: the
    same test accuracy and loss as the training run's own test pass."""
    metrics = train(_tiny(cache, **groups), tmp_path / "train")
    assert metrics["steps"] > 0 and 0.0 <= metrics["test_acc"] <= 1.0
    group, settings = next(iter(groups.items()))
    ckpt = tmp_path / "train" / "best.pt"
    cfg = as_config(checkpoint.load(ckpt)["config"])
    for key, value in settings.items():
        assert getattr(getattr(cfg, group), key) == value
    again = evaluate_checkpoint(EvalConfig(ckpt=str(ckpt), progress=False), tmp_path / "eval")
    assert again["test_acc"] == metrics["test_acc"]
    assert again["test_loss"] == pytest.approx(metrics["test_loss"], rel=1e-6)


# --------------------------------------------------------------------------- view transformer

def _vt(**kw):
    torch.manual_seed(0)
    return build_multiview("view_transformer", build_backbone("small_cnn", 5), 5, **kw)


@pytest.mark.parametrize("M", [1, 2, 12])
def test_view_transformer_any_m_finite_and_order_free(M):
    net = _vt(blocks=2, heads=4).eval()
    x = torch.rand(2, M, 3, 32, 32, generator=torch.Generator().manual_seed(0), requires_grad=True)
    logits, feats = net(x)
    assert logits.shape == (2, 5) and feats.shape == (2, OPTIONS["backbone"]["small_cnn"].feature_dim)
    assert torch.isfinite(logits).all()
    perm = torch.randperm(M, generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(net(x[:, perm])[0], logits, rtol=1e-5, atol=1e-5)
    logits.sum().backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for n, p in net.named_parameters()
               if n.startswith("blocks"))


def test_view_transformer_mixes_views_and_projects_to_width():
    """Attention lets one view change another view's token (MVCNN's pooled features cannot)."""
    net = _vt(blocks=1, heads=2, width=48).eval()
    assert net.feature_dim == 48 and net.head.in_features == 48
    x = torch.rand(1, 3, 3, 32, 32, generator=torch.Generator().manual_seed(0))
    y = x.clone()
    y[:, 2] = torch.rand(3, 32, 32, generator=torch.Generator().manual_seed(5))
    tokens = {}
    net.blocks[0].register_forward_hook(lambda mod, inp, out: tokens.setdefault(len(tokens), out.detach()))
    net(x), net(y)
    assert not torch.allclose(tokens[0][:, 0], tokens[1][:, 0])  # view 0 saw view 2 change


def test_view_transformer_bad_settings_are_one_line_errors():
    with pytest.raises(ValueError, match=r"mvnet.heads=3 must be >= 1 and divide the token width 256"):
        _vt(heads=3)
    with pytest.raises(ValueError, match=r"mvnet.blocks=0"):
        _vt(blocks=0)
    assert isinstance(_vt(), ViewTransformer)


@pytest.mark.parametrize("args,needles", [
    (["mvnet=view_transformer", "mvnet.heads=3"], ["mvnet.heads=3", "backbone=small_cnn", "256"]),
    (["point_encoder=dgcnn", "point_encoder.k=300"], ["point_encoder.k=300", "selector.num_points=256"]),
    (["backbone=vit_tiny", "image_size=40"], ["image_size=40", "backbone=vit_tiny", "multiples of 16"]),
    (["mvnet=viewgcn", "views=1"], ["views=1", "mvnet=viewgcn", "views >= 2"]),
], ids=["view_transformer_heads", "dgcnn_k", "vit_image_size", "viewgcn_m1"])
def test_settings_a_component_cannot_take_fail_at_compose_time(tmp_path, args, needles):
    """One line naming the keys and what is allowed, exit 2, no run folder."""
    r = subprocess.run([sys.executable, "-m", "mvtn_exp.cli.train", *args, f"hydra.run.dir={tmp_path / 'run'}"],
                       cwd=ROOT, capture_output=True, text=True, timeout=120)
    err = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(err) == 1 and "Traceback" not in r.stderr, r.stderr[-800:]
    for needle in needles:
        assert needle in err[0], (needle, err[0])
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("settings,needles", [
    ({"mvnet": {"name": "viewgcn", "stages": [3, 4]}, "epochs": 8}, ["mvnet.stages=[3, 4]", "epochs=8", "epochs=7"]),
    ({"mvnet": {"stages": [3, 5]}, "epochs": 8}, ["mvnet.stages", "mvnet=mvcnn has no key 'stages'", "mvnet=viewgcn"]),
    ({"mvnet": {"name": "viewgcn", "stages": [0, 8]}, "epochs": 8}, ["mvnet.stages=[0, 8]", ">= 1"]),
    ({"mvnet": {"name": "viewgcn", "pool": "mean"}}, ["mvnet=viewgcn has no key 'pool'", "mvnet=late_fusion, logit_mean, mvcnn"]),
    ({"mvnet": {"name": "viewgcn"}, "selector": {"warmup_num_views": 1, "warmup_epochs": 1, "warmup_views": "spherical"}},
     ["selector.warmup_num_views=1", "at least 2"]),
    ({"mvnet": {"name": "viewgcn"}, "selector": {"name": "mvtn_poi", "hypotheses": 4, "race_epochs": 2}}, ["selector.hypotheses=4", "mvnet=viewgcn"]),
], ids=["stages_sum", "stages_not_viewgcn", "stage_zero", "pool", "warmup_views", "hypotheses"])
def test_viewgcn_settings_it_cannot_take_are_refused_naming_the_keys(cache, settings, needles):
    """The same validation runs at compose time (the subprocess test above checks the CLI's one line)."""
    with pytest.raises(ValueError) as err:
        as_config(_tiny(cache, views=4, **settings))
    for needle in needles:
        assert needle in str(err.value), (needle, str(err.value))


def test_every_backbone_config_states_the_feature_dim_it_builds():
    """``feature_dim`` is read before anything is built (the view transformer's check): it must be
    the built backbone's (the cheap ones are also built in tests/test_option_registry.py)."""
    for name, cls in OPTIONS["backbone"].items():
        assert build_backbone(name, 3).feature_dim == cls.feature_dim, name


# --------------------------------------------------------------------------- noisy views

def test_noisy_views_are_the_layout_plus_fresh_noise_in_training_only():
    pts = torch.zeros(4000, 8, 3)
    for layout in ("circular", "spherical"):
        sel = build_selector("noisy", 4, base_layout=layout)
        base = build_selector(layout, 4)(pts)
        sel.eval()
        for a, b in zip(sel(pts), base):
            assert torch.equal(a, b)
        sel.train()
        torch.manual_seed(0)
        azim, elev, dist = sel(pts)
        assert torch.equal(dist, base[2])
        da, de = azim - base[0], elev - base[1]
        assert abs(float(da.std()) - 18.0) < 0.5 and abs(float(de.std()) - 9.0) < 0.3
        assert abs(float(da.mean())) < 0.5 and abs(float(de.mean())) < 0.3
        again = sel(pts)[0]
        assert not torch.equal(again, azim)  # redrawn at every call
        torch.manual_seed(0)
        assert torch.equal(sel(pts)[0], azim)  # reproducible from the seed


def test_noisy_selector_bad_settings():
    with pytest.raises(ValueError, match="layout='random'"):
        NoisySelector(4, layout="random")
    with pytest.raises(ValueError, match="std must be >= 0"):
        NoisySelector(4, azim_std=-1.0)
    with pytest.raises(ValueError, match="selector.base_layout='random'"):
        build_selector("noisy", 4, base_layout="random")
    with pytest.raises(ValueError, match=r"selector.noise_azim=-1.0: must be >= 0"):
        build_selector("noisy", 4, noise_azim=-1.0)


# --------------------------------------------------------------------------- every registered component

@pytest.mark.parametrize("mvnet", IMAGE_NETS)
@pytest.mark.parametrize("backbone", [pytest.param(b, marks=pytest.mark.slow) if b == "resnet101" else b
                                      for b in sorted(OPTIONS["backbone"])])  # (ResNet-101: as ResNet-50, deeper)
@pytest.mark.parametrize("M", [1, 12])
def test_every_multiview_network_with_every_backbone(mvnet, backbone, M):
    """B = 2: output shapes, finite values, gradients to the images and to every used parameter."""
    torch.manual_seed(0)
    net = build_multiview(mvnet, backbone, 4).train()
    x = torch.rand(2, M, 3, 32, 32, requires_grad=True)
    azim, elev = torch.rand(2, M) * 360, (torch.rand(2, M) * 180 - 90)
    views = (azim.requires_grad_(True), elev.requires_grad_(True), torch.full((2, M), 2.2))
    if net.needs_views and M < 2:  # a graph over the views needs two of them (ViewGCN)
        with pytest.raises(ValueError, match="M >= 2"):
            net(x, views)
        return
    points = {"points": torch.rand(2, 64, 3)} if getattr(net, "reads_points", False) else {}  # late fusion's
    logits, feats = net(x, views, **points)
    assert logits.shape == (2, 4) and feats.shape == (2, net.feature_dim)
    assert torch.isfinite(logits).all() and torch.isfinite(feats).all()
    net.training_loss(logits, torch.tensor([0, 3]), lambda z, y: z.square().sum()).backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
    if net.needs_views:  # the view positions shape the graph: the cameras get a gradient through C
        assert torch.isfinite(azim.grad).all() and torch.isfinite(elev.grad).all() and elev.grad.abs().sum() > 0
    unused = (f"backbone.{getattr(net.backbone, 'classifier', 'fc')}.", "single_view_head.")  # never called / stage 1
    for name, p in net.named_parameters():
        if not name.startswith(unused):
            assert p.grad is not None and torch.isfinite(p.grad).all(), name


@pytest.mark.parametrize("name", sorted(OPTIONS["point_encoder"]))
def test_every_point_encoder_b2(name):
    torch.manual_seed(0)
    enc = build_point_encoder(name, out_features=7).train()
    pts = torch.randn(2, 64, 3, requires_grad=True)
    out = enc(pts)
    assert out.shape == (2, 7) and torch.isfinite(out).all()
    out.square().sum().backward()
    assert torch.isfinite(pts.grad).all()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in enc.parameters())


# --------------------------------------------------------------------------- DGCNN

def test_dgcnn_neighbours_and_order_free():
    from mvtn_exp.models.dgcnn import edge_features, knn

    line = torch.tensor([[[0.0, 1.0, 3.0, 7.0, 15.0]]])  # [B=1, C=1, N=5]
    assert knn(line, 2)[0].tolist() == [[0, 1], [1, 0], [2, 1], [3, 2], [4, 3]]
    e = edge_features(line, 2)  # [1, 2, 5, 2]: (x_j - x_i, x_i)
    assert e.shape == (1, 2, 5, 2) and e[0, 0, 3].tolist() == [0.0, -4.0] and e[0, 1, 3].tolist() == [7.0, 7.0]
    torch.manual_seed(0)
    net = build_point_encoder("dgcnn", out_features=6, k=5, emb_dims=32).eval()
    pts = torch.randn(2, 40, 3, generator=torch.Generator().manual_seed(1))
    perm = torch.randperm(40, generator=torch.Generator().manual_seed(2))
    torch.testing.assert_close(net(pts[:, perm]), net(pts), rtol=1e-5, atol=1e-5)
    with pytest.raises(ValueError, match="fewer than point_encoder.k=5"):
        net(pts[:, :4])


@pytest.mark.parametrize("selector,needles", [
    ({"name": "mvtn_spherical"}, ["mvnet=late_fusion", "selector=mvtn_spherical learns its views", "selector=circular"]),
    ({"name": "optimized", "steps": 1}, ["selector=optimized refines its views against C"]),
])
def test_paper_late_fusion_is_refused_on_views_that_move_with_c(cache, selector, needles):
    """The paper fuses points with fixed views; a selector that learns or refines views calls C
    without the points, so the config says so in one line."""
    with pytest.raises(ValueError) as err:
        as_config(_tiny(cache, mvnet={"name": "late_fusion"}, selector=selector))
    assert "\n" not in str(err.value)
    for needle in needles:
        assert needle in str(err.value), (needle, str(err.value))
    as_config(_tiny(cache, mvnet={"name": "late_fusion"}, selector={"name": "optimized", "steps": 0}))  # fixed after all


def test_logit_mean_refuses_another_pool_in_the_config_not_when_built(cache):
    with pytest.raises(ValueError, match="mvnet.pool=max: mvnet=logit_mean averages"):
        as_config(_tiny(cache, mvnet={"name": "logit_mean", "pool": "max"}))


def test_paper_late_fusion_parameters_are_mvcnn_plus_the_papers_pointnet_sized_to_the_view_features():
    from mvtn_exp.models.point_encoders import PaperPointNet

    count = lambda m: sum(p.numel() for p in m.parameters())
    fused, plain = build_multiview("late_fusion", "resnet18", 40), build_multiview("mvcnn", "resnet18", 40)
    assert count(fused) - count(plain) == count(PaperPointNet(out_features=512))
    assert count(PaperPointNet(out_features=512)) == count(PaperPointNet(out_features=40)) + 257 * (512 - 40)


# --------------------------------------------------------------------------- view transfer

@pytest.fixture(scope="module")
def source_run(cache, tmp_path_factory) -> Path:
    run = tmp_path_factory.mktemp("source")
    train(_tiny(cache, epochs=1), run)
    return run / "best.pt"


def test_view_transfer_trains_another_network_on_a_frozen_g(cache, source_run, tmp_path):
    g0 = {k: v for k, v in checkpoint.load(source_run)["model"].items() if k.startswith("selector.")}
    assert any("running_mean" in k for k in g0)  # G's BatchNorm statistics travel too
    target = _tiny(cache, epochs=2, mvnet={"name": "logit_mean", "pool": "mean"},
                   selector={"from_ckpt": str(source_run)})
    metrics = train(target, tmp_path / "dst")
    assert metrics["steps"] > 0
    g1 = {k: v for k, v in checkpoint.load(tmp_path / "dst" / "best.pt")["model"].items() if k.startswith("selector.")}
    assert g1.keys() == g0.keys() and all(torch.equal(g0[k], g1[k]) for k in g0)  # frozen: weights and statistics
    again = evaluate_checkpoint(EvalConfig(ckpt=str(tmp_path / "dst" / "best.pt"), progress=False), tmp_path / "eval")
    assert again["test_acc"] == metrics["test_acc"]


def test_a_finished_runs_backbone_starts_another_run(cache, source_run, tmp_path):
    """The paper's FSL pretraining, phase 2: ``backbone.weights=RUN/best.pt`` starts C's backbone
    from a finished run's (its ``mvnet.backbone.*``; G, the head and everything else start fresh)."""
    phase1 = checkpoint.load(source_run)["model"]
    # (the backbone's own classifier is never used by C: it is not part of what carries over)
    want = {k[len("mvnet.backbone."):]: v for k, v in phase1.items()
            if k.startswith("mvnet.backbone.") and not k.startswith("mvnet.backbone.fc.")}
    assert want
    fresh = build_backbone("small_cnn", 3, weights=source_run)
    got = fresh.state_dict()
    assert all(torch.equal(got[k], v) for k, v in want.items())
    target = _tiny(cache, epochs=1, selector={"name": "spherical"}, backbone={"weights": str(source_run)})
    mvtn = build_mvtn(as_config(target), 3)
    assert all(torch.equal(mvtn.mvnet.backbone.state_dict()[k], v) for k, v in want.items())
    assert not torch.equal(mvtn.mvnet.head.weight, phase1["mvnet.head.weight"])  # the head starts fresh
    assert train(target, tmp_path / "phase2")["steps"] > 0


def test_view_transfer_refuses_another_g(cache, source_run, tmp_path):
    bad = _tiny(cache, views=2, selector={"from_ckpt": str(source_run)})
    with pytest.raises(checkpoint.CheckpointMismatch, match=r"selector.from_ckpt=.*views: checkpoint=3 vs config=2"):
        train(bad, tmp_path / "dst")
    with pytest.raises(ValueError, match="selector=circular has no key .from_ckpt."):
        as_config(_tiny(cache, selector={"name": "circular", "from_ckpt": str(source_run)}))


# --------------------------------------------------------------------------- ViT backbones

@pytest.mark.parametrize("name,params,dim", [("vit_tiny", 5_717_416, 192), ("vit_small", 22_050_664, 384),
                                             ("vit_base", 86_567_656, 768)])
def test_vit_parameters_and_keys_are_timms(name, params, dim):
    net = build_backbone(name, 1000)
    assert sum(p.numel() for p in net.parameters()) == params and net.feature_dim == dim
    sd = net.state_dict()
    want = {"cls_token": [1, 1, dim], "pos_embed": [1, 197, dim], "patch_embed.proj.weight": [dim, 3, 16, 16],
            "blocks.11.attn.qkv.weight": [3 * dim, dim], "blocks.0.attn.proj.bias": [dim],
            "blocks.5.mlp.fc1.weight": [4 * dim, dim], "blocks.5.mlp.fc2.weight": [dim, 4 * dim],
            "blocks.3.norm1.weight": [dim], "blocks.3.norm2.bias": [dim], "norm.weight": [dim], "head.weight": [1000, dim]}
    for key, shape in want.items():
        assert list(sd[key].shape) == shape, key
    assert not any(k.startswith("blocks.12.") for k in sd)


def test_vit_weights_load_at_any_patch_multiple(tmp_path):
    torch.manual_seed(0)
    src = build_backbone("vit_tiny", 1000)
    path = tmp_path / "vit_tiny_patch16_224.pth"
    torch.save({"model": src.state_dict()}, path)
    net = build_backbone("vit_tiny", 7, weights=path).eval()  # another class count: the head stays fresh
    assert net.head.out_features == 7 and torch.equal(net.pos_embed, src.pos_embed)
    x = torch.rand(2, 3, 224, 224, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        torch.testing.assert_close(net.features(x), src.eval().features(x))
        assert net.position(14, 14) is net.pos_embed
        small = net.features(x[:, :, :64, :48])  # a 4 x 3 grid: the embedding resampled
    assert small.shape == (2, 192) and torch.isfinite(small).all()
    with pytest.raises(ValueError, match="multiples of 16"):
        net.features(x[:, :, :40, :40])


# --------------------------------------------------------------------------- scene-parameter optimisation

@pytest.mark.parametrize("objective", ["min_ce", "max_ce", "max_coverage", "min_coverage", "margin", "attack_margin"])
def test_optimized_views_move_the_objective_the_right_way(cache, objective):
    from mvtn_exp.data.collate import collate_shapes
    from mvtn_exp.engine.trainer import make_datasets
    from mvtn_exp.model import build_mvtn
    from mvtn_exp.selectors.optimized import objective_value, optimize_views

    cfg = as_config(_tiny(cache, selector={"name": "optimized", "steps": 3, "step_size": 20.0,
                                           "objective": objective}))
    ds = make_datasets(cfg)["test"]
    torch.manual_seed(0)
    model = build_mvtn(cfg, len(ds.classes)).train()
    model.renderer.eval()  # evaluation light and colour: the objective is a function of the views alone
    batch = collate_shapes([ds[i] for i in range(6)])
    stats = {k: v.clone() for k, v in model.mvnet.state_dict().items() if "running" in k}

    def value(views):
        out = model.render_output(batch, *views)
        with torch.no_grad():
            model.mvnet.eval()
            logits, _ = model.mvnet(out.images)
            model.mvnet.train()
        coverage = out.alpha.reshape(6, -1).mean(1)
        return float(objective_value(objective, logits, batch["labels"], coverage).sum())

    start = model.selector(batch["points"])
    moved = optimize_views(model, batch, start, model.selector, objective)
    assert not torch.equal(moved[0], start[0]) and not moved[0].requires_grad
    assert value(moved) < value(start)  # the steps decrease the objective
    assert model.mvnet.training and all(p.grad is None for p in model.parameters())
    assert all(torch.equal(v, model.mvnet.state_dict()[k]) for k, v in stats.items())  # C's statistics untouched
    views = model.select(batch)  # MVTN.select runs the steps, under no_grad too
    with torch.no_grad():
        assert not torch.equal(model.select(batch)[0], start[0]) and torch.isfinite(views[0]).all()


def test_margin_is_the_label_free_top_two_gap():
    from mvtn_exp.selectors.optimized import objective_value

    logits = torch.tensor([[3.0, 1.0, 0.5], [0.2, 0.1, 2.0]])
    gap = objective_value("margin", logits, None, torch.zeros(2))
    torch.testing.assert_close(gap, torch.tensor([-2.0, -1.8]))  # decreasing it widens the gap
    assert torch.equal(objective_value("margin", logits, torch.tensor([2, 0]), torch.zeros(2)), gap)  # labels unused
    true_margin = objective_value("attack_margin", logits, torch.tensor([2, 0]), torch.zeros(2))
    torch.testing.assert_close(true_margin, torch.tensor([0.5 - 3.0, 0.2 - 2.0]))
    with pytest.raises(ValueError, match="needs the labels"):
        objective_value("min_ce", logits, None, torch.zeros(2))


class _Poison:
    """A labels entry that fails on any use: what the evaluation path must never touch."""

    def __getattr__(self, name):
        raise AssertionError(f"evaluation read the labels (.{name})")


def _selector_settings():
    from mvtn_exp.config.options import OPTIONS, load

    load()
    extra = {"optimized": {"steps": 2, "step_size": 20.0, "objective": "min_ce"}}
    return [{"name": name, **extra.get(name, {})} for name in sorted(OPTIONS["selector"])]


@pytest.mark.parametrize("selector", _selector_settings(), ids=lambda s: s["name"])
def test_no_selector_reads_the_labels_at_evaluation(cache, selector):
    """Every registered selector, evaluated (model.eval()) on a batch whose labels fail on any use,
    gives its views; the labelled objective of ``optimized`` would have read them."""
    from mvtn_exp.data.collate import collate_shapes
    from mvtn_exp.engine.trainer import make_datasets
    from mvtn_exp.model import build_mvtn

    cfg = as_config(_tiny(cache, selector=selector))
    ds = make_datasets(cfg)["test"]
    model = build_mvtn(cfg, len(ds.classes)).eval()
    batch = collate_shapes([ds[i] for i in range(4)])
    real = batch["labels"]
    batch["labels"] = _Poison()
    with torch.no_grad():
        out = model(batch)
    assert out["logits"].shape == (4, len(ds.classes)) and torch.isfinite(out["azim"]).all()
    if selector["name"] == "optimized":  # while training it does read them
        batch["labels"] = _Poison()
        with pytest.raises(AssertionError, match="read the labels"):
            model.train().select(batch)
        batch["labels"] = real
        model.select(batch)


# --------------------------------------------------------------------------- ViewGCN

def _gcn(cache, **kw) -> dict:
    """ViewGCN on the tiny config: M = 4, one single-view epoch, then two of the whole network."""
    return _tiny(cache, mvnet={"name": "viewgcn", "stages": [1, 2], "k": 3}, views=4, epochs=3,
                 selector={"name": "mvtn_spherical"}, **kw)


@pytest.fixture(scope="module")
def gcn_run(cache, tmp_path_factory):
    run = tmp_path_factory.mktemp("gcn_full")
    return run, train(_gcn(cache), run)


def _crash_in_epoch(monkeypatch, epoch: int) -> None:
    """Make the training render raise at the second step of ``epoch`` (1-based; tiny: 6 steps an epoch)."""
    from mvtn_exp.model import MVTN

    steps = -(-12 * 4 // 8)  # 12 classes x 4 shapes, batch 8
    calls, real = {"n": 0}, MVTN.render

    def render(self, batch, *views):
        if self.training:
            calls["n"] += 1
            if calls["n"] == steps * (epoch - 1) + 2:
                raise RuntimeError("killed")
        return real(self, batch, *views)

    monkeypatch.setattr(MVTN, "render", render)


@pytest.mark.parametrize("crash_epoch", [2, 3], ids=["at_the_boundary", "in_stage_2"])
def test_viewgcn_resume_across_the_stage_boundary_is_exact(cache, gcn_run, tmp_path, monkeypatch, crash_epoch):
    """Killed in the middle of epoch 2 (the first of stage 2: last.pt is stage 1's) or of epoch 3,
    then resumed from last.pt: the same history and test metrics as the run that was not stopped."""
    _, full = gcn_run
    with monkeypatch.context() as m:
        _crash_in_epoch(m, crash_epoch)
        with pytest.raises(RuntimeError, match="killed"):
            train(_gcn(cache), tmp_path / "crashed")
    assert checkpoint.load(tmp_path / "crashed" / "last.pt")["epoch"] == crash_epoch - 1
    resumed = train(_gcn(cache, ckpt_path=str(tmp_path / "crashed" / "last.pt")), tmp_path / "resumed")
    for a, b in zip(resumed["history"], full["history"], strict=True):
        assert a["train_loss"] == pytest.approx(b["train_loss"], abs=1e-6) and a["val_acc"] == b["val_acc"]
    assert resumed["test_acc"] == full["test_acc"] and resumed["best_epoch"] == full["best_epoch"]


def test_viewgcn_stages_single_views_first_then_the_graph(cache, gcn_run, tmp_path, monkeypatch):
    """Stage 1 trains the backbone and the single-view head only (G frozen on its initial views,
    the graph untouched); each stage has its own learning-rate schedule; model selection counts
    stage 2 only, and the best checkpoint is evaluated as a whole ViewGCN."""
    import copy

    from mvtn_exp.model import build_mvtn

    run, full = gcn_run
    cfg = as_config(_gcn(cache))
    built = {}

    def build(c, num_classes):  # the model as train() builds it, before any step
        model = build_mvtn(c, num_classes)
        built["init"] = copy.deepcopy(model.state_dict())
        return model
    best = checkpoint.load(run / "best.pt")
    assert int(best["model"]["mvnet.stage"]) == 2 and full["best_epoch"] >= 2
    assert "epoch 2: ViewGCN stage 2" in (run / "train.log").read_text()
    lrs = [h["lr_mvnet"] for h in full["history"]]
    assert lrs[0] == lrs[1] == pytest.approx(cfg.optim.lr) and lrs[2] < lrs[1]  # the schedule restarts at stage 2
    assert full["history"][0]["view_offset_azim"] == 0.0  # stage 1 renders G's initial views
    with monkeypatch.context() as m:
        _crash_in_epoch(m, 2)
        with pytest.raises(RuntimeError, match="killed"):
            train(_gcn(cache), tmp_path / "stage1", build_model=build)
    init = built["init"]
    after = checkpoint.load(tmp_path / "stage1" / "last.pt")["model"]  # the end of stage 1
    assert int(after["mvnet.stage"]) == 1
    for key, value in init.items():
        if key.startswith(("mvnet.local.", "mvnet.nonlocal_mp.", "mvnet.selectors.", "mvnet.head.", "selector.")):
            assert torch.equal(after[key], value), key
    for key in ("mvnet.single_view_head.weight", "mvnet.backbone.body.0.weight"):
        assert not torch.equal(after[key], init[key]), key


def test_margin_of_a_single_class_is_zero():
    """The label-free margin needs the two highest logits; with one class there is no gap."""
    from mvtn_exp.selectors.optimized import objective_value

    logits = torch.tensor([[2.0], [-1.0]])
    assert torch.equal(objective_value("margin", logits, None, torch.zeros(2)), torch.zeros(2))


def test_the_papers_scene_optimisation_rules_steps_and_evaluation():
    """``step_size=null``: 50 for cross-entropy, 25 for coverage and the margins (L507);
    ``eval_objective=if_label_free``: no steps at test for the cross-entropy objectives (L501),
    the training objective for the label-free ones; null keeps this project's ``margin``."""
    from mvtn_exp.selectors.optimized import OptimizedConfig

    def built(**kw):
        return OptimizedConfig(**kw).validate().build(views=4, seed=0)

    assert [built(objective=o, step_size=None).lr for o in ("min_ce", "max_ce", "margin", "max_coverage")] == [50.0, 50.0, 25.0, 25.0]
    assert built(objective="min_ce", step_size=7.0).lr == 7.0
    assert built(objective="min_ce", eval_objective="if_label_free").eval_objective == "none"
    assert built(objective="max_coverage", eval_objective="if_label_free").eval_objective == "max_coverage"
    assert built(objective="max_ce").eval_objective == "margin"
    with pytest.raises(ValueError, match="selector.eval_objective"):
        OptimizedConfig(eval_objective="max_ce").validate()


def test_point_classifier_reads_points_alone_and_nothing_is_rendered(cache, tmp_path, monkeypatch):
    """mvnet=point_classifier: the point encoder classifies the points (the occlusion table's PointNet
    and DGCNN rows); the images are not read, so R never runs; learned views and 2D weights are refused."""
    from mvtn_exp.models.point_classifier import PointClassifier
    from mvtn_exp.render.renderer import MultiViewRenderer

    torch.manual_seed(0)
    net = PointClassifier(None, 5, point_encoder="pointnet").eval()
    pts = torch.rand(2, 64, 3)
    logits, feats = net(torch.rand(2, 3, 3, 8, 8), None, points=pts)
    torch.testing.assert_close(logits, net.point_encoder(pts))
    torch.testing.assert_close(feats, logits)
    same, _ = net(torch.zeros(2, 3, 3, 8, 8), None, points=pts)  # other images: the same logits
    assert torch.equal(same, logits)
    with pytest.raises(ValueError, match="needs points"):
        net(torch.rand(2, 3, 3, 8, 8), None)
    calls = []
    real = MultiViewRenderer.forward
    monkeypatch.setattr(MultiViewRenderer, "forward", lambda *a, **k: calls.append(1) or real(*a, **k))
    cfg = _tiny(cache, mvnet={"name": "point_classifier", "num_points": 64}, selector={"name": "circular"})
    metrics = train(cfg, tmp_path / "run")
    assert metrics["steps"] > 0 and calls == []  # trained and tested without a render
    for selector, needle in (({"name": "mvtn_spherical"}, "selector=mvtn_spherical learns views"),):
        with pytest.raises(ValueError, match=needle):
            as_config(_tiny(cache, mvnet={"name": "point_classifier"}, selector=selector))
    with pytest.raises(ValueError, match="no 2D backbone"):
        as_config(_tiny(cache, mvnet={"name": "point_classifier"}, selector={"name": "circular"},
                        backbone={"name": "resnet18", "weights": "imagenet"}))
