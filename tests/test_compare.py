"""mvtn-compare: sides, pairing by seed, the paired-t interval, refusals, and the run mode end to end."""
from __future__ import annotations

import json
import math

import pytest
from scipy import stats

from mvtn_exp.cli.compare import main, parse_seeds
from mvtn_exp.runs.compare import compare
from mvtn_exp.runs.compare_md import _letter
from mvtn_exp.runs.folders import find_runs
from mvtn_exp.runs.sides import CompareError


def _config(selector="spherical", views=1, seed=0, dataset_seed=0, epochs=20, threads=1, patience=None):
    return {"seed": seed, "views": views, "epochs": epochs, "patience": patience, "threads": threads, "device": "cpu",
            "dataset": {"name": "synthetic_views", "seed": dataset_seed, "root": f"/somewhere/{threads}"},
            "selector": {"name": selector}, "paths": {"output_dir": f"/o{seed}"}}


def _run(folder, name, acc, val=0.5, commit="abc1234def", cpu=None, **cfg):
    d = folder / name
    d.mkdir(parents=True)
    prov = {"commit": commit, "dirty": False, "device": "cpu", **({"cpu": cpu, "cpu_capability": "AVX2"} if cpu else {})}
    (d / "metrics.json").write_text(json.dumps({"test_acc": acc, "best_val_acc": val, "test_detail_seen": acc / 2,
                                                "config": _config(**cfg), "provenance": prov}))
    return d


def _set_config(d, **sections):
    """Replace whole sections of the stored config of the run in ``d`` (e.g. an older record)."""
    m = json.loads((d / "metrics.json").read_text())
    m["config"].update(sections)
    (d / "metrics.json").write_text(json.dumps(m))


FIXED = {0: 0.50, 1: 0.60, 2: 0.55, 3: 0.40}
LEARNED = {0: 0.70, 1: 0.65, 2: 0.75, 3: 0.30}


def _two_sides(tmp_path, **kw):
    for s, a in FIXED.items():
        _run(tmp_path / "f", f"s{s}", a, seed=s, selector="spherical", **kw)
    for s, a in LEARNED.items():
        _run(tmp_path / "l", f"s{s}", a, seed=s, selector="poi", **kw)


def test_paired_t_interval_and_wins_match_scipy(tmp_path, capsys):
    _two_sides(tmp_path)
    assert main([str(tmp_path / "f"), str(tmp_path / "l"), "--out", str(tmp_path / "c"), "--also", "test_detail_seen"]) is None
    out = capsys.readouterr().out
    d = [LEARNED[s] - FIXED[s] for s in range(4)]
    ci = stats.t.interval(0.95, 3, loc=sum(d) / 4, scale=stats.sem(d))
    assert f"[{100 * ci[0]:+.1f}, {100 * ci[1]:+.1f}]" in out
    sd = math.sqrt(sum((x - sum(d) / 4) ** 2 for x in d) / 3)
    assert f"| selector.name=poi | 4 | 0.600 ± {math.sqrt(sum((v - .6) ** 2 for v in LEARNED.values()) / 3):.3f} |" in out
    assert f"{100 * sum(d) / 4:+.1f} ± {100 * sd:.1f}" in out and "| 3 / 0 / 1 |" in out
    assert "| selector.name=spherical | 4 |" in out and "reference" in out
    assert out.strip().splitlines()[-1] == str(tmp_path / "c" / "compare.md")
    saved = json.loads((tmp_path / "c" / "compare.json").read_text())
    side = saved["groups"][0]["sides"][1]
    assert side["seeds"] == [0, 1, 2, 3] and side["values"] == [LEARNED[s] for s in range(4)]
    assert side["ahead"] == 3 and side["behind"] == 1 and side["differs_in"] == ["selector.name"]
    assert side["low"] == pytest.approx(ci[0]) and side["high"] == pytest.approx(ci[1])
    assert side["also_values"]["test_detail_seen"] == [LEARNED[s] / 2 for s in range(4)]
    assert "| 3 | 0.4000 | 0.3000 | 0.2000 | 0.1500 |" in out  # per seed: the metric, then --also, per side
    # the per-seed header names each side by a letter, the legend above it gives the full label once
    assert "| seed | A | B | A test_detail_seen | B test_detail_seen |" in out
    assert "A: selector.name=spherical; B: selector.name=poi):" in out
    assert (tmp_path / "c" / "compare.md").read_text().startswith("# Comparison")


