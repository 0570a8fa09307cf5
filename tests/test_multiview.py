import pytest
import torch

from mvtn_exp.models.backbones import resnet18, small_cnn
from mvtn_exp.models.late_fusion import PointLateFusion
from mvtn_exp.config.options import OPTIONS, load
from mvtn_exp.models.multiview import LogitMean, MVCNN, build_multiview

K, W = 5, 8  # classes, small_cnn width (feature_dim 64)
load("mvnet")
IMAGE_NETS = sorted(n for n, c in OPTIONS["mvnet"].items() if getattr(c.network, "reads_images", True))


def _images(b, m, size=32, seed=0, requires_grad=False):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(b, m, 3, size, size, generator=g).requires_grad_(requires_grad)


def _views(b, m, seed=0):
    """Random views ``(azim, elev, dist)`` ``[b, m]`` (the networks that read views need them)."""
    g = torch.Generator().manual_seed(seed + 100)
    return torch.rand(b, m, generator=g) * 360, torch.rand(b, m, generator=g) * 180 - 90, torch.full((b, m), 2.2)


def _points(net, b, n=40, seed=5):
    """``{"points": [b, n, 3]}`` for a net that reads the shapes' points (the paper's late fusion), else {}."""
    if not getattr(net, "reads_points", False):
        return {}
    return {"points": torch.rand(b, n, 3, generator=torch.Generator().manual_seed(seed))}


def _net(pool="max", cls=MVCNN, **kw):
    torch.manual_seed(0)
    return cls(small_cnn(num_classes=K, width=W), K, pool=pool, **kw)


def _manual_views(net, images):
    """Per-view backbone features by an explicit loop over views: [B, M, D]."""
    return torch.stack([net.backbone.features(images[:, m]) for m in range(images.shape[1])], 1)


@pytest.mark.parametrize("b", [1, 2])
@pytest.mark.parametrize("m", [1, 3, 12])
@pytest.mark.parametrize("pool", ["max", "mean"])
def test_shapes_and_pooled_features_match_manual_loop(b, m, pool):
    net = _net(pool).eval()
    x = _images(b, m)
    with torch.no_grad():
        logits, feats = net(x)
        per_view = _manual_views(net, x)
    assert net.feature_dim == 8 * W
    assert logits.shape == (b, K) and feats.shape == (b, 8 * W)
    ref = per_view.amax(1) if pool == "max" else per_view.mean(1)
    torch.testing.assert_close(feats, ref, atol=1e-5, rtol=0)
    torch.testing.assert_close(logits, net.head(ref), atol=1e-5, rtol=0)


def test_non_contiguous_input_and_non_square_images():
    net = _net().eval()
    x = _images(2, 4, size=40)[..., :24, :].transpose(1, 0).contiguous().transpose(1, 0)  # [2,4,3,24,40]
    assert not x.is_contiguous()
    with torch.no_grad():
        logits, feats = net(x)
        ref = _manual_views(net, x).amax(1)
    assert logits.shape == (2, K)
    torch.testing.assert_close(feats, ref, atol=1e-5, rtol=0)


@pytest.mark.parametrize("name", IMAGE_NETS)
def test_view_permutation_invariance(name):
    torch.manual_seed(0)  # (the same weights whatever ran before)
    net = build_multiview(name, small_cnn(num_classes=K, width=W), K).eval()
    x, views = _images(2, 6), _views(2, 6)
    perm = torch.tensor([3, 0, 5, 1, 4, 2])
    with torch.no_grad():
        l1, f1 = net(x, views, **_points(net, 2))
        l2, f2 = net(x[:, perm], tuple(v[:, perm] for v in views), **_points(net, 2))
    torch.testing.assert_close(l1, l2, atol=1e-5, rtol=1e-6)  # (logits of ~60: float32 sums in another order)
    torch.testing.assert_close(f1, f2, atol=1e-5, rtol=1e-6)


