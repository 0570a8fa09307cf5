import pytest
import torch

from mvtn_exp.render import layouts
from mvtn_exp.selectors import (SELECTORS, VARIANTS, MVTNSelector, RandomSelector, build_selector)
from mvtn_exp.selectors.mvtn import REGRESSORS, regressor_parameters

FIXED = ["circular", "spherical", "random", "noisy", "optimized"]
LEARNED = ["mvtn_direct", "mvtn_direct_offset", "mvtn_circular", "mvtn_spherical", "mvtn_poi", "poi"]


def clouds(B=3, N=32, seed=0, dtype=torch.float32):
    return torch.randn(B, N, 3, generator=torch.Generator().manual_seed(seed), dtype=dtype)


def test_registry_names():
    assert set(SELECTORS) == set(FIXED + LEARNED)
    allowed = ("expected one of circular, mvtn_circular, mvtn_direct, mvtn_direct_offset, mvtn_poi, mvtn_spherical, noisy, optimized, poi, "
               "random, spherical")
    with pytest.raises(ValueError, match=allowed):
        build_selector("mvtn_free", 4)


@pytest.mark.parametrize("name", sorted(SELECTORS))
@pytest.mark.parametrize("M", [1, 4, 12])
@pytest.mark.parametrize("training", [True, False])
def test_every_selector_shapes_dtypes(name, M, training):
    torch.manual_seed(0)
    sel = build_selector(name, M)
    sel.train(training)
    assert sel.views == M and sel.learned == (name in LEARNED)
    out = sel(clouds())
    assert len(out) == 3
    for t in out:
        assert t.shape == (3, M) and t.dtype == torch.float32 and torch.isfinite(t).all()
    assert (out[2] > 0).all()
    if name in LEARNED:
        sum(t.sum() for t in out).backward()
        assert all(p.grad is None or torch.isfinite(p.grad).all() for p in sel.parameters())


@pytest.mark.parametrize("name", FIXED)
def test_fixed_selectors_follow_input_dtype_and_are_the_same_for_all_shapes(name):
    kw = {"eval_draw": "frozen"} if name == "random" else {}  # fresh: a new draw per shape (below)
    sel = build_selector(name, 6, **kw).eval()
    azim, elev, dist = sel(clouds(B=5, dtype=torch.float64))
    for t in (azim, elev, dist):
        assert t.dtype == torch.float64
        assert (t == t[:1]).all()


@pytest.mark.parametrize("name", sorted(SELECTORS))
@pytest.mark.parametrize("bad", [0, -2, 2.5, 4.0, "4", True, None])
def test_bad_views_rejected(name, bad):
    with pytest.raises(ValueError, match="views"):
        build_selector(name, bad)


def test_bad_points_rejected():
    for name in SELECTORS:
        with pytest.raises(ValueError, match=r"\[B, N, 3\]"):
            build_selector(name, 4)(torch.zeros(3, 10))


@pytest.mark.parametrize("M", [1, 3, 4, 12])
def test_circular_selector(M):
    azim, elev, dist = build_selector("circular", M)(clouds())
    assert (elev == 30.0).all() and (dist == 2.2).all()
    expected = torch.tensor([(90.0 + 360.0 * k / M) % 360.0 for k in range(M)])  # the official code starts at 90
    assert torch.allclose(azim, expected.expand(3, -1), atol=1e-5)
    azim0 = build_selector("circular", M, azim_start=0.0)(clouds())[0]
    assert torch.allclose(azim0, torch.tensor([360.0 * k / M for k in range(M)]).expand(3, -1), atol=1e-5)
    azim, elev, dist = build_selector("circular", M, elevation=-10.0, distance=3.0)(clouds())
    assert (elev == -10.0).all() and (dist == 3.0).all()


@pytest.mark.parametrize("M", range(1, 21))
def test_spherical_selector_gives_m_distinct_views(M):
    azim, elev, dist = build_selector("spherical", M)(clouds(B=2))
    a, e = torch.deg2rad(azim[0].double()), torch.deg2rad(elev[0].double())
    dirs = torch.stack([e.cos() * a.sin(), e.sin(), e.cos() * a.cos()], -1)
    assert len(dirs) == M
    d = torch.cdist(dirs, dirs) + torch.eye(M, dtype=dirs.dtype) * 10
    assert d.min() > 0.1  # exactly M distinct directions
    assert torch.equal(azim[0], azim[1])