def test_reference_where_group_and_metric(tmp_path, capsys):
    for views in (1, 4):
        for s in range(3):
            _run(tmp_path, f"f{views}_{s}", 0.1 * s + views / 10, val=0.2, seed=s, views=views)
            _run(tmp_path, f"l{views}_{s}", 0.1 * s + views / 10 + 0.05 * views, val=0.3 + s / 100, seed=s,
                 views=views, selector="poi")
    runs = find_runs([tmp_path])
    res = compare(runs, group="views", reference="selector=poi")
    assert [g["group"] for g in res["groups"]] == [1, 4]
    for g, views in zip(res["groups"], (1, 4)):
        assert g["sides"][0]["label"] == "selector.name=poi"  # the reference comes first
        assert g["sides"][1]["diff"] == pytest.approx(-0.05 * views)
    val = compare(runs, metric="best_val_acc", where=["selector.name=spherical views=1", "selector=poi views=1"])
    assert val["groups"][0]["sides"][1]["diff"] == pytest.approx(0.11)
    ref = compare(runs, metric="best_val_acc", where=["selector.name=spherical views=1", "selector=poi views=1"],
                  reference="selector=poi")  # with --where too, the reference side comes first
    assert [s["label"] for s in ref["groups"][0]["sides"]] == ["selector=poi views=1", "selector.name=spherical views=1"]
    assert ref["groups"][0]["sides"][1]["diff"] == pytest.approx(-0.11)
    with pytest.raises(CompareError, match="differ in views"):  # one side holding two settings
        compare(runs, where=["selector=spherical", "selector=poi"])
    with pytest.raises(SystemExit) as e:
        main([str(tmp_path), "--group", "views", "--metric", "no_such_metric"])
    assert e.value.code == 2 and "no number under 'no_such_metric'" in capsys.readouterr().err


@pytest.mark.parametrize("key,value", [("dataset_seed", 1), ("epochs", 40), ("patience", 10)])
def test_sides_that_differ_in_data_or_epochs_are_refused_unless_named(tmp_path, capsys, key, value):
    for s in range(3):
        _run(tmp_path, f"a{s}", 0.5, seed=s)
        _run(tmp_path, f"b{s}", 0.6, seed=s, selector="poi", **{key: value})
    with pytest.raises(SystemExit) as e:
        main([str(tmp_path)])
    err = capsys.readouterr().err.strip()
    name = {"dataset_seed": "dataset.seed", "epochs": "epochs", "patience": "patience"}[key]
    assert e.value.code == 2 and len(err.splitlines()) == 1 and err.startswith(f"mvtn-compare: {name}:")
    assert f"--key {name}" in err
    main([str(tmp_path), "--key", name.split(".")[0]])  # named: compared
    assert "+10.0" in capsys.readouterr().out


def test_run_local_keys_make_no_difference(tmp_path):
    for s in range(2):
        _run(tmp_path, f"a{s}", 0.5, seed=s, threads=1)
        _run(tmp_path, f"b{s}", 0.6, seed=s, selector="poi", threads=2)
    res = compare(find_runs([tmp_path]))
    assert res["groups"][0]["sides"][1]["differs_in"] == ["selector.name"]


