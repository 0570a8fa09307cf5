"""The part segmentation probes of scripts/studies/ on tiny settings: the perfect-C ceiling and the
time per shape against classification."""
from __future__ import annotations

from studies import study


def test_a_perfect_c_scores_the_views_ceiling_more_views_see_more(tmp_path):
    oracle = study("parts_oracle")
    over = [f"dataset.root={tmp_path}", "dataset.num_per_class=[1,1,2]", "image_size=32"]
    one, four = (oracle.oracle("spherical", M, "test", over) for M in (1, 4))
    assert one["shapes"] == four["shapes"] == 10
    assert 0.0 < one["coverage"] < four["coverage"] <= 1.0
    assert one["instance_miou"] < four["instance_miou"] <= 1.0
    table = oracle.markdown([one, four])
    assert table.count("\n") == 4 and "| spherical | 4 | 32 |" in table


def test_the_time_study_times_every_stage_and_their_sums(tmp_path):
    timing = study("segmentation_time")
    r = timing.row(2, batch=2, image_size=32, repeats=1, cache=str(tmp_path))
    stages = ("render", "index", "C seg", "lift", "C cls")
    assert all(r[k] > 0 for k in stages)
    assert abs(r["segmentation"] - (r["render"] + r["index"] + r["C seg"] + r["lift"])) < 1e-9
    assert abs(r["ratio"] - r["segmentation"] / (r["render"] + r["C cls"])) < 1e-9
    assert timing.markdown([r]).splitlines()[2].startswith("| 2 |")
