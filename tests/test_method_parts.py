"""Each part of the model zoo against what its method says it does, on cases built so that a
plausible wrong implementation fails (issue 30: ViewGCN's graph, passes, sampling and selection;
DGCNN's dynamic graph; ViT's position embedding; input scaling and weights without classifier)."""
from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from mvtn_exp.models import dgcnn as dgcnn_mod
from mvtn_exp.models.backbones import IMAGENET_MEAN, IMAGENET_STD, build_backbone
from mvtn_exp.models.multiview import build_multiview
from mvtn_exp.models.viewgcn import (LocalGCN, NonLocalMP, ViewGCN, ViewSelector, farthest_views, level_views,
                                     view_directions)


def _ring(m: int) -> torch.Tensor:
    """``[1, m, 3]`` unit directions of m views evenly around the equator."""
    az = torch.arange(m, dtype=torch.float32) * 360.0 / m
    return view_directions(az[None], torch.zeros(1, m))


# --------------------------------------------------------------------------- ViewGCN: sampling

def test_farthest_views_spread_out_and_never_repeat():
    """Each sampled view is one of the farthest from those sampled before it; on a ring of 12, four
    samples are 90 degrees apart (nearest-point sampling repeats views; a wrong update clusters)."""
    torch.manual_seed(0)
    for v in (_ring(12), view_directions(torch.rand(1, 20) * 360, torch.rand(1, 20) * 180 - 90)):
        for random_start in (False, True):
            idx = farthest_views(v, 8, random_start)[0].tolist()
            assert len(set(idx)) == 8
            for i in range(1, 8):
                d = torch.cdist(v[0], v[0, idx[:i]]).amin(1)  # every view's distance to the chosen
                assert d[idx[i]] == pytest.approx(float(d.max()), abs=1e-6), (i, idx)
    for random_start in (False, True):
        az = sorted(i * 30.0 for i in farthest_views(_ring(12), 4, random_start)[0].tolist())
        assert [b - a for a, b in zip(az, az[1:] + [az[0] + 360.0])] == pytest.approx([90.0] * 4)


def test_farthest_views_start_at_random_in_training_only():
    """The official code starts at a random view in training and deterministically at evaluation."""
    v = _ring(12).expand(64, -1, -1)
    torch.manual_seed(0)
    firsts = farthest_views(v, 3, random_start=True)[:, 0]
    assert len(set(firsts.tolist())) >= 6  # 64 draws over 12 views
    fixed = farthest_views(v, 3, random_start=False)[:, 0]
    assert len(set(fixed.tolist())) == 1
    sel = ViewSelector(8, 5, k=3, fps_start="random")
    f = torch.randn(64, 12, 8)
    sel.train()
    torch.manual_seed(1)
    _, v_train, _ = sel(f, v, 3)
    sel.eval()
    _, v_eval1, _ = sel(f, v, 3)
    _, v_eval2, _ = sel(f, v, 3)
    assert torch.equal(v_eval1, v_eval2)
    assert not torch.equal(v_train, v_eval1)
    sel_fixed = ViewSelector(8, 5, k=3, fps_start="fixed").train()
    assert torch.equal(sel_fixed(f, v, 3)[1], sel_fixed(f, v, 3)[1])


@pytest.mark.parametrize("m,want", [(12, (6, 4)), (20, (10, 5)), (8, (4, 2)), (2, (1, 1)), (3, (1, 1))])
def test_level_views_are_the_official_counts(m, want):
    assert level_views(m) == want
    assert level_views(12, (8, 3)) == (8, 3)


def test_viewgcn_keeps_four_views_at_the_last_level_of_twelve():
    """12 views: 6 selected at level 2, 4 at level 3, each with k candidates scored."""
    torch.manual_seed(0)
    net = ViewGCN("small_cnn", num_classes=5, k=4).train()
    images = torch.rand(2, 12, 3, 32, 32)
    views = (torch.arange(12.0).repeat(2, 1) * 30.0, torch.zeros(2, 12), torch.full((2, 12), 2.0))
    net(images, views)
    assert net._aux["scores"].shape == (2, (6 + 4) * 4, 5)


# --------------------------------------------------------------------------- ViewGCN: selection

class _Peaked(nn.Module):
    """Scores = the candidate's features (D = K): a one-hot feature is a confident candidate."""

    def forward(self, x):
        return x