def test_seeds_must_match_unless_an_unfinished_run_explains_it(tmp_path, capsys):
    _two_sides(tmp_path)
    extra = _run(tmp_path / "l", "s9", 0.9, seed=9, selector="poi")
    with pytest.raises(SystemExit) as e:
        main([str(tmp_path / "f"), str(tmp_path / "l")])
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.startswith("mvtn-compare: seed:") and len(err.strip().splitlines()) == 1
    # seed 9 failed on the fixed side: listed, and the other seeds are compared
    (extra.parent.parent / "f" / "s9").mkdir()
    (tmp_path / "f" / "s9" / "status.json").write_text(json.dumps({"status": "error", "error": "disk full"}))
    (tmp_path / "f" / "s9" / ".hydra").mkdir()
    (tmp_path / "f" / "s9" / ".hydra" / "config.yaml").write_text(json.dumps(_config(seed=9)))
    main([str(tmp_path / "f"), str(tmp_path / "l"), "--out", str(tmp_path / "c")])
    cap = capsys.readouterr()
    assert "s9: error: disk full" in cap.out and "1 run(s) not finished" in cap.err
    side = json.loads((tmp_path / "c" / "compare.json").read_text())["groups"][0]["sides"][1]
    assert side["seeds"] == [0, 1, 2, 3] and side["dropped_seeds"] == [9]


def test_too_few_seeds_or_one_side_or_nothing_is_one_line_exit_2(tmp_path, capsys):
    _run(tmp_path, "a0", 0.5, seed=0)
    _run(tmp_path, "b0", 0.6, seed=0, selector="poi")
    for argv, start in (([str(tmp_path)], "mvtn-compare: seed:"),
                        ([str(tmp_path), "--where", "selector=poi"], "mvtn-compare: only one configuration"),
                        ([str(tmp_path / "none")], "mvtn-compare: "), ([], "mvtn-compare: give the folders"),
                        ([str(tmp_path), "--where", "seed=0"], "mvtn-compare: --where 'seed=0': seed is what"),
                        (["--run", "selector=poi", "--seeds", "0-3"], "mvtn-compare: --run: give at least two"),
                        (["--run", "a=1", "--run", "b=2", "--seeds", "x"], "mvtn-compare: --seeds 'x'")):
        with pytest.raises(SystemExit) as e:
            main(argv)
        err = capsys.readouterr().err
        assert e.value.code == 2 and err.startswith(start) and len(err.strip().splitlines()) == 1, (argv, err)
    assert parse_seeds("0-3,7") == [0, 1, 2, 3, 7]


TINY = ["views=2", "image_size=32", "epochs=1", "batch_size=8", "dataset.num_per_class=[4,2,2]", "backbone=small_cnn",
        "logger.progress=false", "logger.tensorboard=false"]


@pytest.mark.slow  # (longer than 15 s on 2 cores: make test-all)
def test_run_mode_trains_each_side_and_seed_then_reads_them_again(tmp_path, capsys):
    out = tmp_path / "c"
    argv = ["--run", "selector=circular", "--run", "selector=spherical", "--seeds", "0-1", "--jobs", "2",
            "--out", str(out), *TINY, f"dataset.root={tmp_path / 'cache'}"]
    main(argv)
    first = capsys.readouterr().out
    assert "| selector=circular | 2 |" in first and "| selector=spherical | 2 |" in first
    for side, name in ((1, "circular"), (2, "spherical")):
        for seed in (0, 1):
            m = json.loads((out / f"side{side}" / f"seed{seed}" / "metrics.json").read_text())
            assert m["config"]["selector"]["name"] == name and m["config"]["seed"] == seed and m["config"]["threads"] == 1
    stamp = (out / "side1" / "seed0" / "metrics.json").stat().st_mtime_ns
    main(argv)  # finished runs are read, not trained again
    assert capsys.readouterr().out == first
    assert (out / "side1" / "seed0" / "metrics.json").stat().st_mtime_ns == stamp


