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
    assert all(0.0 <= v <= 1.0 for v in four["parts"].values())
    ds = oracle.build_dataset(oracle.compose_train_config(["task=segmentation", "dataset=synthetic_parts", *over]).dataset,
                              "test", progress=False)
    assert set(four["parts"]) == {ds.part_names[int(k)] for i in range(len(ds)) for k in ds[i]["part_labels"].unique()}
    parts = oracle.parts_markdown([one, four]).splitlines()
    assert parts[0] == "| part | spherical M = 1 | spherical M = 4 |" and len(parts) == 2 + len(four["parts"])


def test_the_time_study_times_every_stage_and_their_sums(tmp_path):
    timing = study("segmentation_time")
    r = timing.row(2, batch=2, image_size=32, repeats=1, cache=str(tmp_path))
    stages = ("render", "index", "C seg", "lift", "C cls")
    assert all(r[k] > 0 for k in stages)
    assert abs(r["segmentation"] - (r["render"] + r["index"] + r["C seg"] + r["lift"])) < 1e-9
    assert abs(r["ratio"] - r["segmentation"] / (r["render"] + r["C cls"])) < 1e-9
    assert timing.markdown([r]).splitlines()[2].startswith("| 2 |")


def test_each_parts_iou_from_the_confusion_by_hand(tmp_path):
    import json

    import numpy as np

    pi = study("part_iou")
    conf = [[3, 1, 0], [0, 2, 0], [0, 0, 0]]  # part 2: never true, never predicted
    assert np.allclose(pi.part_iou(conf), [3 / 4, 2 / 3, 0.0])
    for i, (sel, c) in enumerate([("a", conf), ("a", [[4, 0, 0], [0, 2, 0], [0, 0, 1]]), ("b", conf)]):
        run = tmp_path / f"r{i}"
        run.mkdir()
        (run / "metrics.json").write_text(json.dumps({"part_names": ["x/p", "x/q", "y/r"], "confusion_matrix": c,
                                                      "config": {"selector": {"name": sel}, "views": 4},
                                                      "test_instance_miou": 0.5 + i / 10, "test_coverage": 0.9}))
    names, by = pi.sides([tmp_path], "selector.name")
    assert names == ["x/p", "x/q", "y/r"] and by["a"][1] == 2 and by["b"][1] == 1
    assert np.allclose(by["a"][0], [(0.75 + 1.0) / 2, (2 / 3 + 1.0) / 2, 0.5])
    assert "| x/p | 0.875 | 0.750 |" in pi.markdown(names, by)
    lines = pi.curve([tmp_path], "selector.name").splitlines()
    assert lines[2] == "| a | 4 | 2 | 0.550 ± 0.071 | 0.900 ± 0.000 |" and lines[3] == "| b | 4 | 1 | 0.700 ± 0.000 | 0.900 ± 0.000 |"
