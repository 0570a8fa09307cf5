"""G's smoothed (zeroth-order) gradient: the estimator against closed forms, and its place in a training step."""
from __future__ import annotations

import pytest
import torch

from mvtn_exp.runtime import checkpoint
from mvtn_exp.engine import train
from mvtn_exp.engine.trainer import as_config
from mvtn_exp.selectors.view_gradient import eval_mode, noise_generator, smoothed_view_gradient, surrogate

from test_train_e2e import tiny


def quadratic(target_a, target_e, scale):
    """Per-shape loss sum_m scale_m [(a - a*)^2 + (e - e*)^2] and its exact gradient."""
    def loss(azim, elev, dist):
        return (scale * ((azim - target_a) ** 2 + (elev - target_e) ** 2)).sum(1)
    return loss


def test_estimate_is_the_gradient_of_a_quadratic_on_average():
    """Gaussian smoothing keeps a quadratic's gradient, so with many pairs the estimate must
    approach 2 scale (u - u*) for every shape and view; with one pair it is noisy but unbiased."""
    B, M = 3, 2
    g = torch.Generator().manual_seed(0)
    azim, elev = torch.randn(B, M, generator=g) * 30, torch.randn(B, M, generator=g) * 20
    ta, te = torch.randn(B, M, generator=g) * 30, torch.randn(B, M, generator=g) * 20
    scale = torch.rand(B, M, generator=g) + 0.5
    loss = quadratic(ta, te, scale)
    views = (azim, elev, torch.full_like(azim, 2.2))
    ga, ge = smoothed_view_gradient(loss, views, pairs=20000, sigma=7.0, generator=noise_generator(0, 0))
    true_a, true_e = 2 * scale * (azim - ta), 2 * scale * (elev - te)
    err = torch.cat([(ga - true_a).flatten(), (ge - true_e).flatten()]).norm()
    ref = torch.cat([true_a.flatten(), true_e.flatten()]).norm()
    assert err < 0.05 * ref, (err, ref)
    # unbiased per pair: the mean of many one-pair estimates is the same vector
    one = [smoothed_view_gradient(loss, views, 1, 7.0, noise_generator(1, s))[0] for s in range(3000)]
    assert (torch.stack(one).mean(0) - true_a).norm() < 0.1 * true_a.norm()


def test_estimate_is_seeded_and_sees_only_loss_values():
    calls = []

    def loss(azim, elev, dist):
        calls.append(torch.is_grad_enabled())
        return azim.sum(1) - 2 * elev.sum(1)

    views = (torch.zeros(2, 3, requires_grad=True), torch.zeros(2, 3), torch.full((2, 3), 2.2))
    a1 = smoothed_view_gradient(loss, views, 3, 5.0, noise_generator(4, 17))
    a2 = smoothed_view_gradient(loss, views, 3, 5.0, noise_generator(4, 17))
    b = smoothed_view_gradient(loss, views, 3, 5.0, noise_generator(4, 18))
    assert all(torch.equal(x, y) for x, y in zip(a1, a2)) and not torch.equal(a1[0], b[0])
    assert calls == [False] * 18  # 2 renders per pair, three calls, never with autograd on
    with pytest.raises(ValueError, match="pairs >= 1 and sigma > 0"):
        smoothed_view_gradient(loss, views, 0, 5.0, noise_generator(0, 0))


def test_batched_probes_are_the_same_estimate_in_one_call():
    """batched=True: one call on all 2 * pairs probe sets (set-major per shape), the same noise and
    the same estimate as 2 * pairs separate calls."""
    B, M, pairs = 3, 2, 3
    g = torch.Generator().manual_seed(0)
    azim, elev = torch.randn(B, M, generator=g, dtype=torch.float64) * 30, torch.randn(B, M, generator=g, dtype=torch.float64) * 20
    target = torch.randn(B, M, generator=g, dtype=torch.float64) * 30
    shapes = []

    def loss(azim, elev, dist, sets=1):
        shapes.append((tuple(azim.shape), sets))
        per_view = (azim - target.repeat(1, sets)) ** 2 + elev ** 3 / 100 + dist
        return per_view.reshape(B, sets, M).sum(2).squeeze(1) if sets == 1 else per_view.reshape(B, sets, M).sum(2)

    views = (azim, elev, torch.full_like(azim, 2.2))
    one = smoothed_view_gradient(loss, views, pairs, 5.0, noise_generator(3, 9))
    assert shapes == [((B, M), 1)] * (2 * pairs)
    shapes.clear()
    batched = smoothed_view_gradient(loss, views, pairs, 5.0, noise_generator(3, 9), batched=True)
    assert shapes == [((B, 2 * pairs * M), 2 * pairs)]
    for x, y in zip(one, batched):
        torch.testing.assert_close(x, y, rtol=1e-12, atol=1e-12)