def test_run_mode_checks_every_side_before_training(tmp_path, capsys):
    for sides, start in ((["selector=circular", "selector=circular selector.nope=1"], "mvtn-compare: config error"),
                         (["selector=circular", "selector=spherical epochs=3"], "mvtn-compare: epochs:"),
                         (["selector=circular", "selector=circular"], "mvtn-compare: --run 'selector=circular' gives the same")):
        with pytest.raises(SystemExit) as e:
            main([x for s in sides for x in ("--run", s)] + ["--seeds", "0-1", "--out", str(tmp_path / "c"), *TINY])
        err = capsys.readouterr().err
        assert e.value.code == 2 and err.startswith(start) and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "c").exists()


def test_a_side_whose_every_run_failed_is_listed_and_the_rest_compared(tmp_path, capsys):
    _two_sides(tmp_path)
    for s in range(3):  # a third configuration (views=4) all of whose runs failed, seen first
        d = tmp_path / "a" / f"s{s}"
        (d / ".hydra").mkdir(parents=True)
        (d / ".hydra" / "config.yaml").write_text(json.dumps(_config(seed=s, views=4)))
        (d / "status.json").write_text(json.dumps({"status": "error", "error": "cuda and cpu"}))
    main([str(tmp_path / "a"), str(tmp_path / "f"), str(tmp_path / "l"), "--out", str(tmp_path / "c")])
    cap = capsys.readouterr()
    assert "3 run(s) not finished" in cap.err and cap.out.count(": error: cuda and cpu") == 3
    sides = json.loads((tmp_path / "c" / "compare.json").read_text())["groups"][0]["sides"]
    assert [s["label"] for s in sides] == ["selector.name=spherical", "selector.name=poi"]
    assert sides[1]["diff"] == pytest.approx(sum(LEARNED[s] - FIXED[s] for s in FIXED) / 4)


def test_a_side_still_running_is_named_when_only_the_other_has_finished(tmp_path, capsys):
    for s in range(2):
        _run(tmp_path / "f", f"s{s}", 0.5, seed=s)
        d = tmp_path / "l" / f"s{s}"  # started (its config written), no metrics.json yet
        (d / ".hydra").mkdir(parents=True)
        (d / ".hydra" / "config.yaml").write_text(json.dumps(_config(seed=s, selector="poi")))
    (tmp_path / "f" / "s9" / ".hydra").mkdir(parents=True)  # the finished side's own unfinished seed: not named
    (tmp_path / "f" / "s9" / ".hydra" / "config.yaml").write_text(json.dumps(_config(seed=9)))
    with pytest.raises(SystemExit) as e:
        main([str(tmp_path / "f"), str(tmp_path / "l")])
    err = capsys.readouterr().err
    assert e.value.code == 2 and len(err.strip().splitlines()) == 1, err
    assert err.startswith("mvtn-compare: only one configuration with finished runs ('(defaults)' ...)")
    assert f"2 run(s) of another configuration not finished ({tmp_path / 'l' / 's0'}: incomplete, ...)" in err


def test_ratio_is_the_paired_geometric_mean_with_its_log_interval(tmp_path, capsys):
    """--ratio train_wall_seconds: side / reference per seed, geometric mean, t interval on the logs;
    older runs without the number have it from their epoch_seconds."""
    walls = {0: (100.0, 130.0), 1: (80.0, 120.0), 2: (120.0, 150.0), 3: (90.0, 99.0)}
    for s, (f, l) in walls.items():
        _run(tmp_path / "f", f"s{s}", FIXED[s], seed=s, selector="spherical")
        d = _run(tmp_path / "l", f"s{s}", LEARNED[s], seed=s, selector="poi")
        for folder, wall in ((tmp_path / "f" / f"s{s}", f), (d, l)):
            m = json.loads((folder / "metrics.json").read_text())
            m.update({"epoch_seconds": [wall / 4] * 4} if s % 2 else {"train_wall_seconds": wall})
            (folder / "metrics.json").write_text(json.dumps(m))
    main([str(tmp_path / "f"), str(tmp_path / "l"), "--out", str(tmp_path / "c"), "--ratio", "train_wall_seconds"])
    out = capsys.readouterr().out
    logs = [math.log(l / f) for f, l in walls.values()]
    m, half = sum(logs) / 4, stats.t.ppf(0.975, 3) * stats.sem(logs)
    assert f"| {math.exp(m):.2f} x [{math.exp(m - half):.2f}, {math.exp(m + half):.2f}] |" in out
    assert "train_wall_seconds / reference [95%]" in out and "| 1 (reference) |" in out
    side = json.loads((tmp_path / "c" / "compare.json").read_text())["groups"][0]["sides"][1]
    assert side["ratios"]["train_wall_seconds"]["ratio"] == pytest.approx(math.exp(m))
    m = json.loads((tmp_path / "l" / "s0" / "metrics.json").read_text())
    m["train_wall_seconds"] = 0.0
    (tmp_path / "l" / "s0" / "metrics.json").write_text(json.dumps(m))
    with pytest.raises(SystemExit) as e:
        main([str(tmp_path / "f"), str(tmp_path / "l"), "--out", str(tmp_path / "c"), "--ratio", "train_wall_seconds"])
    assert e.value.code == 2 and "must be > 0" in capsys.readouterr().err