# --------------------------------------------------------------------------- random


def test_random_selector_training_redraws_and_is_globally_seeded():
    sel = RandomSelector(5).train()
    x = clouds()
    torch.manual_seed(123)
    a1 = sel(x)
    a2 = sel(x)
    assert not torch.equal(a1[0], a2[0]) and not torch.equal(a1[1], a2[1])
    assert not torch.equal(a1[0][0], a1[0][1])  # per shape
    torch.manual_seed(123)
    b1 = sel(x)
    assert torch.equal(a1[0], b1[0]) and torch.equal(a1[1], b1[1])
    assert (a1[2] == 2.2).all()


def test_random_selector_eval_draws_anew_per_shape_and_each_pass_repeats():
    """``eval_draw=fresh`` (the official code): new directions for every shape and call at
    evaluation, the same sequence in every evaluation pass, whatever the global generator."""
    sel = RandomSelector(7, seed=3)
    sel.eval()
    first = [sel(clouds(B=4)) for _ in range(2)]
    assert not torch.equal(first[0][0], first[1][0])   # each call draws anew
    assert not torch.equal(first[0][0][0], first[0][0][1])  # each shape too
    sel.train()
    sel(clouds(B=4))
    torch.manual_seed(99)
    sel.eval()
    again = [sel(clouds(B=4)) for _ in range(2)]
    for a, b in zip(first, again):
        assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
    other = RandomSelector(7, seed=4).eval()
    assert not torch.equal(other(clouds(B=4))[0], first[0][0])
    with pytest.raises(ValueError, match="selector.eval_draw='new'"):
        RandomSelector(7, eval_draw="new")


def test_random_selector_eval_is_fixed():
    sel = RandomSelector(7, seed=3, eval_draw="frozen").eval()
    a, b = sel(clouds(B=4)), sel(clouds(B=4, seed=9))
    for s, t in zip(a, b):
        assert torch.equal(s, t) and (s == s[:1]).all()
    assert torch.equal(RandomSelector(7, seed=3, eval_draw="frozen").eval()(clouds())[0][0], a[0][0])
    assert not torch.equal(RandomSelector(7, seed=4, eval_draw="frozen").eval()(clouds())[0][0], a[0][0])
    torch.manual_seed(0)  # the global generator does not matter in eval mode
    assert torch.equal(sel(clouds(B=4))[1], a[1])


def test_random_selector_uniform_on_sphere():
    torch.manual_seed(0)
    azim, elev, _ = RandomSelector(200).train()(clouds(B=100, N=1))
    assert azim.numel() == 20000
    assert (azim >= 0).all() and (azim < 360).all() and (elev.abs() <= 90).all()
    s = torch.sin(torch.deg2rad(elev.double()))
    assert abs(float(s.mean())) < 0.02
    assert abs(float((elev > 30).double().mean()) - 0.25) < 0.02
    assert abs(float(azim.double().mean()) - 180.0) < 5.0


# --------------------------------------------------------------------------- MVTN


OFFSET_VARIANTS = [v for v in VARIANTS if v != "direct"]


def u0_of(variant, M, B):
    if variant == "circular":  # the official learned circular layout starts at azimuth 180
        a, e, d = layouts.circular(M, B, azim_start=180.0)
    elif variant == "direct":
        a, e, d = layouts.circular(M, B)
        a, e = torch.zeros_like(a), torch.zeros_like(e)
    else:
        a, e, d = layouts.spherical(M, B)
    return a, e, d


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("M", [1, 4, 12])
def test_mvtn_bounds_defined_once(variant, M):
    sel = MVTNSelector(M, variant, learn_distance=True, distance_bound=0.5)
    expected = [180.0 if variant.startswith("direct") else 180.0 / M, 90.0, 0.5]
    assert torch.allclose(sel.u_bound, torch.tensor(expected))
    assert MVTNSelector(M, variant).u_bound[2] == 0


@pytest.mark.parametrize("variant", OFFSET_VARIANTS)
@pytest.mark.parametrize("training", [True, False])
@pytest.mark.parametrize("kind", REGRESSORS)
def test_mvtn_starts_at_u0_exactly(variant, training, kind):
    torch.manual_seed(0)
    sel = MVTNSelector(4, variant, learn_distance=True, regressor=kind).train(training)
    azim, elev, dist = sel(clouds())
    a0, e0, d0 = u0_of(variant, 4, 3)
    assert torch.equal(azim, a0) and torch.equal(elev, e0) and torch.equal(dist, d0)
    ia, ie, idist = sel.initial_views(3)
    assert torch.equal(ia, a0) and torch.equal(ie, e0) and torch.equal(idist, d0)