def test_batched_probes_train_g_as_separate_probes_do(tmp_path, monkeypatch):
    """selector.probe_batched=true in a training step: one renderer call for the probes instead of
    2 * pairs, C bit-identical (its step does not read the probes), G the same up to float rounding."""
    from mvtn_exp.model import MVTN

    renders = []
    real = MVTN.render

    def counting(self, batch, azim, *a, **k):
        renders.append(azim.shape[1])
        return real(self, batch, azim, *a, **k)

    monkeypatch.setattr(MVTN, "render", counting)
    cache = str(tmp_path / "cache")
    runs = {}
    for batched in (False, True):
        renders.clear()
        kw = {"selector.grad": "smoothed", "selector.probe_pairs": 2, "selector.probe_batched": batched}
        train(tiny(cache, epochs=1, batch_size=48, **kw), tmp_path / str(batched))
        runs[batched] = (checkpoint.load(tmp_path / str(batched) / "last.pt")["model"], list(renders))
    (a, ra), (b, rb) = runs[False], runs[True]
    M = ra[0]
    assert ra[:5] == [M] * 5 and rb[:2] == [M, 4 * M]  # the step's render, then its probes
    assert len(rb) == len(ra) - 3
    assert all(torch.equal(a[k], b[k]) for k in a if k.startswith("mvnet."))
    g_keys = [k for k in a if k.startswith("selector.") and a[k].is_floating_point()]
    assert g_keys and all(torch.allclose(a[k], b[k], rtol=1e-4, atol=1e-6) for k in g_keys)


def test_surrogate_hands_g_over_b_to_the_views():
    azim, elev = torch.randn(4, 2, requires_grad=True), torch.randn(4, 2, requires_grad=True)
    ga, ge = torch.randn(4, 2), torch.randn(4, 2)
    surrogate((azim, elev, None), ga, ge).backward()
    torch.testing.assert_close(azim.grad, ga / 4)
    torch.testing.assert_close(elev.grad, ge / 4)


def test_eval_mode_restores_every_flag():
    net = torch.nn.Sequential(torch.nn.Linear(2, 2), torch.nn.BatchNorm1d(2), torch.nn.Dropout())
    net.train()
    net[2].eval()  # a mixed state must come back as it was
    with eval_mode(net):
        assert not any(m.training for m in net.modules())
    assert [m.training for m in net.modules()] == [True, True, True, False]


def test_a_smoothed_step_moves_g_and_leaves_c_and_the_rngs_as_autograd_does(tmp_path):
    """One training step (the whole tiny train split in one batch): C sees the same images and loss
    in both modes, so C, its BatchNorm statistics and the saved RNG states must come out
    bit-identical; only G differs (the perturbed renders run in eval mode under no_grad)."""
    cache = str(tmp_path / "cache")
    runs = {}
    for mode in ("autograd", "smoothed"):
        train(tiny(cache, epochs=1, batch_size=48, **{"selector.grad": mode}), tmp_path / mode)
        runs[mode] = checkpoint.load(tmp_path / mode / "last.pt")
    a, s = runs["autograd"]["model"], runs["smoothed"]["model"]
    c_keys = [k for k in a if k.startswith("mvnet.")]
    g_keys = [k for k in a if k.startswith("selector.") and a[k].is_floating_point()]
    assert c_keys and g_keys
    assert all(torch.equal(a[k], s[k]) for k in c_keys)
    assert any(not torch.equal(a[k], s[k]) for k in g_keys)
    assert torch.equal(runs["autograd"]["rng"]["torch"], runs["smoothed"]["rng"]["torch"])