def test_a_key_added_after_a_run_reads_as_its_current_default(tmp_path, capsys):
    """An older run's record lacks renderer.compile (added later, default null): it pairs with
    newer runs that have null (one side, the filled key listed), not with runs that have true."""
    def run(folder, name, acc, seed, compile_):
        d = _run(folder, name, acc, seed=seed, selector="poi")
        if compile_ != "absent":
            _set_config(d, renderer={"compile": compile_})

    for s in range(3):
        run(tmp_path / "old", f"s{s}", 0.5, s, "absent")  # before the key existed
        run(tmp_path / "new", f"s{s}", 0.5, s + 3, None)  # the same setting, later, other seeds
    for s in range(6):
        run(tmp_path / "on", f"s{s}", 0.6 + 0.01 * s, s, True)
    result = compare(find_runs([tmp_path / "old", tmp_path / "new"]) + find_runs([tmp_path / "on"]),
                     where=["renderer.compile=null", "renderer.compile=true"])
    sides = result["groups"][0]["sides"]
    assert sides[0]["seeds"] == sides[1]["seeds"] == [0, 1, 2, 3, 4, 5]
    assert sides[1]["differs_in"] == ["renderer.compile"]
    assert result["filled"] == {"renderer.compile": 3}
    with pytest.raises(CompareError, match="differ in renderer.compile"):  # true is no default: not filled away
        compare(find_runs([tmp_path / "old", tmp_path / "on"]), where=["selector=poi"])
    main([str(tmp_path / "old"), str(tmp_path / "new"), str(tmp_path / "on"), "--out", str(tmp_path / "c")])
    out = capsys.readouterr().out
    assert "read as the current default: renderer.compile (3 runs)" in out


def test_count_gives_each_sides_share_of_seeds_with_wilson_interval(tmp_path, capsys):
    """test_detail_seen is acc / 2: fixed 0.25 / 0.30 / 0.275 / 0.20, learned 0.35 / 0.325 / 0.375 / 0.15;
    >= 0.3 holds for 1 and 3 seeds of 4 (a tie at the bound counts); Wilson 95%: [0.046, 0.699], [0.301, 0.954]."""
    _two_sides(tmp_path)
    main([str(tmp_path / "f"), str(tmp_path / "l"), "--out", str(tmp_path / "c"), "--count", "test_detail_seen>=0.3",
          "--count", "test_acc<0.5"])
    out = capsys.readouterr().out
    assert "seeds with test_detail_seen>=0.3 [Wilson 95%] | seeds with test_acc<0.5 [Wilson 95%] |" in out
    assert "| 1 of 4 [0.05, 0.70] | 1 of 4 [0.05, 0.70] |" in out  # fixed: 0.30 >= 0.3; acc 0.40 < 0.5
    assert "| 3 of 4 [0.30, 0.95] | 1 of 4 [0.05, 0.70] |" in out  # learned: acc 0.30 < 0.5
    side = json.loads((tmp_path / "c" / "compare.json").read_text())["groups"][0]["sides"][1]
    low, high = side["counts"]["test_detail_seen>=0.3"]["low"], side["counts"]["test_detail_seen>=0.3"]["high"]
    assert (low, high) == (pytest.approx(0.3006, abs=1e-4), pytest.approx(0.9544, abs=1e-4))


