import math

import torch

from mvtn_exp.render.view_stats import view_stats
from mvtn_exp.render import layouts
from mvtn_exp.selectors.fixed import random_directions


def test_fixed_layout_has_no_spread_and_its_own_separation():
    azim, elev, _ = layouts.circular(4, batch=5, elevation=0.0)
    s = view_stats(azim, elev)
    assert abs(s["view_spread"]) < 1e-6
    assert math.isclose(s["view_separation"], 90.0, abs_tol=1e-6)  # four views 90 deg apart on the equator


def test_collapsed_views_and_the_pole():
    # two views at the north pole with different azimuths are one camera: separation 0
    azim, elev = torch.tensor([[0.0, 123.0], [50.0, 270.0]]), torch.full((2, 2), 90.0)
    s = view_stats(azim, elev)
    assert s["view_separation"] < 1e-6 and s["view_spread"] < 1e-6


def test_spread_of_per_shape_views():
    # two shapes, one slot: cameras 60 deg apart on the equator -> each 30 deg from their mean
    s = view_stats(torch.tensor([[0.0], [60.0]]), torch.zeros(2, 1))
    assert math.isclose(s["view_spread"], 30.0, abs_tol=1e-6) and s["view_separation"] is None
    # uniform random directions: the mean angle to any fixed direction is 90 deg
    a, e = random_directions((20000, 1), torch.Generator().manual_seed(0))
    assert abs(view_stats(a.float(), e.float())["view_spread"] - 90.0) < 2.0
    # opposite cameras cancel: no mean direction, counted as 90 deg, finite
    s = view_stats(torch.tensor([[0.0], [180.0]]), torch.zeros(2, 1))
    assert s["view_spread"] == 90.0


def test_empty():
    assert view_stats(torch.zeros(0, 3), torch.zeros(0, 3)) == {"view_spread": 0.0, "view_separation": None}
