"""The cost block of metrics.json (engine/cost.py): FLOPs and parameters against hand counts, and a real run's record."""
from __future__ import annotations

import math

import torch
from torch import nn

from mvtn_exp.engine import cost

from test_train_e2e import cache, full_run  # noqa: F401  (fixtures)


class _Stub(nn.Module):
    """select: a Linear(6, 4) on the flattened first two points; mvnet: a Linear(12, 5) on the images."""

    def __init__(self):
        super().__init__()
        self.g, self.c = nn.Linear(6, 4), nn.Linear(12, 5)

    def select(self, batch, refine=True):
        v = self.g(batch["points"][:, :2].flatten(1))
        return v[:, :2], v[:, 2:], torch.full_like(v[:, :2], 2.2)

    def render(self, batch, azim, elev, dist):
        return torch.ones(len(azim), 12)

    def mvnet_forward(self, images, views, batch=None):
        return self.mvnet(images, views)

    def mvnet(self, images, views=None):
        return self.c(images), None

    def parameter_groups(self):
        return {"mvnet": list(self.c.parameters()), "selector": list(self.g.parameters())}


def test_flops_and_parameters_match_hand_counts():
    model = _Stub().train()
    batch = {"points": torch.randn(3, 10, 3), "labels": torch.zeros(3, dtype=torch.long)}
    flops = cost.flops_per_shape(model, batch)
    assert flops == {"flops_selector_per_shape": 2 * 6 * 4, "flops_mvnet_per_shape": 2 * 12 * 5}
    assert model.training  # the mode comes back as it was
    assert cost.parameter_counts(model) == {"params_mvnet": 12 * 5 + 5, "params_selector": 6 * 4 + 4}


def test_peak_memory_sees_a_large_allocation():
    with cost.peak_memory("cpu") as m:
        x = torch.ones(64 << 20, dtype=torch.uint8)  # 64 MiB, touched
        del x
    assert m.peak_mib > 48 and cost.peak_total_mib(m) >= m.peak_mib + m.baseline_mib - 1e-6


def test_every_run_records_its_cost(full_run):
    """``full_run``: the tiny run of test_train_e2e (mvtn_spherical, M = 2, 32 px)."""
    run, m = full_run
    c = m["cost"]
    for key in ("train_seconds_per_shape", "infer_ms_per_shape", "train_peak_mib", "infer_peak_mib",
                "flops_selector_per_shape", "flops_mvnet_per_shape", "render_ms_per_shape"):
        assert math.isfinite(c[key]) and c[key] > 0, key
    assert c["render_pixels_per_shape"] == 2 * 32 * 32
    assert c["memory_method"].startswith("rss")
    state = torch.load(run / "best.pt", weights_only=True)["model"]
    n_c = sum(v.numel() for k, v in state.items() if k.startswith("mvnet.") and "running_" not in k
              and "num_batches" not in k)
    assert c["params_mvnet"] == n_c
    # training time per shape covers the training passes only, inside the epochs' wall time
    shapes = len(m["history"]) * 48
    assert c["train_seconds_per_shape"] * shapes <= sum(m["epoch_seconds"]) + 1e-6