@pytest.mark.parametrize("condition", ["test_detail_seen=0.5", "test_detail_seen>=", ">=0.5", "test_detail_seen>=a"])
def test_a_bad_count_is_one_line_before_anything_runs(tmp_path, capsys, condition):
    _two_sides(tmp_path)
    with pytest.raises(SystemExit) as e:
        main(["--run", "selector=spherical", "--run", "selector=poi", "--seeds", "0-1", "--out", str(tmp_path / "o"),
              "--count", condition])
    err = capsys.readouterr().err.strip()
    assert e.value.code == 2 and err == f"mvtn-compare: --count {condition!r}: expected METRIC>=VALUE (or <=, >, <), " \
                                        "e.g. test_detail_seen>=0.5"
    assert not (tmp_path / "o").exists()


def test_count_of_a_metric_a_run_lacks_names_it(tmp_path, capsys):
    _two_sides(tmp_path)
    with pytest.raises(SystemExit) as e:
        main([str(tmp_path / "f"), str(tmp_path / "l"), "--count", "test_nothing>=1"])
    assert e.value.code == 2 and "no number under 'test_nothing'" in capsys.readouterr().err


def test_best_val_detail_seen_is_read_at_the_best_epoch(tmp_path, capsys):
    """A derived number: the validation views' detail share at the run's best epoch (for --count on validation)."""
    for s, (best, seen) in enumerate([(2, [0.1, 0.9, 0.2]), (3, [0.8, 0.7, 0.3])]):
        for side, sel in (("a", "spherical"), ("b", "poi")):
            d = _run(tmp_path / side, f"s{s}", 0.5, seed=s, selector=sel)
            m = json.loads((d / "metrics.json").read_text())
            m.update(best_epoch=best, history=[{"val_detail_seen": x} for x in seen])
            (d / "metrics.json").write_text(json.dumps(m))
    main([str(tmp_path / "a"), str(tmp_path / "b"), "--also", "best_val_detail_seen", "--count", "best_val_detail_seen>=0.5"])
    out = capsys.readouterr().out
    assert "| 0 | 0.5000 | 0.5000 | 0.9000 | 0.9000 |" in out and "| 1 | 0.5000 | 0.5000 | 0.3000 | 0.3000 |" in out
    assert "| 1 of 2 [" in out


def test_race_led_counts_races_ended_by_a_clear_lead(tmp_path, capsys):
    """A derived number: 1 where the race's last recorded end is a lead, 0 at its cap or batch
    budget; a run without a recorded race end has none, and --count names the metric."""
    ends = {"a": ["lead", "cap", "batches"], "b": ["lead", "lead", "cap"]}
    for side, sel in (("a", "spherical"), ("b", "poi")):
        for s, end in enumerate(ends[side]):
            d = _run(tmp_path / side, f"s{s}", 0.5, seed=s, selector=sel)
            m = json.loads((d / "metrics.json").read_text())
            m["history"] = [{"race_end": None}, {"race_end": end}, {"race_end": None}]
            (d / "metrics.json").write_text(json.dumps(m))
    main([str(tmp_path / "a"), str(tmp_path / "b"), "--count", "race_led>=1", "--out", str(tmp_path / "c")])
    sides = json.loads((tmp_path / "c" / "compare.json").read_text())["groups"][0]["sides"]
    assert [x["counts"]["race_led>=1"]["k"] for x in sides] == [1, 2]
    capsys.readouterr()
    for d in (tmp_path / "b").iterdir():  # records made before race_end was kept
        m = json.loads((d / "metrics.json").read_text())
        m["history"] = [{"hypothesis_active": 0}]
        (d / "metrics.json").write_text(json.dumps(m))
    with pytest.raises(SystemExit) as e:
        main([str(tmp_path / "a"), str(tmp_path / "b"), "--count", "race_led>=1"])
    assert e.value.code == 2 and "no number under 'race_led'" in capsys.readouterr().err