def test_mvtn_direct_is_the_papers():
    """u = u_bound * tanh(G(S)): G reads the shape's features only (no u0 input), the views are
    exactly the bounded tanh of the regressor's output, distinct per view from the start, and
    no initial layout is added."""
    torch.manual_seed(0)
    M, b = 6, 40
    sel = MVTNSelector(M, "direct").eval()
    assert sel.regressor[0].in_features == b and not sel.uses_u0
    x = clouds(B=3)
    azim, elev, dist = sel(x)
    t = torch.tanh(sel.regressor(sel.encoder(x)))
    torch.testing.assert_close(azim, 180.0 * t[:, :M])
    torch.testing.assert_close(elev, 90.0 * t[:, M:])
    assert (azim.abs() < 180).all() and (elev.abs() < 90).all() and torch.equal(dist, torch.full_like(dist, 2.2))
    assert len({round(float(a), 4) for a in azim[0].detach()}) == M  # the M views are not stuck together
    ia, ie, _ = sel.initial_views(2)
    assert not ia.any() and not ie.any()
    offset = MVTNSelector(M, "direct_offset")
    assert offset.regressor[0].in_features == b + 2 * M and offset.uses_u0
    # the regressor of the paper's G: b -> b -> b -> 5M -> 2M
    lin = [m for m in sel.regressor if isinstance(m, torch.nn.Linear)]
    assert [(m.in_features, m.out_features) for m in lin] == [(b, b), (b, b), (b, 5 * M), (5 * M, 2 * M)]


# hand-expanded polynomials at b = 40 (see the selectors/mvtn.py docstring), not the code's formula
SIZES = {("compact", True): (10, 297, 3440), ("compact", False): (10, 217, 3440),
         ("official", True): (14, 303, 3440), ("official", False): (14, 223, 3440)}


@pytest.mark.parametrize("kind", REGRESSORS)
@pytest.mark.parametrize("variant", ["spherical", "direct"])
def test_regressor_sizes(kind, variant):
    """G's MLP has exactly the stated parameter count at every M; the official one is the official
    code's layers (Linear + BatchNorm + ReLU + Dropout(0.5) four times, then Linear(2M, 2M))."""
    u0 = variant != "direct"
    a, b_, c = SIZES[kind, u0]
    for M in (1, 2, 4, 12, 20):
        sel = MVTNSelector(M, variant, regressor=kind)
        n = sum(p.numel() for p in sel.regressor.parameters())
        assert n == a * M * M + b_ * M + c == regressor_parameters(M, 40, u0, kind)
    M, b = 12, 40
    sel = MVTNSelector(M, variant, regressor=kind)
    lin = [(m.in_features, m.out_features) for m in sel.regressor if isinstance(m, torch.nn.Linear)]
    widths = [(b + 2 * M * u0, b), (b, b), (b, 5 * M), (5 * M, 2 * M)] + ([(2 * M, 2 * M)] if kind == "official" else [])
    assert lin == widths
    drops = [m.p for m in sel.regressor if isinstance(m, torch.nn.Dropout)]
    assert drops == ([0.5] * 4 if kind == "official" else [])
    assert sum(isinstance(m, torch.nn.BatchNorm1d) for m in sel.regressor) == len(widths) - 1
    with pytest.raises(ValueError, match="unknown regressor 'mlp'"):
        MVTNSelector(M, variant, regressor="mlp")


def test_official_regressor_dropout_only_in_training():
    """The official MLP's dropout makes training outputs vary from call to call; eval is deterministic."""
    torch.manual_seed(0)
    sel = MVTNSelector(4, "direct", regressor="official")
    x = clouds(B=4)
    sel.train()
    assert not torch.equal(sel(x)[0], sel(x)[0])
    sel.eval()
    assert torch.equal(sel(x)[0], sel(x)[0])