def test_view_selector_keeps_the_most_confident_candidate():
    """Each sampled view is replaced by the candidate whose class scores are most peaked: here the
    neighbour of a sampled view, not the view itself (keeping the least confident candidate, or
    always the first, the sampled view, fails)."""
    m, k_cls = 12, 6
    v = _ring(m)
    centres = farthest_views(v, 4)[0].tolist()
    j = (centres[0] + 1) % m  # a neighbour of the first sampled view, itself not sampled
    assert j not in centres
    f = torch.zeros(1, m, k_cls)  # flat scores: confidence 1/6
    f[0, j, 2] = 8.0
    sel = ViewSelector(k_cls, k_cls, k=3, fps_start="fixed").eval()
    sel.score = _Peaked()
    out_f, out_v, scores = sel(f, v, 4)
    assert scores.shape == (1, 4, 3, k_cls)
    torch.testing.assert_close(out_f[0, 0], f[0, j])
    torch.testing.assert_close(out_v[0, 0], v[0, j])
    torch.testing.assert_close(out_v[0, 1:], v[0, centres[1:]])  # flat candidates: the sampled view itself


# --------------------------------------------------------------------------- ViewGCN: local and non-local passes

def test_local_gcn_reads_only_the_k_nearest_views():
    """LocalGCN: a view's output changes with its neighbours' features and not with a far view's."""
    torch.manual_seed(0)
    g = LocalGCN(8, k=3).eval()
    v = _ring(12)
    f = torch.randn(1, 12, 8)
    base = g(f, v)
    near, far = f.clone(), f.clone()
    near[0, 1] += 5.0  # view 1 is a neighbour of view 0
    far[0, 6] += 5.0   # view 6 is opposite
    assert not torch.allclose(g(near, v)[0, 0], base[0, 0])
    torch.testing.assert_close(g(far, v)[0, 0], base[0, 0])
    # the edge weights depend on the relative positions: moving view 1 (same features) changes view 0
    v2 = view_directions(torch.tensor([[0.0, 40.0] + [i * 30.0 for i in range(2, 12)]]), torch.zeros(1, 12))
    assert not torch.allclose(g(f, v2)[0, 0], base[0, 0])


def test_non_local_message_passing_reads_every_view():
    """NonLocalMP: every view's output depends on every other view's feature, the farthest too."""
    torch.manual_seed(0)
    mp = NonLocalMP(8).eval()
    f = torch.randn(1, 12, 8)
    base = mp(f)
    for j in (1, 6, 11):
        g = f.clone()
        g[0, j] += 3.0
        assert not torch.allclose(mp(g)[0, 0], base[0, 0]), j
    # order-free: permuting the other views leaves view 0's output as it was
    perm = torch.cat([torch.tensor([0]), torch.randperm(11) + 1])
    torch.testing.assert_close(mp(f[:, perm])[0, 0], base[0, 0], rtol=1e-5, atol=1e-5)


# --------------------------------------------------------------------------- DGCNN

def test_dgcnn_rebuilds_the_graph_from_each_layers_features(monkeypatch):
    """The dynamic graph: layer 1 finds neighbours in xyz, layers 2-4 in the previous layer's
    features (a graph built once from xyz fails)."""
    seen = []
    real = dgcnn_mod.knn

    def spy(x, k):
        seen.append(x.shape[1])
        return real(x, k)

    monkeypatch.setattr(dgcnn_mod, "knn", spy)
    net = dgcnn_mod.DGCNN(out_features=4, k=5, emb_dims=16).eval()
    net(torch.randn(2, 30, 3))
    assert seen == [3, 64, 64, 128]


def test_dgcnn_head_is_the_originals():
    """2 emb_dims -> 512 -> 256 -> out, BatchNorm, LeakyReLU and dropout 0.5 after each hidden layer."""
    net = dgcnn_mod.DGCNN(out_features=7, k=4, emb_dims=1024)
    linears = [m for m in net.head if isinstance(m, nn.Linear)]
    assert [(m.in_features, m.out_features) for m in linears] == [(2048, 512), (512, 256), (256, 7)]
    assert [m.p for m in net.head if isinstance(m, nn.Dropout)] == [0.5, 0.5]
    flat = dgcnn_mod.DGCNN(out_features=7, k=4, emb_dims=1024, head_widths=())
    assert [type(m) for m in flat.head] == [nn.Linear]


# --------------------------------------------------------------------------- ViT

def test_vit_position_embedding_is_resampled_not_cropped():
    """A 7 x 7 grid gets the 14 x 14 embedding resampled: a ramp along rows stays a ramp along
    rows, from one edge to the other (cropping the first 49 tokens does not)."""
    net = build_backbone("vit_tiny", 10)
    with torch.no_grad():
        net.pos_embed.zero_()
        net.pos_embed[0, 0] = torch.linspace(-1, 1, 192)  # the class token's own embedding
        ramp = torch.linspace(0, 1, 14)
        grid = net.pos_embed[0, 1:].view(14, 14, -1)
        grid[:, :, 0] = ramp[:, None]  # channel 0: the row
        grid[:, :, 1] = ramp[None, :]  # channel 1: the column
        pos = net.position(7, 7)
    assert pos.shape == (1, 50, 192)
    g = pos[0, 1:].view(7, 7, -1)
    rows, cols = g[:, :, 0], g[:, :, 1]
    assert (rows[1:] - rows[:-1] > 0.05).all() and torch.allclose(rows, rows[:, :1].expand_as(rows), atol=1e-5)
    assert (cols[:, 1:] - cols[:, :-1] > 0.05).all() and torch.allclose(cols, cols[:1].expand_as(cols), atol=1e-5)
    assert rows[0, 0] < 0.1 and rows[-1, 0] > 0.9
    torch.testing.assert_close(pos[0, 0], net.pos_embed[0, 0])  # the class token's own embedding


