"""scripts/studies/compare_seeds.py: pairs runs by seed within each group and states the paired-t interval."""
from __future__ import annotations

import json
import math

from scipy import stats

from studies import study

cs = study("compare_seeds")


def _run(folder, name, views, seed, acc):
    d = folder / f"{name}_{views}_{seed}"
    d.mkdir(parents=True)
    (d / "metrics.json").write_text(json.dumps({"test_acc": acc, "config": {"seed": seed, "views": views,
                                                                            "selector": {"name": name}}}))


def test_pairs_by_seed_and_group_with_the_paired_t_interval(tmp_path, capsys):
    fixed = {0: 0.50, 1: 0.60, 2: 0.55, 3: 0.40}
    learned = {0: 0.70, 1: 0.65, 2: 0.75, 9: 0.99}  # seed 3 and 9 have no partner: left out
    for s, a in fixed.items():
        _run(tmp_path / "f", "spherical", 1, s, a)
    for s, a in learned.items():
        _run(tmp_path / "l", "poi", 1, s, a)
    _run(tmp_path / "f", "spherical", 4, 0, 0.1)  # a group with one seed only: no comparison
    _run(tmp_path / "l", "poi", 4, 0, 0.9)
    assert cs.main([str(tmp_path / "f"), str(tmp_path / "l"), "--a", "selector.name=spherical",
                    "--b", "selector.name=poi"]) == 0
    out = capsys.readouterr().out
    d = [0.20, 0.05, 0.20]
    mean, sd = sum(d) / 3, math.sqrt(sum((x - sum(d) / 3) ** 2 for x in d) / 2)
    half = stats.t.ppf(0.975, 2) * sd / math.sqrt(3)
    assert "views=1, seeds 0, 1, 2 (n=3)" in out and "views=4" not in out
    assert f"B - A {100 * mean:+.1f} +- {100 * sd:.1f} points" in out
    assert f"[{100 * (mean - half):+.1f}, {100 * (mean + half):+.1f}]" in out and "B ahead 3, tied 0, behind 0" in out


def test_nothing_to_compare_is_one_line_exit_2(tmp_path, capsys):
    _run(tmp_path, "spherical", 1, 0, 0.5)
    assert cs.main([str(tmp_path), "--a", "selector.name=spherical", "--b", "selector.name=poi"]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
    assert cs.main([str(tmp_path), "--a", "spherical", "--b", "selector.name=poi"]) == 2
