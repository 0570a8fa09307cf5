"""The 2D segmentation networks: DeepLabV3 as torchvision builds it (parameter counts of its
published models, output stride 8, the ResNet's keys kept for ImageNet weights) and the small FCN."""
from __future__ import annotations

import pytest
import torch

from mvtn_exp.config.options import OPTIONS, load
from mvtn_exp.models import backbones
from mvtn_exp.models.segnets import DeepLabV3, SmallFCN

load()


def _params(net: torch.nn.Module) -> int:
    return sum(p.numel() for p in net.parameters())


@pytest.mark.parametrize("layers,expected", [([3, 4, 6, 3], 42_004_074),
                                             pytest.param([3, 4, 23, 3], 60_996_202, marks=pytest.mark.slow)])
def test_deeplabv3_has_the_parameters_of_torchvisions_published_models(layers, expected):
    """torchvision's deeplabv3_resnet50 / _resnet101 with the auxiliary head, 21 classes (the
    paper's MVPartSeg DeepLabV3: 61 M)."""
    net = DeepLabV3(backbones.ResNet(backbones.Bottleneck, layers), 21, aux=True)
    assert _params(net) == expected


def test_deeplabv3_keeps_the_resnets_keys_and_sees_at_output_stride_8():
    plain = backbones.resnet50()
    net = DeepLabV3(backbones.resnet50(), 5, aux=True).train()
    own = net.backbone.state_dict()
    assert {k: v.shape for k, v in own.items()} == {k: v.shape for k, v in plain.state_dict().items()
                                                    if not k.startswith("fc.")}
    seen = {}
    net.backbone.layer4.register_forward_hook(lambda m, i, o: seen.update(layer4=o.shape))
    out = net(torch.rand(2, 3, 64, 48))
    assert out.shape == (2, 5, 64, 48) and seen["layer4"][-2:] == (8, 6)
    assert net.aux_logits.shape == (2, 5, 64, 48)
    net.eval()
    with torch.no_grad():
        net(torch.rand(1, 3, 32, 32))
    assert net.aux_logits is None


def test_the_small_fcn_maps_any_size_to_per_pixel_logits_and_learns():
    torch.manual_seed(0)
    net = SmallFCN(3, width=8)
    for size in ((32, 32), (33, 47), (1, 1)):
        assert net.eval()(torch.rand(2, 3, *size)).shape == (2, 3, *size)
    x = torch.rand(4, 3, 24, 24)
    target = (x[:, 0] > 0.5).long() + (x[:, 1] > 0.5).long()  # a per-pixel rule of the input
    opt = torch.optim.Adam(net.parameters(), 1e-2)
    net.train()
    losses = []
    for _ in range(40):
        loss = torch.nn.functional.cross_entropy(net(x), target)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0]  # (0.26 after 40 steps on this machine)


@pytest.mark.parametrize("name", sorted(OPTIONS["segnet"]))
def test_every_segnet_option_builds_from_its_config(name):
    cfg = OPTIONS["segnet"][name]().validate()
    net = cfg.build(4, backbone="resnet18").eval()
    with torch.no_grad():
        assert net(torch.rand(1, 3, 32, 32)).shape == (1, 4, 32, 32)


def test_deeplabv3_refuses_a_backbone_that_is_no_resnet():
    with pytest.raises(ValueError, match="needs a ResNet backbone"):
        OPTIONS["segnet"]["deeplabv3"]().build(4, backbone="small_cnn")


def test_the_small_fcns_stages_and_depth_shape_the_network_and_keep_the_default():
    """``stages`` downsamplings (the bottleneck at 1 / 2**stages of the input), ``depth`` conv layers
    per stage (the extra ones residual); the defaults give the original network's keys."""
    base = SmallFCN(5, width=8)
    assert [k for k in base.state_dict() if k.endswith("weight")][:3] == ["stem.0.weight", "stem.1.weight",
                                                                          "down.0.1.0.weight"]
    seen = {}
    deep = SmallFCN(5, width=8, stages=3, depth=3)
    deep.context.register_forward_hook(lambda m, i, o: seen.update(context=o.shape))
    assert deep.eval()(torch.rand(2, 3, 64, 40)).shape == (2, 5, 64, 40)
    assert seen["context"] == (2, 64, 8, 5)  # 8 * 2**3 channels at 64 / 8 by ceil(40 / 8)
    convs = lambda net: sum(isinstance(m, torch.nn.Conv2d) for m in net.modules())
    assert convs(base) == 1 + 2 + 1 + 2 + 1  # stem, 2 stages, context, 2 decoder steps, classifier
    assert convs(deep) == 3 * (1 + 3 + 1 + 3) + 1
    residual = deep.down[0][1][1]
    with torch.no_grad():
        for p in residual.f.parameters():
            p.zero_()  # f(x) = relu(bn(0)) = 0: a residual layer passes its input through
        x = torch.rand(1, 16, 6, 6)
        assert torch.equal(residual.eval()(x), x)


@pytest.mark.parametrize("key", ["width", "stages", "depth"])
def test_the_small_fcn_refuses_a_size_below_one(key):
    with pytest.raises(ValueError, match=f"segnet.{key}"):
        OPTIONS["segnet"]["fcn_small"](**{key: 0}).validate()
