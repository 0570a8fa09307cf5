"""scripts/studies/g_capacity.py: the supervised loss is right, and a G trained on it gets closer to the cup axis."""
from __future__ import annotations

import torch

from studies import study

gc = study("g_capacity")


def test_capacity_loss_is_one_minus_the_best_cosine():
    axis = torch.tensor([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    azim = torch.tensor([[0.0, 90.0], [0.0, 180.0]])
    elev = torch.tensor([[90.0, 0.0], [0.0, 0.0]])  # shape 0: view 0 on the axis; shape 1: view 0 on it, view 1 opposite
    views = (azim, elev, torch.full_like(azim, 2.2))
    assert float(gc.capacity_loss(views, axis)) < 1e-6
    views = (azim[:, 1:], elev[:, 1:], torch.full_like(azim[:, 1:], 2.2))
    torch.testing.assert_close(gc.capacity_loss(views, axis), torch.tensor(1.5))  # (1 - 0 + 1 + 1) / 2


def test_a_supervised_g_learns_to_aim(tmp_path):
    res = gc.run(["dataset=synthetic_views", "selector=mvtn_direct", "views=1", "batch_size=8", "seed=0",
                  "dataset.num_per_class=[6,2,2]", "augment.rotate=none", f"dataset.root={tmp_path}",
                  "logger.progress=false"], epochs=6, lr=3e-3, progress=False)
    losses = [h["loss"] for h in res["history"]]
    assert losses[-1] < 0.8 * losses[0] and 0.0 <= res["test_seen"] <= 1.0