def test_keys_of_another_option_are_not_filled_into_a_fixed_selectors_record(tmp_path, capsys):
    """A fixed selector's schema has no learning rate: pairing its runs with learned ones (whose
    records hold ``selector.lr``) neither fills the learned default into the fixed runs nor lists
    the key as added after them; a key the fixed schema has and an old fixed record lacks is."""
    for s in range(3):
        _set_config(_run(tmp_path / "f", f"s{s}", 0.2, seed=s),
                    selector={"name": "spherical", "distance": 2.2})  # before `canonical` existed
        _set_config(_run(tmp_path / "l", f"s{s}", 0.4, seed=s),
                    selector={"name": "poi", "lr": 0.01, "distance": 2.2, "canonical": "none"})
    result = compare(find_runs([tmp_path / "f", tmp_path / "l"]))
    assert result["filled"] == {"selector.canonical": 3}
    assert result["groups"][0]["sides"][1]["differs_in"] == ["selector.lr", "selector.name"]
    main([str(tmp_path / "f"), str(tmp_path / "l"), "--out", str(tmp_path / "c")])
    assert "read as the current default: selector.canonical (3 runs)" in capsys.readouterr().out


def test_side_letters_run_past_z_without_repeating():
    names = [_letter(i) for i in range(26 * 27 + 1)]
    assert names[:3] == ["A", "B", "C"] and names[25:28] == ["Z", "AA", "AB"] and names[-1] == "AAA"
    assert len(set(names)) == len(names)


def test_runs_from_more_than_one_machine_are_named_with_their_counts(tmp_path, capsys):
    for s, a in FIXED.items():
        _run(tmp_path / "f", f"s{s}", a, seed=s, cpu="Intel Xeon" if s < 3 else "AMD EPYC")
    for s, a in LEARNED.items():
        _run(tmp_path / "l", f"s{s}", a, seed=s, selector="poi", cpu="AMD EPYC")
    main([str(tmp_path / "f"), str(tmp_path / "l"), "--out", str(tmp_path / "c")])
    out = capsys.readouterr().out
    assert "more than one machine" in out and "AMD EPYC (AVX2) (5 runs), Intel Xeon (AVX2) (3 runs)" in out
    saved = json.loads((tmp_path / "c" / "compare.json").read_text())
    assert saved["machines"] == {"AMD EPYC (AVX2)": 5, "Intel Xeon (AVX2)": 3}


def test_runs_from_one_machine_or_older_records_say_nothing_of_machines(tmp_path, capsys):
    _two_sides(tmp_path)  # records without the CPU: one "not recorded" machine
    main([str(tmp_path / "f"), str(tmp_path / "l"), "--out", str(tmp_path / "c")])
    assert "more than one machine" not in capsys.readouterr().out
    assert json.loads((tmp_path / "c" / "compare.json").read_text())["machines"] == {"not recorded": 8}


def test_a_record_names_the_cpu_and_its_capability_and_a_cuda_run_its_gpu():
    from mvtn_exp.engine.provenance import machine, provenance

    prov = provenance("cpu")
    assert prov["cpu"] and prov["cpu_capability"] not in ("", "None")
    assert machine(prov) == f"{prov['cpu']} ({prov['cpu_capability']})"
    assert machine({"device": "cuda:0", "device_name": "NVIDIA H100", "cpu": "AMD EPYC"}) == "NVIDIA H100"
    assert machine({"device": "cpu", "device_name": "x86_64"}) is None  # made before the CPU was kept
