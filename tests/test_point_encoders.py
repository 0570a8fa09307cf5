import copy

import pytest
import torch

from conftest import box_mesh
from mvtn_exp.data.shapes import Meshes, PointClouds
from mvtn_exp.config.options import OPTIONS, load
from mvtn_exp.models.point_encoders import PaperPointNet, PointNet, build_point_encoder, sample_points
from mvtn_exp.models.pooled_layer import _PooledLayer, pooled_layer


def clouds(B=3, N=200, seed=0):
    return torch.randn(B, N, 3, generator=torch.Generator().manual_seed(seed))


# --------------------------------------------------------------------------- PointNet


@pytest.mark.parametrize("out_features,head", [(40, ()), (7, ()), (16, (512, 256))])
def test_pointnet_output_shape(out_features, head):
    torch.manual_seed(0)
    net = PointNet(out_features=out_features, head_widths=head)
    y = net(clouds())
    assert y.shape == (3, out_features) and y.dtype == torch.float32 and torch.isfinite(y).all()
    assert net.out_features == out_features
    assert net.global_features(clouds()).shape == (3, 1024)


def _layer_pair(Cin=6, C=9, momentum=0.1, seed=0):
    """A conv + BatchNorm pair in float64 with some negative BatchNorm weights, and a copy."""
    torch.manual_seed(seed)
    conv = torch.nn.Conv1d(Cin, C, 1, bias=False).double()
    bn = torch.nn.BatchNorm1d(C, momentum=momentum).double()
    with torch.no_grad():
        bn.weight.copy_(torch.randn(C, dtype=torch.float64))  # about half negative: max becomes min
        bn.bias.copy_(torch.randn(C, dtype=torch.float64))
        bn.running_mean.normal_()
        bn.running_var.uniform_(0.5, 2.0)
    return (conv, bn), (copy.deepcopy(conv), copy.deepcopy(bn))


@pytest.mark.parametrize("momentum", [0.1, None])
def test_pooled_layer_matches_the_plain_modules(momentum):
    """max_n ReLU(BN(W h)) fused: output, every gradient and the running statistics equal the
    modules run one by one (training mode), over two steps; evaluation mode too."""
    (conv, bn), (conv2, bn2) = _layer_pair(momentum=momentum)
    assert (bn.weight < 0).any() and (bn.weight > 0).any()
    for step in range(2):
        h = (torch.randn(4, 6, 11, dtype=torch.float64) * 3 + 5).requires_grad_()  # large mean: no cancellation
        h2 = h.detach().clone().requires_grad_()
        up = torch.randn(4, 9, dtype=torch.float64)
        out = pooled_layer(h, conv, bn)
        ref = torch.relu(bn2(conv2(h2))).amax(dim=2)
        torch.testing.assert_close(out, ref, rtol=1e-10, atol=1e-10)
        (out * up).sum().backward()
        (ref * up).sum().backward()
        for a, b in ((h.grad, h2.grad), (conv.weight.grad, conv2.weight.grad), (bn.weight.grad, bn2.weight.grad),
                     (bn.bias.grad, bn2.bias.grad)):
            torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-10)
        for key in ("running_mean", "running_var", "num_batches_tracked"):
            torch.testing.assert_close(getattr(bn, key), getattr(bn2, key), rtol=1e-10, atol=1e-12)
    bn.eval(), bn2.eval()
    h = torch.randn(2, 6, 5, dtype=torch.float64)
    torch.testing.assert_close(pooled_layer(h, conv, bn), torch.relu(bn2(conv2(h))).amax(dim=2))


def test_pooled_layer_gradcheck():
    torch.manual_seed(1)
    h = torch.randn(3, 4, 5, dtype=torch.float64, requires_grad=True)
    w = torch.randn(6, 4, dtype=torch.float64, requires_grad=True)
    gamma = torch.tensor([1.0, -0.5, 2.0, 0.3, -1.5, 0.8], dtype=torch.float64, requires_grad=True)
    beta = torch.randn(6, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda *a: _PooledLayer.apply(*a, 1e-5)[0], (h, w, gamma, beta))


