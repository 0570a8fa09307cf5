"""selector.grad=search: candidates, the nearest-view assignment of targets, and G pulled to the best view."""
from __future__ import annotations

import json

import pytest
import torch

from mvtn_exp.runtime import checkpoint
from mvtn_exp.engine import train
from mvtn_exp.model import build_mvtn
from mvtn_exp.engine.trainer import as_config
from mvtn_exp.selectors.strategies import search
from mvtn_exp.selectors.strategies.search import candidates, targets, to_angles, unit_directions

from conftest import tiny_config


def test_candidates_cover_the_sphere_and_turn_with_the_generator():
    a, e, d = candidates(12, 3, 2.2, torch.Generator().manual_seed(0), "cpu")
    assert a.shape == (3, 12) and torch.equal(a[0], a[2]) and torch.all(d == 2.2)
    dirs = unit_directions(a[0].double(), e[0].double())
    assert dirs.mean(0).norm() < 0.25  # spread all round
    b, f, _ = candidates(12, 3, 2.2, torch.Generator().manual_seed(1), "cpu")
    assert not torch.allclose(a, b)
    again = to_angles(unit_directions(a, e))
    torch.testing.assert_close(again[1], e, atol=1e-4, rtol=0)


def test_each_view_targets_the_best_candidate_nearest_to_it():
    up, down, x, z = (torch.tensor(v, dtype=torch.float64) for v in ([0, 1, 0], [0, -1, 0], [1, 0, 0], [0, 0, 1]))
    views = torch.stack([up, down])[None]  # one shape, M = 2: looking from above and from below
    cand = torch.stack([up, down, torch.nn.functional.normalize(up + 0.5 * x, dim=0),
                        torch.nn.functional.normalize(down + 0.5 * z, dim=0), x])[None]
    scores = torch.tensor([[0.5, 0.9, 0.1, 0.3, 0.0]])
    t = targets(views, cand, scores)
    # x (score 0.0) is 90 deg from both views: the first (upper) view owns it
    torch.testing.assert_close(t[0, 0], x)
    torch.testing.assert_close(t[0, 1], cand[0, 3])  # below: the best of {down, down + z}
    one = targets(up[None, None], cand, scores)  # M = 1: the best of all
    torch.testing.assert_close(one[0, 0], x)


def test_g_follows_the_search_to_the_best_direction(tmp_path, monkeypatch):
    """With C's score replaced by the angle to +Y (lowest straight above), G's single view climbs."""
    def score(self, model, batch, views, labels):
        return -unit_directions(views[0], views[1])[..., 1]

    monkeypatch.setattr(search.Search, "score", score)
    cfg = tiny_config(str(tmp_path / "cache"), **{"selector.name": "mvtn_spherical", "selector.grad": "search",
                                                  "selector.lr": 0.05, "views": 1, "epochs": 3, "image_size": 16,
                                                  "dataset.num_per_class": [6, 1, 1]})
    metrics = train(cfg, tmp_path / "run")
    offset = json.loads((tmp_path / "run" / "metrics.json").read_text())["test_view_offset_elev"]
    state = checkpoint.load(tmp_path / "run" / "best.pt")
    model = build_mvtn(as_config(state["config"]), len(metrics["classes"]))
    model.load_state_dict(state["model"])
    points = torch.randn(6, 256, 3, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        elev = model.eval().select({"points": points})[1]
    assert offset > 20 and elev.min() > 20, (offset, elev)  # from elevation 0 (the layout) upwards
    assert metrics["steps"] > 0


def test_search_is_validated():
    base = {"selector.name": "mvtn_spherical", "selector.grad": "search"}
    with pytest.raises(ValueError, match="selector.flip_explore"):
        as_config(tiny_config("/tmp/x", **base, **{"selector.flip_explore": 0.2}))
    with pytest.raises(ValueError, match="selector.search_views"):
        as_config(tiny_config("/tmp/x", **base, **{"selector.search_views": 0}))
    with pytest.raises(ValueError, match="choose one way"):
        as_config(tiny_config("/tmp/x", **{"selector.name": "poi", "selector.grad": "search", "selector.hypotheses": 4,
                                           "selector.race_epochs": 8}))
    as_config(tiny_config("/tmp/x", **base, **{"selector.loss": "centered_logit"}))  # allowed with search