@pytest.mark.parametrize("variant", VARIANTS)
def test_mvtn_learns_and_gradients_reach_the_encoder(variant):
    torch.manual_seed(0)
    sel = MVTNSelector(4, variant, learn_distance=True).train()
    opt = torch.optim.SGD(sel.parameters(), lr=0.1)
    x = clouds()

    def step():
        opt.zero_grad()
        azim, elev, dist = sel(x)
        loss = azim.mean() + elev.mean() + dist.mean()
        loss.backward()
        return azim.detach(), elev.detach(), dist.detach()

    a0, e0, d0 = step()
    last = sel.regressor[-1]
    assert last.weight.grad.abs().sum() > 0 and last.bias.grad.abs().sum() > 0
    opt.step()
    a1, e1, d1 = step()
    if variant == "direct":  # every layer moves at once (no zero last layer): the loss goes down
        assert a1.mean() + e1.mean() + d1.mean() < a0.mean() + e0.mean() + d0.mean()
    else:
        assert (a1 < a0).all() and (e1 < e0).all() and (d1 < d0).all()  # moved down the loss
    enc = [p.grad for p in sel.encoder.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in enc)
    assert sum(float(g.abs().sum()) for g in enc) > 0
    assert sel.encoder.mlp[0].weight.grad.abs().sum() > 0  # the very first conv


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("M", [1, 5])
def test_mvtn_offsets_never_exceed_the_bounds(variant, M):
    torch.manual_seed(0)
    sel = MVTNSelector(M, variant, learn_distance=True, distance_bound=0.7, distance=2.0).train()
    opt = torch.optim.SGD(sel.parameters(), lr=1e3)
    x = clouds(B=4)
    g = torch.Generator().manual_seed(1)
    sign = torch.randint(0, 2, (3, 1, M), generator=g).float() * 2 - 1  # push both ways
    a0, e0, d0 = sel.initial_views(4)
    seen = torch.zeros(3)
    for _ in range(5):
        opt.zero_grad()
        azim, elev, dist = sel(x)
        off = torch.stack([azim - a0, elev - e0, dist - d0]).abs().amax(dim=(1, 2))
        assert (off <= sel.u_bound + 1e-4).all(), (off, sel.u_bound)
        seen = torch.maximum(seen, off.detach())
        loss = 1e4 * (sign * torch.stack([azim, elev, dist])).sum()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(sel.parameters(), 30.0)  # as the trainer does
        opt.step()
    sel.eval()
    azim, elev, dist = sel(x)
    off = torch.stack([azim - a0, elev - e0, dist - d0]).abs().amax(dim=(1, 2))
    assert (off <= sel.u_bound + 1e-4).all()
    assert (seen >= 0.9 * sel.u_bound).all()  # the push did reach the bounds
    assert (dist >= 2.0 - 0.7 - 1e-5).all() and (dist <= 2.0 + 0.7 + 1e-5).all()


def test_mvtn_constant_distance_when_not_learned():
    sel = MVTNSelector(3, "spherical", distance=1.7)
    assert (sel(clouds())[2] == 1.7).all()


@pytest.mark.parametrize("variant", VARIANTS)
def test_mvtn_eval_output_independent_of_batch(variant):
    torch.manual_seed(0)
    sel = MVTNSelector(4, variant, learn_distance=True).train()
    # direct starts with a non-zero last layer: a small step keeps its tanh away from saturation
    opt = torch.optim.SGD(sel.parameters(), lr=1e-4 if variant == "direct" else 0.01)
    for i in range(3):  # non-zero last layer and non-default BN statistics
        opt.zero_grad()
        a, e, d = sel(clouds(B=4, seed=i))
        (a.mean() + e.mean() + d.mean()).backward()
        opt.step()
    sel.eval()
    x = clouds(B=5, seed=10)
    with torch.no_grad():
        batched = sel(x)
        alone = sel(x[2:3])
        others = sel(torch.cat([x[2:3], clouds(B=3, seed=11)]))
    assert not torch.allclose(batched[0][0], batched[0][1])  # views are per shape
    for full, one, mixed in zip(batched, alone, others):
        assert torch.allclose(full[2:3], one, atol=1e-5)
        assert torch.allclose(mixed[:1], one, atol=1e-5)


def test_mvtn_bad_arguments_and_custom_encoder():
    with pytest.raises(ValueError, match="variant"):
        MVTNSelector(4, "free")
    with pytest.raises(ValueError, match="allowed: dgcnn, pointnet"):
        MVTNSelector(4, "direct", point_encoder="pointnet2")
    sel = MVTNSelector(4, "circular", point_encoder="pointnet", features=8, point_encoder_kwargs={"use_tnet": True})
    assert sel.encoder.out_features == 8 and sel.encoder.tnet is not None
    assert sel.regressor[0].in_features == 8 + 2 * 4 and sel.regressor[-1].out_features == 2 * 4
    widths = [m.out_features for m in sel.regressor if isinstance(m, torch.nn.Linear)]
    assert widths == [8, 8, 20, 8]
    enc = torch.nn.Sequential(torch.nn.Flatten(), torch.nn.LazyLinear(40))
    out = MVTNSelector(2, "direct", point_encoder=enc)(clouds(N=16))
    assert out[0].shape == (3, 2)