def test_pointnet_fused_pool_matches_modules():
    """PointNet's global feature (and so G) is the shared MLP then a max, whichever way it runs."""
    torch.manual_seed(0)
    net = PointNet().double().train()
    x = clouds().double()
    ref = torch.relu(copy.deepcopy(net).mlp(x.transpose(1, 2))).amax(dim=2)
    torch.testing.assert_close(net.global_features(x), ref, rtol=1e-10, atol=1e-10)


def test_pointnet_default_is_paper_b_without_tnet():
    net = build_point_encoder("pointnet")
    assert net.out_features == 40 and net.tnet is None
    convs = [m for m in net.mlp if isinstance(m, torch.nn.Conv1d)]
    assert [(c.in_channels, c.out_channels, c.kernel_size) for c in convs] == [(3, 64, (1,)), (64, 128, (1,)),
                                                                               (128, 1024, (1,))]
    assert sum(isinstance(m, torch.nn.BatchNorm1d) for m in net.mlp) == 3


@pytest.mark.parametrize("use_tnet", [False, True])
def test_pointnet_permutation_invariant(use_tnet):
    torch.manual_seed(0)
    net = PointNet(use_tnet=use_tnet)
    net.train()
    net(clouds(B=4, seed=1))  # move BN running stats away from their defaults
    net.eval()
    x = clouds(B=3, N=300, seed=2)
    perm = torch.randperm(300, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        a, b = net(x), net(x[:, perm])
    assert (a - b).abs().max() < 1e-5
    assert (a[0] - a[1]).abs().max() > 1e-3  # the check above is not trivially satisfied


def test_pointnet_tnet_runs_and_starts_at_identity():
    torch.manual_seed(0)
    net = PointNet(out_features=10, use_tnet=True)
    x = clouds(B=2, N=64)
    T = net.tnet(x)
    assert T.shape == (2, 3, 3)
    assert torch.allclose(T, torch.eye(3).expand(2, 3, 3))
    y = net(x)
    y.square().sum().backward()
    assert y.shape == (2, 10)
    g = net.tnet.out.weight.grad
    assert g is not None and torch.isfinite(g).all() and g.abs().sum() > 0
    net.eval()
    assert net(clouds(B=1, N=50)).shape == (1, 10)


def test_pointnet_rejects_bad_input():
    net = PointNet()
    with pytest.raises(ValueError, match=r"\[B, N, 3\]"):
        net(torch.zeros(2, 10, 2))
    with pytest.raises(ValueError, match="N = 0"):
        net(torch.zeros(2, 0, 3))
    with pytest.raises(ValueError, match="out_features"):
        PointNet(out_features=0)


def test_point_encoder_registry():
    load("point_encoder")
    assert set(OPTIONS["point_encoder"]) == {"pointnet", "pointnet_paper", "dgcnn"}
    assert build_point_encoder("pointnet", out_features=12, use_tnet=True).tnet is not None
    assert build_point_encoder("dgcnn", out_features=12, k=4).k == 4
    assert build_point_encoder("pointnet_paper", out_features=12, dropout=0.0).drop.p == 0.0
    with pytest.raises(ValueError, match="allowed: dgcnn, pointnet, pointnet_paper"):
        build_point_encoder("pointnet2")


# --------------------------------------------------------------------------- the paper's PointNet


def test_the_papers_pointnet_has_the_papers_size_and_layers():
    """3.47-3.49 M parameters in the paper (L736, L777-L781) at b = 40: the reference classifier
    with both T-nets (3,471,473), nineteen times the compact encoder."""
    net = PaperPointNet(40)
    n = sum(p.numel() for p in net.parameters())
    assert n == 3_471_473 and abs(n - 3.47e6) / 3.47e6 < 0.01
    assert sum(p.numel() for p in PointNet(40).parameters()) * 15 < n
    assert (net.input_tnet.k, net.feature_tnet.k) == (3, 64)
    convs = [m for m in net.modules() if isinstance(m, torch.nn.Conv1d) and m not in set(net.input_tnet.modules())
             and m not in set(net.feature_tnet.modules())]
    assert [(c.in_channels, c.out_channels) for c in convs] == [(3, 64), (64, 128), (128, 1024)]
    assert [(l.in_features, l.out_features) for l in (net.fc1[0], net.fc2, net.fc3)] == [(1024, 512), (512, 256), (256, 40)]


def test_the_papers_pointnet_starts_at_identity_transforms_and_trains_them():
    torch.manual_seed(0)
    net = PaperPointNet(10).train()
    x = clouds(B=4, N=64)
    assert torch.equal(net.input_tnet(x.transpose(1, 2)), torch.eye(3).expand(4, 3, 3))
    assert torch.equal(net.feature_tnet(torch.randn(4, 64, 64)), torch.eye(64).expand(4, 64, 64))
    y = net(x)
    y.square().sum().backward()
    for tnet in (net.input_tnet, net.feature_tnet):
        g = tnet.out.weight.grad
        assert g is not None and torch.isfinite(g).all() and g.abs().sum() > 0
    net.eval()
    x = clouds(B=3, N=300, seed=2)
    perm = torch.randperm(300, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        a, b = net(x), net(x[:, perm])
    assert (a - b).abs().max() < 1e-4 and (a[0] - a[1]).abs().max() > 1e-4
    with pytest.raises(ValueError, match="N = 0"):
        net(torch.zeros(2, 0, 3))


def test_g_on_the_papers_pointnet_is_the_papers_size(tmp_path):
    """G = the paper's PointNet + the regressor: 3.47-3.49 M + 9.09 K in the paper; within 1%."""
    from conftest import tiny_config
    from mvtn_exp.engine.cost import parameter_counts
    from mvtn_exp.engine.trainer import as_config
    from mvtn_exp.model import build_mvtn

    cfg = as_config(tiny_config(str(tmp_path), **{"selector.name": "mvtn_spherical", "point_encoder.name": "pointnet_paper",
                                                     "views": 12}))
    g = parameter_counts(build_mvtn(cfg, 40))["params_selector"]
    assert abs(g - (3.47e6 + 9.09e3)) / 3.479e6 < 0.01, g


# --------------------------------------------------------------------------- sample_points


def test_sample_mesh_cube_points_on_surface():
    cube = box_mesh(extents=(1.0, 1.0, 1.0))
    p = sample_points(cube, 2000, generator=torch.Generator().manual_seed(0))
    assert p.shape == (1, 2000, 3) and p.dtype == torch.float32
    a = p[0].abs()
    assert (a <= 0.5 + 1e-6).all()
    assert ((a.max(dim=1).values - 0.5).abs() <= 1e-6).all()
    # all six faces are hit, in proportion to their (equal) areas
    face_id = a.argmax(1) * 2 + (p[0].gather(1, a.argmax(1, keepdim=True))[:, 0] > 0).long()
    frac = torch.bincount(face_id, minlength=6).float() / 2000
    assert (frac - 1 / 6).abs().max() < 0.03


def two_triangles():
    # big (area 2) at z = 0, small (area 0.5) at z = 1: expected fractions 0.8 / 0.2
    verts = torch.tensor([[0, 0, 0], [2, 0, 0], [0, 2, 0], [0, 0, 1], [1, 0, 1], [0, 1, 1]], dtype=torch.float32)
    faces = torch.tensor([[0, 1, 2], [3, 4, 5]])
    return verts, faces


def test_sample_mesh_area_weighted():
    verts, faces = two_triangles()
    n = 20000
    p = sample_points(Meshes.from_list([verts], [faces]), n, generator=torch.Generator().manual_seed(1))[0]
    assert ((p[:, 2] - p[:, 2].round()).abs() < 1e-6).all()  # on one of the two planes
    big = (p[:, 2] < 0.5).float().mean()
    small = 1 - big
    assert abs(big / 0.8 - 1) < 0.05 and abs(small / 0.2 - 1) < 0.05
    # uniform inside a triangle: the mean is the centroid, and points stay inside
    on_big = p[p[:, 2] < 0.5]
    assert (on_big[:, :2].mean(0) - torch.tensor([2 / 3, 2 / 3])).abs().max() < 0.02
    assert (on_big[:, 0] >= -1e-6).all() and (on_big[:, 1] >= -1e-6).all()
    assert (on_big[:, 0] + on_big[:, 1] <= 2 + 1e-5).all()


def test_sample_mesh_batch_each_shape_samples_itself_and_grads_reach_verts():
    verts, faces = two_triangles()
    cube = box_mesh(extents=(1.0, 1.0, 1.0))
    v2 = cube.verts + torch.tensor([10.0, 0, 0])
    meshes = Meshes.from_list([verts, v2], [faces, cube.faces])
    meshes = meshes.with_verts(meshes.verts.clone().requires_grad_(True))
    p = sample_points(meshes, 500, generator=torch.Generator().manual_seed(0))
    assert p.shape == (2, 500, 3)
    assert (p[0, :, 0] <= 2 + 1e-5).all() and (p[1, :, 0] >= 9.5 - 1e-5).all()
    p.sum().backward()
    assert torch.isfinite(meshes.verts.grad).all() and meshes.verts.grad.abs().sum() > 0


@pytest.mark.parametrize("kind", ["mesh", "cloud"])
def test_sample_deterministic_with_generator(kind):
    shapes = box_mesh() if kind == "mesh" else PointClouds.from_list([clouds(1, 500)[0], clouds(1, 30)[0]])
    a = sample_points(shapes, 256, generator=torch.Generator().manual_seed(5))
    b = sample_points(shapes, 256, generator=torch.Generator().manual_seed(5))
    c = sample_points(shapes, 256, generator=torch.Generator().manual_seed(6))
    assert torch.equal(a, b)
    assert not torch.equal(a, c)


def test_sample_cloud_fewer_points_resampled_uniformly():
    pts = torch.arange(12, dtype=torch.float32).reshape(4, 3)
    n = 4 + 40000
    p = sample_points(PointClouds.from_list([pts]), n, generator=torch.Generator().manual_seed(0))
    assert p.shape == (1, n, 3)
    ids = (p[0, :, 0] / 3).long()
    assert torch.equal(p[0], pts[ids])  # only original points
    counts = torch.bincount(ids, minlength=4).float()
    assert (counts >= 1).all()
    assert (counts / (n / 4) - 1).abs().max() < 0.05  # no bias towards the first points


def test_sample_cloud_more_exact_and_dense():
    pts = clouds(1, 500)[0]
    sub = sample_points(PointClouds.from_list([pts]), 100, generator=torch.Generator().manual_seed(0))[0]
    assert len(torch.unique(sub, dim=0)) == 100  # without replacement
    assert (sub[:, None, :] == pts[None]).all(-1).any(1).all()  # rows of the original cloud
    same = sample_points(PointClouds.from_list([pts]), 500)
    assert torch.equal(same[0], pts)
    dense = sample_points(clouds(3, 50), 80, generator=torch.Generator().manual_seed(0))
    assert dense.shape == (3, 80, 3)


def test_sample_empty_shapes():
    pcs = PointClouds.from_list([clouds(1, 10)[0], torch.zeros(0, 3)], names=["chair_0001", "empty_thing"])
    with pytest.raises(ValueError, match="empty_thing"):
        sample_points(pcs, 16)
    p = sample_points(pcs, 16, allow_empty=True)
    assert p.shape == (2, 16, 3) and (p[1] == 0).all() and (p[0] != 0).any()

    verts, faces = two_triangles()
    meshes = Meshes.from_list([verts, verts], [faces, torch.zeros(0, 3, dtype=torch.long)], names=["ok", "no_faces"])
    with pytest.raises(ValueError, match="no_faces"):
        sample_points(meshes, 16)
    p = sample_points(meshes, 16, allow_empty=True)
    assert (p[1] == 0).all() and (p[0, :, 2] >= 0).all()
    with pytest.raises(ValueError, match="n must be"):
        sample_points(pcs, 0)