@pytest.mark.parametrize("name", IMAGE_NETS)
def test_batch_equals_single_shape_calls(name):
    net = build_multiview(name, "small_cnn", K).eval()
    x, views = _images(3, 4, seed=1), _views(3, 4)
    with torch.no_grad():
        pts = _points(net, 3)
        logits, feats = net(x, views, **pts)
        singles = [net(x[i:i + 1], tuple(v[i:i + 1] for v in views), **{k: v[i:i + 1] for k, v in pts.items()})
                   for i in range(3)]
    torch.testing.assert_close(logits, torch.cat([s[0] for s in singles]), atol=1e-5, rtol=0)
    torch.testing.assert_close(feats, torch.cat([s[1] for s in singles]), atol=1e-5, rtol=0)


@pytest.mark.parametrize("name", IMAGE_NETS)
def test_gradients_reach_backbone_and_input_images(name):
    net = build_multiview(name, small_cnn(num_classes=K, width=W), K, dropout=0.2).train()
    x = _images(2, 3, requires_grad=True)
    logits, _ = net(x, _views(2, 3), **_points(net, 2))
    net.training_loss(logits, torch.tensor([0, 1]), lambda z, y: z.square().sum()).backward()
    assert x.grad is not None and torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
    for pname, p in net.named_parameters():
        # the backbone's own classifier is unused by design; ViewGCN's single-view head is stage 1's
        if pname.startswith(("backbone.fc.", "single_view_head.")):
            assert p.grad is None
            continue
        assert p.grad is not None and torch.isfinite(p.grad).all(), pname
    assert net.backbone.body[0].weight.grad.abs().sum() > 0  # first conv: the whole path is live


def test_max_pool_losing_view_gets_zero_grad_mean_pool_all_views():
    """Max pooling: a view that wins no feature channel gets exactly zero gradient.

    small_cnn at init in eval mode is positively homogeneous (bias-free convs, identity BN,
    ReLU, max/avg pools), so features(0.5 x) = 0.5 features(x) <= features(x): view 1 (= 0.5 *
    view 0) never wins the max. With mean pooling every view gets gradient.
    """
    base = _images(2, 1)
    views = torch.cat([base, 0.5 * base, _images(2, 1, seed=3)], 1)  # [2, 3, 3, 32, 32]
    grads = {}
    for pool in ("max", "mean"):
        net = _net(pool).eval()
        x = views.clone().requires_grad_(True)
        net(x)[0].sum().backward()
        grads[pool] = x.grad.abs().flatten(2).sum(-1)  # [B, M]
    assert (grads["max"][:, 1] == 0).all()
    assert (grads["max"].sum(1) > 0).all() and (grads["max"][:, 0] > 0).all()
    assert (grads["mean"] > 0).all()


def test_logit_mean_equals_mean_pool_mvcnn_in_eval():
    mv, lf = _net("mean").eval(), _net("mean", cls=LogitMean, dropout=0.5).eval()
    lf.load_state_dict(mv.state_dict())
    x = _images(2, 5)
    with torch.no_grad():
        for a, b in zip(mv(x), lf(x)):
            torch.testing.assert_close(a, b, atol=1e-5, rtol=0)


