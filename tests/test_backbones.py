import math

import pytest
import torch
import torch.nn.functional as F

from mvtn_exp.config.options import OPTIONS, load
from mvtn_exp.models.backbones import SmallCNN, build_backbone, resnet18, resnet34, resnet50, resnet101, small_cnn

load("backbone")


def n_params(model):
    return sum(p.numel() for p in model.parameters())


@pytest.mark.parametrize("ctor,expected", [(resnet18, 11_689_512), (resnet34, 21_797_672),
                                           (resnet50, 25_557_032), (resnet101, 44_549_160)])
def test_param_count_matches_torchvision(ctor, expected):
    assert n_params(ctor(num_classes=1000)) == expected


RESNET18_KEYS = {
    "conv1.weight": (64, 3, 7, 7),
    "bn1.running_mean": (64,),
    "layer1.0.conv1.weight": (64, 64, 3, 3),
    "layer1.1.bn2.bias": (64,),
    "layer2.0.conv1.weight": (128, 64, 3, 3),
    "layer2.0.downsample.0.weight": (128, 64, 1, 1),
    "layer2.0.downsample.1.weight": (128,),
    "layer3.1.conv2.weight": (256, 256, 3, 3),
    "layer4.1.bn2.running_var": (512,),
    "layer4.1.bn2.num_batches_tracked": (),
    "fc.weight": (1000, 512),
    "fc.bias": (1000,),
}
RESNET50_KEYS = {
    "conv1.weight": (64, 3, 7, 7),
    "layer1.0.conv1.weight": (64, 64, 1, 1),
    "layer1.0.conv2.weight": (64, 64, 3, 3),
    "layer1.0.conv3.weight": (256, 64, 1, 1),
    "layer1.0.downsample.0.weight": (256, 64, 1, 1),
    "layer1.0.downsample.1.running_mean": (256,),
    "layer2.0.conv1.weight": (128, 256, 1, 1),
    "layer3.5.bn3.weight": (1024,),
    "layer4.2.conv3.weight": (2048, 512, 1, 1),
    "fc.weight": (1000, 2048),
}


@pytest.mark.parametrize("ctor,keys,absent", [
    (resnet18, RESNET18_KEYS, ["layer1.0.downsample.0.weight", "layer1.2.conv1.weight", "layer1.0.conv3.weight"]),
    (resnet34, {**RESNET18_KEYS, "layer3.5.conv2.weight": (256, 256, 3, 3), "layer4.2.bn1.weight": (512,)},
     ["layer3.6.conv1.weight", "layer4.3.conv1.weight", "layer2.1.downsample.0.weight"]),
    (resnet50, RESNET50_KEYS, ["layer3.6.conv1.weight", "layer4.3.conv1.weight"]),
])
def test_torchvision_key_names_and_shapes(ctor, keys, absent):
    sd = ctor(num_classes=1000).state_dict()
    for k, shape in keys.items():
        assert k in sd, k
        assert tuple(sd[k].shape) == shape, k
    for k in absent:
        assert k not in sd, k


def test_resnet50_stride_on_3x3_and_feature_dims():
    m = resnet50()
    assert m.layer2[0].conv1.stride == (1, 1) and m.layer2[0].conv2.stride == (2, 2)  # torchvision v1.5
    assert m.feature_dim == 2048 and resnet18().feature_dim == 512 and resnet34().feature_dim == 512


def test_init_matches_torchvision():
    m = resnet18()
    w = m.layer4[0].conv1.weight  # [512, 256, 3, 3], fan_out = 512 * 9
    assert abs(w.std().item() / math.sqrt(2.0 / (512 * 9)) - 1) < 0.05
    for bn in (m.bn1, m.layer3[1].bn2):
        assert torch.all(bn.weight == 1) and torch.all(bn.bias == 0)


def _save(obj, path):
    torch.save(obj, path)
    return path


@pytest.mark.parametrize("name", ["resnet18", "small_cnn"])
@pytest.mark.parametrize("wrap", [None, "state_dict", "model"])
def test_roundtrip_identical_outputs(tmp_path, name, wrap):
    torch.manual_seed(0)
    src = build_backbone(name, num_classes=10)
    src.train()(torch.randn(4, 3, 64, 64))  # make running stats non-trivial
    src.eval()
    sd = src.state_dict()
    path = _save(sd if wrap is None else {wrap: sd, "epoch": 3}, tmp_path / "w.pth")
    torch.manual_seed(1)
    dst = build_backbone(name, num_classes=10, weights=path).eval()
    x = torch.randn(2, 3, 64, 64)
    with torch.no_grad():
        assert torch.equal(src(x), dst(x))