def test_dino_style_weights_without_classifier_load(tmp_path):
    """A self-supervised ViT checkpoint has no ``head.*`` keys (DINO's, also under ``teacher`` with
    ``backbone.`` prefixes): everything else loads and the head stays fresh."""
    torch.manual_seed(0)
    src = build_backbone("vit_tiny", 1000)
    plain = {k: v for k, v in src.state_dict().items() if not k.startswith("head.")}
    torch.save(plain, tmp_path / "dino_vit_tiny.pth")
    wrapped = {"teacher": {**{f"backbone.{k}": v for k, v in plain.items()},
                           "head.mlp.0.weight": torch.zeros(4, 192), "head.last_layer.weight_g": torch.ones(1)}}
    torch.save(wrapped, tmp_path / "dino_full.pth")
    for name in ("dino_vit_tiny.pth", "dino_full.pth"):
        net = build_backbone("vit_tiny", 5, weights=tmp_path / name)
        assert torch.equal(net.pos_embed, src.pos_embed) and torch.equal(net.blocks[3].attn.qkv.weight,
                                                                          src.blocks[3].attn.qkv.weight)
        assert net.head.out_features == 5
    broken = dict(plain)
    del broken["blocks.2.norm1.weight"]
    torch.save(broken, tmp_path / "broken.pth")
    with pytest.raises(ValueError, match=r"missing keys \(1\): blocks.2.norm1.weight"):
        build_backbone("vit_tiny", 5, weights=tmp_path / "broken.pth")


# --------------------------------------------------------------------------- input scaling

def test_imagenet_normalisation_reaches_the_backbone():
    """``backbone.normalize``: the backbone sees (x - mean) / std per channel with ImageNet's values;
    ``auto`` turns it on only with pretrained weights; the scaling is not in the state_dict."""
    from mvtn_exp.models.backbones import ResNet18Config

    class Probe(nn.Module):
        feature_dim = 3

        def features(self, x):
            self.seen = x
            return x.mean((2, 3))

    net = build_multiview("mvcnn", Probe(), 4).normalize_input(IMAGENET_MEAN, IMAGENET_STD)
    images = torch.full((1, 2, 3, 4, 4), 0.5)
    net(images)
    want = [(0.5 - m) / s for m, s in zip(IMAGENET_MEAN, IMAGENET_STD)]
    assert net.backbone.seen[:, :, 0, 0].tolist() == [pytest.approx(want)] * 2
    assert not any("input_" in k for k in net.state_dict())
    assert ResNet18Config(weights="w.pth").input_norm == "imagenet"
    assert ResNet18Config().input_norm == "none"
    assert ResNet18Config(normalize="imagenet").input_norm == "imagenet"
    with pytest.raises(ValueError, match="backbone.normalize='imgnet'"):
        ResNet18Config(normalize="imgnet").validate()
    raw = build_multiview("mvcnn", Probe(), 4)  # input_norm="none": the renders as they are
    raw(images)
    assert torch.equal(raw.backbone.seen, images.reshape(2, 3, 4, 4))


def test_the_config_build_path_applies_the_scaling():
    from mvtn_exp.models.multiview import MVCNNConfig

    on = MVCNNConfig().build("small_cnn", 4, input_norm="imagenet")
    off = MVCNNConfig().build("small_cnn", 4, input_norm="none")
    assert on.input_mean is not None and off.input_mean is None
    x = torch.rand(1, 2, 3, 16, 16)
    off.load_state_dict(on.state_dict())
    on.eval(), off.eval()
    std = torch.tensor(IMAGENET_STD).view(1, 1, 3, 1, 1)
    torch.testing.assert_close(on(x)[0], off((x - torch.tensor(IMAGENET_MEAN).view(1, 1, 3, 1, 1)) / std)[0])


# --------------------------------------------------------------------------- bounds of the point encoders