@pytest.mark.parametrize("pool", ["max", "mean"])
def test_paper_late_fusion_pools_the_point_feature_with_the_view_features(pool):
    """The point encoder's vector is one more member of the view pool (the paper's late fusion,
    L556): features = pool over [M view features; point feature], logits = head(features); the
    loss reaches the backbone, the point encoder and the points."""
    net = _net(pool, cls=PointLateFusion, point_encoder="pointnet").eval()
    x, pts = _images(2, 3), torch.rand(2, 50, 3, requires_grad=True)
    logits, feats = net(x, None, points=pts)
    with torch.no_grad():
        members = torch.cat([_manual_views(net, x), net.point_encoder(pts)[:, None]], 1)  # [B, M + 1, D]
    want = members.amax(1) if pool == "max" else members.mean(1)
    torch.testing.assert_close(feats, want, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(logits, net.head(want), atol=1e-5, rtol=1e-5)
    assert net.point_encoder.out_features == net.feature_dim  # its last layer sized to the view features
    logits.square().sum().backward()
    assert pts.grad.abs().sum() > 0
    assert all(p.grad is not None for p in net.point_encoder.parameters() if p.requires_grad)
    assert net.backbone.features is not None and any(p.grad.abs().sum() > 0 for p in net.backbone.parameters())
    # the point feature wins channels of the max: without the points the features differ
    assert not torch.allclose(feats, _manual_views(net, x).amax(1) if pool == "max" else _manual_views(net, x).mean(1))


def test_paper_late_fusion_reads_the_first_points_and_refuses_without_points():
    net = _net(cls=PointLateFusion, point_encoder="pointnet", num_points=20).eval()
    x, pts = _images(2, 3), torch.rand(2, 50, 3)
    with torch.no_grad():
        a = net(x, None, points=pts)[0]
        b = net(x, None, points=torch.cat([pts[:, :20], torch.rand(2, 30, 3)], 1))[0]
    torch.testing.assert_close(a, b, atol=0, rtol=0)  # only the first 20 points are read
    for bad, needle in ((None, "got none"), (torch.rand(2, 50), "got [2, 50]")):
        with pytest.raises(ValueError, match="needs points") as err:
            net(x, None, points=bad)
        assert needle in str(err.value)
    with pytest.raises(ValueError, match="2 shapes of images but 3 of points"):
        net(x, None, points=torch.rand(3, 50, 3))


def test_dropout_only_in_train_mode():
    net = _net(dropout=0.5)
    x = _images(2, 3)
    net.eval()
    with torch.no_grad():
        assert torch.equal(net(x)[0], net(x)[0])
        net.train()
        torch.manual_seed(1)
        a, fa = net(x)
        torch.manual_seed(2)
        b, fb = net(x)
    assert not torch.allclose(a, b)
    torch.testing.assert_close(fa, fb, atol=1e-6, rtol=0)  # descriptor is taken before dropout


def test_unknown_names_and_bad_input_raise_clear_errors():
    with pytest.raises(ValueError, match=r"unknown multi-view network 'rotationnet'.*late_fusion, logit_mean, mvcnn"):
        build_multiview("rotationnet", "small_cnn", K)
    with pytest.raises(ValueError, match=r"unknown backbone 'resnet7'.*allowed"):
        build_multiview("mvcnn", "resnet7", K)
    with pytest.raises(ValueError, match=r"view pooling 'sum'.*max, mean"):
        MVCNN("small_cnn", K, pool="sum")
    with pytest.raises(ValueError, match=r"\[B, M, C, H, W\]"):
        _net()(torch.rand(2, 3, 32, 32))
    with pytest.raises(ValueError, match=r"M >= 1"):
        _net()(torch.rand(2, 0, 3, 32, 32))


def test_weights_path_loaded_into_named_and_given_backbones(tmp_path):
    torch.manual_seed(7)
    src = small_cnn(num_classes=K)
    path = tmp_path / "small.pth"
    torch.save(src.state_dict(), path)
    for backbone in ("small_cnn", small_cnn(num_classes=K)):
        net = build_multiview("mvcnn", backbone, K, weights=str(path))
        for k, v in src.state_dict().items():
            assert torch.equal(net.backbone.state_dict()[k], v), k
    with pytest.raises(FileNotFoundError, match="missing.pth"):
        MVCNN("small_cnn", K, weights=tmp_path / "missing.pth")


def test_resnet18_weights_and_forward_64px(tmp_path):
    torch.manual_seed(0)
    src = resnet18(num_classes=1000)  # ImageNet-sized head: skipped, the rest must load
    path = tmp_path / "r18.pth"
    torch.save(src.state_dict(), path)
    net = MVCNN("resnet18", K, weights=path).eval()
    sd = net.backbone.state_dict()
    for k, v in src.state_dict().items():
        if not k.startswith("fc."):
            assert torch.equal(sd[k], v), k
    x = _images(2, 3, size=64)
    with torch.no_grad():
        logits, feats = net(x)
        ref = _manual_views(net, x).amax(1)
    assert logits.shape == (2, K) and feats.shape == (2, 512)
    torch.testing.assert_close(feats, ref, atol=1e-5, rtol=0)