def test_old_file_without_num_batches_tracked_loads(tmp_path):
    src = resnet18(num_classes=5).eval()
    sd = {k: v for k, v in src.state_dict().items() if not k.endswith("num_batches_tracked")}
    dst = resnet18(num_classes=5, weights=_save(sd, tmp_path / "old.pth")).eval()
    x = torch.randn(1, 3, 32, 32)
    with torch.no_grad():
        assert torch.equal(src(x), dst(x))


def test_different_num_classes_loads_trunk_keeps_fresh_fc(tmp_path):
    torch.manual_seed(0)
    src = resnet18(num_classes=1000).eval()
    path = _save(src.state_dict(), tmp_path / "imagenet.pth")
    torch.manual_seed(1)
    fresh = resnet18(num_classes=7)
    torch.manual_seed(1)
    dst = resnet18(num_classes=7, weights=path).eval()
    assert dst.fc.weight.shape == (7, 512) and dst.fc.bias.shape == (7,)
    assert torch.equal(dst.fc.weight, fresh.fc.weight)  # head untouched by loading
    for k, v in src.state_dict().items():
        if not k.startswith("fc."):
            assert torch.equal(dst.state_dict()[k], v), k
    x = torch.randn(2, 3, 64, 64)
    with torch.no_grad():
        assert torch.equal(src.features(x), dst.features(x))
        assert dst(x).shape == (2, 7)


def test_wrong_key_error_names_file_and_key(tmp_path):
    sd = resnet18(num_classes=10).state_dict()
    sd["layer1.0.conv1.weigth"] = sd.pop("layer1.0.conv1.weight")
    path = _save(sd, tmp_path / "broken.pth")
    with pytest.raises(ValueError) as ei:
        resnet18(num_classes=10, weights=path)
    msg = str(ei.value)
    assert str(path) in msg and "layer1.0.conv1.weight" in msg and "layer1.0.conv1.weigth" in msg


def test_shape_mismatch_and_wrong_architecture_errors(tmp_path):
    path = _save(resnet18(num_classes=10).state_dict(), tmp_path / "r18.pth")
    with pytest.raises(ValueError, match="conv1.weight") as ei:
        resnet18(num_classes=10, weights=path, in_channels=1)
    assert str(path) in str(ei.value)
    with pytest.raises(ValueError, match=r"\(\+\d+ more\)") as ei:  # long key lists are truncated
        resnet50(num_classes=10, weights=path)
    assert str(path) in str(ei.value)


def test_missing_and_unreadable_files(tmp_path):
    missing = tmp_path / "nope.pth"
    with pytest.raises(FileNotFoundError, match="nope.pth"):
        resnet18(weights=missing)
    junk = tmp_path / "junk.pth"
    junk.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="junk.pth"):
        resnet18(weights=junk)
    notsd = _save([1, 2, 3], tmp_path / "list.pth")
    with pytest.raises(ValueError, match="list.pth"):
        resnet18(weights=notsd)


@pytest.mark.parametrize("name", sorted(OPTIONS["backbone"]))
def test_forward_backward_every_backbone(name):
    torch.manual_seed(0)
    model = build_backbone(name, num_classes=10).train()
    x = torch.randn(2, 3, 64, 64)
    feats = model.features(x)
    assert feats.shape == (2, model.feature_dim)
    out = model(x)
    assert out.shape == (2, 10)
    F.cross_entropy(out, torch.tensor([1, 7])).backward()
    for pname, p in model.named_parameters():
        assert p.grad is not None, pname
        assert torch.isfinite(p.grad).all(), pname
    first_conv = next(p for p in model.parameters() if p.dim() == 4)  # gradient reaches the stem (ViT: patches)
    assert first_conv.shape[1] == 3 and first_conv.grad.abs().sum() > 0


def test_small_cnn_sizes():
    m = SmallCNN(num_classes=4, in_channels=1, width=8).eval()
    assert m.feature_dim == 64
    with torch.no_grad():
        assert m(torch.randn(3, 1, 16, 16)).shape == (3, 4)
        assert m(torch.randn(1, 1, 16, 45)).shape == (1, 4)
        with pytest.raises(ValueError, match="16"):
            m(torch.randn(1, 1, 15, 32))
        with pytest.raises(ValueError, match=r"\[N, 1, H, W\]"):
            m(torch.randn(1, 3, 32, 32))
    assert small_cnn(num_classes=3).feature_dim == 256


def test_unknown_name_lists_allowed():
    with pytest.raises(ValueError) as ei:
        build_backbone("resnet152", num_classes=10)
    msg = str(ei.value)
    assert "resnet152" in msg
    for name in ("resnet18", "resnet34", "resnet50", "small_cnn"):
        assert name in msg
    assert set(OPTIONS["backbone"]) == {"resnet18", "resnet34", "resnet50", "resnet101", "small_cnn", "vit_tiny", "vit_small",
                                       "vit_base"}