def test_centered_logit_is_cross_entropy_without_its_label_free_part():
    """centered_logit = CE - (logsumexp z - mean z); summed over every possible label it is 0 for
    any logits (so a C whose output ignores the label gives G no pull), while CE's sum is not."""
    from mvtn_exp.config.schema import TaskConfig
    from mvtn_exp.tasks.classification import centered_logit_loss, selector_loss_fn

    g = torch.Generator().manual_seed(0)
    z = torch.randn(5, 8, generator=g, dtype=torch.float64) * 3
    y = torch.randint(0, 8, (5,), generator=g)
    ce = torch.nn.functional.cross_entropy(z, y, reduction="none")
    assert torch.allclose(centered_logit_loss(z, y), ce - (torch.logsumexp(z, 1) - z.mean(1)))
    every = torch.stack([centered_logit_loss(z, torch.full((5,), c)) for c in range(8)])
    assert every.sum(0).abs().max() < 1e-12
    ce_every = torch.stack([torch.nn.functional.cross_entropy(z, torch.full((5,), c), reduction="none") for c in range(8)])
    assert ce_every.sum(0).min() > 8 * 2.0  # CE summed over labels is at least K log K and grows with peaked logits
    assert selector_loss_fn("centered_logit", TaskConfig()) is centered_logit_loss
    assert torch.equal(selector_loss_fn("task", TaskConfig())(z, y), ce)


def test_selector_loss_changes_g_only(tmp_path):
    """selector.loss=centered_logit: the same step as the task loss for C (bit-identical C and
    RNG states), a different G."""
    cache = str(tmp_path / "cache")
    runs = {}
    for name in ("task", "centered_logit"):
        kw = {"selector.grad": "smoothed", "selector.probe_pairs": 1, "selector.loss": name}
        train(tiny(cache, epochs=1, batch_size=48, **kw), tmp_path / name)
        runs[name] = checkpoint.load(tmp_path / name / "last.pt")
    a, s = runs["task"]["model"], runs["centered_logit"]["model"]
    assert all(torch.equal(a[k], s[k]) for k in a if k.startswith("mvnet."))
    assert any(not torch.equal(a[k], s[k]) for k in a if k.startswith("selector.") and a[k].is_floating_point())
    assert torch.equal(runs["task"]["rng"]["torch"], runs["centered_logit"]["rng"]["torch"])


def count_probes(monkeypatch) -> list:
    """Every later call of ``view_gradient.smoothed_view_gradient`` appends to the returned list."""
    from mvtn_exp.selectors import view_gradient

    calls = []
    real = view_gradient.smoothed_view_gradient

    def counting(*a, **k):
        calls.append(1)
        return real(*a, **k)

    monkeypatch.setattr(view_gradient, "smoothed_view_gradient", counting)
    return calls


def test_smoothed_every_probes_and_steps_g_only_on_those_steps(tmp_path, monkeypatch):
    """selector.probe_every=5 over 12 steps (2 epochs of 6): the estimate runs at steps 0, 5 and
    10, and AdamW steps G exactly there (G has no gradient in between); C steps every time."""
    calls = count_probes(monkeypatch)
    kw = {"selector.grad": "smoothed", "selector.probe_pairs": 1, "selector.probe_every": 5}
    m = train(tiny(str(tmp_path / "cache"), **kw), tmp_path / "run")
    assert m["steps"] == 12 and len(calls) == 3
    state = checkpoint.load(tmp_path / "run" / "last.pt")["optimizer"]
    groups = {g["name"]: g["params"] for g in state["param_groups"]}
    g_steps = {int(state["state"][i]["step"]) for i in groups["selector"] if i in state["state"]}
    c_steps = {int(state["state"][i]["step"]) for i in groups["mvnet"] if i in state["state"]}
    assert g_steps == {3} and c_steps == {12}


def test_no_probes_once_g_is_frozen(tmp_path, monkeypatch):
    """selector.stop_epoch=1 over 2 epochs of 6 steps: the smoothed estimate runs in epoch 1 only
    (G's learning rate is 0 afterwards), G's AdamW state stops at 6 steps while C's reaches 12, and
    epoch 2 records no gradient for G."""
    calls = count_probes(monkeypatch)
    kw = {"selector.grad": "smoothed", "selector.probe_pairs": 1, "selector.stop_epoch": 1}
    m = train(tiny(str(tmp_path / "cache"), **kw), tmp_path / "run")
    assert m["steps"] == 12 and len(calls) == 6
    assert m["history"][0]["grad_norm_selector"] > 0 and m["history"][1]["grad_norm_selector"] == 0.0
    state = checkpoint.load(tmp_path / "run" / "last.pt")["optimizer"]
    groups = {g["name"]: g["params"] for g in state["param_groups"]}
    assert {int(state["state"][i]["step"]) for i in groups["selector"] if i in state["state"]} == {6}
    assert {int(state["state"][i]["step"]) for i in groups["mvnet"] if i in state["state"]} == {12}


