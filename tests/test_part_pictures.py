"""Part labels as pictures: distinct colours, the label grid's layout, and a depth-tested cloud."""
from __future__ import annotations

import numpy as np
import torch

from mvtn_exp.viz import parts


def test_fifty_parts_get_fifty_distinct_colours_and_the_background_is_white():
    colours = parts.palette(50)
    gaps = np.linalg.norm(colours[:, None] - colours[None], axis=-1) + np.eye(50) * 9
    assert gaps.min() > 0.03 and ((colours >= 0) & (colours <= 1)).all()
    # one category's parts are consecutive ids (at most 6): those differ clearly (0.26 here)
    assert min(gaps[i:i + 6, i:i + 6].min() for i in range(45)) > 0.2
    assert parts.part_colors(torch.tensor([-1, 3]), 50).tolist() == [[1.0, 1.0, 1.0], colours[3].tolist()]


def test_the_label_grid_puts_predictions_above_the_truth_view_by_view():
    pred = torch.zeros(3, 4, 5, dtype=torch.long)
    true = torch.full((3, 4, 5), -1)
    pred[1] = 2
    grid = parts.label_views(pred, true, 5, pad=2)
    assert grid.shape == (2 * 4 + 2, 3 * 5 + 2 * 2, 3) and grid.dtype == np.uint8
    expect = lambda label: np.round(parts.part_colors(np.array(label), 5) * 255).astype(np.uint8)
    assert (grid[0, 0] == expect(0)).all() and (grid[0, 7] == expect(2)).all()  # row 1: predicted, view 2 says 2
    assert (grid[6, 0] == 255).all()  # row 2: the truth, background


def test_a_nearer_point_hides_a_farther_one_in_the_cloud_picture():
    points = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1.0, 1.0, 0.0], [-1.0, -1.0, 0.0]])
    labels = np.array([0, 1, 2, 2])
    front = parts.points_image(points, labels, 3, size=64, azim=0.0, elev=0.0, radius=2)  # camera on +z
    back = parts.points_image(points, labels, 3, size=64, azim=180.0, elev=0.0, radius=2)
    c = lambda label: np.round(parts.palette(3)[label] * 255).astype(np.uint8)
    assert (front[32, 32] == c(0)).all() and (back[32, 32] == c(1)).all()
    assert (front == 255).all(-1).mean() > 0.9  # the rest is background
