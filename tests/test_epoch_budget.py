"""scripts/studies/epoch_budget.py: per-phase epoch seconds read from runs, and the budget arithmetic."""
from __future__ import annotations

import json

import pytest
from studies import study

eb = study("epoch_budget")


def write_run(folder, seconds, racing):
    folder.mkdir(parents=True)
    history = [{"epoch": i + 1, "hypothesis_losses": [0.1, 0.2] if i < racing else None} for i in range(len(seconds))]
    (folder / "metrics.json").write_text(json.dumps({"epoch_seconds": seconds, "history": history}))


@pytest.fixture
def sides(tmp_path):
    write_run(tmp_path / "fixed" / "seed0", [2.0] * 4, 0)
    write_run(tmp_path / "fixed" / "seed1", [3.0] * 4, 0)
    write_run(tmp_path / "learned" / "seed0", [20.0, 22.0, 6.0, 6.0], 2)
    write_run(tmp_path / "learned" / "seed1", [20.0, 6.0, 6.0, 8.0], 1)
    return tmp_path


def test_phases_split_the_racing_epochs_from_the_rest(sides):
    fixed = eb.side_summary(eb.run_files([str(sides / "fixed")]))
    learned = eb.side_summary(eb.run_files([str(sides / "learned" / "seed0"), str(sides / "learned" / "seed1")]))
    assert fixed == dict(runs=2, whole=10.0, epochs=4, race_epochs=0, race=fixed["race"], other=2.5)
    assert learned["race_epochs"] == 1.5 and learned["race"] == pytest.approx(62 / 3)
    assert learned["other"] == pytest.approx(32 / 5) and learned["whole"] == pytest.approx(47.0)
    b = eb.budget(fixed, learned, 1.5)
    # budget 15 s; four epochs at 6.4 s = 25.6 s already exceed it: no racing epoch is affordable
    assert b["budget"] == pytest.approx(15.0) and b["no_race"] == pytest.approx(25.6)
    assert b["affordable"] == pytest.approx((15.0 - 25.6) / (62 / 3 - 6.4)) and b["affordable"] < 0
    assert eb.budget(fixed, learned, 4.0)["affordable"] == pytest.approx((40.0 - 25.6) / (62 / 3 - 6.4))


def test_the_table_and_its_budget_line(sides, capsys):
    assert eb.main(["--fixed", str(sides / "fixed"), "--learned", str(sides / "learned")]) == 0
    out = capsys.readouterr().out
    assert "| learned | 2 | 4 | 47.0 | 1.5 | 20.7 | 6.4 |" in out
    assert "budget at 1.5 x the fixed run: 15.0 s" in out and "(2.56 x the fixed run)" in out


def test_bad_input_is_one_line_exit_2(sides, tmp_path, capsys):
    write_run(tmp_path / "short" / "seed0", [2.0] * 3, 0)
    for argv, says in ((["--fixed", str(tmp_path / "none"), "--learned", str(sides / "learned")], "no metrics.json"),
                       (["--fixed", str(tmp_path / "short"), "--learned", str(sides / "learned")], "same epochs"),
                       (["--fixed", str(sides / "fixed"), "--learned", str(sides / "learned"), "--target", "0"], "--target")):
        assert eb.main(argv) == 2
        err = capsys.readouterr().err
        assert says in err and len(err.strip().splitlines()) == 1