@pytest.mark.slow  # (longer than 15 s on 2 cores: make test-all)
def test_g_moves_in_one_epoch_of_every_k(tmp_path, monkeypatch):
    """selector.move_every=2 over 3 epochs of 6 steps: G probes and steps in epochs 1 and 3 only
    (12 probe estimates, 12 AdamW steps for G, 18 for C), epoch 2 records no gradient for G, and a
    resume from epoch 2 holds and moves as the whole run does."""
    calls = count_probes(monkeypatch)
    kw = {"selector.grad": "smoothed", "selector.probe_pairs": 1, "selector.move_every": 2}
    cache = str(tmp_path / "cache")
    m = train(tiny(cache, epochs=3, **kw), tmp_path / "run")
    assert m["steps"] == 18 and len(calls) == 12
    g = [h["grad_norm_selector"] for h in m["history"]]
    assert g[0] > 0 and g[1] == 0.0 and g[2] > 0
    state = checkpoint.load(tmp_path / "run" / "last.pt")["optimizer"]
    groups = {g["name"]: g["params"] for g in state["param_groups"]}
    assert {int(state["state"][i]["step"]) for i in groups["selector"] if i in state["state"]} == {12}
    assert {int(state["state"][i]["step"]) for i in groups["mvnet"] if i in state["state"]} == {18}
    train(tiny(cache, epochs=2, **kw), tmp_path / "a")
    resumed = train(tiny(cache, epochs=3, ckpt_path=str(tmp_path / "a" / "last.pt"), **kw), tmp_path / "b")
    assert resumed["confusion_matrix"] == m["confusion_matrix"]
    with pytest.raises(ValueError, match="selector.move_every"):
        as_config(tiny(cache, **{**kw, "selector.move_every": 0}))


def test_c_trains_on_jittered_views_while_g_probes_its_own(tmp_path, monkeypatch):
    """selector.train_jitter=20: the training render is at G's views moved by noise of about 20
    degrees (azimuth and elevation, fresh each step), the probes (eval mode) stay centred on G's
    views; 0 renders G's views exactly; without the smoothed gradient it is refused."""
    from mvtn_exp.model import MVTN

    trained, probed, chosen = [], [], []
    real_render, real_select = MVTN.render, MVTN.select

    def render(self, batch, azim, elev, *rest):
        (trained if self.training else probed).append((azim.detach().clone(), elev.detach().clone()))
        return real_render(self, batch, azim, elev, *rest)

    def select(self, batch, **kw):
        out = real_select(self, batch, **kw)
        chosen.append(tuple(v.detach().clone() for v in out[:2]))
        return out

    monkeypatch.setattr(MVTN, "render", render)
    monkeypatch.setattr(MVTN, "select", select)
    cache = str(tmp_path / "cache")
    kw = {"selector.grad": "smoothed", "selector.probe_pairs": 1, "selector.bn_recalibrate": 0}
    train(tiny(cache, epochs=1, **{**kw, "selector.train_jitter": 20.0}), tmp_path / "j")
    train_steps = [c for c in chosen][:len(trained)]
    moved = torch.cat([torch.cat([t[0] - c[0], t[1] - c[1]]).flatten() for t, c in zip(trained, train_steps)])
    assert 12.0 < float(moved.std()) < 28.0 and abs(float(moved.mean())) < 6.0
    first_probe = probed[0]  # the antithetic pair of step 1: centred on G's views
    centre = ((probed[0][0] + probed[1][0]) / 2, (probed[0][1] + probed[1][1]) / 2)
    torch.testing.assert_close(centre[0], chosen[0][0], atol=1e-3, rtol=0)
    assert first_probe[0].shape == chosen[0][0].shape
    trained.clear(), probed.clear(), chosen.clear()
    train(tiny(cache, epochs=1, **kw), tmp_path / "plain")
    for t, c in zip(trained, chosen):
        assert torch.equal(t[0], c[0]) and torch.equal(t[1], c[1])
    with pytest.raises(ValueError, match="selector.train_jitter=5.0"):
        as_config(tiny(cache, **{"selector.train_jitter": 5.0}))