def test_point_encoders_take_their_smallest_valid_inputs():
    """DGCNN takes exactly k points (each point its own nearest neighbour counts) and refuses
    k - 1; PointNet and DGCNN give one output feature when asked for one."""
    from mvtn_exp.models.point_encoders import build_point_encoder

    net = dgcnn_mod.DGCNN(out_features=1, k=5, emb_dims=8).eval()
    assert net(torch.randn(2, 5, 3)).shape == (2, 1)
    with pytest.raises(ValueError, match="4 points per shape, fewer than point_encoder.k=5"):
        net(torch.randn(2, 4, 3))
    pn = build_point_encoder("pointnet", out_features=1).eval()
    assert pn(torch.randn(2, 7, 3)).shape == (2, 1)
    with pytest.raises(ValueError, match="out_features must be an integer >= 1"):
        build_point_encoder("pointnet", out_features=0)


# --------------------------------------------------------------------------- transformer blocks against their definition

def _attention(x, w_in, b_in, w_out, b_out, heads):
    """Multi-head self-attention written from its definition: softmax(q k^T / sqrt(d)) v per head."""
    B, T, D = x.shape
    q, k, v = (x @ w_in.T + b_in).split(D, dim=-1)
    split = lambda t: t.view(B, T, heads, D // heads).transpose(1, 2)  # noqa: E731
    q, k, v = split(q), split(k), split(v)
    a = torch.softmax(q @ k.transpose(-1, -2) / math.sqrt(D // heads), dim=-1) @ v
    return a.transpose(1, 2).reshape(B, T, D) @ w_out.T + b_out


def _pre_norm_block(x, norm1, attn, norm2, mlp):
    x = x + attn(norm1(x))
    return x + mlp(norm2(x))


def test_view_transformer_block_is_a_pre_norm_block():
    from mvtn_exp.models.view_transformer import ViewBlock

    torch.manual_seed(0)
    blk = ViewBlock(16, heads=4).eval()
    x = torch.randn(3, 5, 16)
    a = blk.attn
    want = _pre_norm_block(x, blk.norm1, lambda h: _attention(h, a.in_proj_weight, a.in_proj_bias, a.out_proj.weight,
                                                             a.out_proj.bias, 4), blk.norm2, blk.mlp)
    torch.testing.assert_close(blk(x), want, rtol=1e-5, atol=1e-5)


def test_vit_is_timms_forward():
    """Class token first, position embedding added, pre-norm blocks, final norm, class token out;
    the resampled embedding is bicubic with align_corners=False (timm's), exact on a linear ramp."""
    torch.manual_seed(0)
    net = build_backbone("vit_tiny", 10).eval()
    x = torch.rand(2, 3, 32, 48)
    with torch.no_grad():
        tok = torch.cat([net.cls_token.expand(2, -1, -1), net.patch_embed(x)], 1) + net.position(2, 3)
        for b in net.blocks:
            a = b.attn
            tok = _pre_norm_block(tok, b.norm1, lambda h, a=a: _attention(h, a.qkv.weight, a.qkv.bias, a.proj.weight,
                                                                         a.proj.bias, 3), b.norm2, b.mlp)
        torch.testing.assert_close(net.features(x), net.norm(tok)[:, 0], rtol=1e-4, atol=1e-4)
        net.pos_embed.zero_()
        net.pos_embed[0, 1:].view(14, 14, -1)[:, :, 0] = torch.arange(14.0)[:, None]
        rows = net.position(7, 7)[0, 1:].view(7, 7, -1)[:, 0, 0]
    # output row i samples input row 2 i + 0.5 (align_corners=False); rows 1-5 have all four taps inside
    torch.testing.assert_close(rows[1:6], torch.tensor([2.5, 4.5, 6.5, 8.5, 10.5]), rtol=0, atol=1e-4)


def test_viewgcn_level_views_up_to_m_are_taken_and_more_refused(tmp_path):
    from mvtn_exp.engine.trainer import as_config

    from conftest import tiny_config

    ok = as_config(tiny_config(str(tmp_path), views=4, **{"mvnet.name": "viewgcn", "mvnet.level_views": [4, 2]}))
    assert ok.mvnet.level_views == [4, 2]
    with pytest.raises(ValueError, match=r"mvnet.level_views=\[5, 2\]: level 2 cannot keep more than views=4"):
        as_config(tiny_config(str(tmp_path), views=4, **{"mvnet.name": "viewgcn", "mvnet.level_views": [5, 2]}))
    with pytest.raises(ValueError, match=r"mvnet.level_views=\[2, 3\]"):
        as_config(tiny_config(str(tmp_path), views=4, **{"mvnet.name": "viewgcn", "mvnet.level_views": [2, 3]}))


def test_viewgcn_takes_two_views_and_refuses_one(tmp_path):
    from mvtn_exp.engine.trainer import as_config

    from conftest import tiny_config

    assert as_config(tiny_config(str(tmp_path), views=2, **{"mvnet.name": "viewgcn"})).views == 2
    with pytest.raises(ValueError, match="views=1: mvnet=viewgcn builds a graph over the views and needs views >= 2"):
        as_config(tiny_config(str(tmp_path), views=1, **{"mvnet.name": "viewgcn"}))