def _rotation(seed=0, dtype=torch.float32):
    q, _ = torch.linalg.qr(torch.randn(3, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64))
    return (q * torch.sign(torch.linalg.det(q))).to(dtype)


def test_poi_starts_at_u0_and_turns_with_the_shape():
    """mvtn_poi: exactly u0 at initialisation; its point weights do not depend on the pose, so the
    point of interest (and, without u0, the camera) rotates with the shape."""
    torch.manual_seed(0)
    sel = build_selector("mvtn_poi", 4).eval()
    pts = clouds(B=2, N=96) * torch.tensor([1.0, 0.6, 0.3])  # anisotropic: no accidental symmetry
    azim, elev, _ = sel(pts)
    a0, e0, _ = sel.initial_views(2)
    assert torch.allclose(torch.remainder(azim - a0 + 180, 360) - 180, torch.zeros_like(azim), atol=1e-3)
    assert torch.allclose(elev, e0, atol=1e-3)
    for p in sel.scorer[-1].parameters():
        torch.nn.init.normal_(p, std=1.0)
    R = _rotation()
    p1, w1 = sel.point_weights(pts)
    p2, w2 = sel.point_weights(pts @ R.T + 0.3)  # turned and moved
    assert torch.allclose(w1, w2, atol=1e-4)
    assert not torch.allclose(w1, torch.full_like(w1, 1 / 96), atol=1e-4)  # the weights do depend on the points
    q1, q2 = (torch.einsum("bnm,bnc->bmc", w, p) for w, p in ((w1, p1), (w2, p2)))
    assert torch.allclose(q1 @ R.T, q2, atol=1e-4)


def test_poi_gradient_reaches_the_scorer():
    torch.manual_seed(0)
    sel = build_selector("mvtn_poi", 1).train()
    opt = torch.optim.SGD(sel.parameters(), lr=0.1)
    for _ in range(3):  # the zero last layer blocks the hidden layers on the first step only
        opt.zero_grad()
        azim, elev, _ = sel(clouds(B=4, N=64))
        (elev.sum() + azim.sum()).backward()
        opt.step()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in sel.parameters())
    assert float(sel.scorer[1].weight.grad.abs().max()) > 0


def test_the_constant_u0_input_is_cancelled_by_the_first_batchnorm():
    """G's u0 input is the same for every shape, so in training the first BatchNorm subtracts it
    away: any other constant there gives the same output (issue 9's question, measured here).
    Only the features of the shape reach the views."""
    torch.manual_seed(0)
    sel = MVTNSelector(4, "spherical", init_std=0.01).train()
    f = sel.encoder(clouds(B=8))
    u0 = torch.cat([sel.azim0 / 180.0, sel.elev0 / 90.0]).expand(8, -1)
    with torch.no_grad():
        a = sel.regressor(torch.cat([f, u0], 1))
        b = sel.regressor(torch.cat([f, 5.0 * u0 + 1.0], 1))
    assert float((a - b).abs().max()) < 1e-5 and float(a.abs().max()) > 1e-3