@pytest.mark.slow  # (longer than 15 s on 2 cores: make test-all)
def test_smoothed_resume_is_exact(tmp_path):
    cache = str(tmp_path / "cache")
    kw = {"selector.grad": "smoothed", "selector.probe_pairs": 1}
    full = train(tiny(cache, epochs=2, **kw), tmp_path / "full")
    train(tiny(cache, epochs=1, **kw), tmp_path / "a")
    resumed = train(tiny(cache, epochs=2, ckpt_path=str(tmp_path / "a" / "last.pt"), **kw), tmp_path / "b")
    assert resumed["confusion_matrix"] == full["confusion_matrix"]
    for h_a, h_b in zip(resumed["history"], full["history"], strict=True):
        assert abs(h_a["train_loss"] - h_b["train_loss"]) <= 1e-6


def test_view_landscape_reads_a_synthetic_views_run(tmp_path, capsys):
    from studies import study

    view_landscape = study("view_landscape")

    cfg = tiny(str(tmp_path / "cache"), views=1, epochs=1, **{"selector.name": "circular"})
    cfg["dataset"] = {"name": "synthetic_views", "root": str(tmp_path / "views"), "num_per_class": [2, 1, 2]}
    m = train(cfg, tmp_path / "run")
    assert (tmp_path / "run" / "detail_angles.png").stat().st_size > 1000 and 0 <= m["test_detail_angle_median"] <= 180
    rows = view_landscape.landscape(tmp_path / "run", thetas=(0, 30), shapes=6, pairs=1, sigma=10.0)
    assert [r["theta"] for r in rows] == [0, 30] and "autograd_cos" not in rows[0]
    for key in ("loss", "centered", "acc", "autograd_cos", "autograd_towards", "smoothed_cos", "smoothed_towards"):
        assert torch.isfinite(torch.tensor(rows[1][key])), key
    assert -1 <= rows[1]["smoothed_cos"] <= 1 and 0 <= rows[1]["autograd_towards"] <= 1
    # a run on another dataset, and no run at all: one line, exit 2
    train(tiny(str(tmp_path / "cache"), views=1, epochs=1), tmp_path / "plain")
    for bad, needle in ((tmp_path / "plain", "needs synthetic_views"), (tmp_path / "none", "no such file")):
        with pytest.raises(SystemExit) as e:
            view_landscape.main([str(bad)])
        err = capsys.readouterr().err.strip().splitlines()
        assert e.value.code == 2 and len(err) == 1 and needle in err[0]


def test_axis_views_look_down_the_cup(tmp_path, capsys):
    """The diagnostic cameras: view 1 on each shape's cup axis (so it sees the detail, by the
    dataset's own visibility rule), the others 30 degrees around it; poles included."""
    import numpy as np

    from studies import study

    av = study("axis_views")
    from mvtn_exp.data import synthetic_views as sv
    from mvtn_exp.data import view_detail as vd

    ds = sv.SyntheticViews(tmp_path / "views", "test", (2, 1, 2), seed=0, num_points=64, progress=False)
    axis = torch.as_tensor(ds._a["detail_axis"])
    axis = torch.cat([axis, torch.tensor([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]])])  # the poles too
    azim, elev, dist = av.axis_views(axis, 4, 2.2)
    assert azim.shape == (len(axis), 4) and torch.isfinite(azim).all() and torch.isfinite(elev).all()
    d = torch.as_tensor(vd.camera_positions(azim.numpy(), elev.numpy(), 1.0))  # [N, M, 3] unit directions
    cos = (d * torch.nn.functional.normalize(axis.double(), dim=1)[:, None]).sum(-1)
    torch.testing.assert_close(cos[:, 0], torch.ones(len(axis), dtype=torch.float64), atol=1e-5, rtol=0)
    torch.testing.assert_close(cos[:, 1:], torch.full((len(axis), 3), np.cos(np.radians(30.0)), dtype=torch.float64),
                               atol=1e-5, rtol=0)
    ring = d[:, 1:]
    assert (ring - ring.roll(1, 1)).norm(dim=-1).gt(0.1).all()  # the ring's views are distinct
    n = len(ds)
    assert ds.detail_seen(azim[:n, :1].numpy(), elev[:n, :1].numpy(), dist[:n, :1].numpy()).all()
    with pytest.raises(SystemExit) as e:
        av.main(["--out", str(tmp_path / "run"), "views=1"])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 1 and "need dataset=synthetic_views" in err[0]
    assert not (tmp_path / "run").exists()
    with pytest.raises(SystemExit) as e:
        av.main(["--out", str(tmp_path / "run"), "--tilt", "-5", "dataset=synthetic_views"])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 1 and "--tilt=-5" in err[0]
    assert not (tmp_path / "run").exists()


