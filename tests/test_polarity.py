"""Per-view polarity (selectors/polarity.py): antipodes, exploration flips, the decision rule, and its place in training."""
from __future__ import annotations

import torch

from mvtn_exp.runtime import checkpoint
from mvtn_exp.engine import train
from mvtn_exp.selectors.polarity import ViewPolarity, antipode

from test_train_e2e import tiny


def direction(azim, elev):
    a, e = torch.deg2rad(azim), torch.deg2rad(elev)
    return torch.stack([torch.cos(e) * torch.sin(a), torch.sin(e), torch.cos(e) * torch.cos(a)], -1)


def test_antipode_is_the_opposite_direction_and_differentiable():
    azim = torch.tensor([-180.0, -90.0, 0.0, 37.5, 179.9, 400.0], requires_grad=True)
    elev = torch.tensor([0.0, 90.0, -90.0, 12.0, -45.0, 30.0], requires_grad=True)
    a, e = antipode(azim, elev)
    torch.testing.assert_close(direction(a, e), -direction(azim, elev), atol=1e-6, rtol=0)
    assert bool(((a >= -180) & (a < 180)).all())
    (a.sum() + 2 * e.sum()).backward()
    assert torch.equal(azim.grad, torch.ones(6)) and torch.equal(elev.grad, -2 * torch.ones(6))


def test_forward_turns_only_flipped_views_and_explore_flips_its_share():
    pol = ViewPolarity(3)
    views = (torch.zeros(4, 3), torch.full((4, 3), 30.0), torch.full((4, 3), 2.2))
    assert all(torch.equal(x, y) for x, y in zip(pol(views), views))
    pol.flipped[1] = True
    a, e, d = pol(views)
    assert torch.equal(a[:, 1], torch.full((4,), -180.0)) and torch.equal(e[:, 1], torch.full((4,), -30.0))
    assert torch.equal(a[:, [0, 2]], views[0][:, [0, 2]]) and torch.equal(d, views[2])
    same, mask = pol.explore(views, 0.0, torch.Generator().manual_seed(0))
    assert not mask.any() and all(torch.equal(x, y) for x, y in zip(same, views))
    big = (torch.zeros(2000, 3), torch.full((2000, 3), 30.0), torch.full((2000, 3), 2.2))
    (a, e, _), mask = pol.explore(big, 0.3, torch.Generator().manual_seed(0))
    assert abs(float(mask.float().mean()) - 0.3) < 0.03
    assert torch.equal(e[mask], torch.full((int(mask.sum()),), -30.0)) and torch.equal(e[~mask], big[1][~mask])


def test_decide_turns_a_view_only_when_its_antipode_wins_beyond_the_noise():
    g = torch.Generator().manual_seed(0)
    pol = ViewPolarity(3)
    for _ in range(20):
        mask = torch.rand(16, 3, generator=g) < 0.5
        # view 0's flip lowers the loss by 0.5; view 1's raises it; view 2's does nothing
        loss = 2.0 + 0.1 * torch.randn(16, generator=g) - 0.5 * mask[:, 0].float() + 0.5 * mask[:, 1].float()
        pol.record(loss, mask)
    assert pol.stats[0].sum() == 20 * 16 * 3
    assert pol.decide() == [0]
    assert pol.flipped.tolist() == [True, False, False] and not pol.stats.any()
    pol.record(torch.tensor([0.0, 5.0]), torch.tensor([[True, True, True], [False, False, False]]))
    assert pol.decide() == [] and pol.flipped.tolist() == [True, False, False]  # too few shapes to decide


def test_exploring_run_records_polarity_and_resumes_exactly(tmp_path):
    cache = str(tmp_path / "cache")
    kw = {"selector.flip_explore": 0.5, "selector.flip_epochs": 1}
    full = train(tiny(cache, epochs=2, **kw), tmp_path / "full")
    assert all(len(h["views_flipped"]) == 2 for h in full["history"])
    state = checkpoint.load(tmp_path / "full" / "last.pt")
    assert "polarity.flipped" in state["model"] and not state["model"]["polarity.stats"].any()
    train(tiny(cache, epochs=1, **kw), tmp_path / "a")
    resumed = train(tiny(cache, epochs=2, ckpt_path=str(tmp_path / "a" / "last.pt"), **kw), tmp_path / "b")
    assert resumed["confusion_matrix"] == full["confusion_matrix"]
    for h_a, h_b in zip(resumed["history"], full["history"], strict=True):
        assert abs(h_a["train_loss"] - h_b["train_loss"]) <= 1e-6
    # without exploration the training losses differ: the flips reach C's inputs
    plain = train(tiny(cache, epochs=1), tmp_path / "plain")
    assert abs(plain["history"][0]["train_loss"] - full["history"][0]["train_loss"]) > 1e-6
