"""scripts/studies/poi_oracle.py: the in-cup labels are right, perfect scores aim at the detail, and the study runs."""
from __future__ import annotations

import torch

from studies import study

po = study("poi_oracle")


def test_in_detail_cup_is_the_cylinder_of_the_cup():
    pts = torch.tensor([[[0.0, 0.0, 0.5], [0.0, 0.0, 1.5], [2.0, 0.0, 0.5], [0.0, 0.0, -0.5], [0.9, 0.0, 0.9]]])
    inside = po.in_detail_cup(pts, [[0.0, 0.0, 0.0]], [[0.0, 0.0, 1.0]], [[1.0, 1.0, 0.5]])
    assert inside.tolist() == [[True, False, False, False, True]]


def test_scores_that_know_the_cup_aim_at_the_detail_and_uniform_ones_do_not(tmp_path):
    P, D, y, frame = po.load(str(tmp_path), "decoys", "val", 0, (2, 2, 2), 1024)
    assert D.shape[:2] == y.shape == P.shape[:2] and bool(y.any(1).all())  # every shape has points in its cup
    perfect = po.view_share(y.float(), P, frame, 0.05)
    uniform = po.view_share(torch.ones_like(y, dtype=torch.float32), P, frame, 0.05)
    assert perfect >= 0.9 and perfect > uniform + 0.3


def test_the_study_prints_a_row_per_descriptor_set(tmp_path):
    rows = po.run(str(tmp_path), "decoys", 128, num_per_class=(2, 2, 2))
    assert [r["descriptors"] for r in rows][:2] == ["all", "all but radius"] and len(rows) == 7
    assert all(0.0 <= r["seen"] <= 1.0 and 0.0 <= r["top_in_cup"] <= 1.0 and r["shapes"] == 14 for r in rows)