def test_axis_views_train_through_the_one_trainer(tmp_path, capsys):
    """The diagnostic runs ``mvtn-train``'s loop with its own cameras (tilted here), end to end."""
    import json
    import warnings

    from studies import study

    av = study("axis_views")

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        av.main(["--out", str(tmp_path / "run"), "--tilt", "20", "dataset=synthetic_views",
                 f"dataset.root={tmp_path / 'cache'}", "dataset.num_per_class=[1,1,1]", "dataset.num_points=64",
                 "views=1", "image_size=32", "epochs=1", "batch_size=4", "logger.progress=false",
                 "logger.tensorboard=false"])
    m = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert m["test_size"] == 8 and m["test_detail_seen"] == 1.0  # 20 degrees off the axis still sees it
    assert 15.0 < m["test_detail_angle_median"] < 25.0


def test_tilted_axis_views_keep_their_angle_and_spread_around_the_axis():
    """``axis_views --tilt``: every direction exactly ``tilt`` degrees from its axis (poles too),
    in directions that differ between shapes and between draws."""
    from studies import study

    av = study("axis_views")

    axis = torch.nn.functional.normalize(torch.randn(64, 3, generator=torch.Generator().manual_seed(0)), dim=1)
    axis = torch.cat([axis, torch.tensor([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]])])
    g = torch.Generator().manual_seed(1)
    for tilt in (0.0, 20.0, 40.0, 180.0):
        d = av.tilted(axis, tilt, g)
        torch.testing.assert_close(d.norm(dim=1), torch.ones(len(axis), dtype=torch.float64))
        unit = torch.nn.functional.normalize(axis.double(), dim=1)
        angle = torch.rad2deg(torch.atan2(torch.linalg.cross(d, unit).norm(dim=1), (d * unit).sum(1)))
        torch.testing.assert_close(angle, torch.full_like(angle, tilt), atol=1e-3, rtol=0)
    a, b = av.tilted(axis, 20.0, g), av.tilted(axis, 20.0, g)
    assert (a - b).norm(dim=1).gt(1e-3).float().mean() > 0.9  # a new direction per draw
    off = a - torch.cos(torch.tensor(0.3491, dtype=torch.float64)) * axis.double()
    assert off[:64].mean(0).norm() < 0.1 * off[:64].norm(dim=1).mean()  # spread around, not one side


@pytest.mark.parametrize("elev", [90.0, -90.0, 89.9999, 120.0])
def test_smoothed_gradient_is_finite_at_the_poles(tmp_path, elev):
    """The estimate renders views perturbed around the poles (and past them): finite, seeded."""
    from mvtn_exp.data.collate import collate_shapes
    from mvtn_exp.engine.trainer import make_datasets
    from mvtn_exp.selectors.view_gradient import model_render_loss
    from mvtn_exp.tasks import classification

    from test_train_e2e import tiny_model

    cfg, model = tiny_model(str(tmp_path / "cache"), views=2)
    ds = make_datasets(cfg)["train"]
    batch = collate_shapes([ds[i] for i in range(4)])
    render_loss = model_render_loss(model, batch, batch["labels"], classification.loss_fn(cfg.task, reduction="none"))
    views = (torch.full((4, 2), 30.0), torch.full((4, 2), elev), torch.full((4, 2), 2.2))
    ga, ge = smoothed_view_gradient(render_loss, views, 2, 10.0, noise_generator(0, 0))
    assert torch.isfinite(ga).all() and torch.isfinite(ge).all() and (ga.abs() + ge.abs()).sum() > 0
