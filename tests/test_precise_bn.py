"""BatchNorm re-estimation before validation (engine/precise_bn.py): the plain average, nothing else moves."""
from __future__ import annotations

import torch
from torch import nn

from mvtn_exp.engine import checkpoint, train
from mvtn_exp.engine.precise_bn import recalibrate

from test_train_e2e import tiny


class _Toy(nn.Module):
    """select / render pass the batch's images through; mvnet: a 1x1 conv and a BatchNorm."""

    def __init__(self):
        super().__init__()
        self.mvnet = nn.Sequential(nn.Conv2d(3, 4, 1), nn.BatchNorm2d(4), nn.Dropout())
        self.selector = nn.BatchNorm1d(2)

    def select(self, batch):
        return (batch["x"],)

    def render(self, batch, x):
        return x


def test_running_stats_are_the_plain_average_of_the_batches():
    torch.manual_seed(0)
    model = _Toy().train()
    model.selector.eval()  # a mixed state must come back as it was
    batches = [{"x": torch.randn(5, 3, 6, 6) * (k + 1) + k} for k in range(4)]
    used = recalibrate(model, batches, 3)
    assert used == 3
    with torch.no_grad():
        feats = [model.mvnet[0](b["x"]) for b in batches[:3]]
    means = torch.stack([f.mean((0, 2, 3)) for f in feats])
    vars_ = torch.stack([f.var((0, 2, 3), unbiased=True) for f in feats])
    bn = model.mvnet[1]
    torch.testing.assert_close(bn.running_mean, means.mean(0))
    torch.testing.assert_close(bn.running_var, vars_.mean(0))
    assert bn.momentum == 0.1 and int(bn.num_batches_tracked) == 3
    assert [m.training for m in model.modules()] == [True, True, True, True, True, False]


def test_only_the_batchnorm_statistics_change_in_a_run(tmp_path):
    """Fixed views (no G): with re-estimation the weights, the training losses and the random
    streams are bit-identical to a run without; C's running statistics are not."""
    cache = str(tmp_path / "cache")
    runs = {}
    for n in (0, 2):
        m = train(tiny(cache, epochs=2, selector={"name": "spherical"}, **{"optim.bn_recalibrate": n}), tmp_path / str(n))
        runs[n] = (m, checkpoint.load(tmp_path / str(n) / "last.pt"))
    (m0, s0), (m2, s2) = runs[0], runs[2]
    assert [h["train_loss"] for h in m0["history"]] == [h["train_loss"] for h in m2["history"]]
    weights = [k for k in s0["model"] if k.startswith("mvnet.") and "running_" not in k and "num_batches" not in k]
    assert weights and all(torch.equal(s0["model"][k], s2["model"][k]) for k in weights)
    stats = [k for k in s0["model"] if k.startswith("mvnet.") and k.endswith("running_mean")]
    assert stats and all(not torch.equal(s0["model"][k], s2["model"][k]) for k in stats)
    assert torch.equal(s0["rng"]["torch"], s2["rng"]["torch"])