def test_poi_learned_gain_starts_at_u0_and_shrinks_the_tilt_of_u0():
    """selector.learn_gain: the gain is a parameter of G (log scale) that starts where the fixed
    gain is, so the start (u = u0) and the views for equal weights are unchanged; a larger gain
    brings each camera closer to the direction of its point of interest q, and the gain gets a
    gradient from the views."""
    torch.manual_seed(0)
    fixed = build_selector("mvtn_poi", 2, gain=8.0).eval()
    learned = build_selector("mvtn_poi", 2, gain=8.0, learn_gain=True).eval()
    assert "log_gain" not in dict(fixed.named_parameters())
    assert "log_gain" in dict(learned.named_parameters()) and learned.gain == pytest.approx(8.0)
    pts = clouds(B=3, N=96) * torch.tensor([1.0, 0.6, 0.3])
    a0, e0, _ = learned.initial_views(3)
    azim, elev, _ = learned(pts)
    assert torch.allclose(torch.remainder(azim - a0 + 180, 360) - 180, torch.zeros_like(azim), atol=1e-3)
    for p in learned.scorer[-1].parameters():
        torch.nn.init.normal_(p, std=1.0)
    fixed.load_state_dict(learned.state_dict(), strict=False)
    for a, b in zip(fixed(pts), learned(pts)):
        assert torch.equal(a, b)

    def tilt(sel):  # angle (deg) between each camera and its point of interest's direction
        p, w = sel.point_weights(pts)
        q = torch.nn.functional.normalize(torch.einsum("bnm,bnc->bmc", w, p), dim=-1)
        az, el, _ = sel(pts)
        a, e = torch.deg2rad(az), torch.deg2rad(el)
        d = torch.stack([torch.cos(e) * torch.sin(a), torch.sin(e), torch.cos(e) * torch.cos(a)], -1)
        return torch.rad2deg(torch.acos((d * q).sum(-1).clamp(-1, 1)))

    before = tilt(learned)
    with torch.no_grad():
        learned.log_gain += 3.0  # x 20
    after = tilt(learned)
    assert float(before.min()) > 2.0 and bool((after < before).all())
    assert float(after.median()) < float(before.median()) / 3
    learned.train()
    azim, elev, _ = learned(pts)
    (azim.sum() + elev.sum()).backward()
    assert learned.log_gain.grad is not None and float(learned.log_gain.grad.abs()) > 0


def test_poi_learn_gain_reaches_the_model_from_the_config():
    from mvtn_exp.engine.trainer import as_config
    from mvtn_exp.model import build_mvtn
    model = build_mvtn(as_config({"selector": {"name": "mvtn_poi", "learn_gain": True}}), num_classes=3)
    assert any(p is model.selector.log_gain for p in model.parameter_groups()["selector"])


def test_selector_beta1_is_g_groups_own_and_changes_only_gs_step():
    from mvtn_exp.engine.trainer import as_config, make_optimizer
    from mvtn_exp.model import build_mvtn
    steps = {}
    for beta1 in (0.9, 0.99):
        torch.manual_seed(0)
        cfg = as_config({"selector": {"name": "mvtn_spherical", "beta1": beta1}})
        model = build_mvtn(cfg, num_classes=3)
        opt, _ = make_optimizer(cfg, model, cfg.selector.training()(cfg))
        betas = {g["name"]: g["betas"] for g in opt.param_groups}
        assert betas == {"mvnet": (0.9, 0.999), "selector": (beta1, 0.999)}
        groups = model.parameter_groups()
        before = [p.detach().clone() for p in groups["mvnet"] + groups["selector"]]
        for _ in range(2):  # the first step is lr-sized whatever beta1; the second differs
            opt.zero_grad()
            for p in groups["mvnet"] + groups["selector"]:
                p.grad = torch.ones_like(p) if len(opt.state.get(p, {})) == 0 else -torch.ones_like(p)
            opt.step()
        steps[beta1] = [(p.detach() - b) for p, b in zip(groups["mvnet"] + groups["selector"], before)]
        n_c = len(groups["mvnet"])
    for a, b in zip(steps[0.9][:n_c], steps[0.99][:n_c]):
        assert torch.equal(a, b)  # C's steps are untouched
    assert any(not torch.allclose(a, b) for a, b in zip(steps[0.9][n_c:], steps[0.99][n_c:]))


def test_noisy_views_have_the_stated_spread():
    """Training noise of std 18 degrees in azimuth and 9 in elevation around the layout."""
    sel = build_selector("noisy", 12).train()
    base = build_selector("circular", 12)(clouds(B=400))
    torch.manual_seed(0)
    azim, elev, _ = sel(clouds(B=400))
    assert abs(float((azim - base[0]).std()) - 18.0) < 0.5
    assert abs(float((elev - base[1]).std()) - 9.0) < 0.25
    sel.eval()
    assert torch.equal(sel(clouds(B=2))[0], base[0][:2])  # the plain layout at evaluation


def test_mvtn_takes_one_shape_feature():
    sel = MVTNSelector(3, "spherical", features=1).eval()
    assert sel.features == 1 and sel(clouds(B=2))[0].shape == (2, 3)
    with pytest.raises(ValueError, match="features must be an integer >= 1"):
        MVTNSelector(3, "spherical", features=0)
